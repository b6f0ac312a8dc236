"""The whole job on one program: (expand,) read, plan, compensate, write, report.

Takes an input G-code path, an output path, a machine profile and options; a LinuxCNC program
that needs LinuxCNC's interpreter (or any with ``expand=True``) is first expanded by it
(``expand.py``) and the expanded program is compensated; writes the
compensated program atomically (nothing is written if anything fails) and gives a ``Report``
with the predicted tracking error of every compensated axis before and after, per the model;
with ``verify``, both programs as the firmware's planner runs them (verify.py), and the original
written instead where the output is no better there.
"""
from __future__ import annotations

import itertools
import math
import queue
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from ..fbs.dynamics import AxisDynamics, ModelSet
from ..fbs.fallback import FALLBACK, AxisGuard
from ..fbs.optimizer import AxisCompensator
from ..fbs.settings import AxisLimits, FBSSettings
from ..fbs.smoothing import half_width_samples
from ..fbs.varying import LoadModes, PositionModes
from ..firmware.linuxcnc_time import retimed
from ..firmware.transparency import FirmwareSettings
from ..firmware.verify import Verdict, measured_beside
from ..plan.planner import BATCH_BLOCKS, Plan, PlanStream, RunMargins
from ..profile import AxisProfile, MachineProfile, with_travel
from ..read.expand import check_remaps, expand
from ..read.gcode import AXES, Block, NeedsInterpreter, compensated_by, detect_flavor, read_gcode
from ..write.atomicfile import atomic_write
from ..write.writer import SampleWindow, WriteOptions, format_refusal, shortest_block_s, write_program
from .offload import Offloaded
from .planfeed import PlanFeed, PlanProxy


@dataclass(frozen=True)
class CompensateOptions:
    flavor: str | None = None  # detected from the file when None
    output_format: str = "dense"  # dense | g5 (see writer)
    tolerance_mm: float = 1e-3
    min_segment_time_s: float = 1e-3
    lookahead: str = "limited"
    # With a settle margin after every run, the error after a stop weighs 5 times the error in
    # motion: the butterfly's residual vibration falls below every input shaper's, for a few um
    # of RMS during the motion (0.5, the optimizer's own default, leaves 3 times the 2-hump EI's).
    settings: FBSSettings = FBSSettings(settle_weight=5.0)
    lead_time_s: float | None = None  # the command may move this long before each run (None: from the dynamics)
    settle_time_s: float | None = None  # ... and after it
    fallback: bool = True  # blend to the planned original where compensating would do harm
    expand: bool | None = None  # LinuxCNC: through rs274 first (None: when the program needs it)
    tool_table: Path | None = None  # rs274's tool table (tool length offsets, cutter radii)
    ini: Path | None = None  # rs274's INI (subroutine paths)
    parallel_axes: bool = True  # each compensated axis on its own threads (same output, bit for bit)
    # Each compensated axis' optimizer and fallback in a process of its own, beside the writer, which
    # plans for them (same output, bit for bit); None: for long programs (_in_second_process), with
    # parallel_axes
    second_process: bool | None = None
    # Re-plan both programs on the firmware's planner before committing (verify.py); None: for
    # the firmware whose planner differs from the blocks as written (not Klipper's), at any length.
    verify: bool | None = False


@dataclass
class AxisReport:
    """Modelled tracking error (desired minus modelled actual position) of one axis, over every
    run of motion and the settling after it, for the planned original and (after) for the written
    program as the firmware runs it (``ExecutedError``; for the command itself where the output
    has no such axis: a Z with modes)."""

    rms_error_before_um: float
    max_error_before_um: float
    rms_error_after_um: float
    max_error_after_um: float
    windows: int = 0  # the optimizer's windows
    qp_windows: int = 0  # those whose optimum without the limits broke one (the QP solved)
    rms_error_command_um: float | None = None  # the compensated command's own (a prediction; after: the written blocks)
    max_error_command_um: float | None = None

    @classmethod
    def from_errors(cls, before_mm: np.ndarray, after_mm: np.ndarray) -> AxisReport:
        """From the modelled tracking error of the original and of the compensated command."""
        before, after = _ErrorStats(), _ErrorStats()
        before.add(before_mm)
        after.add(after_mm)
        return cls.from_stats(before, after)

    @classmethod
    def from_stats(cls, before: _ErrorStats, after: _ErrorStats, windows: int = 0, qp_windows: int = 0) -> AxisReport:
        return cls(before.rms_um, before.peak_um, after.rms_um, after.peak_um, windows, qp_windows)


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
    added_time_s: float = 0.0  # the lead and settle margins given to the runs of motion (in print_time_s)
    lead_time_s: float = 0.0  # per run, at most (planner.RunMargins: for Klipper, less by the run's end)
    settle_time_s: float = 0.0
    travel_saved_s: float = 0.0  # less by the travels planned faster (planner.RunMargins.travel_share), about
    axes: dict[str, AxisReport] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    max_line_rate_hz: float = 0.0  # the most lines sent in any second (comments not counted)
    line_rate_budget_hz: float | None = None  # the profile's
    tolerance_used_mm: float = 0.0  # the largest distance of the written blocks from the command
    tolerance_used_at_s: float = 0.0  # where
    rms_deviation_mm: float = 0.0  # of the written blocks from the command, over the samples inside them
    loosened_s: float = 0.0  # time in blocks beyond the tolerance (for the line rate, Marlin's merge)
    stage_time_s: dict[str, float] = field(default_factory=dict)  # read, plan, optimize, fallback, write (, verify)
    verified: Verdict | None = None  # with --verify: both programs as the firmware's planner runs them
    original_kept: bool = False  # --verify found the output no better there: the original was written
    bytes_in: int = 0  # the files' sizes
    bytes_out: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


SHAPING_LEFT_OFF = "input shaping is off after this program"  # (the warning's start)
# On Marlin's whole steps with its merge of short blocks every kept end is rounded to a step on
# the axes but its dominant one: a new error of up to half a step in the modes' band. A block
# nearer the command than a step's share splits into ends that cost more than they follow (the
# Marlin model, printer-two-mode, SD card, RMS contour error through whole steps: the bracket's
# first 2000 lines 5.17 um at 1 um, 4.70 at 8 um; the gear's first 1500 5.73 -> 4.77).
STEP_TOLERANCE_SHARE = 0.64
_CHUNK = 1 << 14  # samples planned, compensated and written at once
_SECOND_PROCESS_BYTES = 256_000  # (a second process starts in about 0.5 s: a program this long takes 5 s)
_EXECUTED_BATCH = 1 << 14  # samples (ExecutedError)
_ANNOUNCE_BYTES = 1 << 20  # of the output written, told the check's process at once (a few hundred ms of writing)
# Chunks of the original the check (LinuxCNC: their line times) may be ahead of the feeds that
# need them: 64 chunks of 50,000 lines, at most about 26 MB held here
_CHECK_AHEAD = 64
_POLL_S = 0.002  # how often the writer, waiting for an axis' process, answers the others' requests


def compensate_file(input_path: str | Path, output_path: str | Path, profile: MachineProfile,
                    options: CompensateOptions = CompensateOptions(), progress=None) -> Report:
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
    verification = _Verification(read_path, input_path, profile, flavor, options.verify, stages)
    blocks = _read(read_path, flavor, profile, stages, progress)
    if flavor == "linuxcnc":  # the original's time as LinuxCNC runs it
        blocks = retimed(blocks, read_path, profile, verification.line_times())
    plan = verification.plan = _plan_stream(blocks, profile, options, flavor)
    compensators = _compensators(profile, options)
    follows_plan = np.array([c not in compensators for c in range(len(AXES))])
    elsewhere = bool(compensators) and _in_second_process(read_path, options)
    if elsewhere:  # a process per axis, sent the plan made here
        requests: queue.Queue = queue.Queue()
        feed = PlanFeed(plan, {c: _columns(c, compensator) for c, compensator in compensators.items()})
        workers = {c: Offloaded(_proxied_chunks, profile, options, c, feed.columns[c], requests=requests, key=c,
                                start=False) for c in compensators}
        for worker in workers.values():
            worker.start()
        chunks = _received(workers, feed, requests)
    else:
        outcome = _Outcome.of(compensators)
        chunks = _compensation_chunks(plan, compensators, options, outcome)
    verification.start()

    def shared_s() -> float:
        """The plan's evaluation and sending to the axes' processes: part of its stage."""
        return feed.time_s if elsewhere else 0.0

    chunks = _timed(chunks, stages, "optimize", exclude=lambda: plan.time_s + shared_s())
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
        outcome = _Outcome.joined([worker.value for worker in workers.values()])
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
        **marlin_steps(profile, flavor),
    )


def _shaping_left_off(written, original_kept: bool) -> list[str]:
    """The warning where the output leaves input shaping off (every later print would run unshaped)."""
    if not written.shaping_left_off or original_kept:
        return []
    return [f"{SHAPING_LEFT_OFF} on {' and '.join(written.shaping_left_off)}: neither the profile nor the program "
            "says what it was. Give it in the profile's [firmware] shaper_frequency (Klipper: fbspost identify "
            "--klipper-cfg printer.cfg --merge PROFILE -o PROFILE reads [input_shaper])"]


def _plan_stream(blocks: Iterable[Block], profile: MachineProfile, options: CompensateOptions,
                 flavor: str) -> PlanStream:
    margins = RunMargins.for_profile(profile, options.lead_time_s, options.settle_time_s, flavor)
    return PlanStream(blocks, profile, margins=margins, firmware=flavor)


def _in_second_process(read_path, options: CompensateOptions) -> bool:
    """Whether each compensated axis runs in a process of its own (``second_process``; None:
    for a program long enough that the processes' start pays)."""
    if options.second_process is not None:
        return options.second_process
    return options.parallel_axes and Path(read_path).stat().st_size >= _SECOND_PROCESS_BYTES


@dataclass
class _Outcome:
    """What compensating a program counts besides its chunks: per compensated axis (column) the
    modelled errors before and after (``AxisGuard``), the optimizers' and fallbacks' warnings,
    their windows and time, and the time of the whole (optimize and fallback, s)."""

    errors: dict[int, tuple[_ErrorStats, _ErrorStats]]
    warnings: list[str] = field(default_factory=list)
    tally: _Tally = field(default_factory=lambda: _Tally())
    optimize_s: float = 0.0

    @classmethod
    def of(cls, compensators: dict[int, AxisCompensator]) -> _Outcome:
        return cls({c: (_ErrorStats(), _ErrorStats()) for c in compensators})

    @classmethod
    def joined(cls, outcomes: list[_Outcome]) -> _Outcome:
        """The outcomes of the axes compensated apart, in their order (the times: the longest)."""
        return cls({c: e for o in outcomes for c, e in o.errors.items()}, [w for o in outcomes for w in o.warnings],
                   _Tally(max(o.tally.fallback_s for o in outcomes),
                          {c: n for o in outcomes for c, n in o.tally.windows.items()}),
                   max(o.optimize_s for o in outcomes))


def _compensation_chunks(plan: PlanStream, compensators: dict[int, AxisCompensator], options: CompensateOptions,
                         outcome: _Outcome) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``_compensated``'s chunks of ``plan``, on threads per axis if ``parallel_axes``;
    ``outcome`` counts the rest."""
    lanes = _Lanes(compensators) if options.parallel_axes else None
    stages = {"work": 0.0}
    try:
        yield from _timed(_compensated(plan, compensators, outcome.errors, outcome.warnings, options.fallback,
                                       lanes, outcome.tally), stages, "work", exclude=lambda: plan.time_s)
    finally:
        if lanes:
            lanes.shutdown()
    outcome.optimize_s = stages["work"]


def _columns(c: int, compensator: AxisCompensator) -> list[int]:
    """The planned samples' columns that compensating column ``c`` uses: its own, and the one its
    varying modes follow."""
    varying = compensator.varying
    return [c] if varying is None or varying.column == c else [c, varying.column]


def _proxied_chunks(channel, profile: MachineProfile, options: CompensateOptions, axis: int,
                    columns: list[int]) -> Iterator[np.ndarray]:
    """In a process of its own (offload.py): the command of ``axis`` (a column), the only one
    compensated, in ``_compensation_chunks``' chunks of the plan that the writer's process sends
    (``PlanFeed``, the samples of ``columns``). Returns the ``_Outcome``."""
    plan = PlanProxy(channel, profile.sample_rate_hz, columns)
    compensators = {axis: _compensators(profile, options)[axis]}
    outcome = _Outcome.of(compensators)
    # (one axis: threads would only hand the interpreter lock back and forth)
    for _, command in _compensation_chunks(plan, compensators, replace(options, parallel_axes=False), outcome):
        yield command[:, axis].copy()
    return outcome


def _received(workers: dict[int, Offloaded], feed: PlanFeed,
              requests: queue.Queue) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The planned samples and the axes' processes' commands (``workers``: by column) joined,
    as far as every one has given them; the processes' ``requests`` for more of the plan are
    answered meanwhile (``PlanFeed.due``: not far ahead of the writer, unless it waits for that
    process: the other may not run on ahead meanwhile, or the plan held here would grow with the
    program)."""
    held = {c: np.zeros(0) for c in workers}  # each axis' command
    asked: list[int] = []  # requests not yet answered

    def command_of(c: int) -> np.ndarray:
        waiting = False
        while True:
            while not requests.empty():
                asked.append(requests.get())
            for key in [key for key in asked if (waiting and key == c) or feed.due(key)]:
                asked.remove(key)
                feed.answer(key, workers[key].send)
            try:
                return workers[c].get(timeout=_POLL_S if waiting else 0.0)
            except queue.Empty:
                waiting = True
            except StopIteration:
                return np.zeros(0)

    while True:
        for c in workers:
            if not len(held[c]):
                held[c] = command_of(c)
        n = min(len(column) for column in held.values())
        if not n:
            if any(len(column) for column in held.values()):
                raise RuntimeError("the axes' processes gave different samples")
            return
        planned = feed.take(n)
        command = planned.copy()
        for c, column in held.items():
            command[:, c], held[c] = column[:n], column[n:]
        yield planned, command


class _Verification:
    """``atomic_write``'s check for ``CompensateOptions.verify`` (verify.py): the written file and
    the program read (``read_path``) re-planned on the firmware's planner, in a process of its own
    beside the compensation (``verify.measured_beside``: the original measured at once, the output
    as it is written); where the output is no better there, the input (``input_path``) copied over
    the written file. The wait for its verdict goes to ``stages["verify"]``."""

    def __init__(self, read_path, input_path, profile: MachineProfile, flavor: str, option: bool | None,
                 stages: dict[str, float]):
        self.read_path, self.input_path, self.profile, self.flavor = read_path, input_path, profile, flavor
        self.stages = stages
        self.plan: PlanStream | None = None  # (its margins: the time fbspost added)
        self.failed: Exception | None = None
        self.auto = option is None and flavor != "klipper"
        self.wanted = bool(option) or self.auto
        self.verdict: Verdict | None = None
        self.warnings: list[str] = []
        self.worker: Offloaded | None = None
        self.written: _Announced | None = None
        if self.wanted:  # (forked here, before the axes' processes and any thread: see Offloaded.start)
            self.worker = Offloaded(measured_beside, read_path, profile, flavor, requests=queue.Queue(), start=False,
                                    ahead=_CHECK_AHEAD)

    @property
    def original_kept(self) -> bool:
        return self.verdict is not None and not self.verdict.better

    def start(self) -> None:
        if self.worker is not None:
            self.worker.start()

    def line_times(self) -> Iterator[np.ndarray]:
        """For LinuxCNC, the check's plan of the original (``verify.measure``'s items) as it comes;
        none once the check failed (it says so in its verdict's place)."""
        while self.worker is not None and self.failed is None:
            try:
                yield self.worker.get()
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 (as in __call__)
                self.failed = exc

    def opened(self, written: Path) -> None:
        """The output's temporary file, made: its name to the check's process."""
        self.written = _Announced(written, None if self.worker is None else self.worker.send)

    def announced(self, f):
        """``f``, the output's temporary file, telling the check's process how much of it is written."""
        self.written.file = f
        return self.written if self.worker is not None else f

    def __call__(self, written: Path) -> None:
        started_s = time.perf_counter()
        self.worker.send((str(written), self.written.size, True))  # (written and closed)
        try:
            for _ in self.worker:  # (LinuxCNC: the plan of the original's chunks past what the feeds needed)
                pass
        except Exception as exc:  # noqa: BLE001 (a model's gap must not cost the user the output)
            self.failed = exc
        measured = self.worker.value
        if self.failed is not None:
            self.warnings.append(f"not verified on the firmware's planner: its model failed "
                                 f"({type(self.failed).__name__}: {' '.join(str(self.failed).split())})")
        elif measured is not None:
            self.verdict = Verdict(self.flavor, *measured, self.plan.added_s)
        if self.original_kept:
            shutil.copyfile(self.input_path, written)
            self.warnings.append("the original was written unchanged: the output is no better on the firmware "
                                 "(the verified line)")
        self.stages["verify"] = time.perf_counter() - started_s

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()


class _Announced:
    """The output's binary file, whose length written (flushed) is sent to the check's process
    (``send((path, bytes, False))``) every ``_ANNOUNCE_BYTES`` (its end: ``_Verification``)."""

    def __init__(self, path: Path, send: Callable | None):
        self.path, self.send, self.file = str(path), send, None
        self.size = self._told = 0

    def write(self, data: bytes) -> int:
        n = self.file.write(data)
        self.size += n
        if self.size - self._told >= _ANNOUNCE_BYTES:
            self.file.flush()
            self.send((self.path, self.size, False))
            self._told = self.size
        return n


def compensated_samples(plan: Plan, profile: MachineProfile, options: CompensateOptions = CompensateOptions(),
                        warnings: list[str] | None = None) -> np.ndarray:
    """The command for every sample of ``plan`` at once (n_samples, 4), as ``compensate_file``
    computes it (for programs that fit in memory); the optimizers' warnings added to ``warnings``."""
    compensators = _compensators(profile, options)
    outcome = _Outcome.of(compensators)
    chunks = _compensated(plan, compensators, outcome.errors, [] if warnings is None else warnings, options.fallback,
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


def marlin_steps(profile: MachineProfile, flavor: str) -> dict:
    """The writer's options for Marlin's merge of short blocks (steps per mm X Y Z E, 0 where the
    profile does not give them), none for other flavors or without steps."""
    steps = profile.firmware.steps_per_mm
    if flavor != "marlin" or not steps:
        return {}
    return {"steps_per_mm": tuple(steps.get(a, 0.0) for a in AXES),
            "min_steps_per_segment": profile.firmware.min_steps_per_segment,
            "axis_modes": tuple(tuple(profile.axes[a].modes) if a in profile.axes else () for a in "XYZ")}


def _compensators(profile: MachineProfile, options: CompensateOptions) -> dict[int, AxisCompensator]:
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


def varying_modes(profile: MachineProfile, axis: AxisProfile) -> LoadModes | PositionModes | None:
    """The axis' modes against the filament printed, if it carries the print (``moving_mass``),
    or against an axis' position (``modes_by_position``); None if they are fixed."""
    table = axis.modes_by_position
    if table is not None:
        return PositionModes(axis.modes, 1.0 / profile.sample_rate_hz, AXES.index(table.axis), table.positions_mm,
                             table.frequency_scales)
    if axis.moving_mass_kg is None:
        return None
    filament_mm2 = math.pi * (0.5 * profile.firmware.filament_diameter_mm) ** 2
    return LoadModes(axis.modes, 1.0 / profile.sample_rate_hz, axis.moving_mass_kg,
                     filament_mm2 * axis.filament_density_g_cm3 * 1e-3)


def _compensated(plan: Plan | PlanStream, compensators: dict[int, AxisCompensator], errors: dict,
                 warnings: list[str], fallback: bool, lanes: _Lanes | None,
                 tally: _Tally) -> Iterator[tuple[np.ndarray, np.ndarray]]:
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
               lanes: dict[int, ThreadPoolExecutor] | None, tally: _Tally):
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


@dataclass
class _Tally:
    """Counted as the work goes: the fallback's wall time, and per axis (column) the optimizer's
    windows and those that needed the QP."""

    fallback_s: float = 0.0
    windows: dict[int, list[int]] = field(default_factory=dict)


@dataclass
class _ErrorStats:
    """Running RMS and largest magnitude of an error given in pieces (mm)."""

    sum_squares_mm2: float = 0.0
    count: int = 0
    peak_mm: float = 0.0

    def add(self, error_mm: np.ndarray) -> None:
        if error_mm.size:
            # (np.dot: BLAS threads, far slower here)
            self.sum_squares_mm2 += float(np.einsum("i,i->", error_mm, error_mm))
            self.count += error_mm.size
            self.peak_mm = max(self.peak_mm, float(np.abs(error_mm).max()))

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(self.sum_squares_mm2 / max(self.count, 1))) * 1e3

    @property
    def peak_um(self) -> float:
        return self.peak_mm * 1e3


class ExecutedError:
    """The modelled tracking error of the written program as the firmware runs it: its blocks
    straight at constant speed between their ends (what the firmware plans with the settings the
    writer emits: tests/test_output_klipper.py against klippy), the plan where the program rests,
    through each compensated axis' modes; and of the planned original, on the same samples: every
    run's and the settling after it (``settle_samples``), as the optimizer's report counts them.

    The writer gives it the executed positions (X Y Z) sample by sample in order (``add``), and
    the rest to the program's end (``finish``). They are modelled ``_EXECUTED_BATCH`` samples
    at a time: the writer gives a few hundred at once, and the filters' calls cost more than
    their work."""

    def __init__(self, compensators: dict[int, AxisCompensator], runs: list):
        self.axes = [c for c in compensators if c < 3]
        self.runs = runs
        self.models = {c: compensators[c].dynamics for c in self.axes}
        self.settle = {c: compensators[c].settings.settle_samples for c in self.axes}
        self.stats = {c: (_ErrorStats(), _ErrorStats()) for c in self.axes}
        self.steps: dict | None = None  # per axis: the modelled original's and the executed program's
        self.last_planned_mm = None  # the last sample's
        self.next = 0  # the next sample
        self.run = 0  # the first run whose settling may include it
        self._held: list[tuple[np.ndarray, np.ndarray]] = []  # (executed, planned) given, not yet modelled
        self._modelled = 0  # samples

    def add(self, first: int, executed_mm: np.ndarray, planned_mm: np.ndarray) -> None:
        """Samples ``first`` on: the executed and the planned positions (rows X Y Z ...)."""
        if first != self.next:
            raise ValueError(f"samples from {first} given, {self.next} expected")
        if len(planned_mm):
            self._held.append((executed_mm[:, :3], planned_mm[:, :3]))
            self.next = first + len(planned_mm)
            if self.next - self._modelled >= _EXECUTED_BATCH:
                self._model_held()

    def _model_held(self) -> None:
        if not self._held:
            return
        first = self._modelled
        executed_mm, planned_mm = (np.concatenate(column) for column in zip(*self._held, strict=True))
        self._held, self._modelled = [], self.next
        n = len(planned_mm)
        # A jump (G28, a move from an unknown position: motion fbspost does not model) starts
        # both models anew at rest where it lands: its error is not the program's.
        restarts = set(self._jumps(first, planned_mm)) | ({0} if self.steps is None else set())
        for a, b in itertools.pairwise(sorted(restarts | {0, n})):
            if a in restarts:
                self.steps = {c: (m.response(planned_mm[a, c]), m.response(executed_mm[a, c]))
                              for c, m in self.models.items()}
            self._count(first + a, executed_mm[a:b], planned_mm[a:b])
        self.last_planned_mm = planned_mm[-1]
        longest = max(self.settle.values(), default=0)
        while self.run < len(self.runs) and self.runs[self.run][1] is not None and \
                self.runs[self.run][1] + longest < self._modelled:
            self.run += 1  # its settling is over on every axis

    def _count(self, first: int, executed_mm: np.ndarray, planned_mm: np.ndarray) -> None:
        for c in self.axes:
            counted = self._counted(first, len(planned_mm), self.settle[c])
            original, written = self.steps[c]
            before, after = self.stats[c]
            before.add((planned_mm[:, c] - original(planned_mm[:, c]))[counted])
            after.add((planned_mm[:, c] - written(executed_mm[:, c]))[counted])

    def _jumps(self, first: int, planned_mm: np.ndarray) -> list[int]:
        """Where in the samples from ``first`` the plan jumps: the sample after a run's last
        (runs start and end at rest) that is not where that last one is on a compensated axis
        (Z alone moves between runs at layer changes: the ringing of X Y goes on)."""
        jumps = []
        for _, last in itertools.islice(self.runs, self.run, None):
            if last is None or last + 1 >= first + len(planned_mm):
                break
            i = last + 1 - first
            if i >= 0:
                before = planned_mm[i - 1] if i else self.last_planned_mm
                if before is not None and (planned_mm[i, self.axes] != before[self.axes]).any():
                    jumps.append(i)
        return jumps

    def finish(self, end_mm: np.ndarray) -> None:
        """The settling after the program's end (``end_mm``, X Y Z), at rest there."""
        rest = np.repeat(end_mm[None, :3], max(self.settle.values(), default=0), axis=0)
        self.add(self.next, rest, rest)
        self._model_held()

    def _counted(self, first: int, n: int, settle: int) -> np.ndarray:
        """Which of samples first .. first + n - 1 lie in a run or ``settle`` samples after it."""
        k = np.arange(first, first + n)
        counted = np.zeros(n, dtype=bool)
        for start, last in itertools.islice(self.runs, self.run, None):
            if start >= first + n:
                break
            counted |= (k >= start) & (k <= (math.inf if last is None else last + settle))
        return counted

    def report(self, c: int, windows: int, qp_windows: int, command_after: _ErrorStats) -> AxisReport:
        return replace(AxisReport.from_stats(*self.stats[c], windows, qp_windows),
                       rms_error_command_um=command_after.rms_um, max_error_command_um=command_after.peak_um)


def _count_lines(path: str | Path) -> int:
    with open(path, "rb") as f:
        return max(1, sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b"")))


def _read(read_path, flavor: str, profile: MachineProfile, stages: dict[str, float], progress=None) -> Iterator[Block]:
    """The program's blocks (a move beyond the profile's travel refused), read a batch at a time:
    the time taken goes to ``stages["read"]``, and ``progress`` is told the fraction of the lines
    read after each batch. (Timed block by block, a CAM program's reading took a tenth longer.)"""
    blocks = read_gcode(read_path, flavor, profile.home_mm, profile.travel_mm("".join(AXES)))
    total_lines = _count_lines(read_path) if progress else 1

    def batches() -> Iterator[list[Block]]:
        while True:
            clock = time.perf_counter()
            batch = list(itertools.islice(blocks, BATCH_BLOCKS))
            stages["read"] += time.perf_counter() - clock
            if progress:
                progress(min(batch[-1].line_no / total_lines, 1.0) if batch else 1.0)
            if not batch:
                return
            yield batch

    return itertools.chain.from_iterable(batches())


def _timed(items: Iterable, stages: dict[str, float], stage: str, exclude=lambda: 0.0) -> Iterator:
    """``items`` as they come, the time taken to make them added to ``stages[stage]``, less the
    time that ``exclude()`` counts meanwhile (another stage's, inside)."""
    iterator = iter(items)
    while True:
        clock, other = time.perf_counter(), exclude()
        try:
            item = next(iterator)
        except StopIteration:
            stages[stage] += time.perf_counter() - clock - (exclude() - other)
            return
        stages[stage] += time.perf_counter() - clock - (exclude() - other)
        yield item
