"""The whole job on one program: (expand,) read, plan, compensate, write, report.

Takes an input G-code path, an output path, a machine profile and options; a LinuxCNC program
that needs LinuxCNC's interpreter (or any with ``expand=True``) is first expanded by it
(``expand.py``) and the expanded program is compensated; writes the
compensated program atomically (nothing is written if anything fails) and gives a ``Report``
with the predicted tracking error of every compensated axis before and after, per the model;
with ``verify``, both programs as the firmware's planner runs them (verify.py), and the original
written instead where the output is no better there.

Its parts: ``report.py`` (the options, the report, the errors counted), ``reading.py`` (the
blocks read and planned), ``axes.py`` (the compensated axes: optimizer and fallback, on threads),
``processes.py`` (each axis in a process of its own), ``verification.py`` (the check beside the job).
"""
from __future__ import annotations

import queue
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from ..firmware.linuxcnc_time import retimed
from ..firmware.transparency import FirmwareSettings
from ..plan.margins import RunMargins
from ..plan.planner import Plan, PlanStream
from ..profile import MachineProfile, with_travel
from ..read.blocks import AXES, NeedsInterpreter
from ..read.expand import check_remaps, expand
from ..read.flavors import compensated_by, detect_flavor
from ..write.atomicfile import atomic_write
from ..write.options import WriteOptions, format_refusal, shortest_block_s
from ..write.samples import SampleWindow
from ..write.writer import write_program
from .axes import axis_compensators, compensated, compensation_chunks
from .offload import Offloaded
from .planfeed import PlanFeed
from .processes import in_second_process, plan_columns, proxied_chunks, received
from .reading import read_blocks
from .report import AxisReport, CompensateOptions, ExecutedError, Outcome, Report, timed
from .verification import Verification

SHAPING_LEFT_OFF = "input shaping is off after this program"  # (the warning's start)
# On Marlin's whole steps with its merge of short blocks every kept end is rounded to a step on
# the axes but its dominant one: a new error of up to half a step in the modes' band. A block
# nearer the command than a step's share splits into ends that cost more than they follow (the
# Marlin model, printer-two-mode, SD card, RMS contour error through whole steps: the bracket's
# first 2000 lines 5.17 um at 1 um, 4.70 at 8 um; the gear's first 1500 5.73 -> 4.77).
STEP_TOLERANCE_SHARE = 0.64


def compensate_file(input_path: str | Path, output_path: str | Path, profile: MachineProfile,
                    options: CompensateOptions = CompensateOptions(), progress=None) -> Report:  # noqa: B008
    """``progress(fraction)`` is called as the program is read (0 to 1), if given.

    Streams: the program is read once; its blocks are planned, compensated and written a
    stretch at a time, so memory holds the planner's, the optimizers' and the writer's
    look-ahead, however long the program is.
    """
    started = time.perf_counter()
    bytes_in = Path(input_path).stat().st_size  # (before an in-place output replaces it)
    header = compensated_by(input_path)
    if header:  # compensated twice, the motion would be wrong and the summary would still show a gain
        raise InputError(input_path, header[0], f"already compensated ({header[1]}): compensate the original instead")
    flavor, flavor_note = _flavor(input_path, profile, options)
    profile = with_travel(profile, flavor)
    refusal = format_refusal(flavor, options.output_format)
    if refusal:  # before the work
        raise InputError(input_path, None, refusal)
    if flavor == "linuxcnc" and options.ini:
        check_remaps(input_path, options.ini)
    if flavor == "linuxcnc" and options.expand:
        report = _compensate_expanded(input_path, output_path, profile, options, "--expand given", progress, started)
    else:
        try:
            report = _compensate(input_path, input_path, output_path, profile, options, flavor, progress, started)
        except NeedsInterpreter as exc:
            if flavor != "linuxcnc" or options.expand is not None:
                raise
            reason = f"line {exc.line} uses {exc.feature}"
            report = _compensate_expanded(input_path, output_path, profile, options, reason, progress, started)
    if flavor_note:
        report.warnings.insert(0, flavor_note)
    report.bytes_in, report.bytes_out = bytes_in, Path(output_path).stat().st_size
    return report


def _flavor(input_path, profile: MachineProfile, options: CompensateOptions) -> tuple[str, str | None]:
    """The flavor to read and write as (``--flavor``, else the profile's firmware, else the file's
    hints), and a note where the profile's firmware and the file's hints disagree (a Klipper
    printer's file sliced as Marlin: written as Marlin, Klipper would ignore M593 and shape twice)."""
    if options.flavor:
        return options.flavor, None
    hinted = detect_flavor(input_path)
    machine = profile.firmware.flavor
    if machine is None:
        return hinted, None
    if machine == hinted:
        return machine, None
    return machine, (f"written for {machine}, the profile's [firmware] flavor; the file's hints say {hinted} "
                     "(as sliced?): --flavor chooses otherwise")


def _compensate_expanded(input_path, output_path, profile, options, reason, progress, started) -> Report:
    """Expands the program with rs274, then compensates the expanded program; its errors name
    the expanded program's line."""
    with tempfile.TemporaryDirectory(prefix="fbspost-expand-") as work:
        expanded = Path(work) / (Path(input_path).stem + ".expanded.ngc")
        expand(input_path, expanded, reason, options.tool_table, options.ini)
        try:
            report = _compensate(expanded, input_path, output_path, profile, options, "linuxcnc", progress, started)
        except InputError as exc:
            where = re.match(re.escape(str(expanded)) + r":(\d+): (.*)", str(exc), re.DOTALL)
            if where is None:
                raise
            raise InputError(input_path, None, f"line {where.group(1)} of its expansion: {where.group(2)}") from None
    report.warnings.insert(0, f"expanded by LinuxCNC's interpreter rs274 ({reason})")
    return report


def _compensate(read_path, input_path, output_path, profile, options, flavor, progress, started) -> Report:
    """Compensates the program at ``read_path`` (``input_path`` itself or its expansion)."""
    stages = dict.fromkeys(("read", "plan", "optimize", "fallback", "write"), 0.0)
    verification = Verification(read_path, input_path, profile, flavor, options.verify, stages)
    blocks = read_blocks(read_path, flavor, profile, stages, progress)
    margins = RunMargins.for_profile(profile, options.lead_time_s, options.settle_time_s, flavor)
    if flavor == "linuxcnc":  # the original's time as LinuxCNC runs it
        blocks = retimed(blocks, read_path, profile, verification.line_times(), margins.lead_s + margins.settle_s)
    plan = verification.plan = PlanStream(blocks, profile, margins=margins, firmware=flavor)
    compensators = axis_compensators(profile, options)
    follows_plan = np.array([c not in compensators for c in range(len(AXES))])
    elsewhere = bool(compensators) and in_second_process(read_path, options)
    if elsewhere:  # a process per axis, sent the plan made here
        requests: queue.Queue = queue.Queue()
        feed = PlanFeed(plan, {c: plan_columns(c, compensator) for c, compensator in compensators.items()})
        workers = {c: Offloaded(proxied_chunks, profile, options, c, feed.columns[c], requests=requests, key=c,
                                start=False) for c in compensators}
        for worker in workers.values():
            worker.start()
        chunks = received(workers, feed, requests)
    else:
        outcome = Outcome.of(compensators)
        chunks = compensation_chunks(plan, compensators, options, outcome)
    verification.start()

    def shared_s() -> float:
        """The plan's evaluation and sending to the axes' processes: part of its stage."""
        return feed.time_s if elsewhere else 0.0

    chunks = timed(chunks, stages, "optimize", exclude=lambda: plan.time_s + shared_s())
    write_options = _write_options(profile, options, flavor)
    stats = []
    executed = ExecutedError(compensators, plan.runs)
    clock = time.perf_counter()
    try:
        atomic_write(output_path, lambda f: stats.append(write_program(
            plan, SampleWindow(chunks, plan, follows_plan), write_options, verification.announced(f), executed)),
            verification if verification.wanted else None, verification.opened)
        # The writer stops once it has every sample; the compensation's end (its time, the
        # axes' processes' outcomes) comes after its last chunk.
        for _ in chunks:
            raise RuntimeError("compensated samples after the plan's end")
    finally:
        verification.close()
        if elsewhere:
            for worker in workers.values():
                worker.close()
    if elsewhere:
        outcome = Outcome.joined([worker.value for worker in workers.values()])
    stages["plan"] = plan.time_s + shared_s() - stages["read"]
    # (optimize: the writer's wait for the chunks; the work's own time follows)
    stages["write"] = (time.perf_counter() - clock - plan.time_s - shared_s() - stages["optimize"]
                       - stages.get("verify", 0.0))
    stages["optimize"] = outcome.optimize_s - outcome.tally.fallback_s
    stages["fallback"] = outcome.tally.fallback_s
    written = stats[0]
    report = Report(str(input_path), str(output_path), profile.name, flavor, plan.n_blocks, written.lines_out,
                    plan.duration_s, 0.0, plan.added_s, plan.margins.lead_s, plan.margins.settle_s,
                    travel_saved_s=plan.travel_saved_s, warnings=plan.warnings + outcome.warnings, stage_time_s=stages,
                    max_line_rate_hz=written.max_line_rate_hz, line_rate_budget_hz=profile.firmware.max_line_rate_hz,
                    tolerance_used_mm=written.max_deviation_mm, tolerance_used_at_s=written.max_deviation_s,
                    loosened_s=written.loosened_s, rms_deviation_mm=written.rms_deviation_mm)
    report.verified = verification.verdict
    report.original_kept = verification.original_kept
    if report.original_kept:
        report.lines_out = report.lines_in  # (the original, line for line)
    report.warnings.extend(verification.warnings + _shaping_left_off(written, report.original_kept))
    for c, (before, after) in outcome.errors.items():
        windows = outcome.tally.windows.get(c, (0, 0))
        if before.count and c in executed.stats:
            report.axes[AXES[c]] = executed.report(c, *windows, after)
        elif before.count:
            report.axes[AXES[c]] = AxisReport.from_stats(before, after, *windows)
    report.compute_time_s = time.perf_counter() - started
    return report


def _write_options(profile: MachineProfile, options: CompensateOptions, flavor: str) -> WriteOptions:
    """The writer's settings: the options', the firmware's (its shortest block, its line rate,
    Marlin's steps) and the output's header."""
    min_segment_s = max(options.min_segment_time_s, shortest_block_s(profile, flavor))
    tolerance_mm = max(options.tolerance_mm, step_tolerance_mm(profile, flavor, options.output_format))
    return WriteOptions(
        flavor=flavor,
        output_format=options.output_format,
        tolerance_mm=tolerance_mm,
        min_segment_time_s=min_segment_s,
        header=(
            f"fbspost {__version__}: filtered B-spline compensation for machine profile {profile.name}",
            f"fbspost settings: format {options.output_format}, tolerance {tolerance_mm:g} mm, "
            f"minimum segment {min_segment_s * 1e3:g} ms, flavor {flavor}, {options.lookahead} look-ahead",
        ),
        firmware=FirmwareSettings.from_profile(profile),
        max_line_rate_hz=profile.firmware.max_line_rate_hz,
        **firmware_steps(profile, flavor),
    )


def _shaping_left_off(written, original_kept: bool) -> list[str]:
    """The warning where the output leaves input shaping off (every later print would run unshaped)."""
    if not written.shaping_left_off or original_kept:
        return []
    return [f"{SHAPING_LEFT_OFF} on {' and '.join(written.shaping_left_off)}: neither the profile nor the program "
            "says what it was. Give it in the profile's [firmware] shaper_frequency (Klipper: fbspost identify "
            "--klipper-cfg printer.cfg --merge PROFILE -o PROFILE reads [input_shaper])"]


def compensated_samples(plan: Plan, profile: MachineProfile, options: CompensateOptions = CompensateOptions(),  # noqa: B008
                        warnings: list[str] | None = None) -> np.ndarray:
    """The command for every sample of ``plan`` at once (n_samples, 4), as ``compensate_file``
    computes it (for programs that fit in memory); the optimizers' warnings added to ``warnings``."""
    compensators = axis_compensators(profile, options)
    outcome = Outcome.of(compensators)
    chunks = compensated(plan, compensators, outcome.errors, [] if warnings is None else warnings, options.fallback,
                          None, outcome.tally)
    return np.concatenate([command for _, command in chunks] or [np.zeros((0, len(AXES)))])


def step_tolerance_mm(profile: MachineProfile, flavor: str, output_format: str = "dense") -> float:
    """The least tolerance of Marlin's dense blocks on its whole steps with its merge of short
    blocks (``writer``: their ends on the lattice): ``STEP_TOLERANCE_SHARE`` of X's or Y's
    step, the larger (0 elsewhere)."""
    steps = profile.firmware.steps_per_mm
    xy = [steps[a] for a in "XY" if steps and steps.get(a, 0.0) > 0.0]
    if flavor != "marlin" or output_format != "dense" or profile.firmware.min_steps_per_segment <= 1 or not xy:
        return 0.0
    return STEP_TOLERANCE_SHARE / min(xy)


def firmware_steps(profile: MachineProfile, flavor: str) -> dict:
    """The writer's options for the firmware's whole steps (steps per mm X Y Z E, 0 where the
    profile does not give them): Marlin's, with its merge of short blocks; RepRapFirmware's, each
    end written in the cell of its step (``WriteOptions.step_cells``); none for other flavors
    or without steps."""
    steps = profile.firmware.steps_per_mm
    if flavor not in ("marlin", "reprap") or not steps:
        return {}
    merge = {"min_steps_per_segment": profile.firmware.min_steps_per_segment} if flavor == "marlin" else \
        {"step_cells": True}
    return {"steps_per_mm": tuple(steps.get(a, 0.0) for a in AXES), **merge,
            "axis_modes": tuple(tuple(profile.axes[a].modes) if a in profile.axes else () for a in "XYZ")}
