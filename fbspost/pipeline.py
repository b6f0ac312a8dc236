"""The whole job on one program: read, plan, compensate, write, report.

Takes an input G-code path, an output path, a machine profile and options; writes the
compensated program atomically (nothing is written if anything fails) and gives a ``Report``
with the predicted tracking error of every compensated axis before and after, per the model.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .atomicfile import atomic_write
from .dynamics import AxisDynamics
from .gcode import AXES, detect_flavor, read_gcode
from .optimizer import AxisCompensator, AxisLimits, FBSSettings
from .planner import plan_blocks
from .profile import MachineProfile
from .trajectory import InputError
from .writer import WriteOptions, format_refusal, write_program


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
        return cls(_rms_um(before_mm), float(np.abs(before_mm).max()) * 1e3,
                   _rms_um(after_mm), float(np.abs(after_mm).max()) * 1e3)


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


def compensate_file(input_path: str | Path, output_path: str | Path, profile: MachineProfile,
                    options: CompensateOptions = CompensateOptions(), progress=None) -> Report:
    """``progress(fraction)`` is called as the axes are compensated (0 to 1), if given."""
    started = time.perf_counter()
    flavor = options.flavor or detect_flavor(input_path)
    refusal = format_refusal(flavor, options.output_format)
    if refusal:  # before the work
        raise InputError(input_path, None, refusal)
    clock = time.perf_counter()
    blocks = list(read_gcode(input_path, flavor))
    stages = {"read": time.perf_counter() - clock}
    clock = time.perf_counter()
    plan = plan_blocks(blocks, profile)
    stages["plan"] = time.perf_counter() - clock
    clock = time.perf_counter()
    period_s = 1.0 / profile.sample_rate_hz
    command = plan.positions_mm.copy()
    report = Report(str(input_path), str(output_path), profile.name, flavor, len(blocks), 0, plan.duration_s, 0.0)
    modelled = [a for a in AXES if a in profile.axes and profile.axes[a].modes]
    total = max(1, sum(last - first + 1 for first, last in plan.runs) * len(modelled))
    done = 0
    for name in modelled:
        column, axis = AXES.index(name), profile.axes[name]
        dynamics = AxisDynamics(axis.modes, period_s)
        compensate = AxisCompensator(dynamics, AxisLimits.from_profile(axis), options.settings, options.lookahead)
        before, after = [], []
        for first, last in plan.runs:
            desired = plan.positions_mm[first:last + 1, column]
            result = compensate(desired)
            command[first:last + 1, column] = result.command_mm
            # The error counts the settling after the run too: the residual vibration the
            # compensation also reduces (and may trade a little in-motion error for).
            hold = np.full(compensate.settings.settle_samples, desired[-1])
            desired = np.concatenate([desired, hold])
            before.append(desired - dynamics.simulate(desired))
            after.append(desired - dynamics.simulate(np.concatenate([result.command_mm, hold])))
            report.warnings += [f"axis {name}, motion starting at {first * period_s:.3f} s: {w}" for w in result.warnings]
            done += last - first + 1
            if progress:
                progress(done / total)
        if before:
            report.axes[name] = AxisReport.from_errors(np.concatenate(before), np.concatenate(after))

    stages["optimize"] = time.perf_counter() - clock
    clock = time.perf_counter()
    write_options = WriteOptions(
        flavor=flavor, output_format=options.output_format, tolerance_mm=options.tolerance_mm,
        min_segment_time_s=options.min_segment_time_s,
        header=(f"fbspost {__version__}: filtered B-spline compensation for machine profile {profile.name}",
                f"fbspost settings: format {options.output_format}, tolerance {options.tolerance_mm:g} mm, "
                f"minimum segment {options.min_segment_time_s * 1e3:g} ms, flavor {flavor}, {options.lookahead} look-ahead"),
        raise_acceleration_mm_s2=_needed_acceleration(command, plan.positions_mm, profile, blocks),
        restore_acceleration_mm_s2=_final_acceleration(profile, blocks))
    stats = []
    atomic_write(output_path, lambda f: stats.append(write_program(blocks, plan, command, write_options, f)))
    stages["write"] = time.perf_counter() - clock
    report.lines_out = stats[0].lines_out
    report.stage_time_s = stages
    report.compute_time_s = time.perf_counter() - started
    return report


def _rms_um(error_mm: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(error_mm)))) * 1e3


def _needed_acceleration(command: np.ndarray, planned: np.ndarray, profile: MachineProfile, blocks) -> float | None:
    """The path acceleration the command reaches (XYZ), at least the planner's, at most the
    largest limit among the compensated axes. None when nothing is compensated."""
    compensated = [i for i, a in enumerate(AXES[:3]) if a in profile.axes and profile.axes[a].modes]
    if not compensated or np.array_equal(command, planned):
        return None
    period_s = 1.0 / profile.sample_rate_hz
    accel = np.linalg.norm(np.diff(command[:, :3], 2, axis=0), axis=1).max(initial=0.0) / period_s**2
    ceiling = max(profile.axes[AXES[i]].max_acceleration_mm_s2 for i in compensated)
    floor = max([profile.planner_acceleration_mm_s2] + [b.limits.acceleration_mm_s2 for b in blocks
                                                        if b.limits is not None and b.limits.acceleration_mm_s2])
    return float(np.ceil(min(max(accel, floor), ceiling)))


def _final_acceleration(profile: MachineProfile, blocks) -> tuple[float, float]:
    """(print, travel) acceleration the program leaves the controller with."""
    accel, travel = profile.planner_acceleration_mm_s2, None
    for block in blocks:
        if block.limits is not None:
            if block.limits.acceleration_mm_s2 is not None:
                accel = block.limits.acceleration_mm_s2
            if block.limits.travel_acceleration_mm_s2 is not None:
                travel = block.limits.travel_acceleration_mm_s2
    return accel, (accel if travel is None else travel)
