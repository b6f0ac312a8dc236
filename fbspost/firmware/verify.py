"""The written program checked on the firmware's planner before it is committed (``--verify``).

Takes the original program, the written one, the profile and the flavor; gives ``Verdict``:
each program's print time and contour error as that firmware plans it (Klipper's rules, or the
model of Marlin's, RepRapFirmware's or LinuxCNC's planner, ``firmware.py``), through the
profile's modes. The contour error is the distance from the modelled position to the original's
commanded path (its extruding pieces for a printer, at the samples where the firmware's E rises
on both sides, neither rise a sliver of the other: ``END_SLIVER``; every piece for a machine
without E, while it moves): what the part shows.

Streams, in memory that does not grow with the program's length (Klipper's planner excepted: it
takes the program whole). The original's path goes to a temporary file first, in groups with
their boxes (``_PathFile``). Then each program is planned a chunk of ``CHUNK_LINES`` lines at a
time: a chunk starts from rest ``OVERLAP_LINES`` lines before its first line (after the settings
the lines before it made) and runs ``OVERLAP_LINES`` past its last, so that the firmware's plan
of its own lines is the plan of the whole program; it is placed on the whole program's time
(the end of the line before its first, as the chunk before planned it) and sampled on the whole
program's grid, a slice of ``SLICE_SAMPLES`` at a time. The modes' state goes on from slice to
slice. The verdict equals the whole program's planned at once (tests/test_verify.py).

``compensate`` runs the check in a process of its own beside the compensation
(``measured_beside``): the original is measured while the output is made, and the output is read
as it is written (``following``), so that the verdict comes soon after the last line.

The output is kept only if it is more accurate there (a lower RMS error, a largest error at
most ``MAX_PEAK_RATIO`` of the original's) and lasts at most the margins fbspost added (its lead
and settle time), ``MAX_TIME_INCREASE`` of the original's time and ``TIME_SLACK_S`` longer; else
the writer commits the original instead.
"""
from __future__ import annotations

import math
import re
import tempfile
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..contour import PathDistance
from ..fbs.dynamics import AxisDynamics
from ..plan.planner import plan_blocks
from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind
from ..read.gcode import read_on_machine
from .linuxcnc_segments import BLEND_MODE
from .marlin import M205_B
from .planners import PLANNER_MODELS
from .reprap import M566, commanded_pieces

# Beyond the margins fbspost adds on purpose, more than this is the firmware falling behind the
# written timing (a starved buffer, Marlin's merges, LinuxCNC's short-block cap). Marlin runs a
# dense output about 1% past them (its junctions and ramps; the tube: +1.1%): within.
MAX_TIME_INCREASE = 0.02
TIME_SLACK_S = 0.05  # (a program of a second: a few servo periods or ramps are not a slower print)
# The largest error is one spot, often one neither program changes much (a corner after a copied
# travel): a few percent there must not throw away a gain everywhere else.
MAX_PEAK_RATIO = 1.1
# A chunk's lines held at once (about 4 kB each); the overlap before and after it is far more than
# a planner looks ahead (Marlin's 16 blocks, RRF's ring, LinuxCNC's optimization depth).
CHUNK_LINES = 50_000
OVERLAP_LINES = 2000
FOLLOW_BYTES = 1 << 20  # read at once of an output being written (its writer announces its length as often)
SLICE_SAMPLES = 1 << 17  # samples modelled and measured at once (a few MB each array)
GROUP_PIECES = 4096  # the original's pieces searched together, within their box
# A sample prints where E rises on both sides by more than this share of the other side's rise:
# one that extrudes for less of a sample period on a side is at the extrusion's end. klippy's
# timing runs microseconds off the written grid (11 us after 80 s of the gear's output), so at an
# end its next sample rose by 1% of a sample's extrusion and counted a sample the model does not.
END_SLIVER = 0.1
_CACHED_GROUPS = 4  # (a group of long pieces is some 10 MB searched: 0.25 mm sub-pieces)
_E = AXES.index("E")
_XYZ = slice(0, 3)


@dataclass
class FirmwareResult:
    """A program as the firmware runs it: print time and contour error (um)."""

    duration_s: float
    rms_um: float
    max_um: float


@dataclass
class Verdict:
    """The original and the output as the firmware of ``flavor`` runs them, and whether to keep the output."""

    flavor: str
    original: FirmwareResult
    output: FirmwareResult
    margins_s: float = 0.0  # the lead and settle time fbspost added (margins.RunMargins)

    @property
    def time_increase(self) -> float:
        return self.output.duration_s / self.original.duration_s - 1.0

    @property
    def better(self) -> bool:
        """The output is more accurate on the firmware and not slower than allowed."""
        return not self.shortfalls

    @property
    def shortfalls(self) -> list[str]:
        """Why the output is not kept, each in a few words (empty: it is better)."""
        out, orig, why = self.output, self.original, []
        if out.rms_um >= orig.rms_um:
            why.append(f"its RMS contour error no lower ({orig.rms_um:.4g} -> {out.rms_um:.4g} um)")
        if out.max_um > MAX_PEAK_RATIO * orig.max_um:
            why.append(f"its largest error over {MAX_PEAK_RATIO:g} times the original's "
                       f"({orig.max_um:.4g} -> {out.max_um:.4g} um)")
        if out.duration_s > self.time_allowed_s:
            why.append(f"it runs {100 * self.time_increase:.2f}% longer than the original, beyond the "
                       f"{100 * MAX_TIME_INCREASE:g}% (and the margins) allowed")
        return why

    @property
    def time_allowed_s(self) -> float:
        return (1.0 + MAX_TIME_INCREASE) * self.original.duration_s + self.margins_s + TIME_SLACK_S

    def summary(self) -> str:
        return (f"on {self.flavor}'s planner (fbspost's model of it), original -> output: RMS contour error "
                f"{self.original.rms_um:.4g} -> {self.output.rms_um:.4g} um, max {self.original.max_um:.4g} -> "
                f"{self.output.max_um:.4g} um; print time {self.original.duration_s:.1f} -> "
                f"{self.output.duration_s:.1f} s ({100 * self.time_increase:+.2f}%)")


def verify(original: Path, output: Path, profile: MachineProfile, flavor: str, margins_s: float = 0.0,
           chunk_lines: float | None = None, overlap_lines: int | None = None) -> Verdict | None:
    """Both programs re-planned as ``flavor``'s firmware plans them and measured on the original's
    path (None: the original has no motion to measure); ``margins_s``: the time fbspost added;
    ``chunk_lines``, ``overlap_lines``: see the module docstring (None: ``CHUNK_LINES`` and
    ``OVERLAP_LINES`` as they are at the call)."""
    measuring = measure(original, profile, flavor, lambda: (output, None), chunk_lines, overlap_lines)
    while True:
        try:
            next(measuring)
        except StopIteration as done:
            measured = done.value
            break
    return None if measured is None else Verdict(flavor, *measured, margins_s)


def measure(original: Path, profile: MachineProfile, flavor: str, output, chunk_lines: float | None = None,
            overlap_lines: int | None = None):
    """A generator: ``verify``'s measures of the original and of the output (its value; None: the
    original has no motion to measure), the original's first; ``output()`` gives the output's path
    and its lines (None: the file itself), asked once the original is measured. Its items: for
    LinuxCNC, when each chunk of the original (``program_chunks`` with ``CHUNK_LINES`` and
    ``OVERLAP_LINES``) has been planned, the time each of its lines ends there
    (``linuxcnc_time.linuxcnc_feeds``' plan of the original, made once)."""
    chunk_lines = CHUNK_LINES if chunk_lines is None else chunk_lines
    overlap_lines = OVERLAP_LINES if overlap_lines is None else overlap_lines
    if flavor == "klipper":  # (its look-ahead has no bound: the program whole)
        chunk_lines = math.inf
    with tempfile.TemporaryFile() as store:
        path = _PathFile.of(original, profile, flavor, store)
        if path is None:
            return None
        before = yield from _measure(original, None, profile, flavor, path, chunk_lines, overlap_lines,
                                     share=flavor == "linuxcnc")
        after = yield from _measure(*output(), profile, flavor, path, chunk_lines, overlap_lines)
        return before, after


def measured_beside(channel, original: Path, profile: MachineProfile, flavor: str):
    """``measure`` in a process of its own (``offload.Offloaded``: its items and value): the
    original measured while the output is made; the output read as it is written, up to the
    length the writer last announced through ``channel`` (``following``)."""
    return (yield from measure(original, profile, flavor, lambda: following(channel)))


def following(channel) -> tuple[Path, Iterator[bytes]]:
    """(the path of a file being written, its lines as they are written): ``channel.get()``
    gives (its path, its length so far (bytes, flushed), whether that is all), again whenever
    the lines read reach that length."""
    name, size, done = channel.get()

    def lines() -> Iterator[bytes]:
        nonlocal size, done
        rest, read = b"", 0
        with open(name, "rb") as f:
            while True:
                while read < size:
                    data = f.read(min(size - read, FOLLOW_BYTES))
                    if not data:
                        raise OSError(f"{name}: shorter than the {size} bytes written")
                    read += len(data)
                    *complete, rest = (rest + data).split(b"\n")
                    yield from (line + b"\n" for line in complete)  # (as a file's lines: at b"\n" only)
                if done:
                    if rest:
                        yield rest
                    return
                _, size, done = channel.get()

    return Path(name), lines()


def printed_path(start_mm: np.ndarray, end_mm: np.ndarray) -> tuple[PathDistance, bool]:
    """(the path, whether it is a printer's) of moves given by their X Y Z E starts and ends:
    the moves of X Y Z (1 nm or more) that extrude, else all of them."""
    moves, extrudes = _kinds(start_mm, end_mm)
    printer = bool(extrudes.any())
    chosen = extrudes if printer else moves
    return PathDistance(start_mm[chosen, :3], end_mm[chosen, :3]), printer


def _kinds(start_mm: np.ndarray, end_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(moves X Y Z 1 nm or more, and of those the ones that extrude) of pieces by X Y Z E ends."""
    delta = end_mm - start_mm
    moves = np.linalg.norm(delta[:, :3], axis=1) >= 1e-9
    return moves, moves & (delta[:, _E] > 0)


class _PathFile:
    """The original's path (``printed_path``) in a file, in groups of ``GROUP_PIECES`` pieces with
    their boxes: a point's distance is searched first in the group whose box is nearest it, then
    in every other group whose box is nearer than the nearest piece found there (the last
    ``_CACHED_GROUPS`` groups searched are kept in memory)."""

    def __init__(self, rows: np.ndarray, printer: bool):
        self.rows, self.printer = rows, printer  # (n, 7): X Y Z start, X Y Z end, chosen
        self.groups = [g for g in range(0, len(rows), GROUP_PIECES) if rows[g:g + GROUP_PIECES, 6].any()]
        boxes = []
        for g in self.groups:
            chosen = self.rows[g:g + GROUP_PIECES]
            chosen = chosen[chosen[:, 6] > 0]
            ends = np.vstack([chosen[:, :3], chosen[:, 3:6]])
            boxes.append((ends.min(axis=0), ends.max(axis=0)))
        self.low, self.high = (np.array(side) for side in zip(*boxes, strict=True))
        self.cache: OrderedDict[int, PathDistance] = OrderedDict()

    @classmethod
    def of(cls, program: Path, profile: MachineProfile, flavor: str, store) -> _PathFile | None:
        """The path of ``program`` written to the open binary file ``store`` (None: no X Y Z motion)."""
        pending, any_extrudes, any_moves = [], False, False
        blocks = read_on_machine(program, flavor, profile)
        for _, _, pieces in commanded_pieces(blocks):
            pending.extend(pieces)
            if len(pending) >= GROUP_PIECES:
                any_moves, any_extrudes = cls._write(pending, store, any_moves, any_extrudes)
                pending = []
        any_moves, any_extrudes = cls._write(pending, store, any_moves, any_extrudes)
        if not any_moves:
            return None
        store.flush()
        rows = np.memmap(store, dtype=float, mode="r+").reshape(-1, 8)
        rows[:, 6] = rows[:, 7] if any_extrudes else rows[:, 6]
        return cls(rows[:, :7], any_extrudes)

    @staticmethod
    def _write(pieces, store, any_moves: bool, any_extrudes: bool) -> tuple[bool, bool]:
        """``pieces`` (start, end) appended as rows: X Y Z start, X Y Z end, moves, extrudes."""
        if not pieces:
            return any_moves, any_extrudes
        start, end = (np.array(side)[:, :_E + 1] for side in zip(*pieces, strict=True))
        moves, extrudes = _kinds(start, end)
        store.write(np.column_stack([start[:, :3], end[:, :3], moves, extrudes]).astype(float).tobytes())
        return any_moves or bool(moves.any()), any_extrudes or bool(extrudes.any())

    def __call__(self, points_mm: np.ndarray) -> tuple[np.ndarray, None]:
        """(the distance (mm) from each of ``points_mm`` (X Y Z) to the nearest piece of the path,
        None: as ``PathDistance`` gives it, without the nearest point)."""
        best = np.full(len(points_mm), np.inf)
        if not len(points_mm):
            return best, None
        # no point is nearer a group than the gap between their boxes: groups in the order of that
        # gap (searching every group for every point made a long print's check grow with its square)
        gap = np.maximum(self.low - points_mm.max(axis=0), 0.0) + np.maximum(points_mm.min(axis=0) - self.high, 0.0)
        bound = np.sqrt(np.einsum("ij,ij->i", gap, gap))
        order = np.argsort(bound, kind="stable").tolist()
        # each point first in the group whose box is nearest it (mostly the one that holds it: a
        # point searched in several groups cost twice the check's search)
        own, own_box = np.full(len(points_mm), -1), np.full(len(points_mm), np.inf)
        for k in order:
            if bound[k] >= own_box.max():
                break
            outside = self._outside(points_mm, k)
            nearer = outside < own_box
            own[nearer], own_box[nearer] = k, outside[nearer]
        for k in np.unique(own).tolist():
            self._search(points_mm, k, best, own == k)
        # then in every other group whose box is nearer than the nearest piece found
        for k in order:
            if bound[k] >= best.max():
                break
            self._search(points_mm, k, best, (own != k) & (self._outside(points_mm, k) < best))
        return best, None

    def _search(self, points_mm: np.ndarray, k: int, best: np.ndarray, chosen: np.ndarray) -> None:
        """``best`` lowered to the distances to group ``k`` of the ``chosen`` points."""
        rows = np.flatnonzero(chosen)
        if rows.size:
            best[rows] = np.minimum(best[rows], self._group(self.groups[k])(points_mm[rows])[0])

    def _outside(self, points_mm: np.ndarray, k: int) -> np.ndarray:
        """The distance from each point to group ``k``'s box: no piece of it is nearer."""
        gap = np.maximum(self.low[k] - points_mm, 0.0) + np.maximum(points_mm - self.high[k], 0.0)
        return np.sqrt(np.einsum("ij,ij->i", gap, gap))

    def _group(self, g: int) -> PathDistance:
        if g not in self.cache:
            chosen = np.asarray(self.rows[g:g + GROUP_PIECES])
            chosen = chosen[chosen[:, 6] > 0]
            self.cache[g] = PathDistance(chosen[:, :3], chosen[:, 3:6])
            if len(self.cache) > _CACHED_GROUPS:
                self.cache.popitem(last=False)
        self.cache.move_to_end(g)
        return self.cache[g]


class _Run:
    """A chunk of a program as the firmware runs it: ``at(t)`` its X Y Z E at times ``t`` (s,
    the chunk's own), the time each of its lines ends and its print time."""

    def __init__(self, blocks: list[Block], profile: MachineProfile, flavor: str):
        if flavor in PLANNER_MODELS:
            run = PLANNER_MODELS[flavor](blocks, profile)
            self.at = lambda t: run.at(t)[:, :_E + 1]
        else:  # Klipper: the planner's samples, on the grid from 0 (one chunk: the program whole)
            run = plan_blocks(blocks, profile, firmware="klipper")
            last = len(run.positions_mm) - 1
            self.at = lambda t: run.positions_mm[np.clip(np.rint(t * profile.sample_rate_hz).astype(int), 0, last),
                                                 :_E + 1]
        self.line_time_s, self.duration_s = run.line_time_s, run.duration_s


def _setting(block: Block) -> bytes | None:
    """A line that changes what a firmware's model plans with (limits, Marlin's M205 B, RRF's M566,
    LinuxCNC's G61 / G64): its letters, which a later line with the same letters overrides; else None."""
    code = block.raw.split(b";")[0]
    if (block.limits is None and M205_B.match(code) is None and M566.match(code) is None
            and BLEND_MODE.search(code) is None):
        return None
    return re.sub(rb"[^A-Za-z]", b"", code).upper()


def program_chunks(program: Path, profile: MachineProfile, flavor: str, chunk_lines: float, overlap_lines: int,
                   lines: Iterable[bytes] | None = None):
    """The chunks of ``program`` (see the module docstring): (its blocks, the index among them of
    the line before its first measured one (None: the program's start), that of its last measured
    one (None: the program's end)). A chunk's last measured line is a MOVE: both chunks plan its end.
    ``lines``: the program's lines, read instead of its file (``read_gcode``'s)."""
    held, held_from, settings = [], 0, {}  # held[i] is line held_from + i
    first = 0  # the chunk's first measured line
    for block in read_on_machine(program, flavor, profile, lines):
        held.append(block)
        if held_from + len(held) < first + chunk_lines + overlap_lines:
            continue
        last = first + chunk_lines - 1
        while last - held_from < len(held) - overlap_lines and not _moves(held[last - held_from]):
            last += 1
        if last - held_from >= len(held) - overlap_lines:
            continue  # no move to end the chunk at yet: more lines
        lead = len(settings) if held_from else 0
        yield (_with_start(held, held_from, settings), first - 1 - held_from + lead if first else None,
               last - held_from + lead)
        first = last + 1
        drop = max(0, first - overlap_lines - held_from)
        for dropped in held[:drop]:
            key = _setting(dropped)
            if key is not None:
                settings.pop(key, None)
                settings[key] = replace(dropped, kind=Kind.PASS, points_mm=None, dwell_s=0.0)
        held, held_from = held[drop:], held_from + drop
    lead = len(settings) if held_from else 0
    yield _with_start(held, held_from, settings), first - 1 - held_from + lead if first else None, None


def _moves(block: Block) -> bool:
    return block.kind is Kind.MOVE and block.points_mm is not None


def _with_start(held: list[Block], held_from: int, settings: dict[bytes, Block]) -> list[Block]:
    """A chunk's blocks: the program's from its start; else the settings made before its first held
    line, that line as a rest where it leaves the machine (its settings kept), and the held lines after it."""
    if not held_from:
        return list(held)
    return [*settings.values(), replace(held[0], kind=Kind.STOP, points_mm=None, dwell_s=0.0), *held[1:]]


def _measure(program: Path, lines: Iterable[bytes] | None, profile: MachineProfile, flavor: str, path: _PathFile,
             chunk_lines: float, overlap_lines: int, share: bool = False):
    """A generator: ``program`` (its ``lines``, None: its file) as the firmware runs it, chunk by
    chunk, measured on ``path`` (its value); with ``share``, each chunk's ``line_time_s`` (its items)."""
    rate_hz = profile.sample_rate_hz
    modes, contour = _Modes(profile), _Contour(path.printer)
    offset_s = cut_s = 0.0  # the chunk's time 0 on the program's; the end of its line before its first
    n_from = 0  # the first sample the chunk measures
    for blocks, before, last in program_chunks(program, profile, flavor, chunk_lines, overlap_lines, lines):
        run = _Run(blocks, profile, flavor)
        del blocks
        if share:
            yield run.line_time_s
        if before is not None:
            offset_s = cut_s - float(run.line_time_s[before])
        if last is None:
            duration_s = offset_s + run.duration_s
            n_to = math.floor(duration_s * rate_hz) + 2  # (as planners.replan samples it)
        else:
            cut_s = offset_s + float(run.line_time_s[last])
            n_to = math.ceil(cut_s * rate_hz)
        for a in range(n_from, n_to, SLICE_SAMPLES):
            b = min(a + SLICE_SAMPLES, n_to)
            # a sample either side: whether E rises around the first and the last
            lo, hi = max(a - 1, 0), b if last is None and b == n_to else b + 1
            command = run.at(np.arange(lo, hi) / rate_hz - offset_s)
            contour.add(command, modes(command[a - lo:b - lo]), a - lo, b - lo, path)
        n_from = max(n_from, n_to)
    return FirmwareResult(duration_s, *contour.result_um())


class _Modes:
    """The actual positions of a command (rows of X Y Z E ...) given slice by slice through the
    profile's modes (axes without modes: as commanded). Where the command jumps (faster than
    twice the axis' top speed: a move from an unknown position, which the firmware runs but no
    model plans), the modes start anew at rest: that motion is not the program's to judge."""

    def __init__(self, profile: MachineProfile):
        self.axes = [(AXES.index(axis), AxisDynamics(spec.modes, 1.0 / profile.sample_rate_hz),
                      2.0 * spec.max_velocity_mm_s / profile.sample_rate_hz)
                     for axis, spec in profile.axes.items() if spec.modes and axis in AXES]
        self.steps, self.last = {}, {}  # per axis: its response going on, its last command

    def __call__(self, command_mm: np.ndarray) -> np.ndarray:
        actual = command_mm.copy()
        if not len(command_mm):
            return actual
        for i, dynamics, jump_mm in self.axes:
            column = command_mm[:, i]
            if i in self.last:
                starts = np.flatnonzero(np.abs(np.diff(column, prepend=self.last[i])) > jump_mm)
            else:
                starts = np.append(0, np.flatnonzero(np.abs(np.diff(column)) > jump_mm) + 1)
            for a, b in zip([0, *starts], [*starts, len(column)], strict=True):
                if a in starts:
                    self.steps[i] = dynamics.response(column[a])
                if b > a:
                    actual[a:b, i] = self.steps[i](column[a:b])
            self.last[i] = column[-1]
        return actual


def modelled(command_mm: np.ndarray, profile: MachineProfile) -> np.ndarray:
    """The actual positions of ``command_mm`` (rows of X Y Z E ...) through the profile's modes (``_Modes``)."""
    return _Modes(profile)(command_mm)


def _printing_samples(e_mm: np.ndarray) -> np.ndarray:
    """Whether each sample of E (mm) prints: E rises on both sides, each rise more than
    ``END_SLIVER`` of the other."""
    rise = np.diff(e_mm)
    inside = np.minimum(rise[:-1], rise[1:]) > END_SLIVER * np.maximum(rise[:-1], rise[1:])
    return np.concatenate([[False], inside, [False]])[:e_mm.size]


class _Contour:
    """The contour error's sums over the samples that print (see the module docstring), slice by
    slice. A machine without E: from the first sample that moves to the one after the last; the
    samples after the last so far are held aside until a later one moves."""

    def __init__(self, printer: bool):
        self.printer = printer
        self.sums = np.zeros(3)  # sum of squares (mm^2), count, max (mm)
        self.pending = np.zeros(3)
        self.started = False

    def add(self, command_mm: np.ndarray, actual_mm: np.ndarray, i0: int, i1: int, path) -> None:
        """Rows ``i0``..``i1`` of ``command_mm`` (the samples measured, with their neighbours) and
        ``actual_mm`` (those samples alone)."""
        if self.printer:
            chosen = _printing_samples(command_mm[:, _E])[i0:i1]
            self._add(self.sums, path(actual_mm[chosen, _XYZ])[0])
            return
        moving = np.flatnonzero(np.abs(np.diff(command_mm[:, _XYZ], axis=0)).max(axis=1) > 0)
        if not self.started and not moving.size:
            return
        begin = i0 if self.started else max(i0, int(moving[0]))
        self.started = True
        error = path(actual_mm[begin - i0:, _XYZ])[0]
        if moving.size:
            self.sums = self._merge(self.sums, self.pending)
            self.pending = np.zeros(3)
        end = min(max(int(moving[-1]) + 2, begin), i1) if moving.size else begin
        self._add(self.sums, error[:end - begin])
        self._add(self.pending, error[end - begin:])

    @staticmethod
    def _add(sums: np.ndarray, error_mm: np.ndarray) -> None:
        sums[:] = _Contour._merge(sums, [np.sum(error_mm**2), error_mm.size, error_mm.max(initial=0.0)])

    @staticmethod
    def _merge(a, b) -> np.ndarray:
        return np.array([a[0] + b[0], a[1] + b[1], max(a[2], b[2])])

    def result_um(self) -> tuple[float, float]:
        """(RMS, max) in um."""
        total, count, peak = self.sums
        return (float(np.sqrt(total / count)) * 1e3 if count else 0.0), float(peak) * 1e3


def contour_um(actual_mm: np.ndarray, command_mm: np.ndarray, path: PathDistance, printer: bool) -> tuple[float, float]:
    """(RMS, max) contour error in um of ``actual_mm`` at the samples that print (see the module docstring)."""
    contour = _Contour(printer)
    contour.add(command_mm, actual_mm, 0, len(command_mm), path)
    return contour.result_um()
