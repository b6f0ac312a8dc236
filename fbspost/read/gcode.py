"""G-code reader: a program's lines as blocks the planner and the writer understand.

Takes a G-code file (bytes, any line endings, any encoding in comments) and a flavor; gives, in
order, one ``Block`` per input line: its number and exact bytes, whether it moves the machine
(MOVE: planned and rewritten by fbspost), passes through while the motion continues (PASS), or
passes through with the machine at rest (STOP), the linear pieces of a move in machine
coordinates (mm, the columns of AXES: X Y Z E, then LinuxCNC's A B C U V W; arcs and Beziers
subdivided), planner-limit changes, and the
modal state after the line. Bad input raises ``trajectory.InputError`` naming the file and line.

``read_gcode(path, flavor)`` streams the blocks; ``detect_flavor(path)`` guesses the flavor from
the first 2000 and last 300 lines. How lines are read:

- Words are a letter and a number, any case, spaces optional (``g1x10y5`` is ``G1 X10 Y5``);
  ``;`` and ``( )`` comments, a leading ``N123``, a trailing ``*checksum`` and a leading ``/``
  are ignored; RRF ``"strings"`` may hold ``;``. Marlin, Klipper and RRF execute the first
  command of a line (later G/M/T letters are its parameters: ``M104 S200 T0`` selects no tool);
  LinuxCNC executes all of them, modal settings first, then G92/G28/..., then the motion.
- Positions are machine coordinates: program = machine - ``Modal.offsets_mm`` (G92 moves the
  offsets, not the machine). XYZ are unknown (NaN) at the start and after probing, macros and
  unknown commands; a G28 leaves the axes it homes at the machine's home position (``home_mm``;
  in LinuxCNC, whose G28 goes to a position stored outside the file, they are unknown); E starts
  known at 0 and is lost only where an unknown command
  may have changed it while E is absolute. A G92 on an unknown axis makes it known; selecting
  another work coordinate system (G54..G59.3, offsets not in the file) makes XYZ unknown. A move
  is a MOVE when the start of every axis it moves (its axis words, and both axes of an arc's
  plane) is known and a feed is set; axes it does not move may be unknown: their column of
  ``points_mm`` is NaN (an XY program that never sets Z). Otherwise it is a STOP (points None):
  the controller plans it, and afterwards the axes it sets absolutely are known.
- G0 is a rapid (feed inf) in LinuxCNC only: Marlin, Klipper and RRF move G0 at the modal feed
  like G1. G90/G91 set E too in Marlin; in Klipper E is relative under G91 or M83; in RRF only
  M82/M83 decide. G92 alone zeroes all axes in Klipper, does nothing in Marlin and RRF and is an
  error in LinuxCNC. G4 P is milliseconds (S seconds) except in LinuxCNC (P seconds).
- Arcs (G2/G3 with I J K or R in G17/G18/G19, helical, full circles, P turns: LinuxCNC P turns
  in all, Marlin P full circles before the arc, ignored elsewhere) and G5 cubic
  Beziers (XY only) are cut into pieces within CHORD_TOLERANCE_MM; Z (helical) and E follow
  the arc length. An arc's end may be off its circle by 0.002 mm or 0.1 % (the radius then
  changes linearly along the arc, as LinuxCNC does); more is an error.
- Limits: M204 S (print and travel) / P (print) / T (travel), Klipper M204 S or min(P, T);
  M201 and M203 per axis (M203 in mm/min in RRF); M205 J; classic jerk M205 X/Y (and RRF M566,
  mm/min) becomes square_corner_velocity = min(X, Y): at a 90 degree corner each axis changes
  speed by the corner speed, so a jerk limit J allows a corner speed J, the meaning of Klipper's
  square corner velocity; SET_VELOCITY_LIMIT VELOCITY ACCEL SQUARE_CORNER_VELOCITY
  MINIMUM_CRUISE_RATIO ACCEL_TO_DECEL.
- LinuxCNC NURBS (G5.2 ... G5.3, and G5.1 quadratic splines, XY only) are evaluated exactly as
  LinuxCNC 2.9 defines them (``nurbs_additional_functions.cc``: order L >= 3, the first control
  point the current position, clamped uniform integer knots, weights P) and cut into pieces
  within CHORD_TOLERANCE_MM (every knot a chord's end); the G5.2 line, its control point lines
  and the G5.3 line each carry a share of the curve (one MOVE each), so that none is copied
  without its curve. G6.2 (LinuxCNC 2.10, as its nc_files/nurbs/G6 examples write it and
  ``nurbs_additional_functions.cc`` evaluates it): the first line gives the order P and every
  line a knot K, the control points X Y (the first where the tool is) their weights R, and
  ``order`` lines of a knot alone end the NURBS; the knots are the K words in order (clamped,
  not decreasing). Q (LinuxCNC's choice of how it steps along the curve) does not change it.
- LinuxCNC's other axes, A B C (degrees, also under G20) and U V W, are columns of AXES after E:
  planned and written like the axes without modes (followed exactly, not compensated); a move's
  feed is along XYZ, else U V W, else A B C (``feed_lengths``, LinuxCNC's rule). They start
  unknown: an axis' first move is a STOP, as a move from an unknown XYZ is. (In the printers'
  flavors they stay at 0 and their words are errors.) E, P, Q, L in M62..M68 are the I/O
  command's words.
- LinuxCNC's G33 (spindle-synchronized, K the distance along the move per revolution) is a
  STOP, copied as written, lasting its X Y Z length over K S / 60 (S from the last S word, the
  spindle on after M3/M4 until M5/M19/M2/M30; without it, under G96 or without K, an error).
- Errors: cutter compensation, rotation, scaling, canned cycles, inverse-time or per-revolution
  feed, parameters and expressions, O-word subroutines and control flow, and in LinuxCNC G7,
  G33.1 and the lathe cycles (``NeedsInterpreter``
  in LinuxCNC programs: ``--expand`` runs them through LinuxCNC's interpreter), unknown motion
  codes, G6.2 in G91, A B C U V W outside LinuxCNC, missing or non-numeric values, arcs without
  a radius or with R shorter than half the chord, feeds <= 0.
"""
from __future__ import annotations

import contextlib
import enum
import itertools
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..profile import FLAVORS

AXES = ("X", "Y", "Z", "E", "A", "B", "C", "U", "V", "W")  # column order of every position array
_E = 3
_EXTRA = tuple(range(4, len(AXES)))  # LinuxCNC's rotary and other axes: followed exactly (no modes)
_DEGREES = (4, 5, 6)  # A B C: degrees, whatever G20/G21 say


def feed_lengths(delta_mm: np.ndarray, xyz_moves: np.ndarray | None = None,
                 still_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The length each move's feed is along, and where XYZ do not move: the XYZ length where XYZ
    move (``xyz_moves``; by default where the XYZ length is above ``still_mm``), else the U V W
    length, else the A B C length (LinuxCNC's rule for its feed, docs "Feed Rate"), else |dE|
    (the printers' extrude-only moves)."""
    def norm(columns):
        return np.sqrt(np.einsum("ij,ij->i", delta_mm[:, columns], delta_mm[:, columns]))

    xyz, uvw, abc = norm(slice(0, 3)), norm(slice(7, 10)), norm(slice(4, 7))
    still = ~(xyz > still_mm) if xyz_moves is None else ~xyz_moves
    other = np.where(uvw > still_mm, uvw, np.where(abc > still_mm, abc, np.abs(delta_mm[:, _E])))
    return np.where(still, other, xyz), still


class NeedsInterpreter(InputError):
    """A LinuxCNC feature fbspost does not interpret itself (parameters, O-words, canned cycles,
    ...): ``--expand`` runs the program through LinuxCNC's own interpreter first."""

    def __init__(self, path: str | Path, line: int, feature: str, message: str):
        super().__init__(path, line, message)
        self.line, self.feature = line, feature
        self._parts = (path, line, feature, message)


class Kind(enum.Enum):
    MOVE = "move"  # motion fbspost plans and rewrites
    PASS = "pass"  # no motion: passes through byte-exact at its time, the motion goes on through it
    STOP = "stop"  # passes through byte-exact; the machine is at rest when it runs


@dataclass(frozen=True)
class PlannerLimits:
    """Planner settings changed by one line; ``None`` (or a missing axis) means unchanged."""

    # M204 S/P, Klipper ACCEL: moves that extrude (all moves if no travel value)
    acceleration_mm_s2: float | None = None
    travel_acceleration_mm_s2: float | None = None  # M204 T (Marlin, RRF): moves that do not extrude
    max_velocity_mm_s: float | None = None  # Klipper VELOCITY
    square_corner_velocity_mm_s: float | None = None  # Klipper SQUARE_CORNER_VELOCITY
    junction_deviation_mm: float | None = None  # Marlin M205 J
    minimum_cruise_ratio: float | None = None  # Klipper SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO
    accel_to_decel_mm_s2: float | None = None  # Klipper SET_VELOCITY_LIMIT ACCEL_TO_DECEL (before 2024)
    axis_max_velocity_mm_s: dict[str, float] = field(default_factory=dict)  # M203
    min_feed_mm_s: float | None = None  # RepRapFirmware M203 I: the slowest a move runs
    axis_max_acceleration_mm_s2: dict[str, float] = field(default_factory=dict)  # M201


@dataclass(frozen=True)
class Modal:
    """The state that decides how coordinates are written, after a line."""

    absolute_xyz: bool = True  # G90 / G91
    absolute_e: bool = True  # M82 / M83 (G90 / G91 set it too, as Marlin and RRF do)
    inches: bool = False  # G20 / G21
    offsets_mm: tuple[float, ...] = (0.0,) * len(AXES)  # program = machine - offset (G92)
    plane: int = 17  # G17 / G18 / G19: the G5 writer needs G17


@dataclass
class Block:
    line_no: int  # 1-based
    raw: bytes  # the line exactly as read, line ending included
    kind: Kind
    modal: Modal  # after this line
    position_mm: np.ndarray  # (len(AXES),) machine position after this line; NaN where unknown
    # MOVE: (k, len(AXES)) machine-coordinate end points of its k >= 1 linear pieces
    points_mm: np.ndarray | None = None
    feed_mm_s: float | None = None  # MOVE: requested feed along the path; math.inf for a rapid (G0)
    dwell_s: float = 0.0  # STOP: time at rest (G4)
    limits: PlannerLimits | None = None  # planner changes made by this line
    # axes (indices into AXES) whose program position this line sets where the machine is (G92)
    sets_position: tuple[int, ...] = ()


# ----------------------------------------------------------------------------------------------
# Reading

CHORD_TOLERANCE_MM = 0.0005  # largest distance between an arc or Bezier and its linear pieces
_INCH = 25.4
_NAN = math.nan
_TWO_PI = 2.0 * math.pi
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(5)

# One word: a letter and its value (a number, NaN or infinity as a C library writes them, so that
# the error can name them, an RRF "string", an RRF {expression}, or nothing), or any other
# non-blank character (junk: an error wherever the line's values are needed).
_WORD = re.compile(
    r'([A-Za-z])\s*([-+]?\s*(?:\d+\.?\d*|\.\d+|(?i:nan|inf(?:inity)?)(?![A-Za-z]))|"(?:[^"]|"")*"?|\{[^}]*\}?|)|(\S)'
)
# The common line, fast, straight from its bytes: [N123] G0/G1 with X Y Z E in this order, F first
# or last, one space between words, [*checksum], [; comment]. Anything else takes the general path.
_NUM = rb"([-+]?[\d.]{1,40})"
_FAST_G01 = re.compile(
    rb"(?:N\d+ +)?G0?([01])(?: +F" + _NUM + rb")?(?: +X" + _NUM + rb")?(?: +Y" + _NUM + rb")?(?: +Z" + _NUM
    + rb")?(?: +E" + _NUM + rb")?(?: +F" + _NUM + rb")?(?: *\*\d+)?(?:[ \t]*;.*|\s*)\Z",
    re.DOTALL,
)
_COMMENT_OR_STRING = re.compile(r'"(?:[^"]|"")*"?|\([^)]*\)?|;')
_HEAD = re.compile(r"\s*(?:/\s*)?(?:[Nn]\s*\d+)?\s*")  # block delete, line number
_CHECKSUM = re.compile(r"\*\s*\d*\s*$")
_EXT_PARAM = re.compile(r'([A-Za-z_][A-Za-z0-9_]*)\s*=\s*("[^"]*"|\S*)')
_OWORD = re.compile(r"[Oo]\s*(?:\d+|<[^>]*>)\s*([A-Za-z_]*)")
# Marlin-style commands whose arguments are free text (messages, file names, version strings).
# Control characters (not white space) in a line's code, or a code that starts with bytes that are
# not UTF-8: binary content, not G-code (a comment may hold any bytes: it passes through)
_BINARY = re.compile("[\x00-\x08\x0e-\x1f\x7f]|^\ufffd")
NOT_GCODE = "not a G-code file: binary content"
_TEXT_CMD = re.compile(r"[Mm]\s*0*(?:117|118|23|28|30|32|33|928|115|0|1)(?![\d.])")

_MOTION = {0.0: 0, 1.0: 1, 2.0: 2, 3.0: 3, 5.0: 5}
_PLANES = {17.0: (0, 1, 2, "I", "J"), 18.0: (2, 0, 1, "K", "I"), 19.0: (1, 2, 0, "J", "K")}
_WCS = {54.0, 55.0, 56.0, 57.0, 58.0, 59.0, 59.1, 59.2, 59.3}
_UNSUPPORTED_G = {
    41.0: "cutter radius compensation (G41)",
    42.0: "cutter radius compensation (G42)",
    41.1: "dynamic cutter radius compensation (G41.1)",
    42.1: "dynamic cutter radius compensation (G42.1)",
    68.0: "coordinate rotation (G68)",
    51.0: "scaling (G51)",
    93.0: "inverse time feed (G93)",
    95.0: "feed per revolution (G95)",
    73.0: "canned cycles (G73)",
    76.0: "canned cycles (G76)",
    **{float(g): f"canned cycles (G{g})" for g in range(81, 90)},
}
_LINUXCNC_PASS_G = {40.0, 49.0, 61.0, 61.1, 64.0, 80.0, 94.0}
_LINUXCNC_INTERPRETED_G = {  # path-changing LinuxCNC codes that only its interpreter runs (--expand)
    7.0: "lathe diameter mode (G7)", 33.1: "rigid tapping (G33.1)",
    70.0: "lathe cycles (G70)", 71.0: "lathe cycles (G71)", 72.0: "lathe cycles (G72)",
    74.0: "canned cycles (G74)", 71.1: "lathe cycles (G71.1)", 71.2: "lathe cycles (G71.2)",
    72.1: "lathe cycles (G72.1)", 72.2: "lathe cycles (G72.2)",
}
# M codes that pass while the machine keeps moving (no motion, no waiting)
_PASS_M = {3.0, 4.0, 5.0, 7.0, 8.0, 9.0, 18.0, 73.0, 84.0, 104.0, 105.0, 106.0, 107.0, 114.0,
           115.0, 117.0, 118.0, 140.0, 141.0, 221.0, 486.0, 900.0}
# M codes after which the machine is at rest where it was
_STOP_M = {0.0, 1.0, 2.0, 6.0, 30.0, 60.0, 109.0, 116.0, 190.0, 191.0, 400.0, 593.0, 600.0}  # (M593: input shaping)
_LIMIT_M = {201.0, 203.0, 204.0, 205.0, 566.0}
_KLIPPER_PASS = {"SET_FAN_SPEED", "SET_PRESSURE_ADVANCE", "SET_HEATER_TEMPERATURE",
                 "EXCLUDE_OBJECT_START", "EXCLUDE_OBJECT_END", "EXCLUDE_OBJECT_DEFINE"}
_OTHER_AXES = "".join(AXES[i] for i in _EXTRA)
_EXPAND_HINT = "--expand runs it through LinuxCNC's interpreter"
_NURBS_G = {5.1, 5.2, 5.3, 6.2}  # LinuxCNC splines (G6.2: LinuxCNC 2.10's NURBS with its own knots)
_IO_M = {62.0, 63.0, 64.0, 65.0, 66.0, 67.0, 68.0}  # LinuxCNC I/O: E P Q L are its words
_LINUXCNC_PASS_M = {48.0, 49.0, 50.0, 51.0, 52.0, 53.0, 61.0, 62.0, 63.0, 64.0, 65.0, 67.0, 68.0}
_TRAVEL_BATCH = 256  # blocks checked against the travel at once
_PARAMETER = re.compile(r"#\s*(?:<[^>]*>?|\d+|\[)|\[[^\]]*\]?")


def read_gcode(path: str | Path, flavor: str, home_mm=(0.0, 0.0, 0.0), travel_mm=None,
               lines: Iterable[bytes] | None = None) -> Iterator[Block]:
    """Blocks of the G-code file ``path`` read as ``flavor`` (one of FLAVORS), one per line, in order.
    ``lines``: the file's lines (with their endings) as they come, read instead of the file (a
    file still being written, ``verify.following``); ``path`` names them in errors.
    ``home_mm``: the X Y Z machine position a G28 leaves the axes it homes at (printers).
    ``travel_mm``: the lowest and the highest machine position of each axis of AXES
    (``MachineProfile.travel_mm``): a line that moves an axis beyond them is refused, as the
    firmware refuses it (Klipper: "Move out of range"; LinuxCNC's soft limits).

    Streams: the file is read line by line as the iterator is consumed. Raises ``InputError``
    (``FILE:LINE: message``) at the first line it cannot interpret safely, ``ValueError`` at once
    for an unknown flavor.
    """
    if flavor not in FLAVORS:
        raise ValueError(f"unknown G-code flavor {flavor!r}: expected one of {', '.join(FLAVORS)}")
    blocks = _blocks(path, flavor, home_mm, lines)
    if travel_mm is None or not np.isfinite(travel_mm).any():
        return blocks
    return _within_travel(blocks, path, *np.asarray(travel_mm, dtype=float))


def _within_travel(blocks: Iterator[Block], path, lowest_mm: np.ndarray, highest_mm: np.ndarray) -> Iterator[Block]:
    """``blocks``, each checked to leave no axis beyond the travel (a position still unknown, NaN,
    is not checked: the machine's own is that of the line that sets it); checked ``_TRAVEL_BATCH``
    blocks at a time (one at a time took a CAM program's reading 3 times as long)."""
    while batch := list(itertools.islice(blocks, _TRAVEL_BATCH)):
        points = [b.points_mm if b.points_mm is not None else b.position_mm[None] for b in batch]
        stacked = np.vstack(points)
        beyond = (stacked < lowest_mm) | (stacked > highest_mm)
        if beyond.any():
            row, axis = np.argwhere(beyond)[0]
            line_no = batch[np.searchsorted(np.cumsum([len(p) for p in points]), row, "right")].line_no
            raise InputError(path, line_no, f"moves {AXES[axis]} to {stacked[row, axis]:.6g} mm, beyond the "
                             f"machine's travel {lowest_mm[axis]:g} to {highest_mm[axis]:g} mm (the profile's "
                             f"axes.{AXES[axis]}.position_min and position_max, or the firmware's default)")
        yield from batch


def _blocks(path: str | Path, flavor: str, home_mm, lines: Iterable[bytes] | None = None) -> Iterator[Block]:
    try:
        handle = open(path, "rb") if lines is None else contextlib.nullcontext(lines)
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    reader = _Reader(path, flavor, home_mm)
    line = reader.line
    with handle as source:
        for line_no, raw in enumerate(source, 1):
            block = line(line_no, raw)
            if block.__class__ is Block:
                yield block
            elif block is not None:  # a spline's lines, held until its end
                yield from block
        if reader.spline is not None:
            first = reader.spline.lines[0][0]
            if reader.spline.knots is not None:
                raise reader.error(first, f"G6.2 NURBS never ended ({reader.spline.order} lines of its last knot "
                                          "alone, K, end it)")
            raise reader.error(first, "G5.2 without G5.3 (the NURBS is never ended)")


@dataclass
class _Effects:
    """What a line's commands do, gathered in LinuxCNC's order of execution before its motion."""

    kind: Kind = Kind.PASS
    dwell: float = 0.0
    limits: PlannerLimits | None = None
    unknown: bool = False  # an unknown command: XYZ (and absolute E) unknown afterwards
    modal_changed: bool = False
    motion: float | None = None
    axis_words_used: bool = False  # a non-motion command took the axis words
    sets_position: tuple[int, ...] = ()


class _Words:
    """The reader's words and values: a line's text to its commands and words (comments,
    line numbers, checksums, O-words, extended commands taken apart), numbers read or refused
    with the line's one-line error. Part of ``_Reader``, whose state it reads."""

    def error(self, line_no: int, message: str) -> InputError:
        return InputError(self.path, line_no, message)

    def number(self, n: int, letter: str, text: str | None) -> float:
        """A word's value as a finite number, or an InputError naming the word."""
        if text is None or text == "":
            raise self.error(n, f"{letter} needs a number")
        try:
            value = float(text.replace(" ", ""))
        except ValueError:
            raise self.error(n, f"{letter}{text} is not a number") from None
        if not -1e300 < value < 1e300:
            raise self.error(n, f"{letter}{text} is not a finite number")
        return value

    def line(self, n: int, raw: bytes) -> Block | list[Block] | None:
        """The line's block; inside a G5.2 NURBS None (held), and at its G5.3 every held line's block."""
        if self.spline is not None:
            block = self.general(n, raw)
            if block.__class__ is Block:  # a comment or blank line inside the NURBS
                self.spline.lines.append(block)
                return None
            return block
        m = _FAST_G01.match(raw)
        if m is not None:
            try:
                block = self.fast_move(n, raw, *m.groups())
            except ValueError:  # "1.2.3": the general path names the word
                block = None
            if block is not None:
                return block
        return self.general(n, raw)

    def general(self, n: int, raw: bytes) -> Block | list[Block] | None:
        text = raw.decode("utf-8", "replace")
        if n == 1 and text.startswith("\ufeff"):
            text = text[1:]
        if '"' in text or "(" in text:
            code = _strip_comments(text)
        else:
            i = text.find(";")
            code = text[:i] if i >= 0 else text
        code = code.strip()
        if not code:
            return Block(n, raw, Kind.PASS, self.modal, np.array(self.pos))
        if _BINARY.search(code):
            raise self.error(n, NOT_GCODE)
        c0 = code[0]
        if c0 in "Nn/":
            code = code[_HEAD.match(code).end():]
            if not code:
                return self.block(n, raw, Kind.PASS)
            c0 = code[0]
        if "*" in code:
            code = _CHECKSUM.sub("", code).rstrip()
            if not code:
                return self.block(n, raw, Kind.PASS)
            c0 = code[0]
        if c0 == "%":
            return self.block(n, raw, Kind.PASS)
        if c0 in "Oo":
            return self.oword(n, raw, code)
        if self.cnc and ("#" in code or "[" in code or "@" in code or "^" in code):
            feature = _PARAMETER.search(code)
            what = "parameters" if feature and feature.group().startswith("#") else "expressions"
            if feature is None:
                what, feature = "polar coordinates", re.search(r"[@^]\s*[-+.\d]*", code)
            shown = feature.group()
            raise NeedsInterpreter(self.path, n, f"{what} ({shown})",
                                   f"{what} ({shown}) need --expand (LinuxCNC's interpreter)")
        if c0 == "_" or (c0.isalpha() and len(code) > 1 and (code[1].isalpha() or code[1] == "_")):
            return self.extended(n, raw, code)
        if not self.cnc:
            if c0 in "Mm" and _TEXT_CMD.match(code):
                number = float(re.match(r"[Mm]\s*(\d+)", code).group(1))
                if number in _PASS_M:
                    return self.block(n, raw, Kind.PASS)
                if number not in _STOP_M:  # M23/M28/M32/M33/M928: files, maybe printed from here
                    self.forget(self.frame, e_too=True)
                return self.block(n, raw, Kind.STOP)
            if "{" in code:  # an RRF/Klipper expression the firmware evaluates
                self.forget(self.frame, e_too=True)
                return self.block(n, raw, Kind.STOP)

        return self.execute(n, raw, *self._words(n, code))

    def _words(self, n: int, code: str) -> tuple:
        """The words of ``code``: (G numbers, M numbers, T value, {letter: value}, letters given
        twice (None: none), what could not be read (None: nothing)). LinuxCNC takes several
        commands on a line; the printers' firmwares one, the rest its parameters."""
        gcodes = []
        mcodes = []
        tool = None
        params = {}
        dups = None
        junk = None
        multi = self.cnc
        command_seen = False
        for letter, value, bad in _WORD.findall(code):
            if bad:
                if junk is None:
                    junk = bad
                continue
            letter = letter.upper()
            if letter == "G" or letter == "M" or letter == "T":
                if multi or not command_seen:
                    command_seen = True
                    if letter == "T":
                        tool = value
                    else:
                        try:
                            number = float(value)
                        except ValueError:
                            raise self.error(n, f"{letter}{value} is not a number") from None
                        (gcodes if letter == "G" else mcodes).append(number)
                    continue
            elif letter == "N" and not params and not command_seen:
                continue
            if letter in params:
                if dups is None:
                    dups = set()
                dups.add(letter)
            else:
                params[letter] = value
        if junk is not None:
            junk = f"cannot read {code!r}: unexpected {junk!r}"
            if multi:
                raise self.error(n, junk + " (expressions and parameters are not supported)")
        return gcodes, mcodes, tool, params, dups, junk

    def oword(self, n, raw, code) -> Block:
        m = _OWORD.match(code)
        if m is None:
            raise self.error(n, f"cannot read {code!r}")
        if m.group(1):
            message = f"O-word {m.group(1)!r}: subroutines and control flow are not supported"
            if self.cnc:
                raise NeedsInterpreter(self.path, n, "O-words", f"{message}: {_EXPAND_HINT}")
            raise self.error(n, message)
        return self.block(n, raw, Kind.PASS)


class _Commands:
    """The reader's commands that set limits or the position, and the flavors' own commands:
    Klipper's extended commands and macros, M201/M203/M204/M205/M566 per flavor, G4, G92,
    LinuxCNC's G33 (timed by the spindle). Part of ``_Reader``, whose state they change."""

    def extended(self, n, raw, code) -> Block:
        """Klipper extended commands and macros, RRF meta commands: a name, then NAME=VALUE."""
        name = re.match(r"[A-Za-z_][A-Za-z0-9_]*", code).group().upper()
        if name == "SET_VELOCITY_LIMIT":
            values = {}
            for key, value in _EXT_PARAM.findall(code[len(name):]):
                key = key.upper()
                if key in ("VELOCITY", "ACCEL", "SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO", "ACCEL_TO_DECEL"):
                    values[key] = self.number(n, key + "=", value.strip('"'))
            for key, value in values.items():
                if value < 0 or (value == 0 and key not in ("SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO")):
                    raise self.error(n, f"{key}={value:g} must be positive")
            if values.get("MINIMUM_CRUISE_RATIO", 0.0) >= 1.0:
                raise self.error(n, f"MINIMUM_CRUISE_RATIO={values['MINIMUM_CRUISE_RATIO']:g} must be below 1")
            limits = None
            if values:
                limits = PlannerLimits(
                    acceleration_mm_s2=values.get("ACCEL"),
                    travel_acceleration_mm_s2=values.get("ACCEL"),
                    max_velocity_mm_s=values.get("VELOCITY"),
                    square_corner_velocity_mm_s=values.get("SQUARE_CORNER_VELOCITY"),
                    minimum_cruise_ratio=values.get("MINIMUM_CRUISE_RATIO"),
                    accel_to_decel_mm_s2=values.get("ACCEL_TO_DECEL"),
                )
            return self.block(n, raw, Kind.PASS, limits=limits)
        if name in _KLIPPER_PASS:
            return self.block(n, raw, Kind.PASS)
        if name == "SET_INPUT_SHAPER":  # Klipper flushes its look-ahead to change shaping: at rest
            return self.block(n, raw, Kind.STOP)
        # a macro or an unknown command: it may move anything
        self.forget(self.frame, e_too=True)
        return self.block(n, raw, Kind.STOP)

    def limits(self, n, m, params, scale):
        """PlannerLimits of M201/M203/M204/M205/M566, None if nothing is set, False if unknown."""
        def value(letter, factor=1.0, zero_ok=False):
            v = params.get(letter)
            if v is None:
                return None
            x = self.number(n, letter, v) * factor
            if x < 0.0 or (x == 0.0 and not zero_ok):
                raise self.error(n, f"M{m:g} {letter}{v} must be {'non-negative' if zero_ok else 'positive'}")
            return x

        flavor = self.flavor
        if m == 204.0:
            s, p, t = value("S", scale), value("P", scale), value("T", scale)
            if flavor == "klipper":  # Klipper: one acceleration, S or min(P, T)
                if s is None and p is not None and t is not None:
                    s = min(p, t)
                return PlannerLimits(s, s) if s is not None else None
            accel = p if p is not None else s
            travel = t if t is not None else s
            if accel is None and travel is None:
                return None
            return PlannerLimits(acceleration_mm_s2=accel, travel_acceleration_mm_s2=travel)
        if m == 201.0 or m == 203.0:
            factor = scale / 60.0 if (m == 203.0 and flavor == "reprap") else scale
            axes = {a: x for a in AXES if (x := value(a, factor)) is not None}
            slowest = value("I", factor) if (m == 203.0 and flavor == "reprap") else None
            if not axes and slowest is None:
                return None
            if m == 201.0:
                return PlannerLimits(axis_max_acceleration_mm_s2=axes)
            return PlannerLimits(axis_max_velocity_mm_s=axes, min_feed_mm_s=slowest)
        if m == 205.0:
            j = value("J", scale)
            jerks = [x for a in "XY" if (x := value(a, scale, zero_ok=True)) is not None]
            if j is None and not jerks:
                return None
            return PlannerLimits(junction_deviation_mm=j, square_corner_velocity_mm_s=min(jerks) if jerks else None)
        # M566: RRF jerk, mm/min
        if flavor != "reprap":
            return False
        jerks = [x for a in "XY" if (x := value(a, scale / 60.0, zero_ok=True)) is not None]
        return PlannerLimits(square_corner_velocity_mm_s=min(jerks)) if jerks else None

    def dwell(self, n, params, junk) -> float:
        if junk is not None:
            raise self.error(n, junk)
        s = params.get("S")
        p = params.get("P")
        if self.cnc:
            seconds = self.number(n, "P", p) if p is not None else 0.0
        elif s is not None:
            seconds = self.number(n, "S", s)
        elif p is not None:
            seconds = self.number(n, "P", p) / 1000.0
        else:
            seconds = 0.0
        if seconds < 0.0:
            raise self.error(n, "dwell time must not be negative")
        return seconds

    def g92(self, n, params, dups, junk, scale) -> tuple[int, ...]:
        """Sets the program position of the axes named (indices into AXES, which it gives)."""
        if junk is not None:
            raise self.error(n, junk)
        if dups and dups & set("XYZE"):
            raise self.error(n, f"{''.join(sorted(dups))} given twice")
        values = {}
        for i in (*self.frame, _E):
            v = params.get(AXES[i])
            if v is not None:  # E follows G20/G21 too (Marlin)
                values[i] = self.number(n, AXES[i], v) * (1.0 if i in _DEGREES else scale)
        if not values:
            if self.flavor == "klipper":  # Klipper: G92 alone zeroes all axes
                values = {0: 0.0, 1: 0.0, 2: 0.0, 3: 0.0}
            elif self.cnc:
                raise self.error(n, "G92 needs at least one axis word")
            else:  # Marlin, RRF: nothing to set
                return ()
        pos, off = self.pos, self.off
        for i, v in values.items():
            if pos[i] != pos[i]:  # unknown machine position: it is now known in this frame
                pos[i] = v + off[i]
            else:
                off[i] = pos[i] - v
        return tuple(values)

    def synced(self, n, raw, params, start, target, scale) -> Block:
        """LinuxCNC's G33: a move at K (distance along its path) per spindle revolution. A rest of
        the compensated motion, copied as written (never compensated): a STOP at its end that
        lasts its length over K S / 60 (0 from an unknown start; the wait for the spindle's
        index, up to a revolution, is not counted)."""
        pitch_mm = self.number(n, "K", params.get("K")) * scale
        if pitch_mm <= 0.0:
            raise self.error(n, "G33 needs K > 0 (the distance per spindle revolution)")
        if not self.spindle_on or self.css or not (self.spindle_rpm or 0.0) > 0.0:
            raise self.error(n, "G33 needs the spindle turning at a known speed (M3/M4 and S, not G96)")
        self.pos = target
        # along X Y Z (unnamed axes hold the very same floats, NaN included; NaN: an unknown start)
        length_mm = math.hypot(*(t - s for s, t in zip(start[:3], target[:3], strict=True) if s is not t))
        dwell_s = length_mm / (pitch_mm * self.spindle_rpm / 60.0) if length_mm == length_mm else 0.0
        return Block(n, raw, Kind.STOP, self.modal, np.array(target), dwell_s=dwell_s)


class _Motion:
    """The reader's motion: G0/G1 (``fast_move`` for the common line), G2/G3 arcs and G5
    cubic Beziers cut into linear pieces within the chord tolerance, in machine mm. Part of
    ``_Reader``, whose position and modes they use."""

    def fast_move(self, n, raw, g, f1, x, y, z, e, f2) -> Block | None:
        """G0/G1 matched by _FAST_G01: the same as move(), or None to take the general path."""
        if f1 is not None:
            if f2 is not None:
                return None
            f2 = f1
        scale = _INCH if self.inches else 1.0
        if f2 is not None:
            feed = float(f2)
            if feed <= 0.0:
                raise self.error(n, f"feed F{f2.decode()} must be positive")
            self.feed = feed * scale / 60.0
        motion = 1 if g == b"1" else 0
        self.motion = motion
        start = self.pos
        target = start[:]
        off = self.off
        if self.abs_xyz:
            if x is not None:
                target[0] = float(x) * scale + off[0]
            if y is not None:
                target[1] = float(y) * scale + off[1]
            if z is not None:
                target[2] = float(z) * scale + off[2]
        else:
            if x is not None:
                target[0] += float(x) * scale
            if y is not None:
                target[1] += float(y) * scale
            if z is not None:
                target[2] += float(z) * scale
        if e is not None:
            if self.cnc:
                return None
            target[3] = float(e) * scale + off[3] if self.eabs else target[3] + float(e) * scale
        elif x is None and y is None and z is None:
            return Block(n, raw, Kind.PASS, self.modal, np.array(start))
        self.pos = target
        feed = math.inf if (motion == 0 and self.cnc) else self.feed
        if feed is None or ((x is not None and start[0] != start[0]) or (y is not None and start[1] != start[1])
                            or (z is not None and start[2] != start[2]) or (e is not None and start[3] != start[3])):
            return Block(n, raw, Kind.STOP, self.modal, np.array(target))  # from an unknown start
        if target == start:  # (unnamed axes hold the very same float objects, NaN included)
            return Block(n, raw, Kind.PASS, self.modal, np.array(target))
        both = np.array((target, target))  # one allocation: row 0 the position, row 1 the piece
        return Block(n, raw, Kind.MOVE, self.modal, both[0], both[1:], feed)

    def move(self, n, raw, motion, params, dups, junk, scale, stop) -> Block:
        for a in AXES:
            if a in params:
                self.number(n, a, params[a])  # "X", "Xnan", "X1.2.3": name the word first
        if junk is not None:
            raise self.error(n, junk)
        if dups:
            raise self.error(n, f"{''.join(sorted(dups))} given twice")
        if not self.cnc:
            for a in _OTHER_AXES:
                if a in params:
                    raise self.error(n, f"axis {a}: only X Y Z E are supported")
        named = False
        start = self.pos
        target = start[:]
        off = self.off
        for i in self.frame:
            v = params.get(AXES[i])
            if v is not None:
                x = self.number(n, AXES[i], v) * (1.0 if i in _DEGREES else scale)
                target[i] = x + off[i] if self.abs_xyz else target[i] + x
                named = True
        v = params.get("E")
        if v is not None:
            if self.cnc:
                raise self.error(n, f"E{v}: LinuxCNC refuses an E word on a motion line (a number has no "
                                    "exponent there: 1e5 reads as 1, then E5)")
            x = self.number(n, "E", v) * scale
            target[3] = x + off[3] if self.eabs else target[3] + x
            named = True

        if motion != 5:
            self.last_bezier_pq = None  # LinuxCNC: only a G5 right after a G5 may omit I and J
        if motion == 0 and self.cnc:
            feed = math.inf
        else:
            feed = self.feed

        if motion == 33:
            return self.synced(n, raw, params, start, target, scale)
        if motion >= 2:
            if not named and motion == 5:
                raise self.error(n, "G5 needs an end point")
        elif not named:
            return self.block(n, raw, Kind.PASS)  # e.g. "G1 F1800": a feed change

        # the axes this move moves: the named ones, and both axes of an arc's or a Bezier's plane
        moving = [i for i, a in enumerate(AXES) if a in params]
        if motion >= 2:
            moving += _PLANES[self.plane][:2]
        known = all(start[i] == start[i] for i in moving)
        if motion == 2 or motion == 3:
            points = self.arc(n, motion, params, start, target, scale, known)
        elif motion == 5:
            points = self.bezier(n, params, start, target, scale, known)
        else:
            points = None
        self.pos = target
        if not known or stop or feed is None:
            return Block(n, raw, Kind.STOP, self.modal, np.array(target))
        if motion <= 1:
            if target == start:  # (unnamed axes hold the very same float objects, NaN included)
                return Block(n, raw, Kind.PASS, self.modal, np.array(target))
            points = np.array([target])
        elif points is None:
            return Block(n, raw, Kind.PASS, self.modal, np.array(target))
        return Block(n, raw, Kind.MOVE, self.modal, np.array(target), points, feed)

    def arc(self, n, motion, params, start, target, scale, known):
        """The pieces of a G2/G3 arc (None when nothing moves); checks the words even if unknown."""
        a, b, lin, ia, ib = _PLANES[self.plane]
        if "R" in params:
            if ia in params or ib in params:
                raise self.error(n, f"an arc with both R and {ia}/{ib}")
            r = self.number(n, "R", params["R"]) * scale
            if not known:
                return None
            u0, v0, u1, v1 = start[a], start[b], target[a], target[b]
            du, dv = u1 - u0, v1 - v0
            d = math.hypot(du, dv)
            if d == 0.0:
                raise self.error(n, "an R arc must end away from its start")
            if abs(r) < 0.5 * d * (1.0 - 1e-6):
                raise self.error(n, f"arc radius {abs(r):.6g} mm is shorter than half the chord ({0.5 * d:.6g} mm)")
            h = math.sqrt(max(r * r - 0.25 * d * d, 0.0))
            e = -1.0 if (motion == 2) != (r < 0.0) else 1.0
            cu = 0.5 * (u0 + u1) - e * h * dv / d
            cv = 0.5 * (v0 + v1) + e * h * du / d
            full = False
        else:
            iv, jv = params.get(ia), params.get(ib)
            if iv is None and jv is None:
                raise self.error(n, f"an arc needs {ia}/{ib} (center) or R (radius)")
            oi = self.number(n, ia, iv) * scale if iv is not None else 0.0
            oj = self.number(n, ib, jv) * scale if jv is not None else 0.0
            if not self.abs_ijk and oi == 0.0 and oj == 0.0:
                raise self.error(n, f"arc center {ia}=0 {ib}=0: the radius is zero")
            if not known:
                return None
            u0, v0, u1, v1 = start[a], start[b], target[a], target[b]
            if self.abs_ijk:
                cu, cv = oi + self.off[a], oj + self.off[b]
            else:
                cu, cv = u0 + oi, v0 + oj
            full = math.hypot(u1 - u0, v1 - v0) <= 1e-9
        r0 = math.hypot(u0 - cu, v0 - cv)
        r1 = math.hypot(u1 - cu, v1 - cv)
        if r0 <= 1e-9:
            raise self.error(n, "the arc's center is its start: the radius is zero")
        if abs(r1 - r0) > 0.002 and abs(r1 - r0) > 1e-3 * r0:
            raise self.error(n, f"the arc's end is {abs(r1 - r0):.4g} mm off its circle (radius {r0:.6g} mm)")
        t0 = math.atan2(v0 - cv, u0 - cu)
        sweep = math.atan2(v1 - cv, u1 - cu) - t0
        if motion == 3:
            if full or sweep <= 0.0:
                sweep += _TWO_PI
            if full:
                sweep = _TWO_PI
        else:
            if full or sweep >= 0.0:
                sweep -= _TWO_PI
            if full:
                sweep = -_TWO_PI
        turns = params.get("P")
        if turns is not None and (self.cnc or self.flavor == "marlin"):
            # LinuxCNC: P turns in all (P1 = the arc alone); Marlin: P full circles, then the arc
            p = self.number(n, "P", turns)
            first = 1 if self.cnc else 0
            if p < first or p != int(p):
                raise self.error(n, f"arc turns P{turns} must be a whole number >= {first}")
            sweep += math.copysign(_TWO_PI * (p - first), sweep)
        r_max = max(r0, r1)
        if r_max > 0.5 * CHORD_TOLERANCE_MM:
            step = 2.0 * math.acos(1.0 - CHORD_TOLERANCE_MM / r_max)
        else:
            step = math.pi
        count = max(1, math.ceil(abs(sweep) / step), math.ceil(abs(sweep) / (0.5 * math.pi) - 1e-9))
        frac = np.arange(1, count + 1) / count
        theta = t0 + sweep * frac
        radius = r0 + (r1 - r0) * frac
        points = _along(start, target, frac)  # the helical axis, E and the other axes
        points[:, a] = cu + radius * np.cos(theta)
        points[:, b] = cv + radius * np.sin(theta)
        points[-1] = target
        return points

    def bezier(self, n, params, start, target, scale, known):
        """The pieces of a G5 cubic Bezier in the XY plane (None when the start is unknown)."""
        if self.plane != 17:
            raise self.error(n, "G5 is only supported in the XY plane (G17)")
        vals = {}
        for letter in "IJPQ":
            v = params.get(letter)
            vals[letter] = self.number(n, letter, v) * scale if v is not None else None
        if vals["I"] is None and vals["J"] is None and self.cnc:
            if self.last_bezier_pq is None:
                raise self.error(n, "the first G5 needs I and J")
            vals["I"], vals["J"] = -self.last_bezier_pq[0], -self.last_bezier_pq[1]
        elif (vals["I"] is None) != (vals["J"] is None) and self.cnc:
            raise self.error(n, "G5 needs both I and J or neither")
        if self.cnc and (vals["P"] is None or vals["Q"] is None):
            raise self.error(n, "G5 needs P and Q")
        i, j, p, q = (0.0 if vals[k] is None else vals[k] for k in "IJPQ")
        self.last_bezier_pq = (p, q)
        if not known:
            return None
        p0 = np.array([start[0], start[1]])
        p3 = np.array([target[0], target[1]])
        p1 = p0 + (i, j)
        p2 = p3 + (p, q)
        curvature = 6.0 * max(np.hypot(*(p0 - 2 * p1 + p2)), np.hypot(*(p1 - 2 * p2 + p3)))
        # chord error <= h^2/8 max|B''| for a step h in t, and B'' is linear: largest at an end
        count = max(1, math.ceil(math.sqrt(curvature / (8.0 * CHORD_TOLERANCE_MM))))
        t = (np.arange(1, count + 1) / count)[:, None]
        s = 1.0 - t
        xy = s**3 * p0 + 3 * s * s * t * p1 + 3 * s * t * t * p2 + t**3 * p3
        # arc length of each piece: 5-point Gauss-Legendre quadrature of |B'(t)|
        lo = np.arange(count)[:, None] / count
        tq = lo + (_GAUSS_X[None, :] + 1.0) / (2.0 * count)  # (count, 5)
        sq = 1.0 - tq
        d1 = ((3 * sq * sq)[..., None] * (p1 - p0) + (6 * sq * tq)[..., None] * (p2 - p1)
              + (3 * tq * tq)[..., None] * (p3 - p2))
        lengths = (np.hypot(d1[..., 0], d1[..., 1]) * _GAUSS_W).sum(axis=1) / (2.0 * count)
        total = lengths.sum()
        frac = np.cumsum(lengths) / total if total > 0.0 else t[:, 0]
        points = _along(start, target, frac)
        points[:, :2] = xy
        points[-1] = target
        if target == start and count == 1:
            return None
        return points


class _Splines:
    """The reader's LinuxCNC splines: G5.1, G5.2 ... G5.3 and G6.2 NURBS lines, held as a
    ``_Spline`` until its end. Part of ``_Reader``."""

    def spline_line(self, n, raw, motion, params, dups, junk, scale):
        """A G5.1 (its block), or a G5.2 or G6.2 NURBS line: held (None) until the NURBS' end
        gives every line's block."""
        if junk is not None:
            raise self.error(n, junk)
        if dups:
            raise self.error(n, f"{''.join(sorted(dups))} given twice")
        if self.plane != 17:
            raise self.error(n, f"G{motion:g} splines are only supported in the XY plane (G17)")
        for a in "Z" + _OTHER_AXES:
            if a in params:
                raise self.error(n, f"G{motion:g} splines move X and Y only: {a} is not allowed")
        if self.spline is not None and (self.spline.knots is not None) != (motion == 6.2):
            raise self.error(n, f"G{motion:g} inside a {'G6.2' if self.spline.knots is not None else 'G5.2'} NURBS")
        if motion == 6.2:
            return self.g62_line(n, raw, params, scale)
        if motion == 5.3:
            if self.spline is None:
                raise self.error(n, "G5.3 without G5.2 first")
            return self.spline.end(self, n, raw)
        if ("X" in params) != ("Y" in params):
            raise self.error(n, "a spline's control point needs both X and Y")
        xy = None
        if "X" in params:
            xy = [self.number(n, a, params[a]) * scale for a in "XY"]
            xy = [v + self.off[i] if self.abs_xyz else self.pos[i] + v for i, v in enumerate(xy)]
        if motion == 5.1:
            if xy is None or "I" not in params or "J" not in params:
                raise self.error(n, "G5.1 needs X, Y, I and J")
            i, j = (self.number(n, a, params[a]) * scale for a in "IJ")
            x0, y0 = self.pos[0], self.pos[1]
            return _Spline([(x0, y0, 1.0), (x0 + i, y0 + j, 1.0), (*xy, 1.0)], 3, [(n, raw)]).end(self)
        weight = self.number(n, "P", params["P"]) if "P" in params else None
        if self.spline is None:  # G5.2: the first control point is where the tool is
            order = self.number(n, "L", params["L"]) if "L" in params else 3.0
            if order != int(order) or order < 3:
                order = 3.0  # LinuxCNC uses L only above 3
            w0 = weight if xy is None and weight is not None and weight > 0.0 else 1.0
            self.spline = _Spline([(self.pos[0], self.pos[1], w0)], int(order), [])
            if xy is None:
                self.spline.lines.append((n, raw))
                return None
        elif xy is None:
            raise self.error(n, "a NURBS control point needs X and Y")
        if weight is None or weight <= 0.0:
            raise self.error(n, "a NURBS control point needs a positive weight P")
        self.spline.points.append((*xy, weight))
        self.spline.lines.append((n, raw))
        return None

    def g62_line(self, n, raw, params, scale):
        """A line of a G6.2 NURBS (LinuxCNC 2.10): the first gives the order P; each a knot K, and
        a control point X Y with its weight R, or (the last ``order`` lines) a knot alone."""
        if not self.abs_xyz:
            raise self.error(n, "G6.2 in incremental distance mode (G91) is not supported")
        if "K" not in params:
            raise self.error(n, "every G6.2 line needs its knot K")
        spline = self.spline
        if spline is None:
            order = self.number(n, "P", params["P"]) if "P" in params else None
            if order is None or order != int(order) or order < 2:
                raise self.error(n, "the first G6.2 line needs its order P, an integer of at least 2")
            if "X" not in params or "Y" not in params:
                raise self.error(n, "the first G6.2 line needs its first control point (X Y R)")
            first = [self.number(n, a, params[a]) * scale + self.off[i] for i, a in enumerate("XY")]
            if math.dist(first, self.pos[:2]) > 1e-9:  # NaN (unknown start) passes: copied at rest
                raise self.error(n, "a G6.2 NURBS starts at its first control point: X Y must be where the tool is")
            spline = self.spline = _Spline([], int(order), [], knots=[])
        if ("X" in params) != ("Y" in params):
            raise self.error(n, "a G6.2 control point needs both X and Y")
        if "X" in params:
            if len(spline.knots) > len(spline.points):
                raise self.error(n, "a G6.2 control point after the knots that end the NURBS")
            weight = self.number(n, "R", params["R"]) if "R" in params else 0.0
            if weight <= 0.0:
                raise self.error(n, "a G6.2 control point needs a positive weight R")
            spline.points.append((*(self.number(n, a, params[a]) * scale + self.off[i] for i, a in enumerate("XY")),
                                  weight))
        spline.knots.append(self.number(n, "K", params["K"]))
        spline.lines.append((n, raw))
        if len(spline.knots) == len(spline.points) + spline.order:
            return spline.end(self)
        return None


class _Reader(_Words, _Commands, _Motion, _Splines):
    """The interpreter's state between lines and the interpretation of one line."""

    def __init__(self, path: str | Path, flavor: str, home_mm=(0.0, 0.0, 0.0)):
        self.path = path
        self.home_mm = [float(v) for v in home_mm]
        self.flavor = flavor
        self.cnc = flavor == "linuxcnc"
        # machine position: XYZ (and LinuxCNC's other axes) unknown, E at 0 (the printers' other axes never move)
        self.pos = [_NAN, _NAN, _NAN, 0.0] + [_NAN if self.cnc else 0.0] * len(_EXTRA)
        self.off = [0.0] * len(AXES)  # program = machine - off (G92)
        self.frame = (0, 1, 2, *_EXTRA) if self.cnc else (0, 1, 2)  # the axes an unknown frame or command loses
        self.saved_off = None  # G92.2 keeps the offsets here for G92.3
        self.abs_xyz = True
        self.abs_e = True  # as given by M82/M83 (and G90/G91 in Marlin)
        self.inches = False
        self.modal = Modal()
        self.eabs = True  # E words are absolute (the effect of G90/G91 and M82/M83 in this flavor)
        self.motion = None  # last motion mode: 0 1 2 3 5
        self.feed = None  # mm/s
        self.plane = 17  # G17 / G18 / G19 (see _PLANES)
        self.abs_ijk = False  # G90.1
        self.wcs = 54.0
        self.tool_length = False  # G43 active (LinuxCNC)
        self.last_bezier_pq = None  # (P, Q) of the previous G5, mm
        self.spline = None  # an open G5.2 or G6.2 NURBS: its lines are held until its end
        self.spindle_rpm = None  # LinuxCNC's S (rev/min; under G96 a surface speed: css)
        self.spindle_on = False  # M3/M4 (until M5, M19, M2/M30)
        self.css = False  # G96 constant surface speed

    def e_absolute(self) -> bool:
        if self.flavor == "klipper":  # Klipper: E is relative under G91 or M83
            return self.abs_e and self.abs_xyz
        return self.abs_e

    def new_modal(self) -> None:
        self.eabs = self.e_absolute()
        self.modal = Modal(self.abs_xyz, self.eabs, self.inches, tuple(self.off), self.plane)

    def block(self, n, raw, kind, **kw) -> Block:
        return Block(n, raw, kind, self.modal, np.array(self.pos), **kw)

    def forget(self, axes, e_too: bool = False) -> None:
        """The machine position of ``axes`` (indices) is unknown after this line."""
        for i in axes:
            self.pos[i] = _NAN
        if e_too and self.eabs and not self.cnc:  # LinuxCNC has no E: it stays at 0
            self.pos[3] = _NAN

    def execute(self, n, raw, gcodes, mcodes, tool, params, dups, junk) -> Block:
        """The block of a line of words, its commands in LinuxCNC's order of execution: modal
        settings, then the others, then motion."""
        fx = _Effects()
        others = self._modal_gcodes(n, gcodes, fx)
        scale = _INCH if self.inches else 1.0
        self._mcodes(n, mcodes, params, junk, scale, fx)
        if tool is not None:
            fx.kind = Kind.STOP

        if fx.motion is not None:  # name a bad axis word before anything else on the line
            for a in AXES:
                if a in params:
                    self.number(n, a, params[a])

        if self.cnc and "S" in params:
            self.spindle_rpm = self.number(n, "S", params["S"])
        # feed
        f = params.get("F")
        if f is not None and (self.cnc or fx.motion is not None or not (gcodes or mcodes or tool is not None)):
            feed = self.number(n, "F", f)
            if feed <= 0.0:
                raise self.error(n, f"feed F{f} must be positive")
            self.feed = feed * scale / 60.0

        for g in others:
            self._other_gcode(n, g, params, dups, junk, scale, fx)
        if fx.modal_changed:
            self.new_modal()
        return self._executed(n, raw, bool(gcodes or mcodes or tool is not None), params, dups, junk, scale, fx)

    def _modal_gcodes(self, n, gcodes, fx: _Effects) -> list[float]:
        """The line's motion and modal G codes applied; gives the other G codes, in order."""
        flavor = self.flavor
        others = []
        for g in gcodes:
            m = _MOTION.get(g)
            if m is not None:
                if fx.motion is not None:
                    raise self.error(n, "two motion commands on one line")
                fx.motion = m
            elif g == 90.0 or g == 91.0:
                self.abs_xyz = g == 90.0
                if flavor == "marlin":
                    self.abs_e = self.abs_xyz
                fx.modal_changed = True
            elif g == 20.0 or g == 21.0:
                self.inches = g == 20.0
                fx.modal_changed = True
            elif g in _PLANES:
                self.plane = int(g)
                fx.modal_changed = True
            elif g == 90.1 or g == 91.1:
                self.abs_ijk = g == 90.1
            elif self.cnc and g == 33.0:
                if fx.motion is not None:
                    raise self.error(n, "two motion commands on one line")
                fx.motion = 33
            elif g in _UNSUPPORTED_G or (self.cnc and g in _LINUXCNC_INTERPRETED_G):
                if self.cnc:
                    what = _UNSUPPORTED_G.get(g) or _LINUXCNC_INTERPRETED_G[g]
                    raise NeedsInterpreter(self.path, n, what, f"{what} is not supported: {_EXPAND_HINT}")
                raise self.error(n, f"{_UNSUPPORTED_G[g]} is not supported")
            elif g in _NURBS_G or (self.cnc and 5.0 < g < 7.0):
                if self.cnc and g in _NURBS_G:
                    if fx.motion is not None:
                        raise self.error(n, "two motion commands on one line")
                    fx.motion = g
                else:
                    raise self.error(n, f"G{g:g} is not supported (a motion fbspost does not know)")
            elif g in _WCS:
                if g != self.wcs:  # another work coordinate system: offsets we do not know
                    self.wcs = g
                    fx.unknown = True
            elif self.cnc and g in _LINUXCNC_PASS_G:
                if g == 49.0 and self.tool_length:
                    self.tool_length = False
                    self.forget((2,))
                    fx.kind = Kind.STOP
            else:
                if self.cnc and (g == 96.0 or g == 97.0):
                    self.css = g == 96.0
                others.append(g)
        return others

    def _mcodes(self, n, mcodes, params, junk, scale, fx: _Effects) -> None:
        for m in mcodes:
            if self.cnc and m in (2.0, 3.0, 4.0, 5.0, 19.0, 30.0):  # the spindle, for G33's speed
                self.spindle_on = m == 3.0 or m == 4.0
            if m == 82.0 or m == 83.0:
                self.abs_e = m == 82.0
                fx.modal_changed = True
            elif self.cnc and 70.0 <= m <= 73.0:
                raise NeedsInterpreter(self.path, n, f"modal state save and restore (M{m:g})",
                                       f"modal state save and restore (M{m:g}) is not supported: {_EXPAND_HINT}")
            elif self.cnc and (m in _LINUXCNC_PASS_M or m == 66.0):
                fx.axis_words_used |= m in _IO_M  # M66 E0 L3: the input's number, not an extruder
                if m == 66.0:
                    fx.kind = Kind.STOP  # waits for an input
            elif m in _PASS_M or 862.0 <= m < 863.0:
                pass
            elif m in _LIMIT_M:
                if junk is not None:
                    raise self.error(n, junk)
                fx.limits = self.limits(n, m, params, scale)
                if fx.limits is False:
                    fx.unknown = True
                    fx.limits = None
            elif m in _STOP_M:
                fx.kind = Kind.STOP
            else:  # M98 (RRF macro call) and every unknown M code
                fx.unknown = True

    def _other_gcode(self, n, g, params, dups, junk, scale, fx: _Effects) -> None:
        """A G code that is neither motion nor a modal setting: dwell, G92 and its kin, homing,
        probing, offsets, and the unknown ones."""
        if g == 4.0:
            fx.kind = Kind.STOP
            fx.dwell = self.dwell(n, params, junk)
        elif g == 92.0:
            fx.axis_words_used = True
            fx.sets_position = self.g92(n, params, dups, junk, scale)
            fx.modal_changed |= bool(fx.sets_position)
        elif g == 92.1 or (self.cnc and g == 92.2):
            if g == 92.2:
                self.saved_off = self.off[:]
            else:
                self.saved_off = None
            for i in self.frame:
                self.off[i] = 0.0
            fx.modal_changed = True
        elif g == 92.3 and self.cnc:
            if self.saved_off is not None:
                self.off = self.saved_off
                self.saved_off = None
                fx.modal_changed = True
        elif g == 28.0:
            fx.axis_words_used = True
            named = [i for i in self.frame if AXES[i] in params] or self.frame
            if self.cnc:  # LinuxCNC: to the position stored in #5161.., not in the file
                self.forget(named)
            else:  # homing: the homed axes are at the machine's home position
                for i in named:
                    self.pos[i] = self.home_mm[i]
            fx.kind = Kind.STOP
        elif g == 29.0 or g == 30.0 or 38.0 <= g < 39.0:
            fx.axis_words_used = True
            self.forget(self.frame)
            fx.kind = Kind.STOP
        elif g == 10.0 or g == 11.0:
            fx.axis_words_used = True
            fx.kind = Kind.STOP
            if self.cnc or "L" in params or any(a in params for a in "XYZ"):
                fx.unknown = True  # coordinate system or tool offsets
        elif self.cnc and 43.0 <= g < 44.0:
            self.tool_length = True
            fx.axis_words_used = True
            fx.unknown = True
        else:  # G53, G60/G61 (Marlin), G80 (Prusa mesh levelling), ... and unknown G codes
            fx.axis_words_used = True
            fx.unknown = True


    def _executed(self, n, raw, commanded: bool, params, dups, junk, scale, fx: _Effects) -> Block:
        """The line's motion (an explicit G0-G5, or axis words continuing the last motion mode)
        or its block without motion; ``commanded``: the line has a G, M or T command."""
        # motion: an explicit G0-G5, or axis words continuing the last motion mode
        if fx.motion is None and not fx.axis_words_used and (self.cnc or not commanded):
            if ("X" in params or "Y" in params or "Z" in params or "E" in params
                    or (self.cnc and any(a in params for a in _OTHER_AXES))):
                fx.motion = self.motion
                if fx.motion is None:
                    raise self.error(n, "axis words without a motion command (G0/G1/G2/G3/G5)")
        if self.spline is not None or fx.motion in _NURBS_G:
            if (fx.unknown or fx.kind is not Kind.PASS or fx.limits is not None or fx.modal_changed
                    or fx.axis_words_used):
                raise self.error(n, "inside a NURBS only control points (X Y P) and G5.3 are allowed")
            if self.spline is not None and self.spline.knots is not None and fx.motion is None:
                fx.motion = 6.2  # a G6.2 line of a knot alone
            self.motion = None if fx.motion == 5.3 else fx.motion
            return self.spline_line(n, raw, fx.motion, params, dups, junk, scale)
        if fx.motion is not None and not fx.unknown:
            self.motion = fx.motion
            block = self.move(n, raw, fx.motion, params, dups, junk, scale, fx.kind is Kind.STOP)
            if fx.kind is Kind.STOP and block.kind is not Kind.STOP:
                block.kind = Kind.STOP
                block.points_mm = None
                block.feed_mm_s = None
            block.dwell_s += fx.dwell
            block.limits = fx.limits
            return block

        if fx.unknown:  # with a motion too ("G53 G0 Z0"): it moves in a frame fbspost does not know
            if fx.motion is not None:
                self.motion = fx.motion
            self.forget(self.frame, e_too=True)
            fx.kind = Kind.STOP
        return self.block(n, raw, fx.kind, dwell_s=fx.dwell, limits=fx.limits, sets_position=fx.sets_position)


class _Spline:
    """A LinuxCNC spline being read: control points (x, y, weight) in machine mm, its order, its
    knots (G6.2; None: LinuxCNC's uniform ones), and its lines: (line number, bytes) of the
    spline's own lines, Blocks of comments between them."""

    def __init__(self, points, order, lines, knots=None):
        self.points, self.order, self.lines, self.knots = points, order, lines, knots

    def end(self, reader: _Reader, n: int | None = None, raw: bytes | None = None) -> list[Block] | Block:
        """Every held line's block: the curve's pieces shared among the spline's own lines."""
        if n is not None:
            self.lines.append((n, raw))
        reader.spline = None
        ctrl = np.array(self.points)
        if len(ctrl) < self.order:
            raise reader.error(self.lines[-1][0], f"a NURBS of order {self.order} needs at least {self.order} "
                                                  f"control points, this one has {len(ctrl)}")
        start = reader.pos
        knots = None if self.knots is None else self.checked_knots(reader)
        target = start[:]
        target[0], target[1] = ctrl[-1, 0], ctrl[-1, 1]
        reader.pos = target
        own = [i for i, line in enumerate(self.lines) if line.__class__ is not Block]
        moves = start[0] == start[0] and start[1] == start[1] and reader.feed is not None
        if moves:
            xy = _spline_pieces(ctrl, self.order, len(own), knots)
            points = np.tile(np.asarray(start, dtype=float), (len(xy), 1))
            points[:, :2] = xy
            points[-1] = target
            shares = np.array_split(points, len(own))
        out = []
        at = np.array(start)
        for i, line in enumerate(self.lines):
            if line.__class__ is Block:
                line.position_mm = at.copy()  # a comment: where the curve has got to
                out.append(line)
            elif moves:
                piece = shares[own.index(i)]
                at = piece[-1].copy()
                out.append(Block(line[0], line[1], Kind.MOVE, reader.modal, at, piece, reader.feed))
            else:
                out.append(Block(line[0], line[1], Kind.STOP, reader.modal, np.array(target)))
        return out[0] if len(out) == 1 else out


    def checked_knots(self, reader: _Reader) -> np.ndarray:
        """The G6.2 knots, which must not decrease and begin and end ``order`` times alike (the
        curve runs from its first control point to its last)."""
        knots, k, line = np.array(self.knots), self.order, self.lines[-1][0]
        if np.any(np.diff(knots) < 0.0):
            raise reader.error(line, "G6.2 knots K must not decrease")
        if np.ptp(knots[:k]) or np.ptp(knots[-k:]) or knots[0] == knots[-1]:
            raise reader.error(line, f"G6.2 knots must begin with {k} equal knots and end with {k} greater "
                                     f"equal ones (P{k}: the curve from its first control point to its last)")
        return knots


def _along(start: list[float], target: list[float], frac: np.ndarray) -> np.ndarray:
    """(len(frac), len(AXES)): every axis moved linearly from ``start`` to ``target`` by ``frac``."""
    start = np.asarray(start)
    return start + (np.asarray(target) - start) * np.asarray(frac)[:, None]


def nurbs_points(ctrl: np.ndarray, order: int, u: np.ndarray, knots: np.ndarray | None = None) -> np.ndarray:
    """Points (len(u), 2) of a NURBS: control points ``ctrl`` (m, 3: x, y, weight), order k
    (degree k - 1), ``knots`` (m + k, clamped), by default G5.2's: k zeros, 1 .. m - k, k times
    m - k + 1 (``knot_vector_creator``), at parameters ``u`` between knots k - 1 and m.
    Cox-de Boor on the weighted points."""
    m, k = len(ctrl), order
    if knots is None:
        knots = np.concatenate([np.zeros(k), np.arange(1.0, m - k + 1), np.full(k, m - k + 1.0)])
    u = np.asarray(u, dtype=float)[:, None]
    basis = ((knots[:-1] <= u) & (u < knots[1:])).astype(float)  # order 1, half-open spans
    basis[u[:, 0] >= knots[-1], m - 1] = 1.0  # the end belongs to the last span
    for r in range(2, k + 1):
        left_den = knots[r - 1:-1] - knots[:-r]
        right_den = knots[r:] - knots[1:-r + 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            left = np.where(left_den > 0, (u - knots[:-r]) / left_den, 0.0)
            right = np.where(right_den > 0, (knots[r:] - u) / right_den, 0.0)
        basis = left * basis[:, :-1] + right * basis[:, 1:]
    weighted = basis * ctrl[:, 2]
    return (weighted @ ctrl[:, :2]) / weighted.sum(axis=1, keepdims=True)


def _spline_pieces(ctrl: np.ndarray, order: int, at_least: int, knots: np.ndarray | None = None) -> np.ndarray:
    """End points of the chords of the NURBS, every chord within CHORD_TOLERANCE_MM of the curve
    (checked at each chord's middle parameter, with a margin), at least ``at_least`` of them; every
    knot is a chord's end (where a repeated knot makes a corner)."""
    if knots is None:
        knots = np.concatenate([np.zeros(order), np.arange(1.0, len(ctrl) - order + 1),
                                np.full(order, len(ctrl) - order + 1.0)])
    breaks = np.unique(knots[order - 1:len(ctrl) + 1])
    per = max(8, -(-at_least // (len(breaks) - 1)))  # chords per knot span
    while True:
        steps = np.arange(per) / per
        u = np.append((breaks[:-1, None] + np.diff(breaks)[:, None] * steps).ravel(), breaks[-1])
        points = nurbs_points(ctrl, order, u, knots)
        middle = nurbs_points(ctrl, order, 0.5 * (u[1:] + u[:-1]), knots)
        a, b = points[:-1], points[1:]
        chord = b - a
        length2 = np.maximum((chord * chord).sum(axis=1), 1e-300)
        t = np.clip(((middle - a) * chord).sum(axis=1) / length2, 0.0, 1.0)
        off = np.hypot(*(middle - a - t[:, None] * chord).T)
        if off.max() <= 0.5 * CHORD_TOLERANCE_MM or per * len(breaks) >= 1 << 20:
            return points[1:]
        per *= 2


def _strip_comments(text: str) -> str:
    """The line without ';' and '( )' comments, keeping RRF "strings" (which may hold ';')."""
    pieces = []
    pos = 0
    for m in _COMMENT_OR_STRING.finditer(text):
        s = m.group()
        if s == ";":
            pieces.append(text[pos:m.start()])
            return " ".join(pieces)
        if s[0] == "(":
            pieces.append(text[pos:m.start()])
            pos = m.end()
    pieces.append(text[pos:])
    return " ".join(pieces)


# ----------------------------------------------------------------------------------------------
# Flavor detection

_HEAD_LINES = 2000
_TAIL_LINES = 300
_DECLARED = re.compile(r";\s*(?:gcode_flavor\s*=|FLAVOR\s*:)\s*([A-Za-z0-9_]+)", re.IGNORECASE)
_KLIPPER_HINT = re.compile(
    r"^\s*(?:PRINT_START|START_PRINT|PRINT_END|END_PRINT|SET_VELOCITY_LIMIT|SET_PRESSURE_ADVANCE|"
    r"EXCLUDE_OBJECT_\w+|SET_FAN_SPEED|SET_HEATER_TEMPERATURE|BED_MESH_\w+|SET_GCODE_OFFSET|"
    r"TURN_OFF_HEATERS|SET_RETRACTION|SET_PRINT_STATS_INFO)\b",
    re.IGNORECASE,
)
_REPRAP_HINT = re.compile(r'^\s*(?:M98\s*P\s*"|M550\b|M291\b|M292\b|M929\b|M566\b|'
                          r'(?:if|while|var|global|set|echo|abort)\s)|^\s*[GM]\d+[^;]*[A-Z]"', re.IGNORECASE)
_CNC_HINT = re.compile(r"^\s*(?:%\s*$|[Oo]\s*\d+|.*\(.*\)|.*\b[Gg]0*(?:17|64|61|40|49|54|80|94)\b|"
                       r".*\b[Mm]0*(?:2|30)\b)")
_E_WORD = re.compile(r"\s*(?:[Nn]\d+\s*)?[Gg]0*[0-3](?![\d.])[^(]*?(?<![A-Za-z])[Ee]\s*[-+]?\.?\d")


def detect_flavor(path: str | Path) -> str:
    """The flavor (one of FLAVORS) the file at ``path`` is written for, from hints in its first
    2000 and last 300 lines: a slicer's declaration (``; gcode_flavor = ...``, ``;FLAVOR:...``),
    Klipper commands, RepRapFirmware commands and strings, CNC conventions (``%``, O-words,
    parenthesis comments, M2/M30, G17/G64/... without any E word, or the name ``*.ngc``); Marlin
    otherwise.

    Klipper commands win over a declared Marlin flavor (Klipper printers are often sliced as
    Marlin); a declared Klipper or RepRapFirmware flavor wins over everything. Binary content in
    the code of the first lines (a picture, random bytes) raises ``InputError`` naming its line.
    """
    try:
        lines = _head_and_tail(path)
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    declared = None
    klipper = reprap = cnc = e_words = False
    for i, text in enumerate(lines):
        if i < _HEAD_LINES and _BINARY.search(_strip_comments(text.split(";", 1)[0]).strip()):
            raise InputError(path, i + 1, NOT_GCODE)  # (before a binary file is taken for LinuxCNC's)
        m = _DECLARED.search(text)
        if m and declared is None:
            declared = m.group(1).lower()
        code = text.split(";", 1)[0]
        if not code.strip():
            continue
        klipper = klipper or bool(_KLIPPER_HINT.match(code))
        if not code.lstrip().upper().startswith(("M862", "M117", "M118")):
            reprap = reprap or bool(_REPRAP_HINT.match(code))
        cnc = cnc or bool(_CNC_HINT.match(code))
        e_words = e_words or bool(_E_WORD.match(code))
    if declared is not None:
        if declared == "klipper":
            return "klipper"
        if declared.startswith("reprap"):
            return "klipper" if klipper else "reprap"
        if declared in ("mach3", "machinekit", "linuxcnc"):
            return "linuxcnc"
    if declared is None and Path(path).suffix.lower() == ".ngc":  # LinuxCNC's own; no slicer writes it
        return "linuxcnc"
    if klipper:
        return "klipper"
    if reprap:
        return "reprap"
    if declared is None and cnc and not e_words:
        return "linuxcnc"
    return "marlin"


_COMPENSATED = re.compile(
    r"^\s*(?:;|\()\s*(fbspost \S+: filtered B-spline compensation for machine profile .*?)\)?\s*$")


def compensated_by(path: str | Path) -> tuple[int, str] | None:
    """(line, header text) where the file at ``path`` says fbspost compensated it (the header
    ``compensate`` writes among the comments before the first code line); None where not."""
    try:
        with open(path, "rb") as f:
            for line_no, raw in enumerate(f, 1):
                text = raw.decode("utf-8", "replace")
                if m := _COMPENSATED.match(text):
                    return line_no, m.group(1)
                if _strip_comments(text.split(";", 1)[0]).strip():
                    return None
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    return None


def _head_and_tail(path: str | Path) -> list[str]:
    """The first _HEAD_LINES lines and the last _TAIL_LINES lines (each line once), decoded."""
    out = []
    with open(path, "rb") as f:
        for _ in range(_HEAD_LINES):
            raw = f.readline()
            if not raw:
                break
            out.append(raw)
        head_end = f.tell()
        f.seek(0, 2)
        size = f.tell()
        if size > head_end:
            chunk = 1 << 16
            start = size
            data = b""
            while start > head_end and data.count(b"\n") <= _TAIL_LINES:
                start = max(head_end, start - chunk)
                f.seek(start)
                data = f.read(size - start)
            tail = data.split(b"\n")
            if start > head_end:
                tail = tail[1:]  # a partial line
            out.extend(tail[-_TAIL_LINES - 1:])
    return [raw.decode("utf-8", "replace") for raw in out]
