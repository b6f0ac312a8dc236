"""Motion planner: the motion the machine's own controller makes for a program.

Takes the blocks of a program (``gcode.Block``) and a machine profile; gives the plan the
machine's own controller would execute, sampled on the profile's time grid: the X Y Z E machine
positions at every sample, when each block happens, and the runs of motion between rests.

The controller is Klipper's look-ahead planner (klippy/toolhead.py) with its accel_to_decel /
minimum_cruise_ratio smoothing switched off:

- Every linear piece of a MOVE block is one move: its distance is the XYZ length, or |dE| when
  XYZ moves less than 1e-9 mm (extrude-only); its cruise speed is the feed, limited by the
  planner's VELOCITY (if set) and, for every axis A with a limit, by max_velocity_A / |u_A|
  (u the piece's direction per mm of distance, E included). G0 (infinite feed) runs as fast as
  the limits allow. Zero-length pieces are dropped, as Klipper does. Axis limits are the
  profile's, changed by M203 / M201 from their line on (also for an axis the profile does not
  list; an axis without any limit is not limited).
- Its acceleration is the planner's (M204 S/P, Klipper ACCEL); pieces that do not extrude
  (dE <= 0) use M204 T when one was set; then limited by max_acceleration_A / |u_A|. Unlike
  Klipper (max_extrude_only_velocity / _accel), extrude-only pieces get the same treatment.
- The speed at a junction is Klipper's Move.calc_junction: the square-corner-velocity model
  (junction deviation scv^2 (sqrt 2 - 1) / accel, accel the M204 S/P value in force, as
  Klipper recomputes it; or Marlin's M205 J directly), the approximated centripetal limit of
  both pieces, and both cruise speeds. Extrude-only pieces start and end at rest; Klipper's
  extruder junction limit (instantaneous_corner_velocity) is not modelled.
- Look-ahead is complete (Klipper's lazy flush gives the same result): the forward and backward
  passes over squared junction speeds are vectorized min-plus scans; each piece is then a
  trapezoid peaking at min(cruise^2, (v0^2 + v1^2 + 2 a d) / 2).

STOP blocks are rests: the motion decelerates to 0 at them and a G4 waits dwell_s there. A STOP
that moved the machine without pieces (G28, a move from an unknown position) takes no time here:
the position jumps to the STOP's position, and the next run starts from there. Every run of
motion starts at rest at one sample and ends at rest at another, and runs do not share samples:
when the rest between two runs is shorter than that needs, the later run starts at the second
sample after the earlier one ends (less than 2 sample periods of extra rest, only at STOPs).

Axes whose position is unknown (NaN in the blocks) are held at their last known value; before
they are first known, at that first value; axes never known, at 0. ``Plan.notes`` says so.
Units: mm, s, mm/s, mm/s^2.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from .gcode import AXES, Block, Kind
from .profile import MachineProfile

EXTRUDE_ONLY_MM = 1e-9  # Klipper: an XYZ length below this makes an extrude-only move
SCAN_CHUNK = 4096  # pieces per chunk of the min-plus scans (bounds the cumulative-sum magnitude)
SAMPLE_CHUNK = 1 << 14  # samples evaluated at once (keeps the temporaries in cache)
MAX_NOTES = 20  # notes about lines with unknown positions, at most
CLAMPED = "feeds beyond the machine's velocity limits run clamped, as the controller runs them"

_NA = len(AXES)
_E = AXES.index("E")


@dataclass
class Pieces:
    """The planned linear pieces in order (m of them; zero-length pieces are dropped)."""

    block: np.ndarray  # (m,) index of the block each piece belongs to
    run: np.ndarray  # (m,) index into Plan.runs
    start_mm: np.ndarray  # (m, 4) X Y Z E at the start
    end_mm: np.ndarray  # (m, 4) at the end
    length_mm: np.ndarray  # (m,) XYZ length; |dE| for extrude-only pieces
    extrude_only: np.ndarray  # (m,) bool
    accel_mm_s2: np.ndarray  # (m,) after the axis limits
    max_v_mm_s: np.ndarray  # (m,) cruise limit: feed and velocity limits (inf: none)
    start_v_mm_s: np.ndarray  # (m,) planned speed at the start junction
    peak_v_mm_s: np.ndarray  # (m,) cruise speed reached
    end_v_mm_s: np.ndarray  # (m,) planned speed at the end junction
    start_s: np.ndarray  # (m,) when the piece starts
    duration_s: np.ndarray  # (m,)


@dataclass
class _Segments:
    """The plan's piecewise-quadratic timeline: position = a0 + a1 tau + a2 tau^2, tau = t - ref,
    from t0 on (sorted by t0; of equal starts the later one rules)."""

    t0: np.ndarray  # (s,) s
    ref: np.ndarray  # (s,) s
    a0: np.ndarray  # (s, 4) mm
    a1: np.ndarray  # (s, 4) mm/s
    a2: np.ndarray  # (s, 4) mm/s^2


@dataclass
class Plan:
    """What the machine does: samples, block times, runs (see the module docstring). The samples
    are evaluated on demand, a stretch at a time (``samples``): a long program's samples need not
    be held."""

    sample_rate_hz: float
    n_samples: int  # samples at t_k = k / sample_rate_hz, k = 0..n-1
    line_time_s: np.ndarray  # (n_blocks,): MOVE: end of its motion; PASS: when the motion reaches it; STOP: at rest at it (before its dwell)
    move_start_s: np.ndarray  # (n_blocks,): MOVE: start of its motion; other blocks: = line_time_s
    is_move: np.ndarray  # (n_blocks,) bool: the block is a MOVE (rewritten), not a copied line
    is_stop: np.ndarray  # (n_blocks,) bool: the block is a STOP (the machine at rest at it)
    runs: list[tuple[int, int]]  # [first, last] sample indices (inclusive) of each run of motion, at rest at both
    duration_s: float  # end of the last motion or dwell
    segments: _Segments
    pieces: Pieces | None = None  # the piece-level plan the samples come from
    notes: list[str] = field(default_factory=list)  # assumptions made (unknown positions)
    warnings: list[str] = field(default_factory=list)  # feeds beyond the machine's limits, clamped (CLAMPED...)

    def samples(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, 4) X Y Z E at samples first .. stop - 1 (mm). Each sample depends on its
        time alone, so any cut into stretches gives the same values."""
        seg = self.segments
        t = np.arange(first, stop) / self.sample_rate_hz
        if not t.size:
            return np.zeros((0, _NA))
        # the segment of each sample (searchsorted right, minus 1) by merging the sorted sample
        # times with the segment starts in the stretch: cheaper than a search per sample
        lo, hi = np.searchsorted(seg.t0, t[[0, -1]], side="right")
        entered = np.searchsorted(t, seg.t0[lo:hi], side="left")  # sample where each later segment starts
        index = (lo - 1) + np.cumsum(np.bincount(entered, minlength=t.size))
        tau = (t - np.take(seg.ref, index))[:, None]
        out = np.take(seg.a2, index, axis=0)
        out *= tau
        out += np.take(seg.a1, index, axis=0)
        out *= tau
        out += np.take(seg.a0, index, axis=0)
        return out

    @functools.cached_property
    def positions_mm(self) -> np.ndarray:
        """(n_samples, 4) every sample at once (for programs that fit in memory)."""
        return np.concatenate([self.samples(k, min(k + SAMPLE_CHUNK, self.n_samples))
                               for k in range(0, self.n_samples, SAMPLE_CHUNK)] or [np.zeros((0, _NA))])


# ---- limits in force, block by block ---------------------------------------------------------

class _LimitState:
    """The planner settings as the blocks change them; ``row()`` is one row of the state table:
    accel, travel accel (NaN: none), planner max velocity, junction deviation, axis max velocity
    (4), axis max acceleration (4)."""

    def __init__(self, profile: MachineProfile):
        self.accel = float(profile.planner_acceleration_mm_s2)
        self.travel_accel = math.nan
        self.max_velocity = math.inf
        self.scv = float(profile.planner_square_corner_velocity_mm_s)
        self.direct_jd: float | None = None  # Marlin M205 J, until a square corner velocity is set
        self.axis_v = np.full(_NA, math.inf)
        self.axis_a = np.full(_NA, math.inf)
        for i, name in enumerate(AXES):
            if name in profile.axes:
                self.axis_v[i] = profile.axes[name].max_velocity_mm_s
                self.axis_a[i] = profile.axes[name].max_acceleration_mm_s2

    def apply(self, limits, line_no: int) -> None:
        def positive(value, what, zero_ok=False):
            if not (math.isfinite(value) and (value > 0 or zero_ok and value == 0)):
                raise ValueError(f"line {line_no}: {what} must be {'>=' if zero_ok else '>'} 0, got {value!r}")
            return float(value)

        if limits.acceleration_mm_s2 is not None:
            self.accel = positive(limits.acceleration_mm_s2, "acceleration")
        if limits.travel_acceleration_mm_s2 is not None:
            self.travel_accel = positive(limits.travel_acceleration_mm_s2, "travel acceleration")
        if limits.max_velocity_mm_s is not None:
            self.max_velocity = positive(limits.max_velocity_mm_s, "max velocity")
        if limits.square_corner_velocity_mm_s is not None:
            self.scv = positive(limits.square_corner_velocity_mm_s, "square corner velocity", zero_ok=True)
            self.direct_jd = None
        if limits.junction_deviation_mm is not None:
            self.direct_jd = positive(limits.junction_deviation_mm, "junction deviation", zero_ok=True)
        for name, value in limits.axis_max_velocity_mm_s.items():
            if name in AXES:
                self.axis_v[AXES.index(name)] = positive(value, f"{name} max velocity")
        for name, value in limits.axis_max_acceleration_mm_s2.items():
            if name in AXES:
                self.axis_a[AXES.index(name)] = positive(value, f"{name} max acceleration")

    def row(self) -> list[float]:
        jd = self.direct_jd
        if jd is None:  # Klipper's _calc_junction_deviation, with the accel in force
            jd = self.scv**2 * (math.sqrt(2.0) - 1.0) / self.accel
        return [self.accel, self.travel_accel, self.max_velocity, jd, *self.axis_v, *self.axis_a]


# ---- the min-plus scans ----------------------------------------------------------------------

def forward_pass(limit_v2: np.ndarray, delta_v2: np.ndarray, chunk: int = SCAN_CHUNK) -> np.ndarray:
    """F[0] = L[0], F[i] = min(L[i], F[i-1] + delta[i-1]): the squared speed reachable at every
    junction accelerating from the earlier ones. ``limit_v2`` has one more entry than
    ``delta_v2`` (2 a d of the piece between junctions i and i+1).

    Computed as F[i] = min(L[i], C[i] + min_{k<i}(L[k] - C[k])), C the cumulative sum of delta
    from the chunk's start; the chunk's first entry carries the previous chunk's result. The
    exclusive minimum keeps a junction's own limit exact; a limit inherited from an earlier
    junction is at least delta[i-1], and its rounding error is a few ulps of C."""
    out = np.empty_like(limit_v2)
    n = limit_v2.size
    carry = math.inf
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        lim = limit_v2[s:e].copy()
        lim[0] = min(lim[0], carry)
        c = np.zeros(e - s)
        np.cumsum(delta_v2[s:e - 1], out=c[1:])
        prefix = np.minimum.accumulate(lim - c)
        res = lim
        res[1:] = np.minimum(lim[1:], c[1:] + prefix[:-1])
        out[s:e] = res
        if e < n:
            carry = res[-1] + delta_v2[e - 1]
    return out


def backward_pass(limit_v2: np.ndarray, delta_v2: np.ndarray, chunk: int = SCAN_CHUNK) -> np.ndarray:
    """B[n] = L[n], B[i] = min(L[i], B[i+1] + delta[i]): the squared speed from which every
    later junction can still be reached decelerating (the mirror image of ``forward_pass``)."""
    return forward_pass(limit_v2[::-1], delta_v2[::-1], chunk)[::-1].copy()


def junction_limits(unit_prev: np.ndarray, unit_next: np.ndarray, jd_prev, jd_next, accel_prev, accel_next,
                    delta_prev, delta_next, cruise_v2_prev, cruise_v2_next) -> np.ndarray:
    """Largest squared speed at junctions between XYZ pieces (Klipper's Move.calc_junction):
    the cruise speeds, and for a real corner the junction-deviation and centripetal limits."""
    cos_theta = -np.einsum("ij,ij->i", unit_prev, unit_next)
    sin_d2 = np.sqrt(np.maximum(0.5 * (1.0 - cos_theta), 0.0))
    cos_d2 = np.sqrt(np.maximum(0.5 * (1.0 + cos_theta), 0.0))
    one_minus_sin = 1.0 - sin_d2
    limit = np.minimum(cruise_v2_prev, cruise_v2_next)
    corner = (one_minus_sin > 0.0) & (cos_d2 > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_jd = sin_d2 / one_minus_sin
        quarter_tan = 0.25 * sin_d2 / cos_d2
        corner_limit = np.minimum.reduce([r_jd * jd_next * accel_next, r_jd * jd_prev * accel_prev,
                                          delta_next * quarter_tan, delta_prev * quarter_tan])
    return np.where(corner, np.minimum(limit, corner_limit), limit)


# ---- the planner -----------------------------------------------------------------------------

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


def plan_blocks(blocks: Iterable[Block], profile: MachineProfile) -> Plan:
    """The plan of ``blocks`` on ``profile`` (see the module docstring). The blocks are taken
    one at a time and not kept."""
    fs = float(profile.sample_rate_hz)
    state = _LimitState(profile)
    states = [state.row()]
    waypoints = [np.full((1, _NA), np.nan)]  # the position before the program: first known values
    row_block, row_count, row_motion = [], [], []  # who added each group of waypoint rows
    move_feed, move_state = [], []  # per motion group
    dwell, is_move, is_stop, row_line = [], [], [], []
    stop_blocks = []
    for j, block in enumerate(blocks):
        dwell.append(0.0)
        is_move.append(block.kind is Kind.MOVE)
        is_stop.append(block.kind is Kind.STOP)
        if block.limits is not None:
            state.apply(block.limits, block.line_no)
            states.append(state.row())
        if block.kind is Kind.MOVE:
            if block.points_mm is None or len(block.points_mm) == 0:
                continue
            points = np.asarray(block.points_mm, dtype=float).reshape(-1, _NA)
            feed = math.inf if block.feed_mm_s is None else float(block.feed_mm_s)
            if not feed > 0:
                raise ValueError(f"line {block.line_no}: feed must be > 0, got {block.feed_mm_s!r}")
            waypoints.append(points)
            row_block.append(j)
            row_line.append(block.line_no)
            row_count.append(points.shape[0])
            row_motion.append(True)
            move_feed.append(feed)
            move_state.append(len(states) - 1)
        elif block.kind is Kind.STOP:
            if not (block.dwell_s >= 0 and math.isfinite(block.dwell_s)):
                raise ValueError(f"line {block.line_no}: dwell must be >= 0, got {block.dwell_s!r}")
            dwell[j] = block.dwell_s
            stop_blocks.append(j)
            waypoints.append(np.asarray(block.position_mm, dtype=float).reshape(1, _NA))
            row_block.append(j)
            row_line.append(block.line_no)
            row_count.append(1)
            row_motion.append(False)
    nb = len(dwell)
    dwell, is_move, is_stop = np.asarray(dwell), np.asarray(is_move, dtype=bool), np.asarray(is_stop, dtype=bool)

    raw = np.concatenate(waypoints)
    filled, never = fill_unknown(raw)
    notes = [f"{AXES[i]}: position never known, planned at 0 mm" for i in np.flatnonzero(never)]
    row_count_a = np.asarray(row_count, dtype=np.int64)
    seg_block = np.repeat(np.asarray(row_block, dtype=np.int64), row_count_a)  # segment i: row i -> i+1
    seg_line = np.repeat(np.asarray(row_line, dtype=np.int64), row_count_a)
    seg_motion = np.repeat(np.asarray(row_motion, dtype=bool), row_count_a)
    ever_known = np.maximum.accumulate(~np.isnan(raw), axis=0)
    lost = (~seg_motion)[:, None] & np.isnan(raw[1:]) & ever_known[:-1]
    lost_rows = np.flatnonzero(lost.any(axis=1))
    for i in lost_rows[:MAX_NOTES]:
        axes = "".join(AXES[a] for a in np.flatnonzero(lost[i]))
        notes.append(f"line {seg_line[i]}: {axes} unknown after this line, "
                     f"held at the last known position")
    if lost_rows.size > MAX_NOTES:
        notes.append(f"... and {lost_rows.size - MAX_NOTES} more lines with unknown positions")

    # pieces: the motion segments that move
    seg_group = np.repeat(np.cumsum(np.asarray(row_motion, dtype=np.int64)) - 1, row_count_a)
    start = filled[:-1]
    delta = filled[1:] - start
    xyz_len = np.sqrt(np.einsum("ij,ij->i", delta[:, :3], delta[:, :3]))
    extrude_only = xyz_len < EXTRUDE_ONLY_MM
    length = np.where(extrude_only, np.abs(delta[:, _E]), xyz_len)
    keep = seg_motion & (length > 0)
    start, delta, length, extrude_only = start[keep], delta[keep], length[keep], extrude_only[keep]
    piece_block = seg_block[keep]
    group = seg_group[keep]
    end = start + delta
    m = length.size

    table = np.asarray(states)[np.asarray(move_state, dtype=np.int64)[group]] if m else np.zeros((0, 4 + 2 * _NA))
    feed = np.asarray(move_feed)[group] if m else np.zeros(0)
    accel_print, accel_travel, planner_v, jd = table[:, 0], table[:, 1], table[:, 2], table[:, 3]
    axis_v, axis_a = table[:, 4:4 + _NA], table[:, 4 + _NA:]
    unit = delta / length[:, None] if m else np.zeros((0, _NA))
    unit[extrude_only, :_E] = 0.0  # |dE| / length is exactly 1 already
    abs_unit = np.abs(unit)
    with np.errstate(divide="ignore"):
        axis_v_limit = np.where(abs_unit > 0, axis_v / abs_unit, np.inf).min(axis=1, initial=np.inf)
        axis_a_limit = np.where(abs_unit > 0, axis_a / abs_unit, np.inf).min(axis=1, initial=np.inf)
    max_v = np.minimum(np.minimum(feed, planner_v), axis_v_limit)
    clamped = np.flatnonzero(np.isfinite(feed) & (axis_v_limit < feed))  # as the controller does (a G0 means it)
    clamped = clamped[np.unique(piece_block[clamped], return_index=True)[1]]  # the first piece of each block
    warnings = []
    if clamped.size:  # one line: slicers write Z moves at travel feeds on every layer
        i = clamped[0]
        warnings.append(f"{CLAMPED}: line {seg_line[keep][i]} (feed {feed[i] * 60:.6g} mm/min, runs at "
                        f"{max_v[i] * 60:.6g} mm/min)" + (f" and {clamped.size - 1} more lines" if clamped.size > 1 else ""))
    extrudes = delta[:, _E] > 0
    accel = np.where(extrudes | np.isnan(accel_travel), accel_print, accel_travel)
    accel = np.minimum(accel, axis_a_limit)
    cruise_v2 = max_v * max_v
    delta_v2 = 2.0 * accel * length

    # runs: pieces between the same two STOP blocks
    run_key = np.searchsorted(np.asarray(stop_blocks, dtype=np.int64), piece_block, side="left")
    new_run = np.ones(m, dtype=bool)
    new_run[1:] = run_key[1:] != run_key[:-1]
    run_first_piece = np.flatnonzero(new_run)
    nr = run_first_piece.size
    run_end_piece = np.append(run_first_piece[1:], m) if nr else run_first_piece  # exclusive
    piece_run = np.cumsum(new_run) - 1

    # junctions: limit_v2[i] is the junction before piece i; limit_v2[m] after the last
    limit_v2 = np.zeros(m + 1)
    if m > 1:
        xyz_unit = unit[:, :3]
        inner = junction_limits(xyz_unit[:-1], xyz_unit[1:], jd[:-1], jd[1:], accel[:-1], accel[1:],
                                delta_v2[:-1], delta_v2[1:], cruise_v2[:-1], cruise_v2[1:])
        together = ~new_run[1:] & ~extrude_only[1:] & ~extrude_only[:-1]
        limit_v2[1:m] = np.where(together, inner, 0.0)
    v2 = backward_pass(forward_pass(limit_v2, delta_v2), delta_v2) if m else limit_v2
    v0_2, v1_2 = v2[:-1], v2[1:]
    peak2 = np.maximum(np.minimum(cruise_v2, 0.5 * (v0_2 + v1_2 + delta_v2)), np.maximum(v0_2, v1_2))
    v0, vp, v1 = np.sqrt(v0_2), np.sqrt(peak2), np.sqrt(v1_2)
    d_accel = (peak2 - v0_2) / (2.0 * accel)
    d_decel = (peak2 - v1_2) / (2.0 * accel)
    d_cruise = np.maximum(length - d_accel - d_decel, 0.0)
    t_accel = 2.0 * d_accel / (v0 + vp)
    t_decel = 2.0 * d_decel / (v1 + vp)
    t_cruise = d_cruise / vp
    duration = t_accel + t_cruise + t_decel

    # times: runs one after the other, separated by the dwells of the STOPs between them
    cum_dur = np.zeros(m + 1)
    np.cumsum(duration, out=cum_dur[1:])
    cum_dwell = np.zeros(nb + 1)
    np.cumsum(dwell, out=cum_dwell[1:])
    run_start_s = np.zeros(nr)
    run_end_s = np.zeros(nr)
    run_first_sample = np.zeros(nr, dtype=np.int64)
    run_last_sample = np.zeros(nr, dtype=np.int64)
    end_s, last_sample, after_block = 0.0, -1, -1
    for r in range(nr):
        p0, p1 = run_first_piece[r], run_end_piece[r]
        clock = end_s + (cum_dwell[piece_block[p0]] - cum_dwell[after_block + 1])
        first = math.floor(clock * fs)
        if first <= last_sample:  # the rest holds no sample of its own: start on the next one
            first = last_sample + 1
            clock = max(clock, first / fs)
        end_s = clock + (cum_dur[p1] - cum_dur[p0])
        last_sample = math.ceil(end_s * fs)
        after_block = piece_block[p1 - 1]
        run_start_s[r], run_end_s[r] = clock, end_s
        run_first_sample[r], run_last_sample[r] = first, last_sample
    base = cum_dur[run_first_piece][piece_run] if m else np.zeros(0)
    piece_start = run_start_s[piece_run] + (cum_dur[:-1] - base)
    piece_end = run_start_s[piece_run] + (cum_dur[1:] - base)

    # block times: a block without pieces happens when the motion before it ends, after the
    # dwells of the STOP blocks between
    idx = np.arange(nb)
    first_piece = np.clip(np.searchsorted(piece_block, idx, side="left"), 0, max(m - 1, 0))
    last_piece = np.searchsorted(piece_block, idx, side="right") - 1
    has = last_piece >= 0
    has[has] = piece_block[last_piece[has]] == idx[has]
    block_end = np.where(has, piece_end[np.maximum(last_piece, 0)] if m else 0.0, 0.0)
    block_start = np.where(has, piece_start[first_piece] if m else 0.0, 0.0)
    latest = np.maximum.accumulate(np.where(has, idx, -1)) if nb else np.zeros(0, dtype=np.int64)
    clock_at = np.where(latest >= 0, block_end[np.maximum(latest, 0)], 0.0) + (cum_dwell[:-1] - cum_dwell[latest + 1])
    line_time = np.where(has, block_end, clock_at)
    move_start = np.where(has, block_start, clock_at)
    final = latest[-1] if nb else -1
    duration_s = float((block_end[final] if final >= 0 else 0.0) + (cum_dwell[nb] - cum_dwell[final + 1]))

    pieces = Pieces(piece_block, piece_run, start, end, length, extrude_only, accel, max_v, v0, vp, v1,
                    piece_start, duration)

    # samples: every sample lies in one segment of a piecewise-quadratic timeline, A0 + A1 tau +
    # A2 tau^2 with tau = t - reference: the three phases of every piece (the braking phase
    # measured from the piece's end, so pieces end exactly at their end point), the rest at the
    # end of each run until its last sample, and, from the sample after that, the start of the
    # next run (a STOP's jump shows there) or, after the last run, the final position
    n_samples = math.ceil(duration_s * fs) + 1
    unit_pos = delta / length[:, None] if m else np.zeros((0, _NA))  # position per mm of the piece
    half_a = (0.5 * accel)[:, None] * unit_pos
    phase_t0 = np.stack([piece_start, piece_start + t_accel, piece_start + (t_accel + t_cruise)], axis=1)
    # Sums of rounded times can put a phase an ulp after the next piece's start; sorted, it would
    # then take over the next piece. Phases are in time order: make their starts say so.
    phase_t0 = np.maximum.accumulate(phase_t0.ravel()).reshape(phase_t0.shape)
    phase_ref = np.stack([piece_start, piece_start + t_accel, piece_end], axis=1)
    phase_a0 = np.stack([start, start + d_accel[:, None] * unit_pos, end], axis=1)  # (m, 3, 4)
    phase_a1 = np.stack([v0[:, None] * unit_pos, vp[:, None] * unit_pos, v1[:, None] * unit_pos], axis=1)
    phase_a2 = np.stack([half_a, np.zeros_like(half_a), -half_a], axis=1)
    run_end = end[run_end_piece - 1]
    hold_t0 = run_end_s
    next_t0 = np.append(-np.inf, (run_last_sample + 0.5) / fs)
    next_pos = np.concatenate([start[run_first_piece], filled[-1:]])
    seg_t0 = np.concatenate([phase_t0.ravel(), hold_t0, next_t0])
    seg_ref = np.concatenate([phase_ref.ravel(), hold_t0, np.zeros(nr + 1)])
    zeros = np.zeros((nr + 1, _NA))
    seg_a0 = np.concatenate([phase_a0.reshape(-1, _NA), run_end, next_pos])
    seg_a1 = np.concatenate([phase_a1.reshape(-1, _NA), zeros[:nr], zeros])
    seg_a2 = np.concatenate([phase_a2.reshape(-1, _NA), zeros[:nr], zeros])
    order = np.argsort(seg_t0, kind="stable")  # of equal starts, the later (non-empty) one is found
    seg_t0, seg_ref = seg_t0[order], seg_ref[order]
    seg_a0, seg_a1, seg_a2 = seg_a0[order], seg_a1[order], seg_a2[order]
    runs = [(int(a), int(b)) for a, b in zip(run_first_sample, run_last_sample)]
    return Plan(fs, n_samples, line_time, move_start, is_move, is_stop, runs, duration_s,
                _Segments(seg_t0, seg_ref, seg_a0, seg_a1, seg_a2), pieces, notes, warnings)
