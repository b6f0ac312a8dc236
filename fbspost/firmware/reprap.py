"""RepRapFirmware 3.5's motion planner over a program: the motion the machine makes.

Takes the blocks of a program (``gcode.read_gcode(..., "reprap")``), a machine profile and a
``ReprapConfig`` (from the profile's ``[firmware]`` table: steps_per_mm, dda_ring_length,
max_line_rate; the profile's square_corner_velocity as M566 X Y); gives a ``ReprapRun``: every
move RRF makes (its line, speeds, start and end), the rests where its ring ran dry, when every
line is taken, and the positions on the profile's sample grid (``planners.replan(..., "reprap")``
wraps it as ``FirmwareMotion``).

Modelled from Duet3D/RepRapFirmware 3.5 (src/Movement/DDA.cpp InitStandardMove, DoLookahead,
MatchSpeeds, RecalculateMove; DDARing.cpp CanAddMove, PrepareMoves; Move.h DdaRingLength;
MoveTiming.h; Config/Configuration.h defaults; read November 2026) and docs.duet3d.com (M201,
M203, M204, M566, M595, "Motion system"):
- targets in whole steps, ``lrintf(mm * steps_per_mm)`` (CartesianToMotorSteps), for the axes
  with steps_per_mm; the move's direction and length come from the commanded coordinates (the
  ring keeps the last target as given, so rounding does not accumulate): the motors cover their
  whole steps in the time the commanded length takes. A move that commands no change is dropped.
- length: the XYZ distance, else that of the other axes, else |E| (extrude-only); the direction
  vector u is the move per mm of length, E included.
- acceleration: min over the moving drives of M201 / |u| (VectorBoxIntersection), and for moves
  with X or Y motion at most M204 P (printing: XY with E forward) or T.
- speed: F, at least M203 I (0.5 mm/s; the program's, at least 0.01), at most min over the moving drives of M203 / |u|.
- junction (MatchSpeeds): at most M566 / |u - u_before| on every drive (E included), and at
  most both moves' speeds. Jerk policy 0 (M566 P0, the default): moves meld only when both or
  neither print, move XY, or extrude alone; else the first stops.
- look-ahead: a move's end speed is fixed when it is prepared, from the moves then in the ring,
  the newest ending at rest (the plan DoLookahead's walks back and forth converge to).
- RecalculateMove: a move that reaches its speed but would accelerate (decelerate) towards it
  for under 10 step clocks (750 kHz), from (to) at least 0.9 of it, cruises at its start (end)
  speed instead: at 1e6 mm/s^2, speed steps under 13 mm/s are not taken.
- the ring (``dda_ring_length``, 50 on Duet 3; the last free slot is never used): move j is
  added once move j - (ring - 1) has finished. A move is prepared once the moves before it have
  under 100 ms left (UsualMinimumPreparedTime) and under half the ring is prepared or running;
  a move that comes to an idle machine is prepared after the grace period (M595 R, 10 ms).
  Moves that come at its prepare time count as in the ring.
- lines: taken ``1 / max_line_rate`` apart (a USB host; an SD-card print: no limit); a line
  that stops the machine (``Kind.STOP``: G4, M400, homing...) waits for the ring to empty, then
  its dwell.
Not modelled: CanAddMove's limit on unprepared time (2 s, or 0.5 s but the first), PrepareMoves'
holding back a deceleration-only move until 50 ms are left (IsGoodToPrepare), RRF's own
arc segmentation, pressure advance, step timing within a move, M593 input shaping (applied by
RRF to each move's acceleration and deceleration: bench/firmware.py compares RRF's own impulses
on the whole plan, through whole steps, ``shaping.reprap_shaper``). Units: mm, s, mm/s,
mm/s^2 (M566 and M203 are in mm/min on the line).
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..plan.limits import LimitState, reprap_jerk_mm_s
from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind
from .marlin import MarlinRun, axis_limited, send_lines, trapezoid_time_s

_NA = len(AXES)
_X, _Y, _E = AXES.index("X"), AXES.index("Y"), AXES.index("E")
_OTHER = [i for i in range(_NA) if i > _E]
M566 = re.compile(rb"^\s*(?:[Nn]\s*\d+\s*)?[Mm]\s*0*566(?![\d.])([^;(]*)")
_WORD = re.compile(rb"([A-Za-z])\s*([-+]?[\d.]+)")
MIN_FEED_FLOOR_MM_S = 0.01  # the lowest M203 I RRF takes (Platform::SetMinMovementSpeed)
STEP_CLOCK_HZ = 750_000.0  # StepClockRate, 48 MHz / 64 on every Duet 3
MIN_RAMP_S = 10.0 / STEP_CLOCK_HZ  # MinimumAccelOrDecelClocks: a shorter ramp to F is not taken
GRACE_S = 0.01  # DefaultGracePeriod (M595 R): a move that comes to an idle machine waits this long for more


@dataclass(frozen=True)
class ReprapConfig:
    """RepRapFirmware's settings the model needs (RRF 3.5's defaults)."""

    steps_per_mm: tuple[float, ...]  # per AXES entry (NaN: not given, not rounded)
    jerk_mm_s: tuple[float, ...]  # M566 per AXES entry at the start
    ring_length: int = 50  # DdaRingLength (M595 P)
    line_rate_hz: float | None = None  # lines the host sends per second (None: SD card)
    jerk_policy: int = 0  # M566 P
    min_speed_mm_s: float = 0.5  # M203 I (DefaultMinFeedrate), until the program sets it
    prepare_ahead_s: float = 0.1  # UsualMinimumPreparedTime
    grace_s: float = GRACE_S
    min_ramp_s: float = MIN_RAMP_S

    @classmethod
    def from_profile(cls, profile: MachineProfile, **changes) -> ReprapConfig:
        fw, scv = profile.firmware, profile.planner_square_corner_velocity_mm_s
        jerk = tuple(reprap_jerk_mm_s(np.array([scv]))[0].tolist())
        values = dict(steps_per_mm=tuple(fw.steps_per_mm.get(a, math.nan) for a in AXES), jerk_mm_s=jerk,
                      ring_length=fw.dda_ring_length, line_rate_hz=fw.max_line_rate_hz)
        return cls(**{**values, **changes})


class ReprapRun(MarlinRun):
    """What RepRapFirmware does with a program: the record of ``marlin.MarlinRun``, per move;
    ``nominal_mm_s`` is the speed it cruises at (RRF's topSpeed), ``length_mm`` the commanded
    length it is timed over, ``start_mm`` / ``end_mm`` its whole-step targets."""


@dataclass
class _Moves:
    """The moves RRF makes, with what does not depend on when they come."""

    start: np.ndarray  # (m, NA) whole steps
    end: np.ndarray
    line: np.ndarray  # (m,) index of the program block
    length: np.ndarray  # (m,) commanded
    accel: np.ndarray
    speed: np.ndarray  # requested speed
    junction2: np.ndarray  # (m,) squared speed limit of the junction with the move before (0: no melding)

    @classmethod
    def of(cls, rows: dict[str, list], config: ReprapConfig) -> _Moves:
        start, end = (np.array(rows[k], dtype=float).reshape(-1, _NA) for k in ("start", "end"))
        delta = end - start
        xyz, other = np.linalg.norm(delta[:, :_E], axis=1), np.linalg.norm(delta[:, _OTHER], axis=1)
        length = np.where(xyz > 0, xyz, np.where(other > 0, other, np.abs(delta[:, _E])))
        u = delta / length[:, None]
        xy = (delta[:, _X] != 0) | (delta[:, _Y] != 0)
        printing = xy & (delta[:, _E] > 0)
        e_alone = (delta[:, _E] != 0) & ~printing
        accel = axis_limited(np.array(rows["axis_a"]).reshape(-1, _NA), u)
        m204 = np.where(printing, rows["print_a"], rows["travel_a"])
        accel = np.where(xy, np.minimum(accel, m204), accel)
        speed = np.minimum(np.maximum(rows["feed"], rows["min_feed"]),
                           axis_limited(np.array(rows["axis_v"]).reshape(-1, _NA), u))
        jerk = np.array(rows["jerk"]).reshape(-1, _NA)
        step = np.abs(np.diff(u, axis=0, prepend=np.nan))
        with np.errstate(divide="ignore", invalid="ignore"):
            cap = np.where(step > 0, jerk / step, np.inf).min(axis=1)
        flags = np.column_stack([xy, printing, e_alone])
        meld = (np.array(rows["policy"]) != 0) | (flags == np.roll(flags, 1, axis=0)).all(axis=1)
        cap = np.minimum(np.minimum(cap, speed), np.roll(speed, 1))
        junction2 = np.where(meld, cap, 0.0) ** 2
        spm = np.array(config.steps_per_mm)
        steps = [np.where(np.isnan(spm), p, np.rint(p * spm) / spm) for p in (start, end)]  # lrintf: ties to even
        return cls(*steps, np.array(rows["line"], dtype=int), length, accel, speed, junction2)


def commanded_pieces(blocks: list[Block]) -> Iterator[tuple[int, Block, list[tuple[np.ndarray, np.ndarray]]]]:
    """Every block with its index and the (start, end) of each of its pieces that changes a
    position, as commanded (before any rounding to steps). An axis whose position is not known
    is where RRF starts it: at 0, or where it was."""
    position = np.zeros(_NA)
    for index, block in enumerate(blocks):
        if block.kind is Kind.STOP:
            position = np.where(np.isnan(block.position_mm), position, block.position_mm)
        pieces = []
        for point in block.points_mm if block.kind is Kind.MOVE and block.points_mm is not None else ():
            point = np.where(np.isnan(point), position, point)
            if (point != position).any():
                pieces.append((position, point))
                position = point
        yield index, block, pieces


def _read(blocks: list[Block], profile: MachineProfile, config: ReprapConfig):
    """The moves of ``blocks`` (rows of ``_Moves.of``) and per line (kind, sent, dwell s)."""
    state = LimitState(profile)
    jerk, policy = np.array(config.jerk_mm_s), config.jerk_policy
    rows = {k: [] for k in ("start", "end", "line", "feed", "print_a", "travel_a", "axis_a", "axis_v", "jerk",
                            "policy", "min_feed")}
    lines = []
    min_feed = config.min_speed_mm_s
    for index, block, pieces in commanded_pieces(blocks):
        if block.limits is not None:
            state.apply(block.limits, block.line_no)
            if block.limits.min_feed_mm_s is not None:  # M203 I (Platform::SetMinMovementSpeed: at least 0.01)
                min_feed = max(block.limits.min_feed_mm_s, MIN_FEED_FLOOR_MM_S)
        m566 = M566.match(block.raw)
        if m566:
            for letter, value in _WORD.findall(m566.group(1).upper()):
                if letter == b"P":
                    policy = int(float(value))
                elif letter.decode() in AXES:
                    jerk[AXES.index(letter.decode())] = float(value) / 60.0
        lines.append((block.kind, bool(block.raw.split(b";")[0].strip()), block.dwell_s))
        travel = state.accel if math.isnan(state.travel_accel) else state.travel_accel
        for start, end in pieces:
            for key, value in zip(rows, (start, end, index, block.feed_mm_s, state.accel, travel, state.axis_a.copy(),
                                         state.axis_v.copy(), jerk.copy(), policy, min_feed), strict=True):
                rows[key].append(value)
    return rows, lines


def top_speed(v0: float, v1: float, speed: float, accel: float, length: float, min_ramp_s: float) -> float:
    """The speed a move from ``v0`` to ``v1`` peaks or cruises at (RecalculateMove; v0 and v1
    reachable from each other within ``length``)."""
    if (2.0 * speed * speed - v0 * v0 - v1 * v1) / (2.0 * accel) < length:
        near = max(v0, v1)
        return near if near + accel * min_ramp_s > speed and near >= 0.9 * speed else speed
    return max(math.sqrt(accel * length + 0.5 * (v0 * v0 + v1 * v1)), v0, v1)


class _Ring:
    """The DDA ring in time: moves are added as their lines come (``arrive``), each is prepared
    and started as RRF does, its end speed planned over the moves then in the ring (``settle``)."""

    def __init__(self, moves: _Moves, config: ReprapConfig):
        self.moves, self.config = moves, config
        m = len(moves.line)
        self.arrive, self.start, self.end = np.full(m, np.inf), np.full(m, np.nan), np.full(m, np.nan)
        self.entry, self.exit, self.top = np.zeros(m), np.zeros(m), np.zeros(m)
        self.added = self.done = self.run_first = 0
        self.free_s = 0.0  # when the machine was left idle by a line that waits for it
        self.starved: list[tuple[float, float]] = []

    def slot_free_s(self, j: int, bound_s: float) -> float:
        """When move ``j`` (not arriving before ``bound_s``) finds a free slot: when the move
        ring - 1 before it has finished."""
        older = j - (self.config.ring_length - 1)
        if older < self.run_first:
            return -np.inf
        self.settle(bound_s, through=older)
        return self.end[older]

    def add(self, j: int, arrive_s: float, slot_wait: bool) -> None:
        """Move ``j`` taken at ``arrive_s`` (``slot_wait``, Marlin's stepper race: none here)."""
        self.arrive[j] = arrive_s
        self.added = j + 1

    def idle(self, free_s: float) -> None:
        """Every move added so far has run and the machine rests until ``free_s`` (a line waited)."""
        self.settle(np.inf)
        self.free_s, self.run_first = free_s, self.added

    def last_end_s(self) -> float:
        return self.end[self.added - 1] if self.added > self.run_first else self.free_s

    def settle(self, bound_s: float, through: int | None = None) -> None:
        """Prepare and start every move whose plan is decided, no move still to come arriving
        before ``bound_s``; at least through move ``through``."""
        while self.done < self.added:
            k = self.done
            prepare_s = self._prepare_s(k)
            window = min(self.added - 1, k + self.config.ring_length - 2)
            if window < k + self.config.ring_length - 2 and bound_s <= prepare_s:
                assert through is None or k > through, "the ring cannot wait for what it holds"
                return
            while window > k and self.arrive[window] > prepare_s:
                window -= 1
            self._run(k, prepare_s, window)

    def _prepare_s(self, k: int) -> float:
        """When RRF prepares move ``k`` (PrepareMoves, the grace period from idle)."""
        before = self.end[k - 1] if k > self.run_first else self.free_s
        if k == self.run_first or self.arrive[k] >= before:
            return self.arrive[k] + self.config.grace_s
        half = k - self.config.ring_length // 2
        return max(self.arrive[k], before - self.config.prepare_ahead_s,
                   self.end[half] if half >= self.run_first else -np.inf)

    def _run(self, k: int, prepare_s: float, last: int) -> None:
        """Move ``k`` prepared at ``prepare_s``: its end speed from the plan through move ``last``."""
        moves, config = self.moves, self.config
        before = self.end[k - 1] if k > self.run_first else self.free_s
        if k > self.run_first and prepare_s > before:
            self.starved.append((before, prepare_s - before))
        v0 = self.exit[k - 1] if k > self.run_first else 0.0
        exit2 = 0.0  # the newest move ends at rest
        for j in range(last, k, -1):
            exit2 = min(moves.junction2[j], exit2 + 2.0 * moves.accel[j] * moves.length[j])
        exit2 = min(exit2, v0 * v0 + 2.0 * moves.accel[k] * moves.length[k])
        v1 = math.sqrt(exit2)
        top = top_speed(v0, v1, moves.speed[k], moves.accel[k], moves.length[k], config.min_ramp_s)
        self.entry[k], self.exit[k], self.top[k] = v0, v1, top
        self.start[k] = max(before, prepare_s)
        self.end[k] = self.start[k] + float(trapezoid_time_s(v0, v1, top, moves.accel[k], moves.length[k]))
        self.done = k + 1


def run_reprap(blocks: list[Block], profile: MachineProfile, config: ReprapConfig | None = None) -> ReprapRun:
    """``blocks`` read by RepRapFirmware line by line and run (see the module docstring)."""
    config = config or ReprapConfig.from_profile(profile)
    rows, lines = _read(list(blocks), profile, config)
    moves = _Moves.of(rows, config)
    ring = _Ring(moves, config)
    first_move = np.searchsorted(moves.line, np.arange(len(lines) + 1))
    taken, line_time = send_lines(lines, first_move, ring, config.line_rate_hz)
    ends = np.append(ring.end, np.nan)
    has_moves = first_move[1:] > first_move[:-1]
    line_time = np.where(has_moves, ends[first_move[1:] - 1], np.where(np.isnan(line_time), taken, line_time))
    duration = float(np.nanmax(np.concatenate([[0.0], ring.end, taken])))
    return ReprapRun(moves.start, moves.end, moves.line, moves.length, moves.accel, ring.top, ring.entry, ring.exit,
                     ring.start, ring.end, line_time, taken, duration, ring.starved, [])
