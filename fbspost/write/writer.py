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

import bisect
import io
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d

from ..firmware.steps import ModalRounding, crossing_ends, lattice_counts, rounding_for, settled_before
from ..firmware.transparency import FirmwareSettings, Transparency
from ..plan.planner import PlanStream
from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind, Modal, feed_lengths
from .bezier import curve_lengths, fit_g5

_DECIMALS = {**dict.fromkeys(AXES, 4), "E": 5}  # mm: 0.1 um (A B C: 1e-4 degree), E: 10 nm of filament
_FEED_DECIMALS = 3  # mm/min (in/min in G20)
_LINES = 1024  # lines formatted at once
_MAX_SAMPLES = 2000  # longest block, samples
_E = AXES.index("E")
_NOT_IN_G5 = [i for i, a in enumerate(AXES) if a not in "XYE"]
# Controllers that run G5: Marlin built with BEZIER_CURVE_SUPPORT, LinuxCNC (XY only). Klipper has
# no G5; RepRapFirmware's is not documented as a timed cubic Bezier.
G5_FLAVORS = ("marlin", "linuxcnc")


@dataclass(frozen=True)
class WriteOptions:
    flavor: str  # marlin | klipper | reprap | linuxcnc
    output_format: str = "dense"  # dense | g5
    tolerance_mm: float = 1e-3
    min_segment_time_s: float = 1e-3
    header: tuple[str, ...] = ()  # comment text, one entry per line
    firmware: FirmwareSettings | None = None  # the program's settings at its start (None: no settings written)
    max_line_rate_hz: float | None = None  # the most lines the machine takes per second
    steps_per_mm: tuple[float, ...] | None = None  # X Y Z E (0: not known): blocks Marlin would merge are merged here
    min_steps_per_segment: int = 0
    axis_modes: tuple = ()  # X Y Z: each axis' profile modes, for the rounding to whole steps (``steps``)


@dataclass
class WriteStats:
    lines_out: int = 0
    motion_blocks: int = 0
    passthrough_lines: int = 0
    max_line_rate_hz: float = 0.0  # the most lines sent in any second of the program's time (no comments)
    max_deviation_mm: float = 0.0  # the largest distance of the written blocks from the command (XYZ, same time)
    max_deviation_s: float = 0.0  # where
    rms_deviation_mm: float = 0.0  # over the samples inside the blocks
    loosened_s: float = 0.0  # time in blocks beyond the tolerance (merged, or stretched for the line rate)
    shaping_left_off: str = ""  # axes whose input shaping the output turns off and cannot turn on (not known)


def format_refusal(flavor: str, output_format: str) -> str | None:
    """Why the flavor's controller cannot run the output format (None: it can)."""
    if output_format == "g5" and flavor not in G5_FLAVORS:
        return (f"{flavor} has no G5 (cubic Bezier) move: use --format dense "
                f"(g5 is for {' and '.join(G5_FLAVORS)})")
    return None


_PIECE = 1 << 16  # samples


class _Breaks:
    """Where the blocks of one run end (see ``breakpoints``), found as its command arrives.

    A chord over n sample steps deviates from the samples it spans by at most n^2/8 times their
    largest second difference (the discrete maximum principle), so a block may span
    n = sqrt(8 tolerance / max |second difference| ahead) steps: never more than the tolerance
    allows, never fewer than ``min_samples`` (where that is shorter, the minimum wins). "Ahead"
    is the next ``max_samples`` steps (past the run's end: the last ones mirrored), so a block
    end is known once that much of the command after it is: the ends are the same however the
    command arrives.
    """

    def __init__(self, n_samples: int | None, tolerance_mm: float, min_samples: int, max_samples: int = _MAX_SAMPLES):
        self.n, self.tolerance_mm, self.min_samples, self.size = n_samples, tolerance_mm, min_samples, max_samples
        self.ends = [0]  # found so far (run sample indices)
        self.bend = np.zeros(0)  # |second difference| at samples bend_base + j (bending at the sample after)
        self.bend_base = 0
        self.tail = None  # the last two samples fed, for the next second differences
        self.fed = 0  # samples fed

    def feed(self, command: np.ndarray) -> None:
        """The run's next samples (rows of X Y Z E, mm)."""
        rows = command if self.tail is None else np.concatenate([self.tail, command])
        self.fed += len(command)
        self.tail = rows[-2:]
        # (by pieces: big temporaries cost more than the arithmetic)
        new = [np.linalg.norm(np.diff(rows[a:a + _PIECE + 2], 2, axis=0), axis=1)
               for a in range(0, max(len(rows) - 2, 0), _PIECE)]
        if self.fed == self.n:
            new.append(np.zeros(min(2, self.n)))  # no bend at the last two samples
        self.bend = np.concatenate([self.bend] + new)
        self.find()

    def find(self) -> None:
        """Every block end that the samples fed so far decide."""
        if self.n is not None and self.n <= 2:
            self.ends = list(range(self.n))
            return
        done = self.fed == self.n
        i0 = i = self.ends[-1]  # a block starts here (or it is the last sample)
        # ahead[j] needs bend[j .. j + size - 1]; past the end of the run they are mirrored
        stop = self.n - 1 if done else self.bend_base + len(self.bend) - self.size + 1
        if i0 < stop:
            low = min(i0, max(self.n - self.size, 0)) if done else i0  # the mirror reaches back size - 1
            ahead = maximum_filter1d(self.bend[low - self.bend_base:], size=self.size,
                                     origin=-(self.size // 2))[i0 - low:stop - low]
            with np.errstate(divide="ignore"):
                span = np.floor(np.sqrt(8.0 * self.tolerance_mm / ahead))
            span = np.clip(np.nan_to_num(span, posinf=self.size), self.min_samples, self.size).astype(int)
            # The blocks run i -> i + span[i]. The span is a maximum over the next size steps, so
            # it changes rarely: step through each stretch of one span at once.
            stretch_ends = (np.flatnonzero(np.diff(span)) + 1 + i0).tolist() + [stop]
            pieces = []
            while i < stop:
                step = int(span[i - i0])
                pieces.append(np.arange(i, stretch_ends[bisect.bisect_right(stretch_ends, i)], step))
                i = int(pieces[-1][-1]) + step
            self.ends.extend(np.concatenate(pieces)[1:].tolist())
            self.ends.append(min(i, self.n - 1) if done else i)
        # Keep what later spans need: from the last start, and the stretch the mirror reaches
        # (the run has at least the samples fed).
        keep = max(min(self.ends[-1], (self.fed if self.n is None else self.n) - self.size), self.bend_base)
        self.bend = self.bend[keep - self.bend_base:]
        self.bend_base = keep


def breakpoints(command: np.ndarray, tolerance_mm: float, min_samples: int,
                max_samples: int = _MAX_SAMPLES) -> np.ndarray:
    """Sample indices where the blocks of a run end (``command``: its samples), first and last
    sample included (see ``_Breaks``)."""
    breaks = _Breaks(len(command), tolerance_mm, min_samples, max_samples)
    breaks.feed(np.asarray(command, dtype=float))
    return np.asarray(breaks.ends)


@dataclass(frozen=True)
class Curves:
    """Which of a sequence of blocks are G5 curves, with their control points (absolute machine
    XY); the other blocks' points mean nothing."""

    curve: np.ndarray  # (m,) bool
    p1_mm: np.ndarray  # (m, 2)
    p2_mm: np.ndarray  # (m, 2)

    def __getitem__(self, rows) -> Curves:
        return Curves(self.curve[rows], self.p1_mm[rows], self.p2_mm[rows])


def g5_blocks(command: np.ndarray, splits: np.ndarray, tolerance_mm: float,
              min_samples: int, step_mm: float = 0.0) -> tuple[np.ndarray, Curves]:
    """Where a run's blocks end (sample indices into ``command``, the run's samples; 0 is its
    start) and which are curves, for the G5 format: every sample in ``splits`` (where copied
    lines run) ends a block.

    The run is fitted whole (fit_g5 searches its blocks in lock step: a call per stretch between
    copied lines is many times slower). Fitted blocks that a split falls inside, in which Z (or
    a LinuxCNC axis other than X Y) moves, or that miss the tolerance (fit_g5 lets the minimum
    length win, and a short block
    before one of its chunk edges may miss where chords do not) become G1 blocks, between the
    splits and the other fitted blocks' ends: ``breakpoints`` of each such stretch, its last two
    blocks sharing their length where the last is shorter than the minimum (each then at least
    half the minimum long, and shorter than the first of them was). A curve whose control points
    lie on its chord's thirds is a straight line at constant speed: G1.
    """
    # (LinuxCNC: E stays 0)
    fit = fit_g5(command[:, [0, 1, _E]], tolerance_mm, min_samples, _MAX_SAMPLES, step_mm=step_mm)
    starts, ends = fit.starts, fit.ends
    # Z and LinuxCNC's other axes move in G1 blocks only
    z_steps = np.concatenate([[0], np.cumsum((np.diff(command[:, _NOT_IN_G5], axis=0) != 0).any(axis=1))])
    as_g1 = ((np.searchsorted(splits, starts, "right") < np.searchsorted(splits, ends, "left"))
             | (z_steps[ends] > z_steps[starts]) | (fit.error_mm > tolerance_mm))
    kept = ~as_g1
    hard = np.union1d(np.concatenate([[0, ends[-1]], starts[kept], ends[kept]]), splits)  # neighbouring G1 blocks merge
    g1 = ~np.isin(hard[1:], ends[kept])  # stretches that are no kept block
    inner = [np.zeros(0, np.int64)]
    for a, b in zip(hard[:-1][g1], hard[1:][g1], strict=True):
        g1_ends = breakpoints(command[a:b + 1], tolerance_mm, min_samples) + a
        if len(g1_ends) > 2 and b - g1_ends[-2] < min_samples:  # a short last block: the last two share
            g1_ends[-2] = (g1_ends[-3] + b) // 2
        inner.append(g1_ends[1:-1])
    all_ends = np.union1d(hard[1:], np.concatenate(inner))
    p0, p3 = command[starts, :2], command[ends, :2]
    straight = np.maximum(np.abs(fit.p1_mm - (p0 + (p3 - p0) / 3.0)).max(axis=1),
                          np.abs(fit.p2_mm - (p3 - (p3 - p0) / 3.0)).max(axis=1)) <= 1e-3 * tolerance_mm
    curve = fit.curve & ~straight & ~as_g1
    block = np.searchsorted(ends, all_ends)  # the fitted block each block ends in (its own, for a curve)
    return all_ends, Curves(np.isin(all_ends, ends[curve]), fit.p1_mm[block], fit.p2_mm[block])


class _Emitter:
    """Formats blocks in the controller's current modes and frame.

    ``written`` is where the controller believes it is, in its program coordinates: it changes
    only by what is written (so relative values carry their rounding residues), by G92 and by
    unit changes.
    """

    def __init__(self, start_mm: np.ndarray, newline: bytes, steps_per_mm: np.ndarray | None = None,
                 min_steps: int = 0, ramp_mm_s2: float = math.inf, axis_modes: tuple = (), crossings: bool = True):
        self.modal = Modal()  # the controller starts in its defaults
        # the firmware ramps each speed step at this acceleration, losing time the next blocks make up
        self.ramp_mm_s2, self.speed_mm_s = ramp_mm_s2, 0.0
        # Marlin merges a block of fewer than min_steps steps on every axis with the next (steps_per_mm per
        # axis, 0 where not known): such blocks are merged here, where their time can go with them
        self.steps_per_mm, self.min_steps, self.crossings = steps_per_mm, min_steps, crossings
        self.held = None  # (targets, durations, ends) of blocks that wait for the next call
        self.crossing_from = self.plain = None  # on crossings: the last kept end written (_held_from), the merge
        self.rounding = [rounding_for(axis_modes[i] if i < len(axis_modes) else ()) for i in range(3)]  # X Y Z steps
        self.rounding_state = [np.zeros(r.size) for r in self.rounding]
        self.shift_mm = np.zeros(len(AXES))  # controller frame minus program frame, per axis (G92 mid-motion)
        self.written = self.to_program(start_mm)
        self.feed = -1  # the last F written, in units of its last digit (none yet: feeds are >= 0)
        self.newline = newline
        self.residue_s = 0.0  # time the blocks so far were written short of theirs: the next block's to take

    @property
    def unit_mm(self) -> float:
        return 25.4 if self.modal.inches else 1.0

    def to_program(self, machine_mm: np.ndarray, axes=slice(None)) -> np.ndarray:
        """Program coordinates of machine positions, of the ``axes`` (columns) given."""
        return (machine_mm - (np.asarray(self.modal.offsets_mm) + self.shift_mm)[axes]) / self.unit_mm

    def to_machine(self, program: np.ndarray) -> np.ndarray:
        """Machine mm of program coordinates (rows of every axis): ``to_program``'s inverse."""
        return program * self.unit_mm + np.asarray(self.modal.offsets_mm) + self.shift_mm

    def passthrough(self, block: Block, command_mm: np.ndarray, planned_mm: np.ndarray) -> None:
        """Follow what a copied line does to the controller. A G92 sets the frame where the command
        is, not where the plan is: keep the difference. A copied move or homing puts the
        controller where the plan says (the command is at rest there)."""
        old_offsets, old_unit = np.asarray(self.modal.offsets_mm), self.unit_mm
        self.modal = block.modal
        self.feed = -1  # a copied line may set F (a retraction, "G1 F1800"): the next block says its own
        if block.kind is Kind.STOP:
            self.residue_s -= self.speed_mm_s / (2.0 * self.ramp_mm_s2)  # the last block's ramp down to rest
            self.speed_mm_s = 0.0
            self.shift_mm[:] = 0.0
            self.written = self.to_program(planned_mm)
            return
        self.written *= old_unit / self.unit_mm
        changed = np.asarray(block.modal.offsets_mm) != old_offsets
        changed[list(block.sets_position)] = True  # an axis set where it already was: set where the command is
        if changed.any():
            self.shift_mm[changed] = (command_mm - planned_mm)[changed]
            self.written[changed] = self.to_program(command_mm)[changed]

    @property
    def digits(self) -> np.ndarray:
        """Decimals written per axis (of AXES), in the controller's units."""
        return np.array([_DECIMALS[a] for a in AXES]) + (1 if self.modal.inches else 0)

    def still(self, targets_mm: np.ndarray) -> int:
        """How many of the first ``targets_mm`` (machine mm) round to where the controller is."""
        scale = 10.0 ** self.digits
        moves = (np.rint(self.to_program(targets_mm) * scale) != np.rint(self.written * scale)).any(axis=1)
        return int(np.argmax(moves)) if moves.any() else len(moves)

    def _marlin_lengths(self, start: np.ndarray, ints: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lengths Marlin times the blocks by (planner.cpp, _populate_block): of the whole
        steps they move, E's where no XYZ axis moves its minimum steps; and the speeds up to
        which Marlin enters each block at once, without a ramp: its minimum planner speed
        sqrt(0.5 a / steps per mm), a the ramps' (where the speed rises above it, it ramps from there)."""
        spm = self.steps_per_mm
        step_counts = np.diff(np.rint(np.vstack([start, ints]) * (spm * self.unit_mm / scale)), axis=0)
        delta_mm = np.where(spm > 0, step_counts / np.where(spm > 0, spm, 1.0),
                            np.diff(np.vstack([start, ints]), axis=0) / scale * self.unit_mm)
        length = _lengths(delta_mm, (np.abs(step_counts[:, :3]) >= self.min_steps).any(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            jump = np.sqrt(0.5 * self.ramp_mm_s2 * length / np.abs(step_counts).max(axis=1, initial=0))
        return length, np.nan_to_num(jump)

    def _shaped(self, units: np.ndarray, ints: np.ndarray, scale: np.ndarray, durations_s: np.ndarray,
                exact_last: bool) -> tuple[np.ndarray, list[np.ndarray | None] | None]:
        """MIN_STEPS_PER_SEGMENT 1: block ends (``units`` wanted, ``ints`` rounded) with X Y Z on
        whole steps chosen by ``steps``, and per axis the rounding's state before each row and
        after the last. With ``exact_last`` the last end is exact and the rounding restarts.
        (Above 1 without crossings: plain rounding, as the merge moves the ends again.)"""
        spu = (self.steps_per_mm * self.unit_mm / scale)[:3]  # steps per written unit
        if self.min_steps > 1 or not (spu > 0).any() or not len(ints):
            return ints, None
        ints, states = ints.copy(), [None] * 3
        for i in np.flatnonzero(spu > 0):
            counts, states[i] = self.rounding[i].round(units[:, i] * spu[i], durations_s, self.rounding_state[i])
            ints[:, i] = np.rint(counts / spu[i])
            if exact_last:
                states[i][-1] = 0.0
        if exact_last:
            ints[-1] = np.rint(units[-1])
        return ints, states

    def _on_crossings(self, start: np.ndarray, ints: np.ndarray, scale: np.ndarray, durations_s: np.ndarray,
                      ends_s: np.ndarray, targets_mm: np.ndarray, exact_last: bool) -> tuple:
        """MIN_STEPS_PER_SEGMENT above 1: the blocks Marlin keeps (``_merged``), each end moved to where
        its dominant axis crosses a step (``steps.crossing_ends``), the ends then on whole steps
        (``_rounded_ends``), merged rows onto the kept end before; merged again where that left a
        block short. Gives the ends, rows' durations and times, targets and rounding's states."""
        n, spu = len(ints), self.steps_per_mm * self.unit_mm / scale
        # row 0: the last kept end's time, wanted and rounded ends, its time and end moved (none: the start)
        t0_s = ends_s[0] - durations_s[0]
        from_s, from_units, from_ints, ended_s, ended_units = self.crossing_from or (t0_s, start, start, t0_s, start)
        ints = _merged(from_ints, ints, spu, self.min_steps, exact_last)
        self.plain = np.vstack([from_ints, ints])
        kept = np.flatnonzero((np.diff(np.vstack([from_ints, ints]), axis=0) != 0).any(axis=1))
        if not len(kept):
            return ints, durations_s, ends_s, targets_mm, None
        times_s, units = np.append(from_s, ends_s), np.vstack([from_units, self.to_program(targets_mm) * scale])
        xyz_spu = np.where(np.arange(len(spu)) < 3, spu, 0.0)
        t_s, ends = crossing_ends(times_s, units, xyz_spu, kept + 1)
        rounded, states = _rounded_ends(self.rounding, self.rounding_state, ends, spu, np.append(ended_s, t_s),
                                        kept, exact_last, times_s, units, ended_units, self.plain, self.min_steps)
        if exact_last and kept[-1] == n - 1:
            rounded[-1] = ints[-1]
        durations_s, ends_s = _moved_in_time(kept, t_s - times_s[kept + 1], durations_s, ends_s)
        targets_mm = targets_mm.copy()
        targets_mm[kept] = self.to_machine(ends / scale)
        source = np.maximum.accumulate(np.where(np.isin(np.arange(n), kept), np.arange(n) + 1, 0))
        ints = np.vstack([start, np.zeros_like(ints)])
        ints[kept + 1] = rounded
        return (_merged(start, ints[source], spu, self.min_steps, exact_last), durations_s, ends_s, targets_mm,
                states)

    def _held_from(self, kept: np.ndarray, wanted_s: np.ndarray, ends_s: np.ndarray, wanted_mm: np.ndarray,
                   ends_mm: np.ndarray, scale: np.ndarray) -> int:
        """The first row held for the next call (``_last_in_both``); ``crossing_from``: the row
        before's, for the next call to merge and move its rows as one call would."""
        row = _last_in_both(self.plain, kept, ends_s)
        if row is not None:
            self.crossing_from = (wanted_s[row], self.to_program(wanted_mm[row]) * scale, self.plain[row + 1],
                                  ends_s[row], self.to_program(ends_mm[row]) * scale)
        return 0 if row is None else row + 1

    def _keep_rounding(self, states: list[np.ndarray | None] | None, row: int) -> None:
        """The rounding's state before block ``row`` (of ``_shaped``'s), for the next call."""
        if states is not None:
            self.rounding_state = [np.zeros(r.size) if st is None else st[row]
                                   for r, st in zip(self.rounding, states, strict=True)]

    def blocks(self, targets_mm: np.ndarray, durations_s: np.ndarray, ends_s: np.ndarray | None = None,
               curves: Curves | None = None, exact_last: bool = True) -> tuple[bytes, int]:
        """G1 lines (G5 where ``curves`` says so) reaching each target (machine mm) in its
        duration, in the controller's modes: their text (each line ended by the newline) and how
        many there are. ``written_s`` and ``written_mm``: the ends (of ``ends_s``) and targets of
        the blocks written. Without ``exact_last`` (Marlin's merge), the last block kept waits for
        the next call, where a later block may yet merge it.

        Values are rounded in integer units of the last written digit: a relative value is the
        difference of two rounded positions, so rounding residues never accumulate.
        """
        ends_s = np.zeros(len(targets_mm)) if ends_s is None else ends_s
        if self.held is not None:
            targets_mm, durations_s, ends_s = (
                np.concatenate(pair) for pair in zip(self.held, (targets_mm, durations_s, ends_s), strict=True)
            )
            self.held = None
        digits = self.digits
        scale = 10.0 ** digits
        relative = np.array([not (self.modal.absolute_e if a == "E" else self.modal.absolute_xyz) for a in AXES])
        start = np.rint(self.written * scale).astype(np.int64)
        ints = np.rint(self.to_program(targets_mm) * scale).astype(np.int64)
        marlin = self.min_steps and curves is None
        if marlin:
            crossing = self.min_steps > 1 and self.crossings
            wanted = targets_mm, durations_s, ends_s  # (the rows before they are moved onto crossings)
            if crossing:
                ints, durations_s, ends_s, targets_mm, states = self._on_crossings(
                    start, ints, scale, durations_s, ends_s, targets_mm, exact_last)
            else:
                ints, states = self._shaped(self.to_program(targets_mm) * scale, ints, scale, durations_s, exact_last)
                ints = _merged(start, ints, self.steps_per_mm * self.unit_mm / scale, self.min_steps, exact_last)
            self._keep_rounding(states, len(ints))
            if exact_last:
                self.crossing_from = None
            else:
                # held: the last kept block (a later one may merge it); on crossings from the end before it
                kept = np.flatnonzero((np.diff(np.vstack([start, ints]), axis=0) != 0).any(axis=1))
                last = self._held_from(kept, wanted[2], ends_s, wanted[0], targets_mm, scale) if crossing else \
                    (kept[-1] if len(kept) else 0)
                self._keep_rounding(states, last)
                self.held = _held(*wanted, ends_s, last)
                targets_mm, durations_s, ends_s, ints = (x[:last] for x in (targets_mm, durations_s, ends_s, ints))
        steps = np.diff(np.vstack([start, ints]), axis=0)
        moved = steps != 0
        moving = moved.any(axis=1)
        jump = np.zeros(len(steps))
        if marlin:  # (of the moving blocks alone: two in three rows are merged away)
            length = np.zeros(len(steps))
            length[moving], jump[moving] = self._marlin_lengths(start, ints[moving], scale)
        else:
            length = _lengths(steps / scale * self.unit_mm)
        if curves is not None:
            offsets = self._curve_offsets(curves, start, ints, scale, length, moved, moving)
        self.written_s, self.written_mm = ends_s[moving], targets_mm[moving]
        # where the firmware goes: Marlin's whole steps (else the targets: 0.1 um from them)
        self.stepped_mm = self.to_machine(ints[moving] / scale) if marlin else self.written_mm
        rows = slice(None) if moving.all() else moving  # nearly always all of them: no copies
        feed, self.residue_s, self.speed_mm_s = _feeds(length, durations_s, moving, self.residue_s,
                                                       60.0 * 10 ** _FEED_DECIMALS / self.unit_mm,
                                                       self.speed_mm_s, self.ramp_mm_s2, jump)
        new_feed = feed != np.concatenate([[self.feed], feed[:-1]])  # F only where it changes
        if len(feed):
            self.feed = int(feed[-1])
        if len(ints):
            self.written = np.where(relative, self.written + (ints[-1] - start) / scale, ints[-1] / scale)
        values = np.column_stack([np.where(relative, steps, ints)[rows], feed])
        shown = np.column_stack([moved[rows], new_feed])
        digits = np.append(digits, _FEED_DECIMALS)
        letters, g5 = "".join(AXES) + "F", np.zeros(len(feed), bool)
        if curves is not None:
            g5 = curves.curve[rows]
            values = np.column_stack([offsets[rows], values])
            shown = np.column_stack([np.repeat(g5[:, None], 4, axis=1), shown])
            digits = np.concatenate([digits[[0, 1, 0, 1]], digits])
            letters = "IJPQ" + letters
        # By _LINES: more lines at once format two to three times slower (measured: the
        # temporaries outgrow the CPU cache).
        return b"".join(_lines(values[a:a + _LINES], shown[a:a + _LINES], digits, letters, self.newline,
                               g5[a:a + _LINES]) for a in range(0, len(feed), _LINES)), len(feed)

    def _curve_offsets(self, curves: Curves, start: np.ndarray, ints: np.ndarray, scale: np.ndarray,
                       length: np.ndarray, moved: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """The G5 blocks' I J P Q in integer units of the last digit; their rounded curves'
        lengths into ``length``, and their ends shown (``moved``, ``moving``), in place.

        Control points rounded as written: I J (P Q) are the rounded point minus the rounded
        start (end), as the controller adds them to the positions it has. The rounded curve is
        what it times: its length differs from the fitted one's by up to 1e-2 on short curves."""
        xy_scale = scale[:2]
        origins = np.vstack([start, ints[:-1]])[:, :2]  # where each block starts
        offsets = np.column_stack([
            np.rint(self.to_program(curves.p1_mm, slice(0, 2)) * xy_scale).astype(np.int64) - origins,
            np.rint(self.to_program(curves.p2_mm, slice(0, 2)) * xy_scale).astype(np.int64) - ints[:, :2]])
        g5_rows = np.flatnonzero(curves.curve)
        p0, p3 = origins[g5_rows], ints[g5_rows, :2]
        length[g5_rows] = curve_lengths(p0 / xy_scale, (p0 + offsets[g5_rows, :2]) / xy_scale,
                                        (p3 + offsets[g5_rows, 2:]) / xy_scale, p3 / xy_scale) * self.unit_mm
        moved[:, :2] |= curves.curve[:, None]  # G5 needs its end point, also where it closes a loop
        moving |= curves.curve
        return offsets


def _held(targets_mm: np.ndarray, durations_s: np.ndarray, ends_s: np.ndarray, moved_ends_s: np.ndarray,
          last: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows from ``last`` on, held for the next call: as wanted (not moved onto crossings, so
    that the next call sees the rows one call would), the first from the end written before it
    (``moved_ends_s``: the ends as moved)."""
    before_s = moved_ends_s[last - 1] if last else ends_s[0] - durations_s[0]
    return targets_mm[last:], np.diff(np.append(before_s, ends_s[last:])), ends_s[last:]


def _moved_in_time(kept: np.ndarray, shift_s: np.ndarray, durations_s: np.ndarray,
                   ends_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows' durations and end times with the ``kept`` rows' ends moved by ``shift_s``, the
    next row taking up the difference (the last kept row is not moved)."""
    durations_s, ends_s = durations_s.copy(), ends_s.copy()
    durations_s[kept] += shift_s
    durations_s[kept[:-1] + 1] -= shift_s[:-1]
    ends_s[kept] += shift_s
    return durations_s, ends_s


def _last_in_both(plain: np.ndarray, kept: np.ndarray, ends_s: np.ndarray) -> int | None:
    """The last row kept both by Marlin's merge of the rows rounded (``plain``: row 0 the start)
    and in the end (``kept``), but for the merge's last (a later row may merge it), that ends
    (``ends_s``) where the lattice has settled its end given the rows up to that one
    (``steps.settled_before``); None: none."""
    both = np.intersect1d(kept, np.flatnonzero((np.diff(plain, axis=0) != 0).any(axis=1))[:-1])
    if len(both):
        both = both[ends_s[both] < settled_before(ends_s[both[-1]])]
    return int(both[-1]) if len(both) else None


def _rounded_ends(rounding: list, rounding_state: list, ends: np.ndarray, spu: np.ndarray, knots_s: np.ndarray,
                  kept: np.ndarray, exact_last: bool, times_s: np.ndarray, units: np.ndarray,
                  knot_from: np.ndarray, plain: np.ndarray, min_steps: int) -> tuple:
    """The kept blocks' ``ends`` (written units, at ``knots_s[1:]``; ``knots_s[0]`` the end
    before them, at ``knot_from``) with X Y Z on whole steps, each axis by its ``rounding``
    (``steps``) from its ``rounding_state``: the axes with modes together on the lattice
    (``steps.Lattice``: the chords between the ends solved through the modes against the
    wanted rows, ``units`` at ``times_s``, row 0 the start), each block kept by Marlin's merge
    (``min_steps`` on some axis; the other axes' steps as in ``plain``, the merge's ends, row 0
    the start); and the rounding's states before each row and after the last."""
    rounded, states = np.rint(ends).astype(np.int64), [None] * 3
    before = np.searchsorted(kept, np.arange(len(units)))  # each row: how many kept rows come before it
    later = times_s > knots_s[0]  # the wanted motion from the end before the kept ones
    wanted_s = np.append(knots_s[0], times_s[later])
    on_lattice = np.array([isinstance(r, ModalRounding) for r in rounding] + [False] * (len(spu) - 3)) & (spu > 0)
    lattices = []
    for i in np.flatnonzero(spu[:3] > 0):
        wanted = ends[:, i] * spu[i]
        wanted = np.where(np.abs(wanted - np.rint(wanted)) < 1e-6, np.rint(wanted), wanted)  # (on a step)
        if on_lattice[i]:
            last = float(np.rint(wanted[-1])) if exact_last else None
            lattices.append(rounding[i].lattice(wanted_s, np.append(knot_from[i], units[later, i]) * spu[i],
                                                knots_s[1:], rounding_state[i], last, wanted))
            continue
        counts, st = rounding[i].round(wanted, np.diff(knots_s), rounding_state[i])
        rounded[:, i], states[i] = np.rint(counts / spu[i]), st[before]
    others = np.flatnonzero((spu > 0) & ~on_lattice)
    at_steps = np.rint(plain[np.append(0, kept + 1)][:, others] * spu[others])
    lattice_counts(lattices, (np.abs(np.diff(at_steps, axis=0)) >= min_steps).any(axis=1), min_steps)
    for i, lattice in zip(np.flatnonzero(on_lattice), lattices, strict=True):
        rounded[:, i], states[i] = np.rint(lattice.counts / spu[i]), lattice.states[before]
    if exact_last:
        for st in states:
            if st is not None:
                st[-1] = 0.0
    return rounded, states


def _lengths(delta_mm: np.ndarray, xyz_moves: np.ndarray | None = None) -> np.ndarray:
    """What a controller times each block by: its XYZ length where XYZ move (``xyz_moves``, by
    default where they move at all), else its U V W, A B C (LinuxCNC) or E length."""
    return feed_lengths(delta_mm, xyz_moves)[0]


def _merged(start: np.ndarray, ints: np.ndarray, steps_per_unit: np.ndarray, min_steps: int,
            exact_last: bool) -> np.ndarray:
    """Block ends (rows of written units; ``start``: where the controller is) with every block
    that Marlin would merge (fewer than ``min_steps`` steps on every axis from the last block
    kept, steps as Marlin rounds the positions) moved back onto that block's end: a block of no
    motion, whose time the next block takes. With ``exact_last`` the last end is kept, merging
    instead the kept blocks before it that are near it."""
    ends = np.vstack([start, ints])
    stepped = steps_per_unit > 0  # (the other columns never step)
    at_steps = np.rint(ends[:, stepped] * steps_per_unit[stepped])
    following = _next_far(at_steps, min_steps)
    if following == list(range(1, len(ends) + 1)):
        return ints
    # The kept rows: the start, then from each kept row the next one far from it.
    kept, k, n = [], 0, len(ends)
    while k < n:
        kept.append(k)
        k = following[k]
        if k < 0:
            k = _next_far_of(at_steps, kept[-1], min_steps)
    if exact_last and kept[-1] != len(ints):  # the kept rows near the last end go instead
        while len(kept) > 1 and np.abs(at_steps[kept[-1]] - at_steps[-1]).max(initial=0.0) < min_steps:
            kept.pop()
        kept.append(len(ints))
    source = np.repeat(kept, np.diff(np.append(kept, n)))  # each row: the last kept at or before it
    return ends[source[1:]]


# Rows looked ahead at once for the next row far from each. On the gear at Marlin's steps most
# find it 3 to 6 rows ahead; the 2% further go row by row (8: the merge 30% faster than 16).
_NEAR_ROWS = 8


def _next_far(at_steps: np.ndarray, min_steps: int) -> list[int]:
    """For each row, the first later row at least ``min_steps`` from it on some column (the
    row count where there is none; -1 where it is more than ``_NEAR_ROWS`` ahead: see
    ``_next_far_of``)."""
    n = len(at_steps)
    following = np.full(n, -1, dtype=np.int64)
    rows = np.arange(n)
    columns = [np.ascontiguousarray(at_steps[:, j]) for j in range(at_steps.shape[1])]
    # (whole columns a row apart: faster than gathering the rows still open, most of them are)
    for ahead in range(1, min(_NEAR_ROWS, n - 1) + 1):
        far = np.zeros(n - ahead, dtype=bool)
        for column in columns:
            far |= np.abs(column[ahead:] - column[:-ahead]) >= min_steps
        found = far & (following[:-ahead] < 0)
        following[:-ahead][found] = rows[:-ahead][found] + ahead
        if (following[:-ahead] >= 0).all():
            break
    following[(following < 0) & (rows >= n - 1 - _NEAR_ROWS)] = n  # every later row looked at
    return following.tolist()


def _next_far_of(at_steps: np.ndarray, row: int, min_steps: int) -> int:
    """The first row after ``row`` at least ``min_steps`` from it on some column (the row count
    where there is none), looked for in ever longer stretches."""
    first, size = row + 1, 4 * _NEAR_ROWS
    while first < len(at_steps):
        gap = np.abs(at_steps[first:first + size] - at_steps[row]).max(axis=1, initial=0.0)
        far = np.flatnonzero(gap >= min_steps)
        if len(far):
            return first + int(far[0])
        first, size = first + size, 2 * size
    return len(at_steps)


def _feeds(length_mm: np.ndarray, durations_s: np.ndarray, moving: np.ndarray, residue_s: float,
           units_per_mm_s: float, speed_mm_s: float = 0.0, ramp_mm_s2: float = math.inf,
           jump_mm_s: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """The F of each moving block (integer units of its last digit; ``units_per_mm_s`` per mm/s),
    the time residue left after them and the last block's speed (``speed_mm_s``: the one's before).

    The controller times a block as its length over its F, and F is rounded: each block is
    given its duration plus the residue (the time the blocks before it were written short of
    theirs, and the whole time of blocks that round to no motion, which are not written), so the
    written time never drifts from the command's by more than one block's rounding. The firmware
    ramps from one block's speed to the next at ``ramp_mm_s2``, inside the faster one, and arrives
    (dv)^2 / (2 ramp max(v)) late: the next block makes that up too. (Where the residue is more
    negative than half a block's duration, the block keeps half its own and the rest goes on.)
    Marlin enters a faster block at once up to its ``jump_mm_s`` (see ``_Emitter._marlin_lengths``).
    """
    residue_s = float(residue_s)  # (a numpy scalar makes every step of the loop three times slower)
    feeds = []
    add = feeds.append
    ramped = ramp_mm_s2 != math.inf
    # (One line per block, the slowest loop of the writer: max() and the ramp's term only where they count.)
    lengths = (length_mm * units_per_mm_s).tolist()
    jumps = [0.0] * len(lengths) if jump_mm_s is None else jump_mm_s.tolist()
    for length_units_s, duration, moves, jump in zip(lengths, durations_s.tolist(), moving.tolist(), jumps,
                                                     strict=True):
        residue_s += duration
        if moves:
            half = 0.5 * duration
            feed = round(length_units_s / (residue_s if residue_s >= half else half))
            if feed < 1:
                feed = 1
            add(feed)
            residue_s -= length_units_s / feed
            speed = feed / units_per_mm_s
            if ramped:
                lower_mm_s = speed_mm_s if speed_mm_s >= jump else jump
                step = speed - lower_mm_s if speed > speed_mm_s else speed_mm_s - speed
                if step > 0.0:
                    residue_s -= step ** 2 / (2.0 * ramp_mm_s2 * (speed if speed >= speed_mm_s else speed_mm_s))
            speed_mm_s = speed
    return np.array(feeds, dtype=np.int64), residue_s, speed_mm_s


def _digits(width: int, form: str) -> np.ndarray:
    """(10**width, width) characters of 0 .. 10**width - 1: zero-padded ("full"), leading zeros
    dropped ("lead": 0 is no text; "lead0": 0 is "0"), trailing zeros dropped ("trail": 0 is no
    text). Dropped characters are NUL."""
    numbers = np.arange(10 ** width)[:, None]
    place = 10 ** np.arange(width - 1, -1, -1)
    keep = {"full": True, "lead": numbers >= place, "lead0": (numbers >= place) | (place == 1),
            "trail": numbers % (10 * place) != 0}[form]
    return (numbers // place % 10 + ord("0")).astype(np.uint8) * keep


def _pointed(chars: np.ndarray) -> np.ndarray:
    """A decimal point before the rows of characters that have any."""
    return np.hstack([np.where(chars.any(axis=1, keepdims=True), ord("."), 0).astype(np.uint8), chars])


def _packed(*tables: np.ndarray) -> np.ndarray:
    """Rows of four characters, the tables one after the other, as one uint32 per row."""
    return np.concatenate(tables).view(np.uint32).ravel()


# _lines writes numbers from four-character pieces looked up by value (plus the offset of
# their form), NUL where the shortest text has no character. The integer part, by four digits:
_INT_PART = _packed(_digits(4, "lead"), _digits(4, "lead0"), _digits(4, "full"))
_LEAD, _LEAD0, _FULL = 0, 10000, 20000
# The fractional part, always at 7 decimals (every _DECIMALS and _FEED_DECIMALS fit): the point
# and three digits (+ 1000: digits follow), then four digits.
_FRACTION_DECIMALS = 7
_FRACTION_HIGH = _packed(_pointed(_digits(3, "trail")), _pointed(_digits(3, "full")))
_FRACTION_LOW = _packed(_digits(4, "trail"))
_LETTERS = "IJPQ" + "".join(AXES) + "F"
_WORD_HEADS = _packed(np.array([[ord(" "), ord(letter), 0, 0] for letter in _LETTERS], np.uint8))
_MINUS, _G1, _G5 = np.frombuffer(b"\0\0-\0G1\0\0G5\0\0", np.uint32)  # " X" + _MINUS is " X-"


def _lines(values: np.ndarray, shown: np.ndarray, digits: np.ndarray, letters: str, newline: bytes,
           g5: np.ndarray) -> bytes:
    """The text of one line per row of ``values`` (n, k: the words ``letters`` as integers in
    units of 10**-``digits``, at most 7 digits), G5 where ``g5`` else G1, with the words that
    are ``shown``, each line ended by ``newline``. Numbers are the shortest decimal: "12.34",
    "-0.005", "0".

    Formatting value by value takes tens of seconds for a million lines, so the rows are built
    together: every word is the same row of four-character pieces (" X-", the integer digits in
    groups of four, ".ddd", "dddd") looked up by value, the characters the short text does not
    have are NUL, and one pass removes the NULs.
    """
    n, k = values.shape
    scaled = values * 10 ** (_FRACTION_DECIMALS - digits)  # the added zeros trail: dropped like any
    magnitude = np.where(shown, np.abs(scaled), 0)
    whole = magnitude // 10 ** _FRACTION_DECIMALS
    fraction = magnitude - whole * 10 ** _FRACTION_DECIMALS
    int_groups = -(-len(str(int(whole.max(initial=0)))) // 4)
    slots = 3 + int_groups
    words = np.empty((n, k, slots), np.uint32)
    heads = np.take(_WORD_HEADS, [_LETTERS.index(letter) for letter in letters])
    words[:, :, 0] = np.where(shown, heads + (scaled < 0) * _MINUS, 0)
    rest = whole
    for slot in range(int_groups, 0, -1):  # least significant group first: are there digits above?
        above = rest // 10000
        form = np.where(above > 0, _FULL, shown * _LEAD0 if slot == int_groups else _LEAD)
        words[:, :, slot] = np.take(_INT_PART, rest - above * 10000 + form)
        rest = above
    high = fraction // 10000
    low = fraction - high * 10000
    words[:, :, -2] = np.take(_FRACTION_HIGH, high + (low > 0) * 1000)
    words[:, :, -1] = np.take(_FRACTION_LOW, low)
    line = np.empty((n, 2 + k * slots), np.uint32)
    line[:, 0] = np.where(g5, _G5, _G1)
    line[:, 1:-1] = words.reshape(n, k * slots)
    line[:, -1] = np.frombuffer(newline.ljust(4, b"\0"), np.uint32)[0]
    return line.tobytes().translate(None, b"\0")


def mode_lines(flavor: str, have: Modal, want: Modal) -> list[str]:
    """Lines that bring the controller from modes ``have`` to ``want`` (plane, distance modes,
    units)."""
    lines = [f"G{want.plane}"] if have.plane != want.plane else []
    if have.inches != want.inches:
        lines.append("G20" if want.inches else "G21")
    if have.absolute_xyz != want.absolute_xyz:
        lines.append("G90" if want.absolute_xyz else "G91")
        if flavor != "linuxcnc":  # G90/G91 set E's mode too
            have = Modal(want.absolute_xyz, want.absolute_xyz, want.inches, have.offsets_mm)
    if flavor != "linuxcnc" and have.absolute_e != want.absolute_e:
        lines.append("M82" if want.absolute_e else "M83")
    return lines


def dwell_line(flavor: str, dwell_s: float) -> tuple[str, float]:
    """The flavor's G4 for about ``dwell_s`` seconds, and how long it dwells: Klipper and LinuxCNC
    read a fraction (to the microsecond here), Marlin and RepRapFirmware whole milliseconds."""
    if flavor in ("klipper", "linuxcnc"):
        us = round(dwell_s * 1e6)
        value = us / 1e6 if flavor == "linuxcnc" else us / 1e3  # LinuxCNC: P in seconds
        return f"G4 P{value:.6f}".rstrip("0").rstrip("."), us / 1e6
    ms = round(dwell_s * 1e3)
    return f"G4 P{ms}", ms / 1e3


class SampleWindow:
    """The planned and the commanded samples (rows X Y Z E, machine mm) as an iterator of
    (planned, command) chunks produces them, in order; rows before ``release``'s index are
    dropped, so a long program's samples are never all held. ``plan`` (``PlanStream``) tells
    how many there are once it is done. ``follows_plan`` (len(AXES),) marks the columns the command
    leaves as planned (E, axes without modes): blocks end exactly where the program puts them."""

    def __init__(self, chunks: Iterable[tuple[np.ndarray, np.ndarray]], plan, follows_plan: np.ndarray):
        self._chunks = iter(chunks)
        self._plan = plan
        self.follows_plan = np.asarray(follows_plan, dtype=bool)
        self.base = 0  # sample index of the first row held
        self.planned = self.command = np.zeros((0, len(AXES)))

    @property
    def end(self) -> int:
        return self.base + len(self.command)

    @property
    def n_samples(self) -> int | None:
        """None until the plan is done."""
        return self._plan.n_samples if self._plan.done else None

    def ensure(self, stop: int) -> None:
        """Hold the samples up to ``stop`` - 1 (at most the last)."""
        planned, command, end = [self.planned], [self.command], self.end
        while end < stop:
            try:
                p, c = next(self._chunks)
            except StopIteration:
                break
            planned.append(p)
            command.append(c)
            end += len(c)
        if len(command) > 1:
            self.planned, self.command = np.concatenate(planned), np.concatenate(command)

    def release(self, first: int) -> None:
        """Rows before sample ``first`` are no longer needed."""
        drop = min(max(first - self.base, 0), len(self.command))
        if drop > len(self.command) // 2:  # copy seldom: the rows kept are a fraction of those dropped
            self.planned, self.command = self.planned[drop:].copy(), self.command[drop:].copy()
            self.base += drop

    def rows(self, first: int, stop: int) -> np.ndarray:
        """Commanded samples first .. stop - 1."""
        assert first >= self.base, "samples asked for after their release"
        self.ensure(stop)
        return self.command[first - self.base:stop - self.base]

    def at(self, t_s: np.ndarray, fs: float, planned: bool = False) -> np.ndarray:
        """Linear interpolation of the commanded (or planned) samples at the times ``t_s``."""
        x = np.maximum(t_s * fs, 0.0)
        self.ensure(int(x.max(initial=0)) + 2)
        n = self.n_samples
        if n is not None:  # (else every row asked for is there)
            x = np.minimum(x, n - 1.0)
        k = x.astype(np.int64) if n is None else np.minimum(x.astype(np.int64), max(n - 2, 0))
        assert k.min(initial=self.base) >= self.base, "samples asked for after their release"
        columns = self.planned if planned else self.command
        w = (x - k)[:, None]
        k = k - self.base
        below, above = np.take(columns, k, axis=0), np.take(columns, np.minimum(k + 1, len(columns) - 1), axis=0)
        return below * (1.0 - w) + above * w  # (np.take gathers rows a few times faster than indexing)


class _LineRate:
    """The most lines in any second, from the lines' times as they come (non-decreasing)."""

    def __init__(self):
        self.recent = np.zeros(0)  # the times within a second of the last
        self.max_per_s = 0

    def add(self, times_s) -> None:
        times = np.concatenate([self.recent, np.atleast_1d(np.asarray(times_s, dtype=float))])
        if len(times) > len(self.recent):
            new = np.arange(len(self.recent), len(times))
            inside = new + 1 - np.searchsorted(times, times[new] - 1.0, "right")  # in (t - 1 s, t]
            self.max_per_s = max(self.max_per_s, int(inside.max()))
            self.recent = times[np.searchsorted(times, times[-1] - 1.0, "right"):]


class _Deviation:
    """How far the written blocks, each run at constant speed, are from the command at the same
    time, over the samples inside them (XYZ): the largest, where, and the time in blocks beyond
    the tolerance (rounding aside)."""

    def __init__(self, samples: SampleWindow, fs: float, tolerance_mm: float, executed=None):
        self.samples, self.fs, self.tolerance_mm, self.executed = samples, fs, tolerance_mm, executed
        self.last_s = 0.0  # the last written block's end
        self.last_mm = self.last_stepped_mm = None  # its end: as written, as stepped
        self.max_mm = self.at_s = self.loosened_s = self.sum_squares_mm2 = 0.0
        self.count = 0

    def add(self, start_s: float | None, ends_s: np.ndarray, targets_mm: np.ndarray, stepped_mm: np.ndarray) -> None:
        """Blocks from ``start_s`` (None: the last block's end) to each of ``ends_s``: ``targets_mm``
        as written, ``stepped_mm`` where the firmware puts them (its whole steps: executed)."""
        if not len(ends_s):
            return
        # A run starts where the command is; a later batch where the last block ended, so that
        # the chords do not depend on where the stream cut the blocks.
        run_start = start_s is not None or self.last_mm is None
        start_s = self.last_s if start_s is None else start_s
        knots_s = np.append(start_s, ends_s)
        grid_s = np.arange(math.ceil(start_s * self.fs), math.floor(ends_s[-1] * self.fs) + 1) / self.fs

        def chords(ends_mm: np.ndarray, last_mm: np.ndarray | None) -> np.ndarray:
            first_mm = self.samples.at(knots_s[:1], self.fs)[0] if run_start else last_mm
            knots_mm = np.vstack([first_mm, ends_mm])[:, :3]
            return np.column_stack([np.interp(grid_s, knots_s, knots_mm[:, c]) for c in range(3)])

        chord, command = chords(targets_mm, self.last_mm), self.samples.at(grid_s, self.fs)[:, :3]
        off_mm = np.linalg.norm(chord - command, axis=1)
        self.sum_squares_mm2 += float(off_mm @ off_mm)
        self.count += len(off_mm)
        # the largest: of the blocks as the firmware runs them (Marlin's ends on the lattice can be steps away)
        executed = chord if stepped_mm is targets_mm else chords(stepped_mm, self.last_stepped_mm)
        far_mm = np.linalg.norm(executed - command, axis=1)
        if len(far_mm) and far_mm.max() > self.max_mm:
            self.max_mm, self.at_s = float(far_mm.max()), float(grid_s[far_mm.argmax()])
        block = np.searchsorted(ends_s, grid_s, "left")
        worst = np.zeros(len(ends_s))
        np.maximum.at(worst, block, off_mm)
        # (rounding: 0.1 um per axis)
        self.loosened_s += float(np.diff(knots_s)[worst > self.tolerance_mm + 1e-4].sum())
        if self.executed is not None and len(grid_s):
            first = round(grid_s[0] * self.fs)
            self.rest_until(first)
            skip = max(self.executed.next - first, 0)  # (a block's start is the last one's end)
            planned = self.samples.at(grid_s[skip:], self.fs, planned=True)[:, :3]
            self.executed.add(first + skip, executed[skip:], planned)
        self.last_s, self.last_mm, self.last_stepped_mm = float(ends_s[-1]), targets_mm[-1], stepped_mm[-1]

    def rest_until(self, stop: int) -> None:
        """The executed program where the plan has it, from the last sample given up to ``stop``."""
        if self.executed is not None and stop > self.executed.next:
            rest = self.samples.at(np.arange(self.executed.next, stop) / self.fs, self.fs, planned=True)[:, :3]
            self.executed.add(self.executed.next, rest, rest)


class _Output:
    """The output program's text. Takes lines to write (each ended by the program's newline,
    counted in ``stats`` and in the line rate at ``written_until_s``) and the program's lines to
    copy as they are; a copied line without a line ending gets one when more follows it."""

    def __init__(self, out, flavor: str):
        self._out, self._flavor = out, flavor
        self.stats = WriteStats()
        self.newline = b"\n"
        self.rate = _LineRate()
        self.written_until_s = 0.0  # the end of the last block written: the time of lines written now
        self._unterminated = False  # the last copied line had no line ending (the end of the file)

    def text(self, text: bytes, count: int) -> None:
        """Write ``count`` lines, each ended by the newline."""
        if count:
            self._out.write((self.newline if self._unterminated else b"") + text)
            self.stats.lines_out += count
            self._unterminated = False

    def lines(self, *lines: str) -> None:
        self.text(b"".join(x.encode() + self.newline for x in lines), len(lines))
        self.rate.add([self.written_until_s] * len(lines))

    def dwell(self, seconds: float) -> float:
        """A G4 for about ``seconds`` (none where it rounds to nothing); gives how long it dwells."""
        line, dwell_s = dwell_line(self._flavor, seconds)
        if dwell_s > 0:
            self.lines(line)
        return dwell_s

    def copy(self, raw: bytes) -> None:
        """One of the program's lines, byte for byte."""
        self._out.write(raw)
        self._unterminated = not raw.endswith((b"\n", b"\r"))
        self.stats.lines_out += 1
        self.stats.passthrough_lines += 1


class _RunWriter:
    """The runs of motion as blocks. Takes the plan's runs and the command (``SampleWindow``);
    writes the blocks from where the output is up to a time (``until``): their ends (dense:
    ``_Breaks``, as the samples come; G5: ``g5_blocks``, each run fitted whole), the firmware's
    settings before them, a dwell for the blocks at a run's start that round to no motion, and
    the end of each run. ``emitter`` formats them (set before the first call)."""

    def __init__(self, plan: PlanStream, samples: SampleWindow, options: WriteOptions, output: _Output,
                 settings: Transparency | None, executed=None):
        self._plan, self._samples, self._options, self._out, self._settings = plan, samples, options, output, settings
        self._fs = fs = plan.sample_rate_hz
        min_segment_s = max(options.min_segment_time_s, shortest_line_s(options.max_line_rate_hz))
        self._min_samples = max(1, int(np.ceil(min_segment_s * fs - 1e-9)))
        self.deviation = _Deviation(samples, fs, options.tolerance_mm, executed)
        self.emitter: _Emitter | None = None
        self.copied_sample = -1  # of the last copied line
        self.dwelt_s = 0.0  # the dwells of the lines at rest since the last block (the controller's time: +)
        self.run_index = 0  # the run being written
        self.run_from_s = None  # the run's start while none of its blocks is written (then None)
        self.latency_s = _marlin_start_latency_s(options)
        self._run_breaks, self._run_g5 = None, None  # the current run's block ends (dense) or blocks and curves (g5)

    def runs_from(self, r: int) -> bool:
        """Whether the program has a run r (or later)."""
        plan = self._plan
        plan.wait(lambda: len(plan.runs) > r or plan.done)
        return len(plan.runs) > r

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
            still = _still_as_dwell(emitter, out.dwell, from_s, ends, targets, self.latency_s) if run_start else 0
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
        # (_start_dwell); the next run's G4 takes the time up (_still_as_dwell), the copied lines
        # run that much earlier, X and Y at rest already.
        if self.latency_s is None:
            self.emitter.residue_s -= self._out.dwell(self.emitter.residue_s)
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
                ahead.append(_copied_sample(line_time_s, is_stop, self._fs, ahead[-1]))
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
        """``_block_ends`` of the dense format: ``_Breaks`` fed the run's samples as they settle."""
        plan, fs = self._plan, self._fs
        if self._run_breaks is None:
            self._run_breaks = _Breaks(None, self._options.tolerance_mm, self._min_samples)
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


class _ProgramWriter:
    """The output program (``write_program``): the program's lines in order, the copied ones at
    their times with the blocks before them (``_RunWriter``), the header comments before the
    first line of code, the modes and the firmware's settings where the copied lines need them."""

    def __init__(self, plan: PlanStream, samples: SampleWindow, options: WriteOptions, out, executed=None):
        self._plan, self._samples, self._options, self._executed = plan, samples, options, executed
        self._fs = plan.sample_rate_hz
        self._settings = None if options.firmware is None else \
            Transparency(options.flavor, options.firmware, options.tolerance_mm)
        self._out = _Output(out, options.flavor)
        self._motion = _RunWriter(plan, samples, options, self._out, self._settings, executed)
        self._previous_modal, self._previous_mm = Modal(), np.full(len(AXES), np.nan)

    def write(self) -> WriteStats:
        header_done = False
        last_line = None
        motion, out = self._motion, self._out
        for block, line_time_s, is_stop in self._plan.blocks():
            if motion.emitter is None:
                out.newline = b"\r\n" if block.raw.endswith(b"\r\n") else b"\n"  # (only the last line has no ending)
                steps = None if self._options.steps_per_mm is None else np.asarray(self._options.steps_per_mm)
                motion.emitter = _Emitter(self._samples.rows(0, 1)[0], out.newline, steps,
                                          self._options.min_steps_per_segment,
                                          math.inf if self._settings is None else self._settings.ramp_mm_s2,
                                          self._options.axis_modes)
            if not header_done and _is_code(block):
                self._header()
                header_done = True
            if block.kind is Kind.MOVE:
                self._previous_modal, self._previous_mm = block.modal, block.position_mm
                # the next copied line runs at or after the sample nearest the end of this motion
                flush_s = line_time_s - 1.0 / self._fs
                if flush_s - out.written_until_s >= _FLUSH_S:  # (else it writes nothing: called per CAM line)
                    motion.until(flush_s, soft=True)
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
        motion.copied_sample = _copied_sample(line_time_s, is_stop, fs, motion.copied_sample)
        t = motion.copied_sample / fs
        motion.until(t, previous_mm)  # the motion before the line ends where the program was before it
        if settings is not None and is_stop and _may_move(previous_mm, block.position_mm, slice(None)):
            # a move fbspost copies runs under the program's own settings (shaping: where it moves X or Y)
            moves_xy = _may_move(previous_mm, block.position_mm, slice(0, 2))
            out.lines(*settings.restore(shaping=moves_xy))
            if motion.emitter.speed_mm_s > 0 and motion.latency_s is None:
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
        out.lines(*_program_feed(self._options.flavor, block, motion.emitter.feed != -1))
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
            motion.emitter = _Emitter(np.zeros(len(AXES)), out.newline)
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
    (``transparency``). ``executed`` (``pipeline.ExecutedError``) is given the written program's
    motion as the firmware runs it, sample by sample.
    """
    refusal = format_refusal(options.flavor, options.output_format)
    if refusal:
        raise ValueError(refusal)
    return _ProgramWriter(plan, samples, options, out, executed).write()


_FEED = 1 << 14  # samples given to the block-end search at once
_FLUSH_S = 10.0  # motion written without waiting for a copied line, once this much is due


def _marlin_start_latency_s(options: WriteOptions) -> float | None:
    """Marlin: how late a run's first block starts after a G4 (None: not Marlin). Marlin's stepper
    starts a block added to an empty buffer once 3 are queued, or after 100 ms (planner.cpp
    ``get_current_block``): the run's third block is taken three line times after the G4."""
    if options.flavor != "marlin":
        return None
    return 3.0 / options.max_line_rate_hz if options.max_line_rate_hz else 0.0


def _start_dwell(dwell, rest_s: float, latency_s: float | None) -> tuple[float, float]:
    """The G4 before a run's first block, for ``rest_s`` of rest: (its dwell, the latency it takes:
    on Marlin, ``latency_s`` not None, the run starts that much after the G4, which dwells less;
    none where the rest is within that latency: the G4 would hold the blocks before it in the
    buffer for BLOCK_DELAY_FOR_1ST_MOVE, the rest is better the first block's, slower)."""
    if latency_s is None:
        return dwell(rest_s), 0.0
    if dwell_line("marlin", rest_s - latency_s)[1] > 0:
        return dwell(rest_s - latency_s), latency_s
    return 0.0, 0.0


def shortest_line_s(max_line_rate_hz: float | None) -> float:
    """The shortest block at a line rate (None: no limit): a line's share of 90% of it, the rest
    left to the other lines (the copied ones), so that the host stays ahead of the firmware."""
    return 1.0 / (0.9 * (max_line_rate_hz or math.inf))


def shortest_block_s(profile: MachineProfile, flavor: str) -> float:
    """The shortest block time ``flavor``'s firmware runs as written on ``profile``: the line
    budget of the profile's max_line_rate (``shortest_line_s``); on LinuxCNC also 2 servo
    periods (its planner caps a block's speed at length / 1.02 servo periods, and shorter blocks
    ran late and off the path on LinuxCNC itself: docs/linuxcnc.md)."""
    shortest_s = shortest_line_s(profile.firmware.max_line_rate_hz)
    if flavor == "linuxcnc":
        shortest_s = max(shortest_s, 2.0 * profile.firmware.linuxcnc.servo_period_s)
    return shortest_s


def _still_as_dwell(emitter: _Emitter, dwell, from_s: float, ends_s: np.ndarray, targets_mm: np.ndarray,
                    latency_s: float | None) -> int:
    """At a run's start (from ``from_s``), the first blocks (ends ``ends_s``, ``targets_mm``) that round
    to no motion as a dwell (``dwell``: writes one for about the seconds given, gives how long it
    dwells), not as a slow first block: how many it stands for (0: none, or the dwell rounds to none).
    On Marlin (``latency_s`` not None) the dwell also takes up what the last run's end left
    (``_RunWriter._end_run``), with or without such blocks."""
    still = emitter.still(targets_mm[:-1])
    if still or latency_s is not None:
        span_s = ends_s[still - 1] - from_s if still else 0.0
        dwell_s, late_s = _start_dwell(dwell, span_s + emitter.residue_s, latency_s)
        if dwell_s > 0:
            emitter.residue_s += span_s - dwell_s - late_s
            return still
    return 0


def timed_blocks(command_mm: np.ndarray, block_s: float, options: WriteOptions) -> list[str]:
    """The lines that run a sampled command (rows X Y Z E, machine mm, one every ``block_s``; at
    rest at the first row, where the firmware is) as blocks of ``block_s`` each on
    ``options.flavor``'s firmware, made transparent by ``options.firmware``'s ``Transparency``
    (whose lines the caller writes around them): F from each block's time with the residues and
    ramps carried, Marlin's whole steps and merge with ``options``' steps (``_Emitter``), a dwell
    for the first blocks that round to no motion and one for the time left at the end (the ramp
    down to rest)."""
    ramp_mm_s2 = math.inf if options.firmware is None else \
        Transparency(options.flavor, options.firmware, options.tolerance_mm).ramp_mm_s2
    steps = None if options.steps_per_mm is None else np.asarray(options.steps_per_mm)
    emitter = _Emitter(command_mm[0], b"\n", steps, options.min_steps_per_segment, ramp_mm_s2, options.axis_modes,
                       crossings=False)  # (blocks of equal time: identify's sweep)
    text = io.BytesIO()
    out = _Output(text, options.flavor)
    ends_s, targets_mm = np.arange(1, len(command_mm)) * block_s, command_mm[1:]
    still = _still_as_dwell(emitter, out.dwell, 0.0, ends_s, targets_mm, None)
    from_s = ends_s[still - 1] if still else 0.0
    out.text(*emitter.blocks(targets_mm[still:], np.diff(np.append(from_s, ends_s[still:])), ends_s[still:]))
    out.dwell(emitter.residue_s - emitter.speed_mm_s / (2.0 * emitter.ramp_mm_s2))  # (as a stop, then a run's end)
    return text.getvalue().decode().splitlines()


def _copied_sample(line_time_s: float, is_stop: bool, fs: float, previous: int) -> int:
    """The sample a copied line runs at. The nearest to its planned time (at most half a sample
    off), so that blocks end on samples of the command: a block ending between two samples
    would bend the command there, and ask more acceleration of the controller than the command
    does. A line at rest runs where the run of motion before it has ended: its last sample, the
    time rounded up (rounded to the nearest, the rest of the run would come after the line).
    Lines run in order."""
    return max(math.ceil(line_time_s * fs) if is_stop else round(line_time_s * fs), previous)


def _may_move(before_mm: np.ndarray, after_mm: np.ndarray, axes: slice) -> bool:
    """Whether a line at rest that took the machine from ``before_mm`` to ``after_mm`` (NaN:
    unknown) may have moved one of ``axes`` (columns of AXES): a copied move, homing, a macro."""
    before, after = before_mm[axes], after_mm[axes]
    return bool(np.any(np.isnan(before) | np.isnan(after) | (before != after)))


_F_WORD = re.compile(rb"[Ff]\s*[-+.0-9]")
_COMMENT = re.compile(rb"\([^)]*\)|;.*")


def _program_feed(flavor: str, block: Block, feed_written: bool) -> list[str]:
    """The line that gives a copied move its program's F back, where the move does not say its
    own and the output has written other feeds since the program's last: the firmware would run
    it at the last written block's F (a Z hop at a creeping block's 0.3 mm/s)."""
    feed = block.feed_mm_s
    if not feed_written or feed is None or not math.isfinite(feed) or _F_WORD.search(_COMMENT.sub(b"", block.raw)):
        return []
    value = f"{feed * 60.0 / (25.4 if block.modal.inches else 1.0):.4f}".rstrip("0").rstrip(".")
    return [f"F{value}" if flavor == "linuxcnc" else f"G1 F{value}"]


def _is_code(block: Block) -> bool:
    """Anything but a blank or comment-only line (or a LinuxCNC '%' marker)."""
    text = block.raw.strip()
    return bool(text) and not text.startswith((b";", b"(", b"%"))

