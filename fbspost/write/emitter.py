"""The emitter: blocks formatted in the controller's current modes and frame.

Takes the blocks' targets (machine mm), durations and end times, the G5 curves where there are,
and what the controller does to its modes and frame (the copied lines: ``passthrough``); gives
the G1 / G5 lines' text, F from each block's time with the time residues and the firmware's
ramps carried, relative values carrying their rounding residues, Marlin's whole steps and merge
(``marlinmerge``) where its steps are given, RepRapFirmware's whole steps (each end written in the
cell of the step chosen for it) (``Emitter``, ``_feeds``).
"""
from __future__ import annotations

import math

import numpy as np

from ..firmware.reprap import MIN_RAMP_S
from ..firmware.steps import crossing_ends, rounding_for
from ..read.blocks import AXES, Block, Kind, Modal, feed_lengths
from .bezier import curve_lengths
from .blockends import Curves
from .linetext import DECIMALS, FEED_DECIMALS, line_text
from .marlinmerge import last_in_both, marlin_merged, moved_in_time, rounded_ends
from .stepcells import StepCells

_LINES = 1024  # lines formatted at once



class Emitter:
    """Formats blocks in the controller's current modes and frame.

    ``written`` is where the controller believes it is, in its program coordinates: it changes
    only by what is written (so relative values carry their rounding residues), by G92 and by
    unit changes.
    """

    def __init__(self, start_mm: np.ndarray, newline: bytes, steps_per_mm: np.ndarray | None = None,
                 min_steps: int = 0, ramp_mm_s2: float = math.inf, axis_modes: tuple = (), crossings: bool = True,
                 cells: bool = False):
        self.modal = Modal()  # the controller starts in its defaults
        # the firmware ramps each speed step at this acceleration, losing time the next blocks make up
        self.ramp_mm_s2, self.speed_mm_s = ramp_mm_s2, 0.0
        # Marlin merges a block of fewer than min_steps steps on every axis with the next (steps_per_mm per
        # axis, 0 where not known): such blocks are merged here, where their time can go with them
        self.steps_per_mm, self.min_steps, self.crossings = steps_per_mm, min_steps, crossings
        self.cells = StepCells() if cells else None  # RRF: no merge, each end written in its step's cell
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
        is, not where the plan is: keep the difference. A copied move or homing puts the controller
        where the plan says (the command is at rest there)."""
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
        changed = np.isin(np.arange(len(old_offsets)), block.sets_position)  # G92.1, G5x: moved, not set
        self.written[~changed] -= (np.asarray(block.modal.offsets_mm) - old_offsets)[~changed] / self.unit_mm
        if changed.any():
            self.shift_mm[changed] = (command_mm - planned_mm)[changed]
            self.written[changed] = self.to_program(command_mm)[changed]

    @property
    def digits(self) -> np.ndarray:
        """Decimals written per axis (of AXES), in the controller's units."""
        return np.array([DECIMALS[a] for a in AXES]) + (1 if self.modal.inches else 0)

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
        """MIN_STEPS_PER_SEGMENT 1 (and RRF): block ends (``units`` wanted, ``ints`` rounded) with X Y Z on
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
        """MIN_STEPS_PER_SEGMENT above 1: the blocks Marlin keeps (``marlin_merged``), each end moved to where
        its dominant axis crosses a step (``steps.crossing_ends``), the ends then on whole steps
        (``rounded_ends``), merged rows onto the kept end before; merged again where that left a
        block short. Gives the ends, rows' durations and times, targets and rounding's states."""
        n, spu = len(ints), self.steps_per_mm * self.unit_mm / scale
        # row 0: the last kept end's time, wanted and rounded ends, its time and end moved (none: the start)
        t0_s = ends_s[0] - durations_s[0]
        from_s, from_units, from_ints, ended_s, ended_units = self.crossing_from or (t0_s, start, start, t0_s, start)
        ints = marlin_merged(from_ints, ints, spu, self.min_steps, exact_last)
        self.plain = np.vstack([from_ints, ints])
        kept = np.flatnonzero((np.diff(np.vstack([from_ints, ints]), axis=0) != 0).any(axis=1))
        if not len(kept):
            return ints, durations_s, ends_s, targets_mm, None
        times_s, units = np.append(from_s, ends_s), np.vstack([from_units, self.to_program(targets_mm) * scale])
        xyz_spu = np.where(np.arange(len(spu)) < 3, spu, 0.0)
        t_s, ends = crossing_ends(times_s, units, xyz_spu, kept + 1)
        rounded, states = rounded_ends(self.rounding, self.rounding_state, ends, spu, np.append(ended_s, t_s),
                                       kept, exact_last, times_s, units, ended_units, self.plain, self.min_steps)
        if exact_last and kept[-1] == n - 1:
            rounded[-1] = ints[-1]
        durations_s, ends_s = moved_in_time(kept, t_s - times_s[kept + 1], durations_s, ends_s)
        targets_mm = targets_mm.copy()
        targets_mm[kept] = self.to_machine(ends / scale)
        source = np.maximum.accumulate(np.where(np.isin(np.arange(n), kept), np.arange(n) + 1, 0))
        ints = np.vstack([start, np.zeros_like(ints)])
        ints[kept + 1] = rounded
        return (marlin_merged(start, ints[source], spu, self.min_steps, exact_last), durations_s, ends_s, targets_mm,
                states)

    def _held_from(self, kept: np.ndarray, wanted_s: np.ndarray, ends_s: np.ndarray, wanted_mm: np.ndarray,
                   ends_mm: np.ndarray, scale: np.ndarray) -> int:
        """The first row held for the next call (``last_in_both``); ``crossing_from``: the row
        before's, for the next call to merge and move its rows as one call would."""
        row = last_in_both(self.plain, kept, ends_s)
        if row is not None:
            self.crossing_from = (wanted_s[row], self.to_program(wanted_mm[row]) * scale, self.plain[row + 1],
                                  ends_s[row], self.to_program(ends_mm[row]) * scale)
        return 0 if row is None else row + 1

    def _keep_rounding(self, states: list[np.ndarray | None] | None, row: int) -> None:
        """The rounding's state before block ``row`` (of ``_shaped``'s), for the next call."""
        if states is not None:
            self.rounding_state = [np.zeros(r.size) if st is None else st[row]
                                   for r, st in zip(self.rounding, states, strict=True)]

    def _on_steps(self, start: np.ndarray, ints: np.ndarray, scale: np.ndarray, targets_mm: np.ndarray,
                  durations_s: np.ndarray, ends_s: np.ndarray, exact_last: bool) -> tuple:
        """The blocks on the firmware's whole steps: Marlin's (merged, on crossings or rounded; the
        last kept held for the next call unless ``exact_last``) or RRF's (each end in its step's
        cell). Gives the targets, durations, end times and ends to write, and the whole steps."""
        crossing = self.min_steps > 1 and self.crossings
        wanted = targets_mm, durations_s, ends_s  # (the rows before they are moved onto crossings)
        stepped = ints
        if crossing:
            ints, durations_s, ends_s, targets_mm, states = self._on_crossings(
                start, ints, scale, durations_s, ends_s, targets_mm, exact_last)
        elif self.cells is not None:
            units = self.to_program(targets_mm) * scale
            stepped, states = self._shaped(units, ints, scale, durations_s, exact_last)
            ints = self.cells.ends(units, stepped, ints, self.steps_per_mm * self.unit_mm / scale, exact_last)
        else:
            ints, states = self._shaped(self.to_program(targets_mm) * scale, ints, scale, durations_s, exact_last)
            ints = marlin_merged(start, ints, self.steps_per_mm * self.unit_mm / scale, self.min_steps, exact_last)
        self._keep_rounding(states, len(ints))
        if exact_last:
            self.crossing_from = None
        elif self.cells is None:  # (RRF merges nothing: no block waits for a later one)
            # held: the last kept block (a later one may merge it); on crossings from the end before it
            kept = np.flatnonzero((np.diff(np.vstack([start, ints]), axis=0) != 0).any(axis=1))
            last = self._held_from(kept, wanted[2], ends_s, wanted[0], targets_mm, scale) if crossing else \
                (kept[-1] if len(kept) else 0)
            self._keep_rounding(states, last)
            self.held = _held(*wanted, ends_s, last)
            targets_mm, durations_s, ends_s, ints = (x[:last] for x in (targets_mm, durations_s, ends_s, ints))
        return targets_mm, durations_s, ends_s, ints, stepped if self.cells is not None else ints

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
        stepping = bool(self.min_steps or self.cells is not None) and curves is None
        stepped = ints  # (RRF: the whole steps its written ends round to)
        if stepping:
            targets_mm, durations_s, ends_s, ints, stepped = self._on_steps(start, ints, scale, targets_mm,
                                                                            durations_s, ends_s, exact_last)
        steps = np.diff(np.vstack([start, ints]), axis=0)
        moved = steps != 0
        moving = moved.any(axis=1)
        jump = np.zeros(len(steps))
        if stepping and self.cells is None:  # (of the moving blocks alone: two in three rows are merged away)
            length = np.zeros(len(steps))
            length[moving], jump[moving] = self._marlin_lengths(start, ints[moving], scale)
        else:
            length = _lengths(steps / scale * self.unit_mm)
        if curves is not None:
            offsets = _curve_offsets(self, curves, start, ints, scale, length, moved, moving)
        self.written_s, self.written_mm = ends_s[moving], targets_mm[moving]
        # where the firmware goes: Marlin's (RRF's) whole steps (else the targets: 0.1 um from them)
        self.stepped_mm = self.to_machine(stepped[moving] / scale) if stepping else self.written_mm
        rows = slice(None) if moving.all() else moving  # nearly always all of them: no copies
        skipped_mm_s = self.ramp_mm_s2 * MIN_RAMP_S if self.cells is not None and math.isfinite(self.ramp_mm_s2) \
            else 0.0
        feed, self.residue_s, self.speed_mm_s = _feeds(length, durations_s, moving, self.residue_s,
                                                       60.0 * 10 ** FEED_DECIMALS / self.unit_mm,
                                                       self.speed_mm_s, self.ramp_mm_s2, jump, skipped_mm_s)
        new_feed = feed != np.concatenate([[self.feed], feed[:-1]])  # F only where it changes
        if len(feed):
            self.feed = int(feed[-1])
        if len(ints):
            self.written = np.where(relative, self.written + (ints[-1] - start) / scale, ints[-1] / scale)
        values = np.column_stack([np.where(relative, steps, ints)[rows], feed])
        shown = np.column_stack([moved[rows], new_feed])
        digits = np.append(digits, FEED_DECIMALS)
        letters, g5 = "".join(AXES) + "F", np.zeros(len(feed), bool)
        if curves is not None:
            g5 = curves.curve[rows]
            values = np.column_stack([offsets[rows], values])
            shown = np.column_stack([np.repeat(g5[:, None], 4, axis=1), shown])
            digits = np.concatenate([digits[[0, 1, 0, 1]], digits])
            letters = "IJPQ" + letters
        # By _LINES: more lines at once format two to three times slower (measured: the
        # temporaries outgrow the CPU cache).
        return b"".join(line_text(values[a:a + _LINES], shown[a:a + _LINES], digits, letters, self.newline,
                                  g5[a:a + _LINES]) for a in range(0, len(feed), _LINES)), len(feed)



def _curve_offsets(emitter: Emitter, curves: Curves, start: np.ndarray, ints: np.ndarray, scale: np.ndarray,
                   length: np.ndarray, moved: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """The G5 blocks' I J P Q in integer units of the last digit (in ``emitter``'s frame); their
    rounded curves' lengths into ``length``, and their ends shown (``moved``, ``moving``), in place.

    Control points rounded as written: I J (P Q) are the rounded point minus the rounded
    start (end), as the controller adds them to the positions it has. The rounded curve is
    what it times: its length differs from the fitted one's by up to 1e-2 on short curves."""
    xy_scale = scale[:2]
    origins = np.vstack([start, ints[:-1]])[:, :2]  # where each block starts
    offsets = np.column_stack([
        np.rint(emitter.to_program(curves.p1_mm, slice(0, 2)) * xy_scale).astype(np.int64) - origins,
        np.rint(emitter.to_program(curves.p2_mm, slice(0, 2)) * xy_scale).astype(np.int64) - ints[:, :2]])
    g5_rows = np.flatnonzero(curves.curve)
    p0, p3 = origins[g5_rows], ints[g5_rows, :2]
    length[g5_rows] = curve_lengths(p0 / xy_scale, (p0 + offsets[g5_rows, :2]) / xy_scale,
                                    (p3 + offsets[g5_rows, 2:]) / xy_scale, p3 / xy_scale) * emitter.unit_mm
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



def _lengths(delta_mm: np.ndarray, xyz_moves: np.ndarray | None = None) -> np.ndarray:
    """What a controller times each block by: its XYZ length where XYZ move (``xyz_moves``, by
    default where they move at all), else its U V W, A B C (LinuxCNC) or E length."""
    return feed_lengths(delta_mm, xyz_moves)[0]



def _feeds(length_mm: np.ndarray, durations_s: np.ndarray, moving: np.ndarray, residue_s: float,
           units_per_mm_s: float, speed_mm_s: float = 0.0, ramp_mm_s2: float = math.inf,
           jump_mm_s: np.ndarray | None = None, skipped_mm_s: float = 0.0) -> tuple[np.ndarray, float, float]:
    """The F of each moving block (integer units of its last digit; ``units_per_mm_s`` per mm/s),
    the time residue left after them and the last block's speed (``speed_mm_s``: the one's before).

    The controller times a block as its length over its F, and F is rounded: each block is
    given its duration plus the residue (the time the blocks before it were written short of
    theirs, and the whole time of blocks that round to no motion, which are not written), so the
    written time never drifts from the command's by more than one block's rounding. The firmware
    ramps from one block's speed to the next at ``ramp_mm_s2``, inside the faster one, and arrives
    (dv)^2 / (2 ramp max(v)) late: the next block makes that up too. (Where the residue is more
    negative than half a block's duration, the block keeps half its own and the rest goes on.)
    Marlin enters a faster block at once up to its ``jump_mm_s`` (see ``Emitter._marlin_lengths``).
    RRF does not ramp up to a block's F for under ``skipped_mm_s`` from at least 0.9 of it where the
    block is faster than its neighbours (``reprap.top_speed``: from the larger of the speed before
    and its exit, here the next block's wanted speed): it cruises at that, and is written so (the
    next blocks make up the time: written at F, it would let them run faster than it, RRF would
    ramp up to F after all, and the output would run short).
    """
    residue_s = float(residue_s)  # (a numpy scalar makes every step of the loop three times slower)
    feeds = []
    add = feeds.append
    ramped = ramp_mm_s2 != math.inf
    # (One line per block, the slowest loop of the writer: max() and the ramp's term only where they count.)
    lengths = (length_mm * units_per_mm_s).tolist()
    jumps = [0.0] * len(lengths) if jump_mm_s is None else jump_mm_s.tolist()
    aheads = [math.inf] * len(lengths)
    if skipped_mm_s:  # each block's next moving block's wanted speed (the last: not known, none)
        rows = np.flatnonzero(moving)
        ahead = np.full(len(lengths), math.inf)
        ahead[rows[:-1]] = length_mm[rows[1:]] / np.maximum(durations_s[rows[1:]], 1e-9)
        aheads = ahead.tolist()
    for length_units_s, duration, moves, jump, ahead_mm_s in zip(lengths, durations_s.tolist(), moving.tolist(),
                                                                  jumps, aheads, strict=True):
        residue_s += duration
        if moves:
            half = 0.5 * duration
            feed = round(length_units_s / (residue_s if residue_s >= half else half))
            if feed < 1:
                feed = 1
            add(feed)
            residue_s -= length_units_s / feed
            speed = feed / units_per_mm_s
            near = max(speed_mm_s, min(speed, ahead_mm_s))
            if near < speed < near + skipped_mm_s and near >= 0.9 * speed:
                # written at the speed RRF would cruise at: the next blocks, made faster by the time
                # this loses, would else let RRF ramp up to F after all, and the output run short
                slower = max(1, round(near * units_per_mm_s))
                residue_s -= length_units_s / slower - length_units_s / feed
                feeds[-1] = feed = slower
                speed = feed / units_per_mm_s
            elif ramped:
                lower_mm_s = speed_mm_s if speed_mm_s >= jump else jump
                step = speed - lower_mm_s if speed > speed_mm_s else speed_mm_s - speed
                if step > 0.0:
                    residue_s -= step ** 2 / (2.0 * ramp_mm_s2 * (speed if speed >= speed_mm_s else speed_mm_s))
            speed_mm_s = speed
    return np.array(feeds, dtype=np.int64), residue_s, speed_mm_s

