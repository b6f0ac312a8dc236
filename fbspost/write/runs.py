"""The runs of motion as blocks: a run's block ends, dwells and end.

Takes the plan's runs, the command (``SampleWindow``), the options and the output; writes the
blocks from where the output is up to a time (``RunWriter.until``): their ends
(``blockends``), the firmware's settings before them, a dwell for the blocks at a run's start
that round to no motion, and each run's end.
"""
from __future__ import annotations

import bisect
import math

import numpy as np

from ..firmware.reprap import GRACE_S
from ..firmware.transparency import Transparency
from ..plan.planner import PlanStream
from ..read.blocks import Kind
from .blockends import Breaks, g5_blocks
from .deviation import Deviation
from .emitter import Emitter
from .options import WriteOptions, shortest_line_s
from .output import Output, dwell_line
from .samples import SampleWindow

_FEED = 1 << 14  # samples given to the block-end search at once
_FLUSH_S = 10.0  # motion written without waiting for a copied line, once this much is due


def _marlin_start_latency_s(options: WriteOptions) -> float | None:
    """Marlin: how late a run's first block starts after a G4 (None: not Marlin). Marlin's stepper
    starts a block added to an empty buffer once 3 are queued, or after 100 ms (planner.cpp
    ``get_current_block``): the run's third block is taken three line times after the G4."""
    if options.flavor != "marlin":
        return None
    return 3.0 / options.max_line_rate_hz if options.max_line_rate_hz else 0.0


def idle_latency_s(options: WriteOptions) -> float:
    """RepRapFirmware: how late the next move starts after a G4 has emptied its ring: a line's time
    (the host sends it once the G4 is done), then the grace period RRF waits for more moves (0: not
    RRF). Each G4 on RRF dwells that much less."""
    if options.flavor != "reprap":
        return 0.0
    return GRACE_S + (1.0 / options.max_line_rate_hz if options.max_line_rate_hz else 0.0)


def _start_dwell(dwell, rest_s: float, latency_s: float | None, idle_s: float = 0.0) -> tuple[float, float]:
    """The G4 before a run's first block, for ``rest_s`` of rest: (its dwell, the latency it takes:
    on Marlin, ``latency_s`` not None, the run starts that much after the G4, which dwells less;
    none where the rest is within that latency: the G4 would hold the blocks before it in the
    buffer for BLOCK_DELAY_FOR_1ST_MOVE, the rest is better the first block's, slower; else the
    firmware's ``idle_s`` after a G4, ``idle_latency_s``)."""
    if latency_s is None:
        dwell_s = dwell(max(rest_s - idle_s, 0.0))
        return dwell_s, idle_s if dwell_s > 0 else 0.0
    if dwell_line("marlin", rest_s - latency_s)[1] > 0:
        return dwell(rest_s - latency_s), latency_s
    return 0.0, 0.0



def still_as_dwell(emitter: Emitter, dwell, from_s: float, ends_s: np.ndarray, targets_mm: np.ndarray,
                   latency_s: float | None, idle_s: float = 0.0) -> int:
    """At a run's start (from ``from_s``), the first blocks (ends ``ends_s``, ``targets_mm``) that round
    to no motion as a dwell (``dwell``: writes one for about the seconds given, gives how long it
    dwells), not as a slow first block: how many it stands for (0: none, or the dwell rounds to none).
    On Marlin (``latency_s`` not None) the dwell also takes up what the last run's end left
    (``RunWriter._end_run``), with or without such blocks; ``idle_s``: ``idle_latency_s``."""
    still = emitter.still(targets_mm[:-1])
    if still or latency_s is not None:
        span_s = ends_s[still - 1] - from_s if still else 0.0
        dwell_s, late_s = _start_dwell(dwell, span_s + emitter.residue_s, latency_s, idle_s)
        if dwell_s > 0:
            emitter.residue_s += span_s - dwell_s - late_s
            return still
    return 0



def copied_sample(line_time_s: float, is_stop: bool, fs: float, previous: int) -> int:
    """The sample a copied line runs at. The nearest to its planned time (at most half a sample
    off), so that blocks end on samples of the command: a block ending between two samples
    would bend the command there, and ask more acceleration of the controller than the command
    does. A line at rest runs where the run of motion before it has ended: its last sample, the
    time rounded up (rounded to the nearest, the rest of the run would come after the line).
    Lines run in order."""
    return max(math.ceil(line_time_s * fs) if is_stop else round(line_time_s * fs), previous)



class RunWriter:
    """The runs of motion as blocks. Takes the plan's runs and the command (``SampleWindow``);
    writes the blocks from where the output is up to a time (``until``): their ends (dense:
    ``Breaks``, as the samples come; G5: ``g5_blocks``, each run fitted whole), the firmware's
    settings before them, a dwell for the blocks at a run's start that round to no motion, and
    the end of each run. ``emitter`` formats them (set before the first call)."""

    def __init__(self, plan: PlanStream, samples: SampleWindow, options: WriteOptions, output: Output,
                 settings: Transparency | None, executed=None):
        self._plan, self._samples, self._options, self._out, self._settings = plan, samples, options, output, settings
        self._fs = fs = plan.sample_rate_hz
        min_segment_s = max(options.min_segment_time_s, shortest_line_s(options.max_line_rate_hz))
        self._min_samples = max(1, int(np.ceil(min_segment_s * fs - 1e-9)))
        self.deviation = Deviation(samples, fs, options.tolerance_mm, executed)
        self.emitter: Emitter | None = None
        self.copied_sample = -1  # of the last copied line
        self.dwelt_s = 0.0  # the dwells of the lines at rest since the last block (the controller's time: +)
        self.run_index = 0  # the run being written
        self.run_from_s = None  # the run's start while none of its blocks is written (then None)
        self.latency_s = _marlin_start_latency_s(options)
        self.idle_s = idle_latency_s(options)
        self._run_breaks, self._run_g5 = None, None  # the current run's block ends (dense) or blocks and curves (g5)

    def runs_from(self, r: int) -> bool:
        """Whether the program has a run r (or later)."""
        plan = self._plan
        plan.wait(lambda: len(plan.runs) > r or plan.done)
        return len(plan.runs) > r

    def flush(self, flush_s: float) -> None:
        """The current run's blocks well before ``flush_s`` (``until``, soft), once _FLUSH_S of
        motion is due since the output's end."""
        if flush_s - self._out.written_until_s >= _FLUSH_S:  # (else it writes nothing: called per CAM line)
            self.until(flush_s, soft=True)

    def until(self, t_end_s: float, end_exact_mm: np.ndarray | None = None, soft: bool = False) -> None:
        """Blocks from where the output is to ``t_end_s``; the axes that follow the plan end
        exactly at ``end_exact_mm`` (the position the program reached there; NaN: as planned).
        ``soft``: only the current run's blocks that end well before ``t_end_s``, where no copied
        line comes before it, once _FLUSH_S is due (dense): so that a program of motion alone is
        written as it goes."""
        plan, fs = self._plan, self._fs
        while self.run_index < len(plan.runs):
            if not soft:  # the run's end, or that it goes on past t_end_s
                plan.wait(lambda: plan.runs[self.run_index][1] is not None or plan.settled_s > t_end_s)
            first, last = plan.runs[self.run_index]
            run_end_s = math.inf if last is None else last / fs
            stop_s = min(t_end_s, run_end_s)
            start_s = max(self._out.written_until_s, first / fs)
            if soft and (t_end_s >= run_end_s or stop_s - start_s < _FLUSH_S or self._options.output_format == "g5"):
                return
            if stop_s > start_s:
                self._blocks(first, start_s, stop_s, soft, end_exact_mm if t_end_s == stop_s else None)
            if soft or t_end_s < run_end_s:
                return
            self._end_run()

    def _blocks(self, first: int, start_s: float, stop_s: float, soft: bool, end_exact_mm: np.ndarray | None) -> None:
        """The blocks of the run from sample ``first`` from ``start_s`` to ``stop_s``; the last
        ends at ``end_exact_mm`` where the run's blocks reach stop_s (not ``soft``)."""
        out, emitter, samples, fs = self._out, self.emitter, self._samples, self._fs
        follows_plan = samples.follows_plan
        # A run's first block starts where the controller is, at most a sample before
        # the run's first sample (planner): it takes up the difference.
        from_s = start_s if out.written_until_s >= first / fs else min(out.written_until_s + self.dwelt_s, start_s)
        for ends, curves in self._block_ends(first, start_s, stop_s, soft):
            run_start = out.written_until_s <= first / fs
            if self._settings is not None:
                out.lines(*self._settings.apply(run_start, emitter.modal))  # (at a run's start: at rest)
            targets = samples.at(ends, fs)
            if ends[-1] == stop_s and end_exact_mm is not None and not soft:
                exact = np.where(np.isnan(end_exact_mm), samples.at(ends[-1:], fs, planned=True)[0], end_exact_mm)
                targets[-1, follows_plan] = exact[follows_plan]
            still = still_as_dwell(emitter, out.dwell, from_s, ends, targets, self.latency_s, self.idle_s) \
                if run_start else 0
            if still:
                from_s, ends, targets = ends[still - 1], ends[still:], targets[still:]
                curves = None if curves is None else curves[still:]
            if run_start:  # (its first blocks may all be held for a later call: they start here)
                self.run_from_s = from_s
            text, count = emitter.blocks(targets, np.diff(np.append(from_s, ends)), ends, curves,
                                         exact_last=ends[-1] >= stop_s)
            out.text(text, count)
            self.deviation.add(self.run_from_s, emitter.written_s, emitter.written_mm, emitter.stepped_mm)
            self.run_from_s = None if len(emitter.written_s) else self.run_from_s
            out.rate.add(emitter.written_s)
            out.stats.motion_blocks += count
            from_s = start_s = out.written_until_s = float(ends[-1])
            self.dwelt_s = 0.0
            samples.release(int(min(start_s, self.deviation.last_s) * fs) - 1)

    def _end_run(self) -> None:
        self.run_index += 1
        self._run_breaks = self._run_g5 = None
        # A run's end where the command no longer moves (a settle margin unused) is a dwell:
        # its time must not slow the next run's first block, nor be lost (the lines after it
        # run at the plan's times). Not on Marlin: its G4 empties the buffer, and a copied move
        # after it (a layer's Z move) would be alone there before the next run's G4, held 100 ms
        # (_start_dwell); the next run's G4 takes the time up (still_as_dwell), the copied lines
        # run that much earlier, X and Y at rest already.
        # On RRF the next move starts ``idle_s`` after the G4 (idle_latency_s).
        if self.latency_s is None:
            dwell_s = self._out.dwell(max(self.emitter.residue_s - self.idle_s, 0.0))
            self.emitter.residue_s -= dwell_s + (self.idle_s if dwell_s > 0 else 0.0)
        if self._settings is not None and not self.runs_from(self.run_index):
            self._out.lines(*self._settings.restore())  # the program's own, as it left them

    def _block_ends(self, first: int, start_s: float, stop_s: float, soft: bool = False):
        """The current run's block ends after ``start_s`` up to ``stop_s`` (s), and their curves, in
        batches as they become known (the last one ends at stop_s; ``soft``: only those before
        stop_s - half the minimum segment, dense only)."""
        if self._options.output_format == "g5" and self.emitter.modal.plane == 17:  # G5 is an XY-plane command
            if self._run_g5 is None:  # fitted whole: the run's samples are held
                self._run_g5 = self._g5_run(first)
            run_ends, run_curves = self._run_g5  # every copied line's sample among them
            rows = slice(*np.searchsorted(run_ends, np.rint(np.array([start_s, stop_s]) * self._fs), "right"))
            yield run_ends[rows] / self._fs, run_curves[rows]
            return
        yield from self._dense_ends(first, start_s, stop_s, soft)

    def _g5_run(self, first: int) -> tuple:
        """The blocks' end samples and curves of the run from sample ``first``, fitted whole, with a
        block end at every copied line's sample in it."""
        plan = self._plan
        plan.wait(lambda: plan.runs[self.run_index][1] is not None)
        last = plan.runs[self.run_index][1]
        ahead = [self.copied_sample]  # this copied line and those settled after it: all of the run's
        for block, line_time_s, is_stop in plan.lines:
            if block.kind is not Kind.MOVE:
                ahead.append(copied_sample(line_time_s, is_stop, self._fs, ahead[-1]))
        copied = np.unique(ahead)
        splits = copied[np.searchsorted(copied, first, "right"):np.searchsorted(copied, last, "left")] - first
        step_mm = 10.0 ** -self.emitter.digits[0] * self.emitter.unit_mm  # I J P Q as written
        run_ends, curves = g5_blocks(self._samples.rows(first, last + 1), splits, self._options.tolerance_mm,
                                     self._min_samples, step_mm)
        return run_ends + first, curves

    def _run_last(self, first: int) -> int | None:
        """The run's last sample (None while it goes on), told to its block-end search."""
        last = self._plan.runs[self.run_index][1]
        self._run_breaks.n = None if last is None else last - first + 1
        return last

    def _dense_ends(self, first: int, start_s: float, stop_s: float, soft: bool):
        """``_block_ends`` of the dense format: ``Breaks`` fed the run's samples as they settle."""
        plan, fs = self._plan, self._fs
        if self._run_breaks is None:
            self._run_breaks = Breaks(None, self._options.tolerance_mm, self._min_samples)
        breaks = self._run_breaks
        half = 0.5 * self._options.min_segment_time_s
        ends = breaks.ends
        while True:
            last = self._run_last(first)
            # The ends known so far strictly between start + half and stop - half (in seconds),
            # until one at or past stop is known.
            final = ends[-1] >= min(stop_s * fs, math.inf if last is None else last) - first or breaks.fed == breaks.n
            low = bisect.bisect_left(ends, math.floor((start_s + half) * fs) - first - 1)
            high = bisect.bisect_right(ends, math.ceil((stop_s - half) * fs) - first + 1)
            times = (np.asarray(ends[low:high]) + first) / fs
            inner = times[np.searchsorted(times, start_s + half, "right"):np.searchsorted(times, stop_s - half, "left")]
            del ends[:min(low, len(ends) - 1)]  # passed: later calls start after them
            if final:
                if not soft:
                    yield np.append(inner, stop_s), None
                elif inner.size:
                    yield inner, None
                return
            if inner.size:
                yield inner, None
                start_s = inner[-1]
            fed = first + breaks.fed
            plan.wait(lambda fed=fed: plan.runs[self.run_index][1] is not None or plan.frontier >= fed + _FEED)
            last = self._run_last(first)
            breaks.feed(self._samples.rows(fed, fed + _FEED if last is None else min(fed + _FEED, last + 1)))

