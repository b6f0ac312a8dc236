"""The compensated axes of a program, run by run: optimizer, then fallback, per axis.

Takes the plan (a ``PlanStream``, a whole ``Plan`` or a ``planfeed.PlanProxy``), the profile and
the options; gives (planned, command) chunks of samples in order (``compensated``): on each
compensated axis the optimizer's command of every run (``AxisCompensator``, one per axis with
modes: ``axis_compensators``), blended toward the plan where it would do harm (``AxisGuard``),
with the warnings of the stretches that fell back. With lanes, each axis' optimizer and fallback
run on threads of their own (``compensation_chunks``).
"""
from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from ..fbs.dynamics import AxisDynamics, ModelSet
from ..fbs.fallback import FALLBACK, AxisGuard
from ..fbs.optimizer import AxisCompensator
from ..fbs.settings import AxisLimits
from ..fbs.smoothing import half_width_samples
from ..fbs.varying import VaryingModes, load_modes, position_modes
from ..plan.planner import Plan, PlanStream
from ..profile import AxisProfile, MachineProfile
from ..read.blocks import AXES
from .report import CompensateOptions, Outcome, Tally, timed

_CHUNK = 1 << 14  # samples planned, compensated and written at once


def axis_compensators(profile: MachineProfile, options: CompensateOptions) -> dict[int, AxisCompensator]:
    """One per axis (column of AXES) that has modes in the profile. With tolerances on any axis
    (robust compensation), every axis tracks its plan smoothed by a Hann window one period of
    the highest mode long (``smoothing``): the same window on every axis keeps the path's shape."""
    period_s = 1.0 / profile.sample_rate_hz
    axes = {c: profile.axes[name] for c, name in enumerate(AXES) if name in profile.axes and profile.axes[name].modes}
    sets = {c: ModelSet.spread(axis.modes, period_s) for c, axis in axes.items()}
    settings = options.settings
    if any(len(models.models) > 1 for models in sets.values()):
        highest_hz = max(m.frequency_hz for axis in axes.values() for m in axis.modes)
        settings = replace(settings, smoothing_half_width=half_width_samples(highest_hz, period_s))
    return {c: AxisCompensator(AxisDynamics(axis.modes, period_s), AxisLimits.from_profile(axis), settings,
                               options.lookahead, sets[c], varying_modes(profile, axis))
            for c, axis in axes.items()}


def varying_modes(profile: MachineProfile, axis: AxisProfile) -> VaryingModes | None:
    """The axis' modes against the filament printed, if it carries the print (``moving_mass``),
    or against an axis' position (``modes_by_position``); None if they are fixed."""
    table = axis.modes_by_position
    if table is not None:
        return position_modes(axis.modes, 1.0 / profile.sample_rate_hz, AXES.index(table.axis), table.positions_mm,
                              table.frequency_scales)
    if axis.moving_mass_kg is None:
        return None
    filament_mm2 = math.pi * (0.5 * profile.firmware.filament_diameter_mm) ** 2
    return load_modes(axis.modes, 1.0 / profile.sample_rate_hz, axis.moving_mass_kg,
                      filament_mm2 * axis.filament_density_g_cm3 * 1e-3)


def compensation_chunks(plan: PlanStream, compensators: dict[int, AxisCompensator], options: CompensateOptions,
                         outcome: Outcome) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``compensated``'s chunks of ``plan``, on threads per axis if ``parallel_axes``;
    ``outcome`` counts the rest."""
    lanes = _Lanes(compensators) if options.parallel_axes else None
    stages = {"work": 0.0}
    try:
        yield from timed(compensated(plan, compensators, outcome.errors, outcome.warnings, options.fallback,
                                       lanes, outcome.tally), stages, "work", exclude=lambda: plan.time_s)
    finally:
        if lanes:
            lanes.shutdown()
    outcome.optimize_s = stages["work"]


def compensated(plan: Plan | PlanStream, compensators: dict[int, AxisCompensator], errors: dict,
                 warnings: list[str], fallback: bool, lanes: _Lanes | None,
                 tally: Tally) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(planned, command) chunks of samples, every sample in order, as the plan settles them:
    the command is the plan but on the compensated axes (columns), where it is the compensated
    command where that does no harm and the planned original where it would
    (fallback.AxisGuard). Adds up every compensated axis' modelled tracking error, before and
    after, over the runs and the settling after each (the residual vibration the compensation
    also reduces, and may trade a little in-motion error for), and a warning for each stretch
    that fell back to ``warnings``. ``lanes``: threads for the axes, which are independent here;
    ``tally``: counts the windows and the fallback's time."""
    guards = {c: AxisGuard(compensator, *errors[c], fallback) for c, compensator in compensators.items()}
    lines = _StretchLines(plan, guards.values())
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

    fallbacks = lanes and lanes.fallback
    for planned, command, moving, follows in _optimized(plan, compensators, lanes and lanes.optimizer, tally):
        held = np.concatenate([held, planned])
        clock = time.perf_counter()
        pushed = _per_axis(fallbacks, lambda c, planned=planned, command=command, moving=moving, follows=follows:
                           guards[c].push(planned[:, c], command[:, c], moving, follows), guards)
        tally.fallback_s += time.perf_counter() - clock
        written = {c: np.concatenate([written[c], pushed[c]]) for c in guards}
        lines.note(min((guard.n for guard in guards.values()), default=np.inf) / plan.sample_rate_hz)
        chunk = ready()
        if len(chunk[0]):
            yield chunk
    clock = time.perf_counter()
    pushed = _per_axis(fallbacks, lambda c: guards[c].finish(), guards)
    tally.fallback_s += time.perf_counter() - clock
    written = {c: np.concatenate([written[c], pushed[c]]) for c in guards}
    lines.note(np.inf)
    for c, guard in guards.items():
        warnings += _fallback_warnings(plan.sample_rate_hz, AXES[c], guard, lines)
    chunk = ready()
    if len(chunk[0]):
        yield chunk


def _optimized(plan: Plan | PlanStream, compensators: dict[int, AxisCompensator],
               lanes: dict[int, ThreadPoolExecutor] | None, tally: Tally):
    """(planned, compensated, moving, follows) chunks of samples, every sample in order, as the
    plan settles them: the compensated command is the plan but on the compensated axes (columns)
    during the runs; ``moving``: the chunk is in a run; ``follows``: it continues the one before
    (not at a rest or a run's start, where the plan may jump). With ``lanes`` (one thread per
    axis, so each axis' pieces are pushed in order), the optimizers work on the next piece of
    the run while the chunk of the last one is written."""
    r = next_sample = 0
    while True:
        plan.wait(lambda r=r: len(plan.runs) > r or plan.done)
        if len(plan.runs) <= r:
            break
        first = plan.runs[r][0]
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

        def pieces(a, r=r):
            """The run's planned samples, a chunk at a time, as the plan settles them."""
            while True:
                plan.wait(lambda a=a: plan.runs[r][1] is not None or plan.frontier >= a + _CHUNK)
                last = plan.runs[r][1]
                stop = min(a + _CHUNK, plan.frontier if last is None else last + 1)
                samples = plan.samples(a, stop)
                plan.release(stop)
                yield samples
                a = stop
                if last is not None and a > last:
                    return

        follows, pending = False, None  # pending: the last piece and its pushes under way
        for planned in itertools.chain(pieces(first), [None]):
            running = None if planned is None else {c: _submit(lanes, c, streams[c].push, planned[:, c],
                                                            _state(compensators[c], planned)) for c in streams}
            if pending is not None:
                planned_rows = np.concatenate([planned_rows, pending[0]])
                commands = {c: np.concatenate([commands[c], pending[1][c].result()]) for c in streams}
                chunk, planned_rows, commands = ready(planned_rows, commands)
                if len(chunk[0]):
                    yield *chunk, True, follows
                    follows = True
            pending = planned, running
        last = plan.runs[r][1]
        # (The optimizer's warnings of limits not met are the fallback's to give: it falls back there.)
        results = _per_axis(lanes, lambda c, streams=streams: streams[c].finish(), streams)
        for c, result in results.items():
            counts = tally.windows.setdefault(c, [0, 0])
            counts[0] += result.windows
            counts[1] += result.qp_windows
        commands = {c: np.concatenate([commands[c], results[c].command_mm]) for c in streams}
        chunk, _, _ = ready(planned_rows, commands)
        yield *chunk, True, follows
        next_sample = last + 1
        r += 1
    if next_sample < plan.n_samples:
        rest = plan.samples(next_sample, plan.n_samples)
        yield rest, rest, False, False


def _state(compensator: AxisCompensator, planned: np.ndarray) -> np.ndarray | None:
    """The column of the planned samples that the axis' varying modes follow (None: fixed modes)."""
    return None if compensator.varying is None else planned[:, compensator.varying.column]


class _Lanes:
    """One thread per compensated axis for its optimizer and one for its fallback: numpy, scipy
    and DAQP release the GIL in their kernels, so the axes, and the optimizers and the writer,
    use both cores. Work given to one lane runs in order."""

    def __init__(self, axes: Iterable[int]):
        self.optimizer = {c: ThreadPoolExecutor(1) for c in axes}
        self.fallback = {c: ThreadPoolExecutor(1) for c in axes}

    def shutdown(self) -> None:
        for lane in [*self.optimizer.values(), *self.fallback.values()]:
            lane.shutdown(cancel_futures=True)


def _submit(lanes: dict[int, ThreadPoolExecutor] | None, c: int, work: Callable, *args) -> Future:
    """``work(*args)`` on axis c's lane, or here and now without lanes."""
    if lanes:
        return lanes[c].submit(work, *args)
    done = Future()
    done.set_result(work(*args))
    return done


def _per_axis(lanes: dict[int, ThreadPoolExecutor] | None, work: Callable[[int], object], axes: Iterable[int]) -> dict:
    """``{c: work(c)}`` for every axis c, each on its lane if given."""
    running = {c: _submit(lanes, c, work, c) for c in axes}
    return {c: future.result() for c, future in running.items()}


class _StretchLines:
    """The program lines moving during the stretches the guards fell back on, found as the
    plan's settled moves ((line, start s, end s), ``plan.moves``) go by; moves are dropped once
    written, and before the start of any stretch still open."""

    def __init__(self, plan: Plan | PlanStream, guards: Iterable[AxisGuard]):
        self.moves, self.guards = plan.moves, list(guards)
        self.fs = plan.sample_rate_hz
        self.found: dict[int, list[int]] = {}  # id(stretch) -> [first line, last line]

    def note(self, written_s: float) -> None:
        """The moves that ended before ``written_s`` (inf: every one) are done with."""
        upto = min([written_s] + [g.open.start / self.fs for g in self.guards if g.open is not None])
        spans = [(s.start / self.fs, (s.stop - 1) / self.fs if s.stop else np.inf, self.found.setdefault(id(s), []))
                 for g in self.guards for s in g.stretches + ([g.open] if g.open is not None else [])]
        moves = self.moves
        while moves and (moves[0][2] < upto or written_s == np.inf):
            line, start_s, end_s = moves.popleft()
            for first_s, last_s, found in spans:
                if start_s <= last_s and end_s >= first_s:
                    if not found:
                        found.append(line)
                    found[1:] = [line]

    def of(self, stretch) -> list[int]:
        return self.found.get(id(stretch), [])


def _fallback_warnings(fs: float, axis: str, guard: AxisGuard, lines: _StretchLines) -> list[str]:
    """One for each stretch where ``guard`` fell back to the planned original, saying when, the
    program lines moving then and why; one more line for those not kept."""
    out = []
    for stretch in guard.stretches:
        moving = lines.of(stretch)
        named = ("" if not moving else f", line {moving[0]}" if moving[0] == moving[-1]
                 else f", lines {moving[0]}-{moving[-1]}")
        kept = f"; {stretch.level:.0%} of the compensation kept" if stretch.level >= 0.005 else ""
        out.append(f"{FALLBACK}: axis {axis}, {stretch.start / fs:.3f}-{(stretch.stop - 1) / fs:.3f} s{named} "
                   f"({' and '.join(sorted(stretch.reasons))}{kept})")
    count, samples = guard.more
    if count:
        out.append(f"{FALLBACK}: axis {axis}, {count} more stretches, {samples / fs:.3f} s in all")
    return out
