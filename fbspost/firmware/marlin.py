"""Marlin 2.1's planner and stepper over a program sent line by line: the motion the machine makes.

Takes the blocks of a program (``gcode.read_gcode``), a machine profile and a ``MarlinConfig``
(from the profile's ``[firmware]`` table: steps_per_mm, block_buffer, max_line_rate,
min_segment_time, min_steps_per_segment); gives ``MarlinRun``: every block Marlin makes (its
line, speeds, start and end), the rests where its buffer ran dry, when every line is taken, and
the positions on the profile's sample grid (``MarlinRun.positions_mm``; ``planners.replan(...,
"marlin")`` wraps it as ``FirmwareMotion``).

Modelled from MarlinFirmware/Marlin bugfix-2.1.x, Marlin/src/module/planner.cpp (commit
000420e3, read November 2026) and Configuration(_adv).h defaults:
- ``buffer_segment``: targets in whole steps, ``lround(mm * steps_per_mm)``; ``_populate_block``:
  a segment whose step_event_count (most steps of any axis, E included) is under
  MIN_STEPS_PER_SEGMENT is no block and the planner keeps its position
  (``merge_short_segments``); millimeters is the XYZ length of the whole steps, or |E| when
  no XYZ axis has MIN_STEPS_PER_SEGMENT steps; nominal speed F, times speed_factor for M203.
- SLOWDOWN: with ``moves_queued`` (blocks queued and not started) in [2, BLOCK_BUFFER_SIZE/2 - 1]
  and a segment time under M205 B, the segment takes ``seg + 2 (B - seg) / moves_queued`` us.
- acceleration: M204 P (blocks with E steps) or T, limited per axis by M201 / |u_axis|; blocks
  without XYZ steps use the retract acceleration (taken here as M204 P: the profile does not
  know M204 R).
- minimum_planner_speed_sqr = 0.5 a / (block steps per mm), at most nominal^2: the safe exit
  speed of the newest block, the floor of every junction and the entry of a block added to an
  empty buffer.
- junction deviation (M205 J): a * J sin(t/2) / (1 - sin(t/2)) over the XYZE unit vectors, a
  limited per axis along the junction's unit vector; JD_HANDLE_SMALL_SEGMENTS: blocks under 1 mm
  turning less than 45 degrees at most millimeters * a / theta (Marlin's polynomial acos); a
  reversal (cos > 0.999999): the minimum planner speed; then the lower nominal speed. Or
  ``classic_jerk`` (CLASSIC_JERK builds): M205 X Y jerk, DEFAULT_ZJERK 0.3, DEFAULT_EJERK 5.
- the buffer: BLOCK_BUFFER_SIZE slots hold BLOCK_BUFFER_SIZE - 1 blocks (``get_next_free_block``).
  The host sends a line when the previous is acknowledged; a line is taken ``1 / max_line_rate``
  after the previous, a move only once a slot is free. A block's exit speed is fixed when the
  stepper starts it, from the plan over the blocks queued by then (the one that takes the slot
  the previous block frees comes after: at most BLOCK_BUFFER_SIZE - 3 after it), the newest
  ending at its safe exit speed (``recalculate``: reverse pass, forward pass from the fixed
  entry). A buffer that runs dry stops the machine; the first block into an empty buffer waits
  until 3 blocks are queued or BLOCK_DELAY_FOR_1ST_MOVE (100 ms) passes (``get_current_block``).
- lines that stop the machine (``Kind.STOP`` as the reader classes them: G4, M400, homing, M109,
  M593...) wait for the buffer to empty, then their dwell; other lines cost their line time only.
Not modelled: the stepper's step-rate quantization (ceil of the accelerate steps, nominal_rate,
minimal_step_rate: under a step per block), S-curve acceleration and linear advance (off by
default), input shaping and FT_MOTION (``firmware_shapers`` shapes a plan as they do, for the
benches), G2/G3 segmentation by Marlin (arcs come as the reader's
chords), sync blocks of G92 and M-codes taking buffer slots, serial buffer and command queue
(BUFSIZE) beyond the ok-handshake. Units: mm, s, mm/s, mm/s^2 (Marlin's M205 B is in us).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from ..plan.limits import LimitState
from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind
from .transparency import first_given

_NA = len(AXES)
_E = AXES.index("E")
_XYZ = slice(0, 3)
M205_B = re.compile(rb"^\s*(?:[Nn]\s*\d+\s*)?[Mm]\s*0*205\b[^;(]*?[Bb]\s*([-+]?[\d.]+)")
_REVERSAL_COS = 0.999999  # planner.cpp: junction_cos_theta > 0.999999, a 0 degree junction
_OCTAGON_COS = -0.7071067812  # JD_HANDLE_SMALL_SEGMENTS: junctions over 135 degrees (turns under 45)
_NO_STEPS_PER_MM = 1e6  # an axis without steps_per_mm: never merged, no minimum speed


@dataclass(frozen=True)
class MarlinConfig:
    """Marlin's build and EEPROM settings the model needs (Configuration.h defaults)."""

    steps_per_mm: tuple[float, ...]  # per AXES entry (NaN: not given)
    block_buffer: int = 16  # BLOCK_BUFFER_SIZE
    line_rate_hz: float | None = None  # lines the host gets acknowledged per second (None: no limit)
    min_segment_time_s: float = 0.02  # M205 B at the start (DEFAULT_MINSEGMENTTIME 20000 us)
    min_steps_per_segment: int = 6  # MIN_STEPS_PER_SEGMENT
    classic_jerk: bool = False  # CLASSIC_JERK build (else junction deviation)
    z_jerk_mm_s: float = 0.3  # DEFAULT_ZJERK
    e_jerk_mm_s: float = 5.0  # DEFAULT_EJERK
    first_move_delay_s: float = 0.1  # BLOCK_DELAY_FOR_1ST_MOVE, ms of the idle stepper ISR

    @classmethod
    def from_profile(cls, profile: MachineProfile, **changes) -> MarlinConfig:
        fw = profile.firmware
        values = dict(steps_per_mm=tuple(fw.steps_per_mm.get(a, math.nan) for a in AXES),
                      block_buffer=fw.block_buffer, line_rate_hz=fw.max_line_rate_hz,
                      min_segment_time_s=fw.min_segment_time_s, min_steps_per_segment=fw.min_steps_per_segment)
        return cls(**{**values, **changes})


@dataclass
class MarlinRun:
    """What Marlin does with a program (see the module docstring)."""

    start_mm: np.ndarray  # (m, NA) every block's start, whole steps (m blocks)
    end_mm: np.ndarray  # (m, NA)
    line: np.ndarray  # (m,) index of the program block (line) each block comes from
    length_mm: np.ndarray  # (m,) Marlin's millimeters
    accel_mm_s2: np.ndarray  # (m,)
    nominal_mm_s: np.ndarray  # (m,) after SLOWDOWN and M203
    entry_mm_s: np.ndarray  # (m,) as run
    exit_mm_s: np.ndarray  # (m,)
    start_s: np.ndarray  # (m,)
    end_s: np.ndarray  # (m,)
    line_time_s: np.ndarray  # (lines,) MOVE: its last block's end (merged: the next's); STOP: at rest; else taken
    taken_s: np.ndarray  # (lines,) when each line is acknowledged (NaN: blank or comment, not sent)
    duration_s: float
    starved: list[tuple[float, float]] = field(default_factory=list)  # (when, seconds at rest): the buffer ran dry
    merged_lines: list[int] = field(default_factory=list)

    def positions_mm(self, sample_rate_hz: float) -> np.ndarray:
        """(n, NA) positions at t = k / sample_rate_hz, k = 0 .. through the end."""
        return self.at(np.arange(math.floor(self.duration_s * sample_rate_hz) + 2) / sample_rate_hz)

    def at(self, t: np.ndarray) -> np.ndarray:
        """(len(t), NA) positions at the times ``t`` (s): along the blocks, at rest between them."""
        if not self.start_s.size:
            return np.zeros((t.size, _NA))
        k = np.maximum(np.searchsorted(self.start_s, t, side="right") - 1, 0)
        tau = np.clip(t - self.start_s[k], 0.0, self.end_s[k] - self.start_s[k])
        v0, v1 = _within(self.entry_mm_s[k], self.exit_mm_s[k], self.nominal_mm_s[k])
        s = _distance_at(tau, v0, self.nominal_peak()[k], v1, self.accel_mm_s2[k], self.length_mm[k])
        frac = np.where(t >= self.start_s[k], s / self.length_mm[k], 0.0)
        return self.start_mm[k] + (self.end_mm[k] - self.start_mm[k]) * frac[:, None]

    def nominal_peak(self) -> np.ndarray:
        """(m,) the highest speed each block reaches."""
        return _peak(*_within(self.entry_mm_s, self.exit_mm_s, self.nominal_mm_s), self.nominal_mm_s,
                     self.accel_mm_s2, self.length_mm)


# (minimum, maximum, sqrt) of numpy arrays, and of Python floats: the buffers' scans time one
# block at a time, where numpy's functions cost several times Python's on a float
_ARRAY_OPS = (np.minimum, np.maximum, np.sqrt)
_FLOAT_OPS = (min, max, math.sqrt)


def _ops(x) -> tuple:
    return _FLOAT_OPS if isinstance(x, float) else _ARRAY_OPS


def _peak(v0, v1, nominal, accel, length):
    """Trapezoid peak: nominal, or where accelerating from v0 meets decelerating to v1 (v0, v1 at
    most nominal: see ``_within``)."""
    minimum, maximum, sqrt = _ops(v0)
    meet2 = 0.5 * (v0 * v0 + v1 * v1) + accel * length
    return maximum(sqrt(minimum(nominal * nominal, meet2)), maximum(v0, v1))


def _within(v0, v1, nominal):
    """The speeds a block starts and ends with in the stepper: a junction above the block's
    nominal speed (the minimum planner speed allows it where the acceleration is high) is left
    at once, the step rate capped at nominal_rate (stepper.cpp), and reached by a jump."""
    minimum = _ops(v0)[0]
    return minimum(v0, nominal), minimum(v1, nominal)


def trapezoid_time_s(v0, v1, nominal, accel, length):
    """Duration of a block: v0 -> peak at accel, cruise, peak -> v1 (calculate_trapezoid_for_block).
    Arrays, or Python floats (all of them)."""
    v0, v1 = _within(v0, v1, nominal)
    peak = _peak(v0, v1, nominal, accel, length)
    ramps = (peak * peak - 0.5 * (v0 * v0 + v1 * v1)) / accel
    return (2.0 * peak - v0 - v1) / accel + _ops(v0)[1](length - ramps, 0.0) / peak


def _distance_at(tau, v0, peak, v1, accel, length):
    """Distance along a trapezoid block ``tau`` after its start (tau within the block)."""
    t_acc = (peak - v0) / accel
    d_acc = 0.5 * (peak + v0) * t_acc
    d_dec = 0.5 * (peak + v1) * (peak - v1) / accel
    t_cruise = np.maximum(length - d_acc - d_dec, 0.0) / peak
    in_acc = np.minimum(tau, t_acc)
    s = v0 * in_acc + 0.5 * accel * in_acc**2
    s = s + peak * np.clip(tau - t_acc, 0.0, t_cruise)
    dec = np.maximum(tau - t_acc - t_cruise, 0.0)
    s = s + peak * dec - 0.5 * accel * dec**2
    return np.minimum(s, length)


def merge_short_segments(blocks: list[Block], profile: MachineProfile) -> tuple[list[Block], list[int]]:
    """Marlin's step quantization and short-segment merge: every MOVE's points at whole steps of
    the axes with ``steps_per_mm``; a point fewer than ``min_steps_per_segment`` steps from the
    last block's end on every axis (E included; an axis without steps_per_mm counts as many
    steps if it moves at all) is dropped, so the next point's block covers its distance.
    Returns the blocks (a MOVE whose points all went keeps none) and the lines of dropped points."""
    scale, stepped = _step_scale(profile)
    least = profile.firmware.min_steps_per_segment
    moving = [b for b in blocks if b.kind is Kind.MOVE and b.points_mm is not None]
    points = np.concatenate([b.points_mm for b in moving]) if moving else np.zeros((0, _NA))
    targets = lround(points * scale)
    on_steps = np.where(stepped, targets / scale, points)
    # whether each point is a block after the point before it, all at once (a numpy call a point
    # was most of the model's time); after any other last end (a merged point, a STOP) the scan
    # compares in Python floats as numpy does: NaN >= n is false, NaN != x true
    moved = np.where(stepped, np.abs(np.diff(targets, axis=0, prepend=np.nan)),
                     np.where(points != np.roll(points, 1, axis=0), np.inf, 0.0))
    after_previous = ((moved >= least).any(axis=1) | (least <= 0)).tolist()
    steps_at, mm_at, axes = targets.tolist(), points.tolist(), list(enumerate(stepped.tolist()))
    last, last_row = None, None  # the planner's position: (steps, mm) of the last block's end (NaN: unknown), its point
    out, merged, row = [], [], 0
    for block in blocks:
        if block.kind is Kind.STOP:  # the firmware's position is where the line leaves the machine
            last, last_row = (lround(block.position_mm * scale).tolist(), block.position_mm.tolist()), None
        if block.kind is not Kind.MOVE or block.points_mm is None:
            out.append(block)
            continue
        kept = []
        for k in range(row, row + len(block.points_mm)):
            if last is not None and not (after_previous[k] if last_row == k - 1 else least <= 0 or any(
                    abs(steps_at[k][i] - last[0][i]) >= least if s else mm_at[k][i] != last[1][i] for i, s in axes)):
                merged.append(block.line_no)
                continue
            last, last_row = (steps_at[k], mm_at[k]), k
            kept.append(k)
        row += len(block.points_mm)
        # a shallow copy (dataclasses.replace runs __init__, copy.copy the reduce protocol: each
        # several times this)
        copied = object.__new__(Block)
        kept_mm = on_steps[kept[0]:kept[-1] + 1] if kept and len(kept) == kept[-1] + 1 - kept[0] else on_steps[kept]
        copied.__dict__.update(block.__dict__, points_mm=kept_mm if kept else None)
        out.append(copied)
    return out, merged


def _step_scale(profile: MachineProfile) -> tuple[np.ndarray, np.ndarray]:
    """(steps per mm of every axis, 1 where it has none; whether it has steps)."""
    steps = profile.firmware.steps_per_mm
    scale = np.array([steps.get(a, np.nan) for a in AXES])
    stepped = ~np.isnan(scale)
    return np.where(stepped, scale, 1.0), stepped


def _on_steps(position_mm: np.ndarray, profile: MachineProfile) -> np.ndarray:
    """``position_mm`` where Marlin puts it: at whole steps of the axes with steps."""
    scale, stepped = _step_scale(profile)
    return np.where(stepped, lround(position_mm * scale) / scale, position_mm)


def lround(x: np.ndarray) -> np.ndarray:
    """C's lround: to the nearest whole number, halves away from zero."""
    return np.trunc(x + np.copysign(0.5, x))


@dataclass
class Segments:
    """The blocks Marlin makes, in order, with what does not depend on when they are queued."""

    line: list[int] = field(default_factory=list)
    start: list[np.ndarray] = field(default_factory=list)
    end: list[np.ndarray] = field(default_factory=list)
    feed: list[float] = field(default_factory=list)
    settings: list[list[float]] = field(default_factory=list)  # LimitState.row() (jerk in it), M205 B (us)


def _read(blocks: list[Block], profile: MachineProfile) -> tuple[Segments, list[tuple[Kind, bool, float]]]:
    """The segments of ``blocks`` (after the merge) and per line (kind, sent to the machine, dwell s).
    An axis whose position is not known is where Marlin starts it: at 0, or where it was."""
    state = LimitState(profile)
    min_segment_us = profile.firmware.min_segment_time_s * 1e6
    junction_mm = state.row()[3]  # M205 J alone sets it (M205 X Y are classic jerk's)
    segments, lines = Segments(), []
    position = np.zeros(_NA)
    settings = None  # a segment's settings, until a line changes them
    for index, block in enumerate(blocks):
        if block.limits is not None:
            state.apply(block.limits, block.line_no)
            junction_mm = first_given(block.limits.junction_deviation_mm, junction_mm)
            settings = None
        b_word = M205_B.match(block.raw)
        if b_word:
            min_segment_us = float(b_word.group(1))
            settings = None
        lines.append((block.kind, bool(block.raw.split(b";")[0].strip()), block.dwell_s))
        if block.kind is Kind.STOP:  # (in whole steps, as the merge left the points: a G4 moves nothing)
            position = np.where(np.isnan(block.position_mm), position, _on_steps(block.position_mm, profile))
        if block.kind is not Kind.MOVE or block.points_mm is None:
            continue
        for point in block.points_mm:
            point = np.where(np.isnan(point), position, point)
            segments.line.append(index)
            segments.start.append(position)
            segments.end.append(point)
            segments.feed.append(block.feed_mm_s)
            if settings is None:
                row = state.row()
                row[3] = junction_mm
                settings = [*row, min_segment_us]
            segments.settings.append(settings)
            position = point
    return segments, lines


@dataclass
class _Geometry:
    """Per block, what ``_populate_block`` computes before it knows the buffer (see the module docstring)."""

    start: np.ndarray  # (m, NA) mm, whole steps
    end: np.ndarray
    line: np.ndarray  # (m,)
    feed: np.ndarray  # (m,) F, mm/s (inf: G0)
    length: np.ndarray  # (m,) millimeters
    accel: np.ndarray  # (m,) block->acceleration
    speed_cap: np.ndarray  # (m,) the nominal speed M203 allows
    min_speed2_raw: np.ndarray  # (m,) 0.5 a / steps_per_mm, before NOMORE nominal^2
    speed_per_mm: np.ndarray  # (m, 4) X Y Z E velocity per unit of nominal speed (classic jerk)
    jerk: np.ndarray  # (m, 4) the jerk limits of X Y Z E
    junction2: np.ndarray  # (m,) the junction deviation limit with the block before (inf: none)
    reversal: np.ndarray  # (m,) bool: the path turns back (minimum planner speed)
    min_segment_us: np.ndarray  # (m,) M205 B in force

    @classmethod
    def of(cls, segments: Segments, config: MarlinConfig) -> _Geometry:
        start, end = np.array(segments.start).reshape(-1, _NA), np.array(segments.end).reshape(-1, _NA)
        rows = np.array(segments.settings, dtype=float).reshape(len(segments.line), 7 + 2 * _NA)
        spm = np.nan_to_num(np.array(config.steps_per_mm), nan=_NO_STEPS_PER_MM)
        delta = np.nan_to_num(end - start)
        steps = np.abs(np.rint(delta * spm))
        event_count = steps.max(axis=1, initial=0.0)
        xyz_enough = (steps[:, _XYZ] >= config.min_steps_per_segment).any(axis=1)
        length = np.where(xyz_enough, np.linalg.norm(delta[:, _XYZ], axis=1), np.abs(delta[:, _E]))
        per_mm = delta / length[:, None]
        axis_v, axis_a = rows[:, 4:4 + _NA], rows[:, 4 + _NA:4 + 2 * _NA]
        has_xyz = steps[:, _XYZ].any(axis=1)
        travel = np.where(np.isnan(rows[:, 1]), rows[:, 0], rows[:, 1])
        accel = np.where(has_xyz & (steps[:, _E] == 0), travel, rows[:, 0])
        accel = np.where(has_xyz, np.minimum(accel, axis_limited(axis_a, per_mm)), accel)  # LIMIT_ACCEL_*
        unit = delta / np.linalg.norm(delta, axis=1)[:, None]  # normalize_junction_vector (XYZE)
        junction2, reversal = _junction_deviation(unit, accel, length, rows[:, 3], axis_a)
        jerk = np.column_stack([rows[:, 4 + 2 * _NA], rows[:, 4 + 2 * _NA],
                                np.full(len(rows), config.z_jerk_mm_s), np.full(len(rows), config.e_jerk_mm_s)])
        return cls(start, end, np.array(segments.line, dtype=int), np.array(segments.feed, dtype=float), length,
                   accel, axis_limited(axis_v, per_mm), 0.5 * accel * length / event_count, per_mm[:, :_E + 1],
                   jerk, junction2, reversal, rows[:, 6 + 2 * _NA])


def axis_limited(limit: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """min over the axes that move of limit_axis / |unit_axis| (limit_value_by_axis_maximum)."""
    with np.errstate(divide="ignore"):
        return np.where(unit != 0, limit / np.abs(unit), np.inf).min(axis=1, initial=np.inf)


def _junction_deviation(unit, accel, length, jd_mm, axis_a):
    """(limit^2 of each block's entry junction, reversal) by Marlin's junction deviation, the
    nominal speeds aside (planner.cpp, HAS_JUNCTION_DEVIATION)."""
    prev = np.vstack([np.full((1, unit.shape[1]), np.nan), unit[:-1]])
    cos = -np.einsum("ij,ij->i", prev, unit)
    reversal = cos > _REVERSAL_COS
    turn = unit - prev
    with np.errstate(invalid="ignore", divide="ignore"):
        turn /= np.linalg.norm(turn, axis=1)[:, None]
        junction_accel = np.minimum(accel, axis_limited(axis_a, np.nan_to_num(turn)))
        sin_d2 = np.sqrt(0.5 * (1.0 - np.maximum(cos, -_REVERSAL_COS)))
        limit = junction_accel * jd_mm * sin_d2 / (1.0 - sin_d2)
        small = (length < 1.0) & (cos < _OCTAGON_COS)  # JD_HANDLE_SMALL_SEGMENTS
        limit = np.where(small, np.minimum(limit, length * junction_accel / _marlin_turn(cos)), limit)
    return np.where(np.isnan(cos), np.inf, limit), reversal


def _marlin_turn(cos: np.ndarray) -> np.ndarray:
    """acos(-cos), the junction's turn, as Marlin approximates it (W. R. Franklin's minimax
    polynomial for asin, error up to 0.033 rad; its least is 0.033)."""
    neg = np.where(cos < 0, -1.0, 1.0)
    t = neg * cos
    asin = 0.032843707 + t * (-1.451838349 + t * (29.66153956 + t * (-131.1123477 + t * (
        262.8130562 + t * (-242.7199627 + t * 84.31466202)))))
    return 0.5 * math.pi + neg * asin


class _Buffer:
    """The block buffer and the stepper in time: blocks are added as their lines are taken
    (``add``), the stepper starts each one as early as Marlin does, with the exit speed the plan
    then gives it (``settle``). Scalar code: each block is planned over at most
    BLOCK_BUFFER_SIZE - 3 blocks after it."""

    def __init__(self, geo: _Geometry, config: MarlinConfig):
        # Python floats in lists: the scan reads and writes them one at a time, where a numpy
        # scalar costs several times more (the same IEEE doubles: the same results)
        self.geo = SimpleNamespace(**{name: column.tolist() if column.ndim == 1 else column
                                      for name, column in vars(geo).items()})
        self.config = config
        m = len(geo.line)
        self.arrive, self.slot_wait = [math.inf] * m, [False] * m
        self.start, self.end = [math.nan] * m, [math.nan] * m
        self.entry2, self.exit2 = [0.0] * m, [0.0] * m
        self.nominal, self.max_entry2, self.min_speed2 = [0.0] * m, [0.0] * m, [0.0] * m
        self.added = self.done = self.run_first = 0
        self.free_s = 0.0  # when the stepper was last left idle by a line that waits for it
        self.starved: list[tuple[float, float]] = []

    def slot_free_s(self, j: int, bound_s: float) -> float:
        """When block ``j`` (not arriving before ``bound_s``) finds a free slot: when the block
        BLOCK_BUFFER_SIZE - 1 before it ends."""
        older = j - (self.config.block_buffer - 1)
        if older < self.run_first:
            return -np.inf
        self.settle(bound_s, through=older)
        return self.end[older]

    def add(self, j: int, arrive_s: float, slot_wait: bool) -> None:
        """``_populate_block`` of block ``j`` at ``arrive_s`` (``slot_wait``: it waited for the slot
        a finished block left, so the stepper took the next block first)."""
        self.settle(arrive_s)
        self.arrive[j], self.slot_wait[j] = arrive_s, slot_wait
        queued = 0  # nonbusy_movesplanned(): queued blocks the stepper has not started
        for i in range(j - 1, self.run_first - 1, -1):
            if i < self.done and (self.start[i] < arrive_s or (self.start[i] == arrive_s and slot_wait)):
                break
            queued += 1
        geo, config = self.geo, self.config
        feed = min(geo.feed[j], geo.speed_cap[j])
        segment_us = math.floor(geo.length[j] / feed * 1e6 + 0.5)
        shortfall = int(geo.min_segment_us[j]) - segment_us
        nominal = feed
        if 2 <= queued <= config.block_buffer // 2 - 1 and shortfall > 0:  # SLOWDOWN
            nominal = geo.length[j] * 1e6 / (segment_us + 2 * shortfall // queued)  # int32 / uint8 in C
        nominal = min(nominal, geo.speed_cap[j])
        self.nominal[j] = nominal
        self.min_speed2[j] = min(geo.min_speed2_raw[j], nominal * nominal)
        previous = self.nominal[j - 1] if j > 0 else 0.0
        self.max_entry2[j] = max(self._junction2(j, queued and previous > 0.0, previous), self.min_speed2[j])
        self.added = j + 1

    def _junction2(self, j: int, joined: bool, previous: float) -> float:
        """vmax_junction_sqr of block ``j`` (``joined``: moves_queued and a previous nominal speed)."""
        geo, nominal = self.geo, self.nominal[j]
        if not self.config.classic_jerk:
            if not joined or geo.reversal[j]:
                return self.min_speed2[j]
            return min(geo.junction2[j], nominal * nominal, previous * previous)
        diff = geo.speed_per_mm[j] * nominal
        limit = nominal
        if joined and nominal < previous:
            diff = diff - geo.speed_per_mm[j - 1] * nominal
        elif joined:
            limit = previous
            diff = diff * (previous / nominal) - geo.speed_per_mm[j - 1] * previous
        with np.errstate(divide="ignore"):
            factor = min(1.0, float(np.min(geo.jerk[j] / np.abs(diff))))
        return (limit * factor) ** 2

    def idle(self, free_s: float) -> None:
        """Every block added so far has run and the machine rests until ``free_s`` (a line waited)."""
        self.settle(np.inf)
        self.free_s, self.run_first = free_s, self.added

    def last_end_s(self) -> float:
        return self.end[self.added - 1] if self.added > self.run_first else self.free_s

    def settle(self, bound_s: float, through: int | None = None) -> None:
        """Start every block whose start and exit speed are decided, no block still to come
        arriving before ``bound_s``; at least through block ``through``."""
        while self.done < self.added:
            k = self.done
            start = self._start_s(k, bound_s)
            window = self._window(k, start, bound_s)
            if start is None or window is None:
                assert through is None or k > through, "the buffer cannot wait for what it holds"
                return
            self._run(k, start, window)

    def _start_s(self, k: int, bound_s: float) -> float | None:
        """When the stepper starts block ``k`` (None: not decided before later arrivals)."""
        before = self.end[k - 1] if k > self.run_first else self.free_s
        if self.arrive[k] < before:  # queued while the block before runs
            return before
        deadline = self.arrive[k] + self.config.first_move_delay_s  # added to an empty buffer
        if k + 2 < self.added:
            return min(self.arrive[k + 2], deadline)
        return deadline if bound_s >= deadline else None

    def _window(self, k: int, start_s: float | None, bound_s: float) -> int | None:
        """The newest block planned with ``k`` when it starts (None: not known yet)."""
        last = min(self.added - 1, k + self.config.block_buffer - 3)
        if start_s is None or (last < k + self.config.block_buffer - 3 and bound_s <= start_s):
            return None
        while last > k and (self.arrive[last] > start_s or (self.arrive[last] == start_s and self.slot_wait[last])):
            last -= 1
        return last

    def _run(self, k: int, start_s: float, last: int) -> None:
        """Block ``k`` started at ``start_s``: its exit speed from the plan through block ``last``."""
        geo = self.geo
        before = self.end[k - 1] if k > self.run_first else self.free_s
        joined = k > self.run_first and self.arrive[k] < before
        if k > self.run_first and start_s > before:
            self.starved.append((before, start_s - before))
        self.entry2[k] = self.exit2[k - 1] if joined else self.min_speed2[k]
        exit2 = self.min_speed2[last]  # the newest block's safe exit speed (reverse_pass)
        for j in range(last, k, -1):
            exit2 = min(self.max_entry2[j], exit2 + 2.0 * geo.accel[j] * geo.length[j])
        reach2 = self.entry2[k] + 2.0 * geo.accel[k] * geo.length[k]  # forward_pass_kernel
        if last > k and reach2 < exit2:
            exit2 = max(reach2, self.min_speed2[k + 1])
        self.exit2[k] = exit2
        self.start[k] = start_s
        self.end[k] = start_s + trapezoid_time_s(math.sqrt(self.entry2[k]), math.sqrt(exit2), self.nominal[k],
                                                 geo.accel[k], geo.length[k])
        self.done = k + 1


def send_lines(lines: list[tuple[Kind, bool, float]], first_block: np.ndarray, queue,
               line_rate_hz: float | None) -> tuple[np.ndarray, np.ndarray]:
    """A host sending ``lines`` (kind, sent, dwell s) one by one at ``line_rate_hz`` (None: at
    once), each line's blocks ``first_block[i]`` .. ``first_block[i + 1] - 1`` into ``queue``
    (Marlin's buffer, RepRapFirmware's ring) as their slots free; a STOP waits for the queue to
    empty, then dwells. Gives per line when it was taken, and a STOP's time (else NaN); the
    queue is left settled."""
    line_s = 1.0 / line_rate_hz if line_rate_hz else 0.0
    taken, line_time = np.full(len(lines), np.nan), np.full(len(lines), np.nan)
    t = 0.0  # when the last line sent was taken
    for index, (kind, sent, dwell_s) in enumerate(lines):
        if not sent:
            continue
        t += line_s
        if kind is Kind.STOP:  # waits for the queue to empty, then its dwell
            queue.settle(np.inf)
            line_time[index] = t = max(t, queue.last_end_s())
            t += dwell_s
            queue.idle(t)
        for j in range(first_block[index], first_block[index + 1]):
            slot = queue.slot_free_s(j, t)
            queue.add(j, max(t, slot), slot >= t)
            t = max(t, slot)
        taken[index] = t
        queue.settle(t + line_s)
    queue.settle(np.inf)
    return taken, line_time


def run_marlin(blocks: list[Block], profile: MachineProfile, config: MarlinConfig | None = None) -> MarlinRun:
    """``blocks`` sent to Marlin line by line and run (see the module docstring)."""
    config = config or MarlinConfig.from_profile(profile)
    blocks, merged = merge_short_segments(list(blocks), profile)
    segments, lines = _read(blocks, profile)
    geo = _Geometry.of(segments, config)
    buffer = _Buffer(geo, config)
    first_block = np.searchsorted(geo.line, np.arange(len(lines) + 1))
    taken, line_time = send_lines(lines, first_block, buffer, config.line_rate_hz)
    start, end, nominal, entry2, exit2 = (np.array(column, dtype=float) for column in (
        buffer.start, buffer.end, buffer.nominal, buffer.entry2, buffer.exit2))
    ends = np.append(end, np.nan)
    moves = np.array([kind is Kind.MOVE for kind, _, _ in lines])
    owner = first_block[1:] - (first_block[1:] > first_block[:-1])  # its last block; merged away: the next
    line_time = np.where(moves, ends[owner], np.where(np.isnan(line_time), taken, line_time))
    duration = float(np.nanmax(np.concatenate([[0.0], end, taken])))
    return MarlinRun(geo.start, geo.end, geo.line, geo.length, geo.accel, nominal, np.sqrt(entry2), np.sqrt(exit2),
                     start, end, line_time, taken, duration, buffer.starved, merged)
