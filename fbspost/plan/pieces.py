"""The program's blocks read a batch at a time and made into pieces.

Takes the blocks (``blocks.Block``) and the profile; gives, per block with waypoints, a row
(``BlockReader``: its index, line, whether it is motion, feed, row of the limits table,
points; a MOVE that moves no compensated axis read as a STOP) and per block its dwells until it
is timed; then the pieces of those rows (``PieceMaker``: the columns ``PIECE_FIELDS``, with
the junction limit before each), the unknown positions filled (``fill_unknown``; the notes say
where) and the feeds clamped by the machine's limits counted (``CLAMPED``).
"""
from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind, feed_lengths
from . import klipper_rules
from .limits import LimitState, axis_piece_limits, jerk_junction_limits, junction_limits, reprap_jerk_mm_s

EXTRUDE_ONLY_MM = 1e-9  # Klipper: an XYZ length below this makes an extrude-only move
PROLOGUE_ROWS = 1 << 16  # waypoints searched for an unknown axis' first position (held until then)
MAX_NOTES = 20  # notes about lines with unknown positions, at most
CLAMPED = "feeds beyond the machine's velocity limits run clamped, as the controller runs them"

_NA = len(AXES)
_E = AXES.index("E")


PIECE_FIELDS = ("block", "run", "start", "end", "length", "extrude_only", "accel", "max_v", "delta_v2", "limit_v2",
                "smooth_delta_v2", "firmware_accel")



def changes_known(point: list[float], before: list[float], columns) -> bool:
    """Whether a straight move from ``before`` to ``point`` (positions, columns of AXES; NaN:
    unknown) changes one of ``columns`` known on both sides: on LinuxCNC a move of A B C U V W,
    copied as written whatever else it moves (``BlockReader``, ``linuxcnc_time``)."""
    return any(point[c] != before[c] and point[c] == point[c] and before[c] == before[c] for c in columns)


def fill_unknown(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hold NaN entries at the last known value of their axis (before it: the first known value;
    never known: 0). Also returns which axes were never known."""
    nan = np.isnan(points)
    rows = np.arange(points.shape[0])[:, None]
    source = np.maximum.accumulate(np.where(nan, -1, rows), axis=0)
    known = ~nan
    first = np.where(known.any(axis=0), known.argmax(axis=0), -1)
    never = first < 0
    source = np.where(source < 0, np.maximum(first, 0)[None, :], source)
    filled = np.take_along_axis(points, source, axis=0)
    filled[:, never] = 0.0
    return filled, never



class PieceMaker:
    """Waypoints to pieces. Takes the rows of waypoints read (per block: its index, line, whether
    it is motion, feed, row of the limits table, points) and gives the new pieces' columns
    (``PIECE_FIELDS``) with the junction limit before each; fills the positions not known (the
    notes say where) and counts the feeds clamped by the machine's limits."""

    def __init__(self, profile: MachineProfile, klipper: bool, notes: list[str], travel_share: float = 0.0,
                 rests_apart: bool = False, reprap: bool = False):
        self._klipper = klipper
        # RepRapFirmware's junctions (``jerk_junction_limits``), and M204 only where X or Y move: its
        # model ran the gear's first 8000 lines 1.66% longer than the junction deviation planned them
        self._reprap = reprap
        self._rests_apart = rests_apart  # a piece that moves no compensated axis starts and ends at rest
        # a travel's acceleration along each axis (inf: none): a share of its hard limit, on the compensated axes
        hard = [profile.axes[a].max_acceleration_mm_s2 if a in profile.axes else math.inf for a in AXES]
        self._travel_a = np.array(hard) * travel_share if travel_share else None
        self._moves_compensated = np.array([a in profile.axes and bool(profile.axes[a].modes) for a in AXES])
        self._rules = klipper_rules.constants(profile) if klipper else None
        self._notes = notes
        self.last_row: np.ndarray | None = None  # the last waypoint, filled (None: the prologue)
        self._ever_known = np.zeros(_NA, dtype=bool)
        self._zeroed = np.zeros(_NA, dtype=bool)  # axes unknown through the prologue, planned at 0 until known
        self._lost, self._clamped = 0, 0
        self._clamped_first = ""
        self.stops = 0  # STOP blocks turned into waypoints
        self._prev = None  # the last piece made: extrude-only, run (for the junction after it)
        self._junction_prev = None  # its columns for the junction limits

    def make(self, rows: list, printing_from: float) -> dict | None:
        """The columns of the pieces of ``rows`` (None: they make none); ``printing_from``: the key of
        the program's first run that prints, as far as known (``BlockReader``)."""
        counts = np.array([len(r[5]) for r in rows], dtype=np.int64)
        raw = np.concatenate([r[5] for r in rows]).astype(float, copy=False)
        seg_block = np.repeat(np.array([r[0] for r in rows], dtype=np.int64), counts)
        seg_line = np.repeat(np.array([r[1] for r in rows], dtype=np.int64), counts)
        seg_motion = np.repeat(np.array([r[2] for r in rows], dtype=bool), counts)
        moving = [r for r in rows if r[2]]
        previous, filled = self._filled(raw, seg_motion, seg_line)
        stop_blocks = seg_block[~seg_motion]
        start = np.concatenate([previous[None], filled[:-1]])
        delta = filled - start
        length, extrude_only = feed_lengths(delta, still_mm=EXTRUDE_ONLY_MM)
        keep = seg_motion & (length > 0)
        group = np.repeat(np.cumsum([r[2] for r in rows]) - 1, counts)[keep]
        start, delta, length, extrude_only = start[keep], delta[keep], length[keep], extrude_only[keep]
        piece_block, piece_line = seg_block[keep], seg_line[keep]
        run_key = self.stops + np.searchsorted(stop_blocks, piece_block, side="left")
        self.stops += stop_blocks.size
        if not length.size:
            return None
        table = np.asarray([r[4] for r in moving])[group]
        feed = np.asarray([r[3] for r in moving])[group]
        unit, max_v, accel, delta_v2, smooth_delta_v2, clamped, corner_a = self.piece_limits(
            delta, length, extrude_only, feed, table, run_key > printing_from)
        inner = self._junction_limits(unit, max_v, corner_a, length, 2.0 * corner_a * length, table[:, 3],
                                      table[:, 4 + 2 * _NA], delta)
        self._count_clamped(clamped, feed, max_v, piece_block, piece_line)

        # junction limits: limit_v2[i] is the junction before piece i (the first after the last
        # piece made before: _prev), 0 between runs and at extrude-only pieces (and with
        # ``rests_apart``, at pieces that move no compensated axis)
        prev = self._prev or (np.ones(1, bool), np.full(1, -1))
        apart = extrude_only | ~(delta[:, self._moves_compensated] != 0).any(axis=1) if self._rests_apart \
            else extrude_only
        eo, key = (np.concatenate([p, q]) for p, q in zip(prev, (apart, run_key), strict=True))
        together = (key[1:] == key[:-1]) & ~eo[1:] & ~eo[:-1]
        limit_v2 = np.where(together, inner, 0.0)
        self._prev = (apart[-1:], run_key[-1:])
        return dict(block=piece_block, run=run_key, start=start, end=start + delta, length=length,
                    extrude_only=extrude_only, accel=accel, max_v=max_v, delta_v2=delta_v2, limit_v2=limit_v2,
                    smooth_delta_v2=smooth_delta_v2, firmware_accel=corner_a)

    def finish(self, warnings: list[str]) -> None:
        """At the end: the notes on axes never known and on lines beyond MAX_NOTES, and the one
        warning on feeds clamped (slicers write Z moves at travel feeds on every layer)."""
        never = np.flatnonzero(~self._ever_known[:4])  # (LinuxCNC's other axes never known: never used)
        self._notes[:0] = [f"{AXES[i]}: position never known, planned at 0 mm" for i in never]
        if self._lost > MAX_NOTES:
            self._notes.append(f"... and {self._lost - MAX_NOTES} more lines with unknown positions")
        if self._clamped:
            more = f" and {self._clamped - 1} more lines" if self._clamped > 1 else ""
            warnings.append(self._clamped_first + more)

    def _filled(self, raw: np.ndarray, seg_motion: np.ndarray, seg_line: np.ndarray) -> tuple:
        """(the position before the waypoints, the waypoints) with the unknown positions filled."""
        n = raw.shape[0]
        nan = np.isnan(raw)
        if self.last_row is None:  # the prologue: before its first known value an axis is there ...
            filled, _ = fill_unknown(np.concatenate([np.full((1, _NA), np.nan), raw]))
            previous, filled = filled[0], filled[1:]
            # ... if it is known within the first PROLOGUE_ROWS waypoints; else at 0 until it is
            self._zeroed = nan[:PROLOGUE_ROWS].all(axis=0)
            if self._zeroed.any():
                source = np.maximum.accumulate(np.where(nan, -1, np.arange(n)[:, None]), axis=0)
                held = np.where(source >= 0, np.take_along_axis(raw, np.maximum(source, 0), axis=0), 0.0)
                filled[:, self._zeroed] = held[:, self._zeroed]
                previous[self._zeroed] = 0.0
        else:  # held at the last known value
            previous = self.last_row
            source = np.maximum.accumulate(np.where(nan, -1, np.arange(n)[:, None]), axis=0)
            filled = np.where(source >= 0, np.take_along_axis(raw, np.maximum(source, 0), axis=0), previous)
        known_before = np.maximum.accumulate(np.concatenate([self._ever_known[None], ~nan]), axis=0)
        self._note_unknown(nan, known_before, seg_motion, seg_line)
        self._ever_known = known_before[-1]
        self.last_row = filled[-1]
        return previous, filled

    def _note_unknown(self, nan: np.ndarray, known_before: np.ndarray, seg_motion: np.ndarray,
                      seg_line: np.ndarray) -> None:
        """Notes: the lines after which a known axis is no longer known; the axes planned at 0."""
        lost = (~seg_motion)[:, None] & nan & known_before[:-1]
        for i in np.flatnonzero(lost.any(axis=1)):
            if self._lost < MAX_NOTES:
                axes = "".join(AXES[a] for a in np.flatnonzero(lost[i]))
                self._notes.append(f"line {seg_line[i]}: {axes} unknown after this line, held at the last known "
                                   "position")
            self._lost += 1
        found = self._zeroed & ~self._ever_known & known_before[-1]
        found[_E + 1:] = False  # (LinuxCNC's other axes: at 0 until their first move, at rest, puts them)
        for a in np.flatnonzero(found):
            line = seg_line[np.flatnonzero(~nan[:, a])[0]]
            self._notes.append(f"{AXES[a]}: position not known in the first {PROLOGUE_ROWS} waypoints, planned at 0 mm "
                               f"until line {line}")

    def piece_limits(self, delta, length, extrude_only, feed, table, after_print=None):
        """Per piece, from its row of the limits table (``LimitState.row``): its direction per mm,
        cruise limit, accel, 2 a d, the same for Klipper's smoothing (2 a d where there is none),
        whether its feed is clamped by the machine's limits, and the accel its junctions are
        limited with (the firmware's: a travel planned faster keeps its corners). ``after_print``:
        the pieces after the program's first run that prints (None: none), whose travels may be
        faster."""
        accel_print, accel_travel, planner_v = table[:, 0], table[:, 1], table[:, 2]
        if self._klipper:
            z_limits, e_limits, _ = self._rules
            unit, max_v, firmware_a = klipper_rules.piece_limits(delta, length, extrude_only, feed, planner_v,
                                                                 accel_print, z_limits, e_limits)
            clamped = np.isfinite(feed) & (max_v < feed) & ~extrude_only
            smooth_a = np.minimum(table[:, -1], firmware_a)
        else:
            axis_v, axis_a = table[:, 4:4 + _NA], table[:, 4 + _NA:4 + 2 * _NA]
            unit, max_v, firmware_a, clamped = axis_piece_limits(delta, length, extrude_only, feed, planner_v,
                                                                 accel_print, accel_travel, axis_v, axis_a,
                                                                 self._reprap)
            smooth_a = firmware_a
        accel = firmware_a if after_print is None else self._in_travel(unit, firmware_a, delta, extrude_only,
                                                                       after_print)
        delta_v2 = 2.0 * accel * length
        return unit, max_v, accel, delta_v2, 2.0 * length * smooth_a * (accel / firmware_a), clamped, firmware_a

    def _in_travel(self, unit, accel, delta, extrude_only, after_print) -> np.ndarray:
        """``accel`` with the travels' raised to ``RunMargins.travel_share`` of the hard limits, once
        the program has printed (a program that never does is every move's contour)."""
        if self._travel_a is None:
            return accel
        moves = (delta[:, self._moves_compensated] != 0).any(axis=1)
        travel = after_print & ~extrude_only & ~(delta[:, _E] > 0) & moves
        abs_unit = np.abs(unit)
        with np.errstate(divide="ignore"):
            fast = np.where(abs_unit > 0, self._travel_a / abs_unit, np.inf).min(axis=1)
        return np.where(travel, np.maximum(accel, fast), accel)

    def _junction_limits(self, unit, max_v, accel, length, delta_v2, jd, scv, delta) -> np.ndarray:
        """The junction limit before each piece (with the last piece made before): Klipper's rules,
        RepRapFirmware's (``jerk_junction_limits``, M566 X Y the ``scv`` in force), or the
        junction-deviation model of ``junction_limits``."""
        cruise_v2 = max_v * max_v
        if self._reprap:
            xy = (delta[:, 0] != 0) | (delta[:, 1] != 0)
            printing = xy & (delta[:, _E] > 0)
            kind = xy + 2 * printing + 4 * ((delta[:, _E] != 0) & ~printing)  # (RRF's flags: they meld if equal)
            u, jerk, cv2, k = self._junction_carry((unit, reprap_jerk_mm_s(scv), cruise_v2, kind))
            return jerk_junction_limits(u[:-1], u[1:], jerk[1:], cv2[:-1], cv2[1:], k[1:] == k[:-1])
        if self._klipper:
            u, jd_, acc, d, cv2 = self._junction_carry((unit, jd, accel, length, cruise_v2))
            return klipper_rules.junction_limits(u[:-1], u[1:], jd_[:-1], jd_[1:], acc[:-1], acc[1:], d[:-1], d[1:],
                                                 cv2[:-1], cv2[1:], self._rules[2])
        u, jd_, acc, dv2, cv2 = self._junction_carry((unit[:, :3], jd, accel, delta_v2, cruise_v2))
        return junction_limits(u[:-1], u[1:], jd_[:-1], jd_[1:], acc[:-1], acc[1:], dv2[:-1], dv2[1:],
                               cv2[:-1], cv2[1:])

    def _count_clamped(self, clamped: np.ndarray, feed, max_v, piece_block, piece_line) -> None:
        clamped = np.flatnonzero(clamped)
        clamped = clamped[np.unique(piece_block[clamped], return_index=True)[1]]  # the first piece of each block
        if clamped.size and not self._clamped:
            i = clamped[0]
            self._clamped_first = (f"{CLAMPED}: line {piece_line[i]} (feed {feed[i] * 60:.6g} mm/min, runs at "
                                   f"{max_v[i] * 60:.6g} mm/min)")
        self._clamped += clamped.size

    def _junction_carry(self, columns: tuple) -> list[np.ndarray]:
        """``columns`` of the new pieces after those of the last piece made before (its own copy the
        first time: a junction with itself, made 0 as the start of a run)."""
        held = self._junction_prev or tuple(c[:1] for c in columns)
        self._junction_prev = tuple(c[-1:] for c in columns)
        return [np.concatenate([p, q]) for p, q in zip(held, columns, strict=True)]



class BlockReader:
    """The program's blocks, read a batch at a time (``read``). Gives, per block with waypoints,
    a row in ``rows`` (its index, line, whether it is motion, feed, row of the limits table,
    points), and per block (block, is MOVE, is STOP, the dwells before it) in ``pending`` until
    it is timed. A MOVE that moves no compensated axis is read as a STOP (``_uncompensated_s``)."""

    def __init__(self, blocks: Iterable[Block], profile: MachineProfile, firmware: str | None, batch: int,
                 settle_s: Callable[[bool], float], piece_limits: Callable, compensated: list[int],
                 copied_with: tuple[int, ...]):
        self._blocks_in = iter(blocks)
        self._batch = batch
        self._settle_s = settle_s
        self.settles: dict[int, float] = {}  # by run key (the STOPs before it): its settle margin, until settled
        self._stops = 0  # STOP blocks read
        self._prints = False  # the last MOVE read ends extruding
        self.printing_from = math.inf  # the key of the first run that prints
        self._piece_limits = piece_limits
        self._compensated = compensated  # the axes a compensated command moves (columns of AXES)
        self._copied_with = copied_with  # a move of one of these (columns of AXES) is copied whatever else it moves
        self._limits = LimitState(profile, firmware)
        self._state_row = self._limits.row()
        self.n_blocks = 0
        self.eof = False
        self.pending: deque = deque()  # (block, is_move, is_stop, dwell before it in total)
        self.rows: list = []
        self.cum_dwell = 0.0  # dwells of every block read (and the settle margins)
        self._read_mm = np.full(_NA, math.nan)  # where the last block read left the machine (NaN: unknown)
        self._moved = False  # a MOVE since the last STOP: a run to close, whose settle margin comes first
        self._prologue_seen, self._prologue_count, self._prologue_known = 0, 0, np.zeros(_NA, dtype=bool)

    def read(self) -> None:
        j0 = j = self.n_blocks
        rows, pending, cum_dwell, state_row = self.rows, self.pending, self.cum_dwell, self._state_row
        move, stop = Kind.MOVE, Kind.STOP
        for block in itertools.islice(self._blocks_in, self._batch):
            kind = block.kind
            if block.limits is not None:
                self._limits.apply(block.limits, block.line_no)
                state_row = self._state_row = self._limits.row()
            if kind is move:
                points = block.points_mm  # (k, 4)
                if points is not None and len(points):
                    feed = math.inf if block.feed_mm_s is None else float(block.feed_mm_s)
                    if not feed > 0:
                        raise ValueError(f"line {block.line_no}: feed must be > 0, got {block.feed_mm_s!r}")
                    rest_s = self._uncompensated_s(points, feed, state_row)
                    if rest_s is None:
                        rows.append((j, block.line_no, True, feed, state_row, points))
                        self._prints = bool(points[-1, _E] > (points[-2] if len(points) > 1 else self._read_mm)[_E])
                        if self._prints:
                            self.printing_from = min(self.printing_from, self._stops)
                        self._read_mm = points[-1]
                    else:
                        block, kind = replace(block, kind=stop, dwell_s=rest_s), stop
                if kind is move:
                    self._moved = True
                    pending.append((block, True, False, cum_dwell))
            if kind is stop:
                dwell = block.dwell_s
                if not (dwell >= 0 and math.isfinite(dwell)):
                    raise ValueError(f"line {block.line_no}: dwell must be >= 0, got {dwell!r}")
                rows.append((j, block.line_no, False, math.nan, state_row, np.reshape(block.position_mm, (1, _NA))))
                self._read_mm = block.position_mm
                cum_dwell = self._margin_after_run(cum_dwell)
                self._stops += 1
                pending.append((block, False, True, cum_dwell))
                cum_dwell += dwell  # (a running sum: np.cumsum's bits)
            elif kind is not move:
                pending.append((block, False, False, cum_dwell))
            j += 1
        self.n_blocks = j
        self.eof = j - j0 < self._batch
        self.cum_dwell = self._margin_after_run(cum_dwell) if self.eof else cum_dwell


    def _uncompensated_s(self, points: np.ndarray, feed: float, state_row: list) -> float | None:
        """How long a MOVE that moves no compensated axis (a retraction, a Z hop, a layer change), or
        one of ``copied_with`` whatever else, takes, from rest to rest as the controller plans it
        (None: it moves a compensated axis, or an axis it moves is not known before or after).
        Such a move is a rest of the compensated axes: copied as it is, like a dwell of that
        length, so that the compensated motion never mixes a creep of X Y with it, and the
        controller runs it as written."""
        if len(points) != 1:
            return None
        # (nearly every move moves a compensated axis: told on floats, a few times faster than on arrays)
        point, read = points[0].tolist(), self._read_mm.tolist()
        if not changes_known(point, read, self._copied_with):
            for c in self._compensated:
                if point[c] != read[c] and (point[c] == point[c] or read[c] == read[c]):  # (not both NaN)
                    return None
        # an axis unknown before and after it did not move (a line of E alone after a macro)
        still = (points == self._read_mm) | np.isnan(points) & np.isnan(self._read_mm)
        delta = np.where(still, 0.0, points - self._read_mm)
        if still.all() or not np.isfinite(delta).all():
            return None
        length, eo = feed_lengths(delta, still_mm=EXTRUDE_ONLY_MM)
        limits = self._piece_limits(delta, length, eo, np.array([feed]), np.array([state_row]))
        max_v, accel, smooth_v2 = limits[1], limits[2], limits[4]
        peak_v2 = min(max_v[0] ** 2, 0.5 * smooth_v2[0])  # a trapezoid from rest to rest
        peak, a = math.sqrt(peak_v2), float(accel[0])
        return 2.0 * peak / a + (length[0] - peak_v2 / a) / peak


    def _margin_after_run(self, cum_dwell: float) -> float:
        """The running dwell sum with the settle margin of the run that a STOP (or the end) closes:
        the lines at rest after it wait for it, as for a dwell."""
        if self._moved:
            self._moved = False
            settle_s = self.settles[self._stops] = self._settle_s(self.end_prints(self._stops, self._prints))
            return cum_dwell + settle_s
        return cum_dwell

    def end_prints(self, key: int, extrudes: bool) -> bool | None:
        """Whether the end of run ``key`` whose piece there ``extrudes`` prints, or (None) the
        program has not printed before that run (``RunMargins``): known from the blocks read up to it."""
        return None if key <= self.printing_from else extrudes

    def prologue_over(self) -> bool:
        """Every axis known (LinuxCNC's other axes need not be: unset, they are at 0 until their
        first move, which is at rest), enough waypoints searched, or the end: the start can be filled."""
        for row in self.rows[self._prologue_seen:]:
            self._prologue_known |= ~np.isnan(row[5]).all(axis=0)
            self._prologue_count += len(row[5])
        self._prologue_seen = len(self.rows)
        return self.eof or bool(self._prologue_known[:_E + 1].all()) or self._prologue_count >= PROLOGUE_ROWS

