"""Motion planner: the motion the machine's own controller makes for a program.

Takes the blocks of a program (``gcode.Block``) and a machine profile; gives the plan the
machine's own controller would execute, sampled on the profile's time grid: the X Y Z E machine
positions at every sample, when each block happens, and the runs of motion between rests.

The controller is Klipper's look-ahead planner (klippy/toolhead.py). With ``firmware="klipper"``
it is Klipper's exactly (``klipper_rules``: minimum_cruise_ratio / accel_to_decel smoothing,
max_velocity, the Z and extruder limits, the extruder's junction limit; equal to klippy's own
code, tests/test_firmware_klipper.py); otherwise, for the other flavors, with the smoothing
switched off and the profile's per-axis limits, as follows:

- Every linear piece of a MOVE block is one move: its distance is the XYZ length, or when XYZ
  moves less than 1e-9 mm (extrude-only) the U V W length, else the A B C length (LinuxCNC's
  rule: its other axes are planned like XYZ and E, followed exactly), else |dE|; its cruise speed
  is the feed, limited by the
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

STOP blocks are rests: the motion decelerates to 0 at them and a G4 waits dwell_s there. So is
a MOVE of one piece that moves no compensated axis (an axis with modes) from a known position: a
retraction, a Z hop, a layer change. It becomes a STOP whose dwell is its own trapezoid from rest
to rest under the limits in force (as the controller plans it: Klipper's rules included), and the
output copies it as it is: one line, the compensated axes exactly still, never a creep of X Y
mixed with a large E change (which Klipper would run at its extrude-only limits). The output
starts and ends its neighbours at rest; where the original's neighbours let such a move keep
some speed (a Z move after a travel), the controller runs the original a few ms faster than
planned here. A STOP
that moved the machine without pieces (G28, a move from an unknown position) takes no time here:
the position jumps to the STOP's position, and the next run starts from there. Every run of
motion starts at rest at one sample and ends at rest at another (its end rounded up), and runs do
not share samples: the rest after a run (its STOPs' dwells) is timed from its last sample, where
the output runs the line at rest, and the next run starts on the first sample at or after the
rest's end, the sample after the last at the earliest (less than 2 sample periods of extra
rest, only at STOPs).

Margins (``RunMargins``): every run of motion is given ``lead_s`` before its first motion and
``settle_s`` after its last, where the original rests and the compensated command may prepare the
start and cancel the ringing after the stop; the lines at rest after a run wait for its settle
margin as for a dwell. ``added_s`` is their total time. With ``travel_share``, once the program has
printed, the travels are planned faster to pay for them (``travel_saved_s``, about).

Axes whose position is unknown (NaN in the blocks) are held at their last known value; before
they are first known, at that first value if they are known within the first PROLOGUE_ROWS
waypoints, else at 0 until they are; axes never known, at 0. ``Plan.notes`` says so.

The plan streams (``PlanStream``): blocks are read a batch at a time, and what they decide is
settled: pieces whose junction speeds no later block can change (the min-plus scans are
monotone: a speed is decided where the backward pass gives the same bits with the motion
assumed to stop after the last piece read as with it assumed to go on), their samples, the
lines they time and the runs. Every sum and scan is carried over batches in the order a single
batch would take it, so the plan is bit for bit the same however the program is cut:
``plan_blocks`` is the stream read to the end and held whole.
Units: mm, s, mm/s, mm/s^2.
"""
from __future__ import annotations

import functools
import itertools
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind, feed_lengths
from . import klipper_rules

EXTRUDE_ONLY_MM = 1e-9  # Klipper: an XYZ length below this makes an extrude-only move
SCAN_CHUNK = 4096  # pieces per chunk of the min-plus scans (bounds the cumulative-sum magnitude), from piece 0 on
BATCH_BLOCKS = 4096  # blocks read per step of the stream
PROLOGUE_ROWS = 1 << 16  # waypoints searched for an unknown axis' first position (held until then)
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
    start_mm: np.ndarray  # (m, len(AXES)) machine positions at the start
    end_mm: np.ndarray  # (m, len(AXES)) at the end
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
    from t0 on (t0 never decreases; of equal starts the later one rules)."""

    t0: np.ndarray  # (s,) s
    ref: np.ndarray  # (s,) s
    a0: np.ndarray  # (s, len(AXES)) mm
    a1: np.ndarray  # (s, len(AXES)) mm/s
    a2: np.ndarray  # (s, len(AXES)) mm/s^2

    def evaluate(self, first: int, stop: int, fs: float) -> np.ndarray:
        """(stop - first, len(AXES)) positions at samples first .. stop - 1 (t = k / fs)."""
        t = np.arange(first, stop) / fs
        if not t.size:
            return np.zeros((0, _NA))
        # the segment of each sample (searchsorted right, minus 1) by merging the sorted sample
        # times with the segment starts in the stretch: cheaper than a search per sample
        lo, hi = np.searchsorted(self.t0, t[[0, -1]], side="right")
        entered = np.searchsorted(t, self.t0[lo:hi], side="left")  # sample where each later segment starts
        index = (lo - 1) + np.cumsum(np.bincount(entered, minlength=t.size))
        tau = (t - np.take(self.ref, index))[:, None]
        out = np.take(self.a2, index, axis=0)
        out *= tau
        out += np.take(self.a1, index, axis=0)
        out *= tau
        out += np.take(self.a0, index, axis=0)
        return out

    def __getitem__(self, rows) -> _Segments:
        return _Segments(self.t0[rows], self.ref[rows], self.a0[rows], self.a1[rows], self.a2[rows])

    @classmethod
    def joined(cls, parts: list[_Segments]) -> _Segments:
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t0", "ref", "a0", "a1", "a2")))


@dataclass
class Plan:
    """What the machine does: samples, block times, runs (see the module docstring). The samples
    are evaluated on demand, a stretch at a time (``samples``): a long program's samples need not
    be held."""

    sample_rate_hz: float
    n_samples: int  # samples at t_k = k / sample_rate_hz, k = 0..n-1
    # (n_blocks,): MOVE: end of its motion; PASS: when the motion reaches it; STOP: at rest at it (before its dwell)
    line_time_s: np.ndarray
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
        """(stop - first, len(AXES)) positions at samples first .. stop - 1 (mm). Each sample depends on its
        time alone, so any cut into stretches gives the same values."""
        return self.segments.evaluate(first, stop, self.sample_rate_hz)

    # The stream's interface (``PlanStream``), for a plan that is whole: everything is known.
    done = True

    @functools.cached_property
    def moves(self) -> deque:
        """(line, start s, end s) of every MOVE block (a block per line)."""
        index = np.flatnonzero(self.is_move)
        return deque(
            zip((index + 1).tolist(), self.move_start_s[index].tolist(), self.line_time_s[index].tolist(), strict=True)
        )

    @property
    def frontier(self) -> int:
        return self.n_samples

    def wait(self, known: Callable[[], bool]) -> None:
        pass

    def release(self, sample: int) -> None:
        pass

    @functools.cached_property
    def positions_mm(self) -> np.ndarray:
        """(n_samples, len(AXES)) every sample at once (for programs that fit in memory)."""
        return np.concatenate([self.samples(k, min(k + SAMPLE_CHUNK, self.n_samples))
                               for k in range(0, self.n_samples, SAMPLE_CHUNK)] or [np.zeros((0, _NA))])


@dataclass(frozen=True)
class RunMargins:
    """Time given to a run of motion before its first motion (lead) and after its last (settle),
    where the compensated command may move and the original rests: the optimal command prepares
    a start (right-half-plane zeros, lightly damped modes) and cancels the ringing after a stop.
    Once a program has printed (after its first run whose pieces extrude), ``printing`` and
    ``travel`` (each (lead s, settle s); None: the same everywhere) at a run's end whose piece
    extrudes and at one whose piece does not. Rounded to whole samples. ``travel_share``: the
    margins are paid for in the travel: a piece that moves a compensated axis and does not extrude
    is planned at up to that share of the axes' hard acceleration limits (never below the
    firmware's): the contour error counts only where the print extrudes, and the compensated
    command may use the hard limits anyway (0: as the firmware plans it)."""

    lead_s: float = 0.0
    settle_s: float = 0.0
    printing: tuple[float, float] | None = None
    travel: tuple[float, float] | None = None
    travel_share: float = 0.0

    def lead_at(self, prints: bool | None, fs: float) -> int:
        """The lead (samples at ``fs``) before a run whose first piece extrudes (``prints``), or
        does not, or (None) up to the program's first run that prints."""
        return round(self._times(prints)[0] * fs)

    def settle_at(self, prints: bool | None, fs: float) -> float:
        """The settle margin (s, whole samples at ``fs``) after a run (``prints`` as ``lead_at``'s)."""
        return round(self._times(prints)[1] * fs) / fs

    def _times(self, prints: bool | None) -> tuple[float, float]:
        by_end = None if prints is None else self.printing if prints else self.travel
        return (self.lead_s, self.settle_s) if by_end is None else by_end

    @classmethod
    def for_profile(cls, profile: MachineProfile, lead_s: float | None = None, settle_s: float | None = None,
                    flavor: str | None = None) -> RunMargins:
        """The given times, at every run; each one not given: what the shortest input shaper (ZV)
        for the profile's lowest mode shifts the motion by, half its damped period (no margin
        without modes). With neither given, for a flavor of ``BY_END_FLAVORS``, once the program
        prints: that times ``BY_END``'s fractions."""
        modes = [m for axis in profile.axes.values() for m in axis.modes]
        half_s = 0.0
        if modes:
            lowest = min(modes, key=lambda m: m.frequency_hz)
            half_s = 0.5 / (lowest.frequency_hz * math.sqrt(1.0 - lowest.damping**2))
        margins = cls(half_s if lead_s is None else lead_s, half_s if settle_s is None else settle_s)
        if lead_s is None and settle_s is None and flavor in BY_END_FLAVORS:
            (lead, settle), (travel_lead, travel_settle) = BY_END
            margins = replace(margins, printing=(half_s * lead, half_s * settle),
                              travel=(half_s * travel_lead, half_s * travel_settle), travel_share=TRAVEL_SHARE)
        return margins


# The margins by what a run's end does, in half damped periods of the lowest mode: (lead before,
# settle after) a run's end that prints, and a travel's. A travel's stop needs little settle
# margin: the rest after it (its unretraction) settles it. Before every run some lead: none before
# a travel leaves a transient that rings on into the print. Through klippy, printer-two-mode (half
# period 14.7 ms), the gear's first 8000 lines: 1 everywhere (the other flavors' default) ran 1.33%
# long at 0.361 um RMS contour error, these 0.47% at 0.362 um; a lead of 1/4 before printing
# 0.83 um, none before a travel 1.83 um; no settle after a travel kept the gear's error but cost
# the pocket (a print checked after) 15% of its gain (docs/compensate.md).
BY_END = ((1 / 2, 1 / 3), (1 / 4, 1 / 5))
BY_END_FLAVORS = ("klipper", "marlin", "reprap")  # (LinuxCNC: every move's contour counts, no travel)
# With BY_END, the share of the hard accelerations the travels are planned at (RunMargins.travel_share):
# in fbspost's plan of the gear's and the tube's first 8000 lines for Klipper 0.4 left them +0.20%
# and +0.35%, 0.5 +0.04% and +0.05% (through klippy alike, at 94% and 95% of the old gain).
TRAVEL_SHARE = 0.5


# ---- limits in force, block by block ---------------------------------------------------------

class _LimitState:
    """The planner settings as the blocks change them; ``row()`` is one row of the state table:
    accel, travel accel (NaN: none), planner max velocity, junction deviation, axis max velocity
    (4), axis max acceleration (4), accel_to_decel (Klipper's smoothing; accel elsewhere).

    Klipper: max_velocity starts at the profile's toolhead max_velocity; accel_to_decel is
    accel * (1 - minimum_cruise_ratio), or, with the profile's max_accel_to_decel (klippy before
    2024), min(that, accel), SET_VELOCITY_LIMIT ACCEL_TO_DECEL changing it (MINIMUM_CRUISE_RATIO
    unknown there); in the newer Klipper, ACCEL_TO_DECEL sets the ratio 1 - min(1, it / accel)."""

    def __init__(self, profile: MachineProfile, klipper: bool = False):
        self.accel = float(profile.planner_acceleration_mm_s2)
        self.travel_accel = math.nan
        self.max_velocity = profile.toolhead_max_velocity_mm_s if klipper else math.inf
        self.klipper = klipper
        self.cruise_ratio = profile.firmware.minimum_cruise_ratio
        self.accel_to_decel = profile.firmware.max_accel_to_decel_mm_s2  # None: the ratio rules
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
        if limits.junction_deviation_mm is not None and not self.klipper:
            self.direct_jd = positive(limits.junction_deviation_mm, "junction deviation", zero_ok=True)
        self._apply_smoothing(limits)
        if self.klipper:  # Klipper knows no M201 / M203 / M205 J
            return
        for name, value in limits.axis_max_velocity_mm_s.items():
            if name in AXES:
                self.axis_v[AXES.index(name)] = positive(value, f"{name} max velocity")
        for name, value in limits.axis_max_acceleration_mm_s2.items():
            if name in AXES:
                self.axis_a[AXES.index(name)] = positive(value, f"{name} max acceleration")

    def _apply_smoothing(self, limits) -> None:
        ratio, to_decel = limits.minimum_cruise_ratio, limits.accel_to_decel_mm_s2
        if self.accel_to_decel is not None:  # klippy before 2024
            self.accel_to_decel = to_decel if to_decel is not None else self.accel_to_decel
        elif ratio is not None:
            self.cruise_ratio = ratio
        elif to_decel is not None:
            self.cruise_ratio = 1.0 - min(1.0, to_decel / self.accel)

    def row(self) -> list[float]:
        jd = self.direct_jd
        if jd is None:  # Klipper's _calc_junction_deviation, with the accel in force
            jd = self.scv**2 * (math.sqrt(2.0) - 1.0) / self.accel
        if not self.klipper:
            to_decel = self.accel
        elif self.accel_to_decel is None:
            to_decel = self.accel * (1.0 - self.cruise_ratio)
        else:
            to_decel = min(self.accel_to_decel, self.accel)
        return [self.accel, self.travel_accel, self.max_velocity, jd, *self.axis_v, *self.axis_a, to_decel]


# ---- the min-plus scans ----------------------------------------------------------------------

def forward_pass(limit_v2: np.ndarray, delta_v2: np.ndarray, chunk: int = SCAN_CHUNK,
                 carry: float = math.inf) -> np.ndarray:
    """F[0] = min(L[0], carry), F[i] = min(L[i], F[i-1] + delta[i-1]): the squared speed reachable
    at every junction accelerating from the earlier ones. ``limit_v2`` has one more entry than
    ``delta_v2`` (2 a d of the piece between junctions i and i+1), or as many (the last piece
    leads to a junction not given).

    Computed as F[i] = min(L[i], C[i] + min_{k<i}(L[k] - C[k])), C the sequential cumulative sum
    of delta from the chunk's start (chunks from entry 0 on); the chunk's first entry carries
    the previous chunk's result. The exclusive minimum keeps a junction's own limit exact; a
    limit inherited from an earlier junction is at least delta[i-1], and its rounding error is a
    few ulps of C. An entry depends only on the entries before it, from its chunk's start."""
    out = np.empty_like(limit_v2)
    n = limit_v2.size
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
    later junction can still be reached decelerating.

    Computed as B[i] = min(L[i], min_{k>i}(L[k] + C[k]) - C[i]), C the sequential cumulative sum
    of delta from the chunk's start (chunks from entry 0 on, as in ``forward_pass``, so that a
    batch of junctions cut anywhere gives the same bits wherever its result is decided); the
    chunk's last candidate is the next chunk's first result. Monotone in every L: a lower or
    higher end gives a lower or higher result, bits included."""
    out = np.empty_like(limit_v2)
    n = limit_v2.size
    later = math.inf  # the next chunk's first result
    for s in range(((n - 1) // chunk) * chunk, -1, -chunk):
        e = min(s + chunk, n)
        c = np.zeros(e - s + 1)
        np.cumsum(delta_v2[s:e], out=c[1:1 + min(e, n - 1) - s])  # c[e - s]: the next chunk's first junction
        candidate = np.empty(e - s + 1)
        candidate[:-1] = limit_v2[s:e] + c[:-1]
        candidate[-1] = later + c[-1] if e < n else math.inf
        suffix = np.minimum.accumulate(candidate[::-1])[::-1]
        out[s:e] = np.minimum(limit_v2[s:e], suffix[1:] - c[:-1])
        later = out[s]
    return out


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

def axis_piece_limits(delta, length, extrude_only, feed, planner_v, accel_print, accel_travel, axis_v, axis_a):
    """(unit, cruise limit, accel, feed clamped) of pieces by the per-axis rules (not Klipper's)."""
    unit = delta / length[:, None]
    unit[extrude_only, :3] = 0.0  # along E (or LinuxCNC's other axes) alone
    abs_unit = np.abs(unit)
    with np.errstate(divide="ignore"):
        axis_v_limit = np.where(abs_unit > 0, axis_v / abs_unit, np.inf).min(axis=1, initial=np.inf)
        axis_a_limit = np.where(abs_unit > 0, axis_a / abs_unit, np.inf).min(axis=1, initial=np.inf)
    max_v = np.minimum(np.minimum(feed, planner_v), axis_v_limit)
    clamped = np.isfinite(feed) & (axis_v_limit < feed)  # as the controller does (a G0 means it)
    extrudes = delta[:, _E] > 0
    accel = np.where(extrudes | np.isnan(accel_travel), accel_print, accel_travel)
    return unit, max_v, np.minimum(accel, axis_a_limit), clamped


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


def plan_blocks(blocks: Iterable[Block], profile: MachineProfile, batch_blocks: int | None = None,
                margins: RunMargins | None = None, firmware: str | None = None, every_axis: bool = False) -> Plan:
    """The whole plan of ``blocks`` on ``profile`` (see the module docstring), held in memory;
    ``every_axis``: every axis counts as compensated (no move of an axis without modes becomes a
    rest: the firmware's own motion of them, as ``firmware.replan`` of an excite sweep needs)."""
    stream = PlanStream(blocks, profile, batch_blocks, keep=True, margins=margins, firmware=firmware,
                        every_axis=every_axis)
    while stream.advance():
        pass
    return stream.whole()


_PIECE_FIELDS = ("block", "run", "start", "end", "length", "extrude_only", "accel", "max_v", "delta_v2", "limit_v2",
                 "smooth_delta_v2", "firmware_accel")


def _trapezoids(length, accel, v0_2, peak2, v1_2) -> tuple:
    """Pieces of ``length`` and ``accel`` from squared speed v0_2 through peak2 to v1_2:
    ((v0, peak, v1), accelerating distance, accelerating and cruising times, duration)."""
    v0, vp, v1 = np.sqrt(v0_2), np.sqrt(peak2), np.sqrt(v1_2)
    d_accel = (peak2 - v0_2) / (2.0 * accel)
    d_decel = (peak2 - v1_2) / (2.0 * accel)
    d_cruise = np.maximum(length - d_accel - d_decel, 0.0)
    t_accel = 2.0 * d_accel / (v0 + vp)
    t_decel = 2.0 * d_decel / (v1 + vp)
    t_cruise = d_cruise / vp
    return (v0, vp, v1), d_accel, t_accel, t_cruise, t_accel + t_cruise + t_decel


def _travel_saved_s(taken: dict, speeds: tuple, duration: np.ndarray) -> float:
    """What the travels planned faster (``RunMargins.travel_share``) among the pieces ``taken``
    save: each at the firmware's acceleration between the same squared speeds, its peak Klipper's
    smoothed one (exact from rest to rest on the other firmwares)."""
    fast = np.flatnonzero(taken["accel"] != taken["firmware_accel"])
    if not fast.size:
        return 0.0
    v0_2, _, v1_2 = (v[fast] for v in speeds)
    length, accel, max_v = taken["length"][fast], taken["firmware_accel"][fast], taken["max_v"][fast]
    smooth_v2 = taken["smooth_delta_v2"][fast] * (accel / taken["accel"][fast])
    peak2 = np.maximum(np.minimum(max_v * max_v, 0.5 * (v0_2 + v1_2 + smooth_v2)), np.maximum(v0_2, v1_2))
    return float((_trapezoids(length, accel, v0_2, peak2, v1_2)[-1] - duration[fast]).sum())


class _PieceMaker:
    """Waypoints to pieces. Takes the rows of waypoints read (per block: its index, line, whether
    it is motion, feed, row of the limits table, points) and gives the new pieces' columns
    (``_PIECE_FIELDS``) with the junction limit before each; fills the positions not known (the
    notes say where) and counts the feeds clamped by the machine's limits."""

    def __init__(self, profile: MachineProfile, klipper: bool, notes: list[str], travel_share: float = 0.0):
        self._klipper = klipper
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
        the program's first run that prints, as far as known (``_BlockReader``)."""
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
        inner = self._junction_limits(unit, max_v, corner_a, length, 2.0 * corner_a * length, table[:, 3])
        self._count_clamped(clamped, feed, max_v, piece_block, piece_line)

        # junction limits: limit_v2[i] is the junction before piece i (the first after the last
        # piece made before: _prev), 0 between runs and at extrude-only pieces
        prev = self._prev or (np.ones(1, bool), np.full(1, -1))
        eo, key = (np.concatenate([p, q]) for p, q in zip(prev, (extrude_only, run_key), strict=True))
        together = (key[1:] == key[:-1]) & ~eo[1:] & ~eo[:-1]
        limit_v2 = np.where(together, inner, 0.0)
        self._prev = (extrude_only[-1:], run_key[-1:])
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
        """Per piece, from its row of the limits table (``_LimitState.row``): its direction per mm,
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
                                                                 accel_print, accel_travel, axis_v, axis_a)
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

    def _junction_limits(self, unit, max_v, accel, length, delta_v2, jd) -> np.ndarray:
        """The junction limit before each piece (with the last piece made before): Klipper's rules,
        or the junction-deviation model of ``junction_limits``."""
        cruise_v2 = max_v * max_v
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


class _LookAhead:
    """The look-ahead's min-plus scans over the pieces not yet settled (see the module docstring).

    Takes each new piece's junction limit and 2 a d, and Klipper's smoothed 2 a d (``extend``);
    gives how many of the pending pieces no later piece can change, with their squared speeds
    (``decided``). The scans start at a chunk boundary with the forward pass carried into it, so
    their bits are those of one scan from piece 0."""

    def __init__(self, klipper: bool):
        self._klipper = klipper
        self._s0 = 0  # the scans' first junction (a chunk start) ...
        self._limit, self._delta = np.zeros(0), np.zeros(0)  # ... its limits and deltas on
        self._carry = math.inf  # the forward pass arriving at _s0
        self._smooth = np.zeros(0)  # Klipper: the smoothed pass' deltas from _s0 on ...
        self._smooth_carry = math.inf  # ... and its forward pass arriving at _s0
        self._peak_carry = 0.0  # Klipper: the cruise a decelerating run carries past the last settled piece
        self._reach = self._reach_smooth = None  # the last decision's forward passes

    def extend(self, pieces: dict) -> None:
        self._limit = np.concatenate([self._limit, pieces["limit_v2"]])
        self._delta = np.concatenate([self._delta, pieces["delta_v2"]])
        self._smooth = np.concatenate([self._smooth, pieces["smooth_delta_v2"]])

    def decided(self, pending: dict, p0: int, ends_at_rest: bool) -> tuple:
        """(n, v2, speeds): the first n of the ``pending`` pieces (piece p0 on) are decided, with
        their squared junction speeds v2 (n + 1), or Klipper's (start, cruise, end) squared speeds."""
        s0 = self._s0
        limit = np.append(self._limit, 0.0 if ends_at_rest else math.inf)
        reach = self._reach = forward_pass(limit, self._delta, SCAN_CHUNK, self._carry)
        v2 = backward_pass(reach, self._delta, SCAN_CHUNK)
        if self._klipper:
            n, speeds, self._reach_smooth = self._klipper_speeds(pending, p0, reach, v2, ends_at_rest)
            if n:
                self._peak_carry = float(speeds[4][n - 1])
            return n, None, [x[:n] for x in speeds[:3]]
        n = len(pending["block"])
        if not ends_at_rest:  # settle the pieces whose both junctions are decided
            reach[-1] = 0.0
            differ = np.flatnonzero(backward_pass(reach, self._delta, SCAN_CHUNK)[p0 - s0:] != v2[p0 - s0:])
            n = max(int(differ[0]) - 1, 0) if differ.size else n
        return n, v2[p0 - s0:p0 - s0 + n + 1], None

    def restart(self, p0: int) -> None:
        """The pieces before ``p0`` are settled: the scans restart at the chunk of piece p0."""
        s0, s1 = self._s0, (p0 // SCAN_CHUNK) * SCAN_CHUNK
        if s1 > s0:
            self._carry = self._reach[s1 - 1 - s0] + self._delta[s1 - 1 - s0]
            self._limit, self._delta = self._limit[s1 - s0:], self._delta[s1 - s0:]
            if self._klipper:
                self._smooth_carry = self._reach_smooth[s1 - 1 - s0] + self._smooth[s1 - 1 - s0]
            self._smooth = self._smooth[s1 - s0:]
            self._s0 = s1

    def _klipper_speeds(self, pending: dict, p0: int, reach: np.ndarray, v2: np.ndarray, ends_at_rest: bool) -> tuple:
        """Klipper's smoothed look-ahead over the pending pieces (``klipper_rules.cruise_speeds``):
        how many are settled and their speeds. ``reach`` and ``v2`` are the forward and backward
        passes from the scans' start; a piece is settled when its speeds are the same however
        the program goes on: the junction speeds it and the next piece depend on are decided
        (as in ``decided``, for both passes) and so is the piece that sets its peak."""
        s0, smooth = self._s0, self._smooth
        reach_smooth = forward_pass(reach, smooth, SCAN_CHUNK, self._smooth_carry)
        smoothed = backward_pass(reach_smooth, smooth, SCAN_CHUNK)
        speeds = klipper_rules.cruise_speeds(v2[p0 - s0:], smoothed[p0 - s0:], pending["delta_v2"],
                                             pending["smooth_delta_v2"], pending["max_v"] ** 2, self._peak_carry)
        n = len(pending["block"])
        if not ends_at_rest:
            low, low_smooth = reach.copy(), reach_smooth.copy()
            low[-1] = low_smooth[-1] = 0.0
            differ = np.flatnonzero((backward_pass(low, self._delta, SCAN_CHUNK)[p0 - s0:] != v2[p0 - s0:])
                                    | (backward_pass(low_smooth, smooth, SCAN_CHUNK)[p0 - s0:] != smoothed[p0 - s0:]))
            decided = speeds[3][:max(int(differ[0]) - 2, 0)] if differ.size else speeds[3]
            n = int(np.flatnonzero(decided)[-1]) + 1 if decided.any() else 0
        return n, speeds, reach_smooth


class _Timeline:
    """The plan's samples. Takes the segments of the settled motion (``add``: pieces' phases,
    rests, each with an order key) and gives the samples below the frontier (``samples``), dropping
    what is ``release``d; with ``keep``, holds every segment for the whole plan (``kept``)."""

    def __init__(self, fs: float, keep: bool):
        self._fs, self._keep = fs, keep
        self._segments = _Segments(np.zeros(0), np.zeros(0), np.zeros((0, _NA)), np.zeros((0, _NA)), np.zeros((0, _NA)))
        self._t0_max = -math.inf
        self.kept: list[_Segments] = []

    def samples(self, first: int, stop: int) -> np.ndarray:
        return self._segments.evaluate(first, stop, self._fs)

    def release(self, sample: int) -> None:
        drop = int(np.searchsorted(self._segments.t0, sample / self._fs, side="right")) - 1
        if drop > len(self._segments.t0) // 2:  # copy seldom
            self._segments = self._segments[drop:]

    def add(self, parts: list) -> None:
        """The segments ``parts`` ((order keys, _Segments) each), in the order of their keys."""
        keys = np.concatenate([np.ravel(k) for k, _ in parts])
        seg = _Segments.joined([s for _, s in parts])[np.argsort(keys, kind="stable")]
        # Sums of rounded times can put a phase an ulp after the next one's start: they are in
        # time order, make their starts say so (of equal starts, the later rules)
        seg.t0 = np.maximum.accumulate(np.concatenate([[self._t0_max], seg.t0]))[1:]
        self._t0_max = seg.t0[-1]
        if self._keep:
            self.kept.append(seg)
        else:
            self._segments = _Segments.joined([self._segments, seg])

    @staticmethod
    def held(key: int, t0: float, ref: float, position: np.ndarray) -> tuple:
        """A rest at ``position`` from ``t0`` on, with its order key."""
        t = np.array([t0])
        return np.array([key]), _Segments(t, np.array([ref]), position[None], np.zeros((1, _NA)), np.zeros((1, _NA)))

    @staticmethod
    def phases(first_piece: int, piece_start, piece_end, t_accel, t_cruise, start, end, d_accel, length, accel,
               speeds) -> tuple:
        """The three phases of every piece (the braking phase measured from the piece's end, so
        pieces end exactly at their end point), with their order keys."""
        v0, vp, v1 = speeds
        unit_pos = (end - start) / length[:, None]  # position per mm of the piece
        half_a = (0.5 * accel)[:, None] * unit_pos
        n = len(piece_start)
        return (8 * (first_piece + np.arange(n))[:, None] + np.arange(3), _Segments(
            np.stack([piece_start, piece_start + t_accel, piece_start + (t_accel + t_cruise)], axis=1).ravel(),
            np.stack([piece_start, piece_start + t_accel, piece_end], axis=1).ravel(),
            np.stack([start, start + d_accel[:, None] * unit_pos, end], axis=1).reshape(-1, _NA),
            np.stack([v0[:, None] * unit_pos, vp[:, None] * unit_pos, v1[:, None] * unit_pos], axis=1).reshape(-1, _NA),
            np.stack([half_a, np.zeros_like(half_a), -half_a], axis=1).reshape(-1, _NA)))


class _BlockReader:
    """The program's blocks, read a batch at a time (``read``). Gives, per block with waypoints,
    a row in ``rows`` (its index, line, whether it is motion, feed, row of the limits table,
    points), and per block (block, is MOVE, is STOP, the dwells before it) in ``pending`` until
    it is timed. A MOVE that moves no compensated axis is read as a STOP (``_uncompensated_s``)."""

    def __init__(self, blocks: Iterable[Block], profile: MachineProfile, klipper: bool, batch: int,
                 settle_s: Callable[[bool], float], piece_limits: Callable, every_axis: bool = False):
        self._blocks_in = iter(blocks)
        self._batch = batch
        self._settle_s = settle_s
        self.settles: dict[int, float] = {}  # by run key (the STOPs before it): its settle margin, until settled
        self._stops = 0  # STOP blocks read
        self._prints = False  # the last MOVE read ends extruding
        self.printing_from = math.inf  # the key of the first run that prints
        self._piece_limits = piece_limits
        # the axes a compensated command moves: a move of the others alone is a rest of these
        self._compensated = [c for c, name in enumerate(AXES)
                             if every_axis or name in profile.axes and profile.axes[name].modes]
        self._limits = _LimitState(profile, klipper)
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
        """How long a MOVE that moves no compensated axis (a retraction, a Z hop, a layer change)
        takes, from rest to rest as the controller plans it (None: it moves a compensated axis,
        or an axis it moves is not known before or after). Such a move is a rest of the
        compensated axes: copied as it is, like a dwell of that length, so that the compensated
        motion never mixes a creep of X Y with it, and the controller runs it as written."""
        if len(points) != 1:
            return None
        # (nearly every move moves a compensated axis: told on floats, a few times faster than on arrays)
        point, read = points[0].tolist(), self._read_mm.tolist()
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


class _BlockClock:
    """The blocks' times. Takes the blocks read (``_BlockReader.pending``) and, as their pieces are
    settled, the pieces' blocks and times (``settle``); gives each block timed with its line time
    and whether it is a STOP (``lines``) and the MOVE blocks' (line, start s, end s) (``moves``),
    or with ``keep`` the columns of the whole plan (``kept``). A block without pieces happens when
    the motion before it ends, after the dwells between."""

    def __init__(self, pending: deque, keep: bool):
        self._pending, self._keep = pending, keep
        self.first = 0  # the first block not yet timed
        self.latest_end, self.latest_dwell = 0.0, 0.0  # the last block with pieces: its end, dwells to it
        self.lines: deque = deque()  # (block, line time s, is_stop) settled and not yet taken
        self.moves: deque = deque()  # (line, start s, end s) of the MOVE blocks settled and not yet taken
        self.kept: list[tuple] = []

    def dwell_before(self, block: int) -> float:
        """The dwells of the blocks before ``block`` (a block not yet timed)."""
        return self._pending[block - self.first][3]

    def settle(self, stop: int, pieces: tuple) -> None:
        """Time the blocks before ``stop`` (the first with waypoints or pieces not settled), with
        the pieces settled since the last call: (block, start s, end s) each, and the (block,
        start s) of the block whose pieces the last call left going on."""
        block, piece_start, piece_end, trail = pieces
        count = stop - self.first
        if count <= 0:
            return
        taken = [self._pending.popleft() for _ in range(count)]
        idx = np.arange(self.first, stop)
        self.first = stop
        dwell_before = np.array([t[3] for t in taken])
        is_move = np.array([t[1] for t in taken], dtype=bool)
        is_stop = np.array([t[2] for t in taken], dtype=bool)
        last_piece = np.searchsorted(block, idx, side="right") - 1
        has = last_piece >= 0
        has[has] = block[last_piece[has]] == idx[has]
        if block.size:
            first_piece = np.minimum(np.searchsorted(block, idx, side="left"), block.size - 1)
            block_end = np.where(has, piece_end[np.maximum(last_piece, 0)], 0.0)
            block_start = np.where(has, np.where(idx == trail[0], trail[1], piece_start[first_piece]), 0.0)
        else:
            block_end = block_start = np.zeros(count)
        latest = np.maximum.accumulate(np.where(has, np.arange(count), -1))
        end_at = np.where(latest >= 0, block_end[np.maximum(latest, 0)], self.latest_end)
        # (a MOVE has no dwell)
        dwell_at = np.where(latest >= 0, dwell_before[np.maximum(latest, 0)], self.latest_dwell)
        clock_at = end_at + (dwell_before - dwell_at)
        line_time = np.where(has, block_end, clock_at)
        move_start = np.where(has, block_start, clock_at)
        if latest[-1] >= 0:
            self.latest_end, self.latest_dwell = float(end_at[-1]), float(dwell_at[-1])
        if self._keep:
            self.kept.append((line_time, move_start, is_move, is_stop))
        else:
            self.lines.extend(zip((t[0] for t in taken), line_time.tolist(), is_stop.tolist(), strict=True))
            moves = np.flatnonzero(is_move)
            self.moves.extend(zip((taken[i][0].line_no for i in moves), move_start[moves].tolist(),
                                  line_time[moves].tolist(), strict=True))


class PlanStream:
    """The plan of a program as its blocks are read (see the module docstring).

    Consumers ask for more with ``advance`` (or ``wait``) and find, settled so far: ``runs``
    ([first, last] sample indices, last None while the run goes on), the samples below
    ``frontier`` (``samples``; ``release`` drops what is behind), the blocks with their times
    (``blocks``), and at the end (``done``) ``n_samples``, ``duration_s``, ``notes`` and
    ``warnings``. ``keep`` holds everything for ``whole`` (``plan_blocks``, as is ``every_axis``).
    ``firmware`` "klipper" plans with Klipper's rules (``klipper_rules``), anything else as above.

    The stream reads blocks (``_BlockReader``), makes their pieces (``_PieceMaker``), decides
    their speeds (``_LookAhead``) and settles them here: the pieces' times, the runs and the
    blocks' times, whose motion goes to the samples (``_Timeline``)."""

    def __init__(self, blocks: Iterable[Block], profile: MachineProfile, batch_blocks: int | None = None,
                 keep: bool = False, margins: RunMargins | None = None, firmware: str | None = None,
                 every_axis: bool = False):
        self.sample_rate_hz = self._fs = float(profile.sample_rate_hz)
        self.margins = margins = margins or RunMargins()
        self.added_s = self.travel_saved_s = 0.0  # as settled: the margins' time; what faster travels save
        self._keep = keep
        klipper = firmware == "klipper"
        # settled, for the consumers
        self.runs: list[list] = []
        self.frontier = 0  # samples below it are settled
        self.settled_s = 0.0  # the motion is settled up to this time (the end of the last piece settled)
        self.done, self.n_blocks = False, 0
        self.n_samples: int | None = None
        self.duration_s: float | None = None
        self.notes: list[str] = []
        self.warnings: list[str] = []
        self.time_s = 0.0  # spent in advance(), reading included
        self._pieces = _PieceMaker(profile, klipper, self.notes, margins.travel_share)
        self._reader = _BlockReader(blocks, profile, klipper, batch_blocks or BATCH_BLOCKS,
                                    functools.partial(margins.settle_at, fs=self._fs), self._pieces.piece_limits,
                                    every_axis)
        self._scans = _LookAhead(klipper)
        self._timeline = _Timeline(self._fs, keep)
        self._clock = _BlockClock(self._reader.pending, keep)
        self.lines, self.moves = self._clock.lines, self._clock.moves  # (see _BlockClock)
        # made, not yet settled
        self._pending = {name: None for name in _PIECE_FIELDS}  # pieces from _p0 on
        self._m = self._p0 = 0  # pieces made; settled
        # carried over settled pieces and blocks
        self._cum_dur = 0.0
        self._open, self._run_key = False, -1  # the last run goes on; the STOPs before the last settled piece
        self._run_clock = self._run_base = 0.0
        self._last_sample, self._dwell_after_run = -1, 0.0
        self._last_end = np.zeros(_NA)  # where the last settled piece ends
        self._last_dwell_after = 0.0  # dwells up to the block of the last settled piece
        self._last_piece = -1
        self._trail = (-1, 0.0)  # (block, start s) of the block whose pieces are being settled
        self._kept_pieces: list[tuple] = []
        self._settled_pieces = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), self._trail)

    # ---- for the consumers ----

    def advance(self) -> bool:
        """Read the next batch of blocks and settle what it decides; False once done."""
        if self.done:
            return False
        clock = time.perf_counter()
        reader = self._reader
        reader.read()
        self.n_blocks = reader.n_blocks
        if reader.rows and (self._pieces.last_row is not None or reader.prologue_over()):
            rows, reader.rows = reader.rows, []
            self._add_pieces(self._pieces.make(rows, self._reader.printing_from))
        self._settle()
        if reader.eof and not reader.rows and self._m == self._p0:
            self._finish()
        self.time_s += time.perf_counter() - clock
        return True

    def wait(self, known: Callable[[], bool]) -> None:
        """Advance until ``known()`` or the end."""
        while not known() and self.advance():
            pass

    def samples(self, first: int, stop: int) -> np.ndarray:
        """(stop - first, 4) settled samples first .. stop - 1 (``wait`` for the frontier first)."""
        assert stop <= self.frontier, "samples asked for before they are settled"
        return self._timeline.samples(first, stop)

    def release(self, sample: int) -> None:
        """Samples before ``sample`` will not be asked for again."""
        self._timeline.release(sample)

    def blocks(self) -> Iterator[tuple[Block, float, bool]]:
        """The program's blocks in order, each with its line time (s: see ``Plan.line_time_s``)
        and whether it is a STOP, as they are settled."""
        while True:
            if self.lines:
                yield self.lines.popleft()
            elif not self.advance():
                return

    def whole(self) -> Plan:
        """The plan held (``keep``), once done."""
        kept_blocks, kept_pieces = self._clock.kept, self._kept_pieces
        blocks = [np.concatenate(column) for column in zip(*kept_blocks, strict=True)] \
            or [np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)]
        pieces = Pieces(*(np.concatenate(column) for column in zip(*kept_pieces, strict=True))) if kept_pieces else \
            Pieces(*([np.zeros(0, dtype=np.int64)] * 2 + [np.zeros((0, _NA))] * 2 + [np.zeros(0)] * 9))
        return Plan(self._fs, self.n_samples, *blocks, [tuple(r) for r in self.runs], self.duration_s,
                    _Segments.joined(self._timeline.kept), pieces, self.notes, self.warnings)

    # ---- settling ----

    def _add_pieces(self, new: dict | None) -> None:
        if new is None:
            return
        for name, value in new.items():
            held = self._pending[name]
            self._pending[name] = value if held is None else np.concatenate([held, value])
        self._scans.extend(new)
        self._m += len(new["block"])

    def _settle(self) -> None:
        reader, stops = self._reader, self._pieces.stops
        if self._m > self._p0:
            pending = self._pending
            ends_at_rest = reader.eof or stops > pending["run"][-1] or pending["extrude_only"][-1]
            n, v2, speeds = self._scans.decided(pending, self._p0, ends_at_rest)
            if n:
                self._settle_pieces(n, v2, speeds)
                self._scans.restart(self._p0)
        over = stops > self._run_key or reader.eof and not reader.rows
        if self._open and over and (self._m == self._p0 or self._pending["run"][0] != self._run_key):
            self._close_run()  # (its last piece settled, the next run's first not yet)
        self._settle_blocks()
        if self.runs and self.runs[-1][1] is None:
            self.frontier = max(self.runs[-1][0] + 1, math.floor(self.settled_s * self._fs) - 1)
        elif self.runs:
            self.frontier = self.runs[-1][1] + 1

    def _settle_pieces(self, n: int, v2: np.ndarray | None = None, speeds: list | None = None) -> None:
        """Settle the next ``n`` pieces, their squared junction speeds ``v2`` (n + 1) given, or
        their (start, cruise, end) squared speeds ``speeds`` (Klipper's)."""
        taken = {name: value[:n] for name, value in self._pending.items()}
        self._pending = {name: value[n:] for name, value in self._pending.items()}
        p0 = self._p0
        self._p0 += n
        block, key, start, end, length = taken["block"], taken["run"], taken["start"], taken["end"], taken["length"]
        accel, max_v = taken["accel"], taken["max_v"]
        if speeds is None:
            v0_2, v1_2 = v2[:-1], v2[1:]
            peak2 = np.maximum(np.minimum(max_v * max_v, 0.5 * (v0_2 + v1_2 + taken["delta_v2"])),
                               np.maximum(v0_2, v1_2))
            speeds = (v0_2, peak2, v1_2)
        (v0, vp, v1), d_accel, t_accel, t_cruise, duration = _trapezoids(length, accel, *speeds)
        self.travel_saved_s += _travel_saved_s(taken, speeds, duration)
        cum = np.cumsum(np.concatenate([[self._cum_dur], duration]))  # (the running sum's bits)

        # runs: pieces between the same two STOP blocks, one after the other, separated by the
        # dwells of the STOPs between them
        segments = []  # (order key, _Segments)
        clock, base, run = np.empty(n), np.empty(n), np.empty(n, dtype=np.int64)
        i = 0
        while i < n:
            if key[i] != self._run_key:
                if i:
                    self._settled_to(p0 + i - 1, cum[i], end[i - 1], block[i - 1])
                if self._open:
                    self._close_run(segments)
                self._lead = self.margins.lead_at(self._reader.end_prints(key[i], end[i, _E] > start[i, _E]), self._fs)
                self._open_run(p0 + i, int(key[i]), block[i], start[i], cum[i], segments)
            j = i + int(np.searchsorted(key[i:], key[i], side="right"))  # (keys never decrease)
            clock[i:j], base[i:j], run[i:j] = self._run_clock, self._run_base, len(self.runs) - 1
            i = j
        piece_start = clock + (cum[:-1] - base)
        piece_end = clock + (cum[1:] - base)
        self._settled_to(p0 + n - 1, cum[-1], end[-1], block[-1])
        self.settled_s = piece_end[-1]
        self._settled_pieces = (block, piece_start, piece_end, self._trail)
        last_block_first = int(np.searchsorted(block, block[-1], side="left"))
        if last_block_first or self._trail[0] != block[-1]:  # its pieces may go on in the next batch
            self._trail = (int(block[-1]), float(piece_start[last_block_first]))
        if self._keep:
            self._kept_pieces.append((block, run, start, end, length, taken["extrude_only"], accel, max_v,
                                      v0, vp, v1, piece_start, duration))

        # every sample lies in one segment of a piecewise-quadratic timeline: the three phases of
        # every piece, the rest at the end of each run until its last sample, and, from the
        # sample after that, the start of the next run (a STOP's jump shows there) or, after the
        # last run, the final position
        segments.append(_Timeline.phases(p0, piece_start, piece_end, t_accel, t_cruise, start, end, d_accel, length,
                                         accel, (v0, vp, v1)))
        self._timeline.add(segments)

    def _settled_to(self, piece: int, cum: float, end: np.ndarray, block: int) -> None:
        """The last piece settled (a run closing ends there)."""
        self._last_piece, self._cum_dur, self._last_end = piece, cum, end
        self._last_dwell_after = self._clock.dwell_before(block)  # (a MOVE block has no dwell)

    def _settle_blocks(self) -> None:
        if self._m > self._p0:
            stop = int(self._pending["block"][0])
        else:
            stop = self._reader.rows[0][0] if self._reader.rows else self._reader.n_blocks
        pieces = self._settled_pieces
        self._settled_pieces = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), self._trail)
        self._clock.settle(stop, pieces)

    def _finish(self) -> None:
        if self._open:
            self._close_run()
        segments = []
        self._next_segment(np.zeros(_NA) if self._pieces.last_row is None else self._pieces.last_row, 0, segments)
        self._timeline.add(segments)
        clock = self._clock
        self.duration_s = float(clock.latest_end + (self._reader.cum_dwell - clock.latest_dwell))
        self.n_samples = math.ceil(self.duration_s * self._fs) + 1
        self._pieces.finish(self.warnings)
        self.frontier = self.n_samples
        self.done = True

    def _open_run(self, piece: int, key: int, block: int, start: np.ndarray, cum: float, segments: list) -> None:
        fs = self._fs
        # The rest is timed from the run before's last sample (where the output's line at rest
        # runs) and the run starts on the first sample after it: a whole sample later at least
        # (runs do not share samples; the output's first block takes that up: writer).
        rest_from_s = self._last_sample / fs if self.runs else 0.0
        clock = rest_from_s + (self._clock.dwell_before(block) - self._dwell_after_run)
        first = max(math.ceil(clock * fs - 1e-6), self._last_sample + 1)  # (an ulp over is not a sample later)
        clock = (first + self._lead) / fs  # the lead margin: the run starts before its motion
        self._next_segment(start, 8 * piece - 2, segments)
        self.runs.append([first, None])
        self._open, self._run_key = True, key
        self._run_clock, self._run_base = clock, cum

    def _close_run(self, segments: list | None = None) -> None:
        own = segments is None
        segments = [] if own else segments
        end_s = self._run_clock + (self._cum_dur - self._run_base)
        # the settle margin, as the lines at rest after the run are timed (the same sum: the same bits)
        dwell_after = self._last_dwell_after + self._reader.settles.pop(self._run_key)  # (the STOP's running sum)
        last = math.ceil((end_s + (dwell_after - self._last_dwell_after)) * self._fs)
        self.added_s += (self._lead + last - math.ceil(end_s * self._fs)) / self._fs
        self.runs[-1][1] = last
        self._last_sample, self._dwell_after_run = last, dwell_after
        self._open = False
        segments.append(_Timeline.held(8 * self._last_piece + 3, end_s, end_s, self._last_end))
        if own:
            self._timeline.add(segments)

    def _next_segment(self, position: np.ndarray, key: int, segments: list) -> None:
        """The position from the sample after the last run's end (before the first run: always)."""
        t0 = (self._last_sample + 0.5) / self._fs if self.runs else -np.inf
        segments.append(_Timeline.held(key, t0, 0.0, position))
