"""The whole job on one program: read, plan, compensate, write, report.

Takes an input G-code path, an output path, a machine profile and options; writes the
compensated program atomically (nothing is written if anything fails) and gives a ``Report``
with the predicted tracking error of every compensated axis before and after, per the model.
"""
from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .atomicfile import atomic_write
from .dynamics import AxisDynamics
from .fallback import FALLBACK, AxisGuard
from .gcode import AXES, Block, detect_flavor, read_gcode
from .optimizer import AxisCompensator, AxisLimits, FBSSettings
from .planner import Plan, plan_blocks
from .profile import MachineProfile
from .trajectory import InputError
from .writer import SampleWindow, WriteOptions, format_refusal, write_program


@dataclass(frozen=True)
class CompensateOptions:
    flavor: str | None = None  # detected from the file when None
    output_format: str = "dense"  # dense | g5 (see writer)
    tolerance_mm: float = 1e-3
    min_segment_time_s: float = 1e-3
    lookahead: str = "limited"
    settings: FBSSettings = FBSSettings()


@dataclass
class AxisReport:
    """Modelled tracking error (desired minus modelled actual position) of one axis, over every
    run of motion and the settling after it, for the planned and for the compensated command."""

    rms_error_before_um: float
    max_error_before_um: float
    rms_error_after_um: float
    max_error_after_um: float

    @classmethod
    def from_errors(cls, before_mm: np.ndarray, after_mm: np.ndarray) -> AxisReport:
        """From the modelled tracking error of the original and of the compensated command."""
        before, after = _ErrorStats(), _ErrorStats()
        before.add(before_mm)
        after.add(after_mm)
        return cls.from_stats(before, after)

    @classmethod
    def from_stats(cls, before: _ErrorStats, after: _ErrorStats) -> AxisReport:
        return cls(before.rms_um, before.peak_um, after.rms_um, after.peak_um)


@dataclass
class Report:
    input: str
    output: str
    profile: str
    flavor: str
    lines_in: int
    lines_out: int
    print_time_s: float
    compute_time_s: float
    axes: dict[str, AxisReport] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    stage_time_s: dict[str, float] = field(default_factory=dict)  # read, plan, optimize, write

    def as_dict(self) -> dict:
        return asdict(self)


_CHUNK = 1 << 14  # samples planned, compensated and written at once


def compensate_file(input_path: str | Path, output_path: str | Path, profile: MachineProfile,
                    options: CompensateOptions = CompensateOptions(), progress=None) -> Report:
    """``progress(fraction)`` is called as the motion is compensated (0 to 1), if given.

    Streams: the program is read twice (to plan it, then to write it: the blocks are not
    held) and its samples are planned, compensated and written a stretch at a time, so memory
    holds the piece-level plan, the optimizers' look-ahead and the writer's, not the samples.
    """
    started = time.perf_counter()
    flavor = options.flavor or detect_flavor(input_path)
    refusal = format_refusal(flavor, options.output_format)
    if refusal:  # before the work
        raise InputError(input_path, None, refusal)
    stages = dict.fromkeys(("read", "plan", "optimize", "write"), 0.0)
    clock = time.perf_counter()
    limits = _LimitsSeen(profile)
    plan = plan_blocks(limits.watch(_timed(read_gcode(input_path, flavor), stages, "read")), profile)
    stages["plan"] = time.perf_counter() - clock - stages["read"]
    report = Report(str(input_path), str(output_path), profile.name, flavor, len(plan.line_time_s), 0,
                    plan.duration_s, 0.0, warnings=list(plan.warnings))
    compensators = _compensators(profile, options)
    errors = {c: (_ErrorStats(), _ErrorStats()) for c in compensators}
    follows_plan = np.array([c not in compensators for c in range(len(AXES))])
    chunks = _timed(_compensated(plan, compensators, errors, report.warnings, progress), stages, "optimize")
    ceilings = [profile.axes[AXES[c]].max_acceleration_mm_s2 for c in compensators if c < 3]  # XYZ
    write_options = WriteOptions(
        flavor=flavor, output_format=options.output_format, tolerance_mm=options.tolerance_mm,
        min_segment_time_s=options.min_segment_time_s,
        header=(f"fbspost {__version__}: filtered B-spline compensation for machine profile {profile.name}",
                f"fbspost settings: format {options.output_format}, tolerance {options.tolerance_mm:g} mm, "
                f"minimum segment {options.min_segment_time_s * 1e3:g} ms, flavor {flavor}, {options.lookahead} look-ahead"),
        raise_acceleration_mm_s2=(limits.highest, max(ceilings)) if ceilings else None,
        restore_acceleration_mm_s2=limits.final)
    stats = []
    clock = time.perf_counter()
    read_before = stages["read"]
    atomic_write(output_path, lambda f: stats.append(write_program(
        _timed(read_gcode(input_path, flavor), stages, "read"), plan,
        SampleWindow(chunks, plan.n_samples, follows_plan), write_options, f)))
    stages["write"] = time.perf_counter() - clock - stages["optimize"] - (stages["read"] - read_before)
    for c, (before, after) in errors.items():
        if before.count:
            report.axes[AXES[c]] = AxisReport.from_stats(before, after)
    report.lines_out = stats[0].lines_out
    report.stage_time_s = stages
    report.compute_time_s = time.perf_counter() - started
    return report


def compensated_samples(plan: Plan, profile: MachineProfile, options: CompensateOptions = CompensateOptions(),
                        warnings: list[str] | None = None) -> np.ndarray:
    """The command for every sample of ``plan`` at once (n_samples, 4), as ``compensate_file``
    computes it (for programs that fit in memory); the optimizers' warnings added to ``warnings``."""
    compensators = _compensators(profile, options)
    errors = {c: (_ErrorStats(), _ErrorStats()) for c in compensators}
    chunks = _compensated(plan, compensators, errors, [] if warnings is None else warnings, None)
    return np.concatenate([command for _, command in chunks] or [np.zeros((0, len(AXES)))])


def _compensators(profile: MachineProfile, options: CompensateOptions) -> dict[int, AxisCompensator]:
    """One per axis (column of AXES) that has modes in the profile."""
    period_s = 1.0 / profile.sample_rate_hz
    axes = {c: profile.axes[name] for c, name in enumerate(AXES) if name in profile.axes and profile.axes[name].modes}
    return {c: AxisCompensator(AxisDynamics(axis.modes, period_s), AxisLimits.from_profile(axis), options.settings,
                               options.lookahead) for c, axis in axes.items()}


def _compensated(plan: Plan, compensators: dict[int, AxisCompensator], errors: dict, warnings: list[str], progress):
    """(planned, command) chunks of samples, every sample in order: the command is the plan but
    on the compensated axes (columns), where it is the compensated command where that does no
    harm and the planned original where it would (fallback.AxisGuard). Adds up every compensated
    axis' modelled tracking error, before and after, over the runs and the settling after each
    (the residual vibration the compensation also reduces, and may trade a little in-motion
    error for), and a warning for each stretch that fell back to ``warnings``."""
    guards = {c: AxisGuard(compensator, *errors[c]) for c, compensator in compensators.items()}
    held, written = np.zeros((0, len(AXES))), {c: np.zeros(0) for c in guards}

    def ready():
        """The rows that every axis has its command for."""
        nonlocal held
        n = min([len(v) for v in written.values()] + [len(held)])
        command = held[:n].copy()
        for c in guards:
            command[:, c], written[c] = written[c][:n], written[c][n:]
        planned, held = held[:n], held[n:]
        return planned, command

    for planned, command, moving, follows in _optimized(plan, compensators, progress):
        held = np.concatenate([held, planned])
        for c, guard in guards.items():
            written[c] = np.concatenate([written[c], guard.push(planned[:, c], command[:, c], moving, follows)])
        chunk = ready()
        if len(chunk[0]):
            yield chunk
    for c, guard in guards.items():
        written[c] = np.concatenate([written[c], guard.finish()])
        warnings += _fallback_warnings(plan, AXES[c], guard)
    chunk = ready()
    if len(chunk[0]):
        yield chunk


def _optimized(plan: Plan, compensators: dict[int, AxisCompensator], progress):
    """(planned, compensated, moving, follows) chunks of samples, every sample in order: the
    compensated command is the plan but on the compensated axes (columns) during the runs;
    ``moving``: the chunk is in a run; ``follows``: it continues the one before (not at a rest or
    a run's start, where the plan may jump)."""
    total = max(1, sum(last - first + 1 for first, last in plan.runs))
    done = next_sample = 0
    for first, last in plan.runs:
        if next_sample < first:  # at rest
            rest = plan.samples(next_sample, first)
            yield rest, rest, False, False
        streams = {c: compensator.stream() for c, compensator in compensators.items()}
        planned_rows, commands = np.zeros((0, len(AXES))), {c: np.zeros(0) for c in compensators}

        def ready(planned_rows, commands):
            """The rows that every axis has its command for, and what remains."""
            n = min([len(v) for v in commands.values()] + [len(planned_rows)])
            command = planned_rows[:n].copy()
            for c in commands:
                command[:, c] = commands[c][:n]
            return (planned_rows[:n], command), planned_rows[n:], {c: v[n:] for c, v in commands.items()}

        follows = False
        for a in range(first, last + 1, _CHUNK):
            planned = plan.samples(a, min(a + _CHUNK, last + 1))
            planned_rows = np.concatenate([planned_rows, planned])
            for c, stream in streams.items():
                commands[c] = np.concatenate([commands[c], stream.push(planned[:, c])])
            chunk, planned_rows, commands = ready(planned_rows, commands)
            if len(chunk[0]):
                done += len(chunk[0])
                yield *chunk, True, follows
                follows = True
            if progress:
                progress(done / total)
        # (The optimizer's warnings of limits not met are the fallback's to give: it falls back there.)
        for c, stream in streams.items():
            commands[c] = np.concatenate([commands[c], stream.finish().command_mm])
        chunk, _, _ = ready(planned_rows, commands)
        done += len(chunk[0])
        yield *chunk, True, follows
        next_sample = last + 1
    if next_sample < plan.n_samples:
        rest = plan.samples(next_sample, plan.n_samples)
        yield rest, rest, False, False


def _fallback_warnings(plan: Plan, axis: str, guard: AxisGuard) -> list[str]:
    """One for each stretch where ``guard`` fell back to the planned original, saying when, the
    program lines moving then and why; one more line for those not kept."""
    fs, out = plan.sample_rate_hz, []
    for stretch in guard.stretches:
        start_s, end_s = stretch.start / fs, (min(stretch.stop, plan.n_samples) - 1) / fs
        moving = np.flatnonzero(plan.is_move & (plan.move_start_s <= end_s) & (plan.line_time_s >= start_s)) + 1
        lines = ("" if not moving.size else f", line {moving[0]}" if moving.size == 1
                 else f", lines {moving[0]}-{moving[-1]}")
        kept = f"; {stretch.level:.0%} of the compensation kept" if stretch.level >= 0.005 else ""
        out.append(f"{FALLBACK}: axis {axis}, {start_s:.3f}-{end_s:.3f} s{lines} "
                   f"({' and '.join(sorted(stretch.reasons))}{kept})")
    count, samples = guard.more
    if count:
        out.append(f"{FALLBACK}: axis {axis}, {count} more stretches, {samples / fs:.3f} s in all")
    return out


@dataclass
class _ErrorStats:
    """Running RMS and largest magnitude of an error given in pieces (mm)."""

    sum_squares_mm2: float = 0.0
    count: int = 0
    peak_mm: float = 0.0

    def add(self, error_mm: np.ndarray) -> None:
        if error_mm.size:
            self.sum_squares_mm2 += float(np.einsum("i,i->", error_mm, error_mm))  # (np.dot: BLAS threads, far slower here)
            self.count += error_mm.size
            self.peak_mm = max(self.peak_mm, float(np.abs(error_mm).max()))

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(self.sum_squares_mm2 / max(self.count, 1))) * 1e3

    @property
    def peak_um(self) -> float:
        return self.peak_mm * 1e3


class _LimitsSeen:
    """The acceleration limits a program sets, noted as its blocks pass: the highest (with the
    profile's planner value: the least the raised limit may be) and the (print, travel) pair the
    program leaves the controller with."""

    def __init__(self, profile: MachineProfile):
        self.highest = profile.planner_acceleration_mm_s2
        self.accel, self.travel = profile.planner_acceleration_mm_s2, None

    def watch(self, blocks: Iterable[Block]) -> Iterator[Block]:
        for block in blocks:
            if block.limits is not None:
                if block.limits.acceleration_mm_s2:
                    self.accel = block.limits.acceleration_mm_s2
                    self.highest = max(self.highest, self.accel)
                if block.limits.travel_acceleration_mm_s2 is not None:
                    self.travel = block.limits.travel_acceleration_mm_s2
            yield block

    @property
    def final(self) -> tuple[float, float]:
        return self.accel, (self.accel if self.travel is None else self.travel)


def _timed(items: Iterable, stages: dict[str, float], stage: str) -> Iterator:
    """``items`` as they come, the time taken to make them added to ``stages[stage]``."""
    iterator = iter(items)
    while True:
        clock = time.perf_counter()
        try:
            item = next(iterator)
        except StopIteration:
            stages[stage] += time.perf_counter() - clock
            return
        stages[stage] += time.perf_counter() - clock
        yield item
