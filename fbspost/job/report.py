"""What a job takes and gives, and what it counts on the way.

Takes the command line's choices; gives ``CompensateOptions`` (what ``compensate_file`` takes)
and ``Report`` (what it gives: per axis an ``AxisReport``). On the way: ``ErrorStats`` (a running
RMS and peak), ``Tally`` and ``Outcome`` (the axes' windows, warnings and times),
``ExecutedError`` (the written program's modelled error as the firmware runs it, sample by sample
from the writer) and ``timed`` (a stage's time, item by item).
"""
from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..fbs.optimizer import AxisCompensator
from ..fbs.settings import FBSSettings
from ..firmware.verify import Verdict

_EXECUTED_BATCH = 1 << 14  # samples (ExecutedError)


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
    # plans for them (same output, bit for bit); None: for long programs (in_second_process), with
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
        before, after = ErrorStats(), ErrorStats()
        before.add(before_mm)
        after.add(after_mm)
        return cls.from_stats(before, after)

    @classmethod
    def from_stats(cls, before: ErrorStats, after: ErrorStats, windows: int = 0, qp_windows: int = 0) -> AxisReport:
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
    lead_time_s: float = 0.0  # per run, at most (margins.RunMargins: for Klipper, less by the run's end)
    settle_time_s: float = 0.0
    travel_saved_s: float = 0.0  # less by the travels planned faster (margins.RunMargins.travel_share), about
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


@dataclass
class Tally:
    """Counted as the work goes: the fallback's wall time, and per axis (column) the optimizer's
    windows and those that needed the QP."""

    fallback_s: float = 0.0
    windows: dict[int, list[int]] = field(default_factory=dict)


@dataclass
class ErrorStats:
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


@dataclass
class Outcome:
    """What compensating a program counts besides its chunks: per compensated axis (column) the
    modelled errors before and after (``AxisGuard``), the optimizers' and fallbacks' warnings,
    their windows and time, and the time of the whole (optimize and fallback, s)."""

    errors: dict[int, tuple[ErrorStats, ErrorStats]]
    warnings: list[str] = field(default_factory=list)
    tally: Tally = field(default_factory=lambda: Tally())
    optimize_s: float = 0.0

    @classmethod
    def of(cls, compensators: dict[int, AxisCompensator]) -> Outcome:
        return cls({c: (ErrorStats(), ErrorStats()) for c in compensators})

    @classmethod
    def joined(cls, outcomes: list[Outcome]) -> Outcome:
        """The outcomes of the axes compensated apart, in their order (the times: the longest)."""
        return cls({c: e for o in outcomes for c, e in o.errors.items()}, [w for o in outcomes for w in o.warnings],
                   Tally(max(o.tally.fallback_s for o in outcomes),
                          {c: n for o in outcomes for c, n in o.tally.windows.items()}),
                   max(o.optimize_s for o in outcomes))


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
        self.stats = {c: (ErrorStats(), ErrorStats()) for c in self.axes}
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

    def report(self, c: int, windows: int, qp_windows: int, command_after: ErrorStats) -> AxisReport:
        return replace(AxisReport.from_stats(*self.stats[c], windows, qp_windows),
                       rms_error_command_um=command_after.rms_um, max_error_command_um=command_after.peak_um)


def timed(items: Iterable, stages: dict[str, float], stage: str, exclude=lambda: 0.0) -> Iterator:
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
