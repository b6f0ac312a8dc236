"""Motion planner: the motion the machine's own controller makes for a program.

Takes the blocks of a program (``blocks.Block``) and a machine profile; gives the plan the
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
  extruder junction limit (instantaneous_corner_velocity) is not modelled. For RepRapFirmware
  (``firmware="reprap"``) RRF's own rule instead (``limits.jerk_junction_limits``: every drive's
  M566 over the change of its speed per unit of path speed, E included, X and Y at the square
  corner velocity; jerk policy 0: printing moves, travels and extrude-only moves do not meld),
  and M204 only for pieces that move X or Y (a retraction takes M201 E alone), as RRF runs them.
- Look-ahead is complete (Klipper's lazy flush gives the same result): the forward and backward
  passes over squared junction speeds are vectorized min-plus scans; each piece is then a
  trapezoid peaking at min(cruise^2, (v0^2 + v1^2 + 2 a d) / 2).

STOP blocks are rests: the motion decelerates to 0 at them and a G4 waits dwell_s there. So is a
MOVE of one piece that moves no compensated axis (an axis with modes) from a known position: a
retraction, a Z hop, a layer change. It becomes a STOP whose dwell is its own trapezoid from rest
to rest under the limits in force (as the controller plans it: Klipper's rules included), and the
output copies it as it is: one line, the compensated axes exactly still, never a creep of X Y mixed
with a large E change (which Klipper would run at its extrude-only limits). For the flavors of
``RESTS_WITHIN_RUNS`` (LinuxCNC) it is a piece of its run instead, from rest to rest, the
compensated axes' lead and settling overlapping it (``PieceMaker``'s ``rests_apart``); there a move
of A B C U V W, alone or with X Y Z, stays a STOP copied as written (LinuxCNC blends no segment
that moves them). The output starts and ends its neighbours at rest; where the original's
neighbours let such a move keep some speed (a Z move after a travel), the controller runs the
original a few ms faster than planned here. A STOP that moved the machine without pieces (G28, a
move from an unknown position) takes no time here: the position jumps to the STOP's position, and
the next run starts from there. Every run of motion starts at rest at one sample and ends at rest
at another (its end rounded up), and runs do not share samples: the rest after a run (its STOPs'
dwells) is timed from its last sample, where the output runs the line at rest, and the next run
starts on the first sample at or after the rest's end, the sample after the last at the earliest
(less than 2 sample periods of extra rest, only at STOPs).

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
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from ..profile import MachineProfile
from ..read.blocks import AXES, EXTRA_AXES, Block
from .clock import BlockClock
from .lookahead import LookAhead
from .margins import RunMargins
from .pieces import PIECE_FIELDS, BlockReader, PieceMaker
from .timeline import Segments, Timeline

# Flavors whose moves of axes without modes alone (LinuxCNC's Z plunges and retractions) are pieces
# of the run they are in, the compensated axes at rest on either side: the command's lead and
# settling overlap them instead of margins added to the time (not STOPs: see the module docstring).
# On the model of LinuxCNC's planner, the first 12 s of craftsmancnc.ngc (1 ms; 12 runs): +5.40% ->
# +1.7% of the original's time at the same RMS contour error (docs/linuxcnc.md).
RESTS_WITHIN_RUNS = ("linuxcnc",)
BATCH_BLOCKS = 4096  # blocks read per step of the stream
SAMPLE_CHUNK = 1 << 14  # samples evaluated at once (keeps the temporaries in cache)

_NA = len(AXES)
_E = AXES.index("E")


def _compensated_columns(profile: MachineProfile, firmware: str | None,
                         every_axis: bool) -> tuple[list[int], tuple[int, ...]]:
    """The axes (columns of AXES) a compensated command moves: a move of the others alone is a rest
    of these, copied as written; and those whose move is copied whatever else it moves. Those with
    modes; with ``every_axis`` all. For ``RESTS_WITHIN_RUNS`` (LinuxCNC) every axis but A B C U V W,
    so that a move of Z alone is a piece of its run, while a move of A B C U V W, alone or with X Y
    Z, is copied: LinuxCNC blends no segment that moves them (linuxcnc_tp), so written in the run's
    dense blocks it ran twice as long."""
    if every_axis:
        return list(range(len(AXES))), ()
    if firmware in RESTS_WITHIN_RUNS:
        return [c for c in range(len(AXES)) if c not in EXTRA_AXES], EXTRA_AXES
    return [c for c, name in enumerate(AXES) if name in profile.axes and profile.axes[name].modes], ()


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
    segments: Segments
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


def plan_blocks(blocks: Iterable[Block], profile: MachineProfile, batch_blocks: int | None = None,
                margins: RunMargins | None = None, firmware: str | None = None, every_axis: bool = False) -> Plan:
    """The whole plan of ``blocks`` on ``profile`` (see the module docstring), held in memory;
    ``every_axis``: every axis counts as compensated (no move of an axis without modes becomes a
    rest: the firmware's own motion of them, as ``planners.replan`` of an excite sweep needs)."""
    stream = PlanStream(blocks, profile, batch_blocks, keep=True, margins=margins, firmware=firmware,
                        every_axis=every_axis)
    while stream.advance():
        pass
    return stream.whole()


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


class PlanStream:
    """The plan of a program as its blocks are read (see the module docstring).

    Consumers ask for more with ``advance`` (or ``wait``) and find, settled so far: ``runs``
    ([first, last] sample indices, last None while the run goes on), the samples below
    ``frontier`` (``samples``; ``release`` drops what is behind), the blocks with their times
    (``blocks``), and at the end (``done``) ``n_samples``, ``duration_s``, ``notes`` and
    ``warnings``. ``keep`` holds everything for ``whole`` (``plan_blocks``, as is ``every_axis``).
    ``firmware`` "klipper" plans with Klipper's rules (``klipper_rules``), anything else as above.

    The stream reads blocks (``BlockReader``), makes their pieces (``PieceMaker``), decides
    their speeds (``LookAhead``) and settles them here: the pieces' times, the runs and the
    blocks' times, whose motion goes to the samples (``Timeline``)."""

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
        self._pieces = PieceMaker(profile, klipper, self.notes, margins.travel_share, firmware in RESTS_WITHIN_RUNS,
                                  firmware == "reprap")
        self._reader = BlockReader(blocks, profile, firmware, batch_blocks or BATCH_BLOCKS,
                                   functools.partial(margins.settle_at, fs=self._fs), self._pieces.piece_limits,
                                   *_compensated_columns(profile, firmware, every_axis))
        self._scans = LookAhead(klipper)
        self._timeline = Timeline(self._fs, keep)
        self._clock = BlockClock(self._reader.pending, keep)
        self.lines, self.moves = self._clock.lines, self._clock.moves  # (see BlockClock)
        # made, not yet settled
        self._pending = {name: None for name in PIECE_FIELDS}  # pieces from _p0 on
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
                    Segments.joined(self._timeline.kept), pieces, self.notes, self.warnings)

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
        segments = []  # (order key, Segments)
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
        segments.append(Timeline.phases(p0, piece_start, piece_end, t_accel, t_cruise, start, end, d_accel, length,
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
        segments.append(Timeline.held(8 * self._last_piece + 3, end_s, end_s, self._last_end))
        if own:
            self._timeline.add(segments)

    def _next_segment(self, position: np.ndarray, key: int, segments: list) -> None:
        """The position from the sample after the last run's end (before the first run: always)."""
        t0 = (self._last_sample + 0.5) / self._fs if self.runs else -np.inf
        segments.append(Timeline.held(key, t0, 0.0, position))
