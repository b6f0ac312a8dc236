"""G-code writer: the compensated command as dense G1 or as G5 blocks, every other line untouched.

Takes the program's blocks, its plan, the command to send (machine coordinates, mm, on the
plan's time grid: compensated axes replaced, the others as planned) and the writing options;
gives the output program as bytes, line by line. Lines that do not move the machine are copied
byte-exact, in order, at their planned time; the motion between them becomes blocks whose end
points lie on the command and whose F makes each last exactly its time. Dense format: G1 blocks,
boundaries chosen so that the piecewise-linear command stays within the tolerance, no block
shorter than the minimum segment time. G5 format: cubic Bezier blocks fitted by
``bezier.fit_g5`` within the same tolerance (F = curve length / duration), G1 where no curve
fits, where Z moves (G5 moves Z in the curve parameter and the controller times the block by
its XYZ length, not by the curve's) and while the controller is not in the G17 plane. Coordinates
are written in the program's own modes (G90/G91, M82/M83, G20/G21, G92 frames); relative values
carry their rounding residues, so nothing accumulates.
"""
from __future__ import annotations

import io
import math
import re

import numpy as np

from ..firmware.transparency import Transparency
from ..plan.planner import PlanStream
from ..read.blocks import AXES, Block, Kind, Modal
from .emitter import Emitter
from .options import WriteOptions, WriteStats, format_refusal
from .output import Output, dwell_line, mode_lines
from .runs import RunWriter, copied_sample, still_as_dwell
from .samples import SampleWindow


class _ProgramWriter:
    """The output program (``write_program``): the program's lines in order, the copied ones at
    their times with the blocks before them (``RunWriter``), the header comments before the
    first line of code, the modes and the firmware's settings where the copied lines need them."""

    def __init__(self, plan: PlanStream, samples: SampleWindow, options: WriteOptions, out, executed=None):
        self._plan, self._samples, self._options, self._executed = plan, samples, options, executed
        self._fs = plan.sample_rate_hz
        self._settings = None if options.firmware is None else \
            Transparency(options.flavor, options.firmware, options.tolerance_mm)
        self._out = Output(out, options.flavor)
        self._motion = RunWriter(plan, samples, options, self._out, self._settings, executed)
        self._previous_modal, self._previous_mm = Modal(), np.full(len(AXES), np.nan)

    def write(self) -> WriteStats:
        header_done = False
        last_line = None
        motion, out = self._motion, self._out
        for block, line_time_s, is_stop in self._plan.blocks():
            if motion.emitter is None:
                out.newline = b"\r\n" if block.raw.endswith(b"\r\n") else b"\n"  # (only the last line has no ending)
                steps = None if self._options.steps_per_mm is None else np.asarray(self._options.steps_per_mm)
                motion.emitter = Emitter(self._samples.rows(0, 1)[0], out.newline, steps,
                                         self._options.min_steps_per_segment,
                                         math.inf if self._settings is None else self._settings.ramp_mm_s2,
                                         self._options.axis_modes, cells=self._options.step_cells)
            if not header_done and _is_code(block):
                self._header()
                header_done = True
            if block.kind is Kind.MOVE:
                self._previous_modal, self._previous_mm = block.modal, block.position_mm
                # the next copied line runs at or after the sample nearest the end of this motion
                motion.flush(line_time_s - 1.0 / self._fs)
                continue
            if not is_stop and not block.raw.endswith((b"\n", b"\r")):
                last_line = block  # the file's last line has no ending: after the motion (of a settle margin)
                break
            self._copy(block, line_time_s, is_stop)
        self._finish(last_line)
        return out.stats

    def _header(self) -> None:
        settings, options = self._settings, self._options
        comment = ("(", ")") if options.flavor == "linuxcnc" else ("; ", "")
        notes = settings.header() if settings is not None and self._motion.runs_from(0) else []
        header = [f"{comment[0]}{text}{comment[1]}" for text in options.header + tuple(notes)]
        self._out.text(b"".join(x.encode() + self._out.newline for x in header), len(header))  # (comments: not sent)

    def _copy(self, block: Block, line_time_s: float, is_stop: bool) -> None:
        """A line that does not move the machine, at its time, after the motion before it."""
        out, motion, settings, samples, fs = self._out, self._motion, self._settings, self._samples, self._fs
        previous_mm, follows_plan = self._previous_mm, samples.follows_plan
        motion.copied_sample = copied_sample(line_time_s, is_stop, fs, motion.copied_sample)
        t = motion.copied_sample / fs
        motion.until(t, previous_mm)  # the motion before the line ends where the program was before it
        if settings is not None and is_stop and _may_move(previous_mm, block.position_mm, slice(None)):
            # a move fbspost copies runs under the program's own settings (shaping: where it moves X or Y)
            moves_xy = _may_move(previous_mm, block.position_mm, slice(0, 2))
            out.lines(*settings.restore(shaping=moves_xy))
            # (RRF, at jerk policy 0 as fbspost plans it, stops before a move without X or Y itself; a G4
            # there would empty its ring: the move then waits its grace period, the look-ahead starves)
            stops_itself = self._options.flavor == "reprap" and not moves_xy
            if motion.emitter.speed_mm_s > 0 and motion.latency_s is None and not stops_itself:
                # from rest, as planned: the last block's speed would carry into it
                out.lines(dwell_line(self._options.flavor, 0.0)[0])
            # (Marlin: no G4. Its junction caps the move's entry at the slow last block's speed, and a G4
            # would leave the move alone in the buffer before the next run's G4, held 100 ms: _start_dwell)
            if motion.latency_s is not None and not moves_xy and motion.run_index == 0:
                # Marlin's M593 waits for the buffer to empty: at the first run, after this move, it would
                # leave the move alone in the buffer (held 100 ms, see _start_dwell); X Y shaping does not touch it
                out.lines(*settings.shaping_off_lines())
        # where the program is: the plan where the line does not say
        reached = samples.at(np.array([t]), fs, planned=True)[0]
        reached = np.where(np.isnan(block.position_mm), reached, block.position_mm)
        commanded = samples.at(np.array([t]), fs)[0]
        out.lines(*mode_lines(self._options.flavor, motion.emitter.modal, self._previous_modal))
        out.lines(*_program_modes(self._options.flavor, block, motion.emitter.feed != -1,
                                  self._options.output_format == "g5"))
        if _is_code(block):
            out.rate.add(t)
        out.copy(block.raw)
        commanded[follows_plan] = reached[follows_plan]  # the last block ended exactly there
        motion.emitter.passthrough(block, commanded, reached)
        if is_stop:
            motion.dwelt_s += block.dwell_s
        self._previous_modal, self._previous_mm = block.modal, block.position_mm
        if settings is not None:
            settings.note(block)  # the program's settings, and whether the firmware still has ours

    def _finish(self, last_line: Block | None) -> None:
        """The motion after the last copied line, the modes restored, the last line if it has no ending."""
        out, motion, samples = self._out, self._motion, self._samples
        if motion.emitter is None:
            motion.emitter = Emitter(np.zeros(len(AXES)), out.newline)
        samples.ensure(samples.n_samples)
        motion.until(np.inf, samples.planned[-1])
        motion.deviation.rest_until(samples.n_samples)
        if self._executed is not None:
            self._executed.finish(samples.planned[-1])
        out.lines(*mode_lines(self._options.flavor, motion.emitter.modal, self._previous_modal))
        if last_line is not None:
            out.copy(last_line.raw)
        stats, deviation = out.stats, motion.deviation
        stats.max_line_rate_hz = float(out.rate.max_per_s)
        stats.max_deviation_mm, stats.max_deviation_s = deviation.max_mm, deviation.at_s
        stats.loosened_s = deviation.loosened_s
        stats.rms_deviation_mm = math.sqrt(deviation.sum_squares_mm2 / max(deviation.count, 1))
        stats.shaping_left_off = self._settings.left_off if self._settings is not None else ""


def write_program(plan: PlanStream, samples: SampleWindow, options: WriteOptions, out, executed=None) -> WriteStats:
    """Write the output program to the binary stream ``out``. The program's blocks come from
    ``plan`` as it settles them. With ``options.firmware``, the firmware is made transparent
    before the written blocks and given back the program's settings (as its copied lines change
    them) before every copied line that may move the machine and after the last run
    (``transparency``). ``executed`` (``report.ExecutedError``) is given the written program's
    motion as the firmware runs it, sample by sample.
    """
    refusal = format_refusal(options.flavor, options.output_format)
    if refusal:
        raise ValueError(refusal)
    return _ProgramWriter(plan, samples, options, out, executed).write()


def timed_blocks(command_mm: np.ndarray, block_s: float, options: WriteOptions) -> list[str]:
    """The lines that run a sampled command (rows X Y Z E, machine mm, one every ``block_s``; at
    rest at the first row, where the firmware is) as blocks of ``block_s`` each on
    ``options.flavor``'s firmware, made transparent by ``options.firmware``'s ``Transparency``
    (whose lines the caller writes around them): F from each block's time with the residues and
    ramps carried, Marlin's whole steps and merge with ``options``' steps (``Emitter``), a dwell
    for the first blocks that round to no motion and one for the time left at the end (the ramp
    down to rest)."""
    ramp_mm_s2 = math.inf if options.firmware is None else \
        Transparency(options.flavor, options.firmware, options.tolerance_mm).ramp_mm_s2
    steps = None if options.steps_per_mm is None else np.asarray(options.steps_per_mm)
    emitter = Emitter(command_mm[0], b"\n", steps, options.min_steps_per_segment, ramp_mm_s2, options.axis_modes,
                      crossings=False, cells=options.step_cells)  # (blocks of equal time: identify's sweep)
    text = io.BytesIO()
    out = Output(text, options.flavor)
    ends_s, targets_mm = np.arange(1, len(command_mm)) * block_s, command_mm[1:]
    still = still_as_dwell(emitter, out.dwell, 0.0, ends_s, targets_mm, None)
    from_s = ends_s[still - 1] if still else 0.0
    out.text(*emitter.blocks(targets_mm[still:], np.diff(np.append(from_s, ends_s[still:])), ends_s[still:]))
    out.dwell(emitter.residue_s - emitter.speed_mm_s / (2.0 * emitter.ramp_mm_s2))  # (as a stop, then a run's end)
    return text.getvalue().decode().splitlines()


def _may_move(before_mm: np.ndarray, after_mm: np.ndarray, axes: slice) -> bool:
    """Whether a line at rest that took the machine from ``before_mm`` to ``after_mm`` (NaN:
    unknown) may have moved one of ``axes`` (columns of AXES): a copied move, homing, a macro."""
    before, after = before_mm[axes], after_mm[axes]
    return bool(np.any(np.isnan(before) | np.isnan(after) | (before != after)))


_F_WORD = re.compile(rb"[Ff]\s*[-+.0-9]")
_COMMENT = re.compile(rb"\([^)]*\)|;.*")


def _program_modes(flavor: str, block: Block, blocks_written: bool, curves: bool) -> list[str]:
    """The lines that give a copied move its program's modes back where the output has written
    blocks since the program's last line: its F, where the move does not say its own (the firmware
    would run it at the last written block's F: a Z hop at a creeping block's 0.3 mm/s, LinuxCNC's
    B axis at 28 degrees/min for F500), and on LinuxCNC its G0 (or G1 after the output's G5
    blocks, ``curves``), where the line moves by the mode in force (the axis words of a rapid after
    the output's G1 blocks ran as a feed move). A copied arc that continues G2 or G3 gets no mode
    back: G2 alone is refused (not seen in a program)."""
    if not blocks_written:
        return []
    restored = block.inherited_motion in ((0, 1) if curves else (0,))
    lines = [f"G{block.inherited_motion:g}"] if flavor == "linuxcnc" and restored else []
    feed = block.feed_mm_s
    if feed is None or not math.isfinite(feed) or _F_WORD.search(_COMMENT.sub(b"", block.raw)):
        return lines
    value = f"{feed * 60.0 / (25.4 if block.modal.inches else 1.0):.4f}".rstrip("0").rstrip(".")
    return lines + [f"F{value}" if flavor == "linuxcnc" else f"G1 F{value}"]


def _is_code(block: Block) -> bool:
    """Anything but a blank or comment-only line (or a LinuxCNC '%' marker)."""
    text = block.raw.strip()
    return bool(text) and not text.startswith((b";", b"(", b"%"))
