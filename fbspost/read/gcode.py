"""G-code reader: a program's lines as blocks the planner and the writer understand.

Takes a G-code file (bytes, any line endings, any encoding in comments) and a flavor; gives, in
order, one ``Block`` per input line: its number and exact bytes, whether it moves the machine
(MOVE: planned and rewritten by fbspost), passes through while the motion continues (PASS), or
passes through with the machine at rest (STOP), the linear pieces of a move in machine
coordinates (mm, the columns of AXES: X Y Z E, then LinuxCNC's A B C U V W; arcs and Beziers
subdivided), planner-limit changes, and the
modal state after the line. Bad input raises ``errors.InputError`` naming the file and line.

``read_gcode(path, flavor)`` streams the blocks; ``flavors.detect_flavor(path)`` guesses the flavor
from the first 2000 and last 300 lines. How lines are read:

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
  another work coordinate system (G54..G59.3, offsets not in the file) makes XYZ unknown, unless
  the profile gives LinuxCNC's parameter file (``work_offsets_mm``) and the system in use was
  selected by the program: the switch then moves the offsets by the difference of the two
  (positions stay in the frame of the program's first system; a G10 there drops the file's
  offsets, the program setting its own; with the file, a program's first selection loses XYZ). A move
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

The reader's parts, a module each: what it gives (``blocks``: ``Block``, ``Kind``, ``Modal``,
``PlannerLimits``, ``AXES``); a line's words and numbers (``words``); the machine state between
lines (``state``); the commands other than motion (``commands``); G0-G3, G5 and G33
(``motion``); the splines (``splines``); the driver that runs a line through them in LinuxCNC's
order (``reader``). The flavor a file is written for: ``flavors``.
"""
from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..profile import FLAVORS, MachineProfile
from .blocks import AXES, Block
from .reader import Reader

_TRAVEL_BATCH = 256  # blocks checked against the travel at once


def read_gcode(path: str | Path, flavor: str, home_mm=(0.0, 0.0, 0.0), travel_mm=None,
               lines: Iterable[bytes] | None = None, work_offsets_mm=()) -> Iterator[Block]:
    """Blocks of the G-code file ``path`` read as ``flavor`` (one of FLAVORS), one per line, in order.
    ``lines``: the file's lines (with their endings) as they come, read instead of the file (a
    file still being written, ``verify.following``); ``path`` names them in errors.
    ``home_mm``: the X Y Z machine position a G28 leaves the axes it homes at (printers).
    ``work_offsets_mm``: LinuxCNC's G54..G59.3 X Y Z offsets (``LinuxCNCSettings.work_offsets_mm``).
    ``travel_mm``: the lowest and the highest machine position of each axis of AXES
    (``MachineProfile.travel_mm``): a line that moves an axis beyond them is refused, as the
    firmware refuses it (Klipper: "Move out of range"; LinuxCNC's soft limits).

    Streams: the file is read line by line as the iterator is consumed. Raises ``InputError``
    (``FILE:LINE: message``) at the first line it cannot interpret safely, ``ValueError`` at once
    for an unknown flavor.
    """
    if flavor not in FLAVORS:
        raise ValueError(f"unknown G-code flavor {flavor!r}: expected one of {', '.join(FLAVORS)}")
    blocks = _blocks(path, flavor, home_mm, lines, work_offsets_mm)
    if travel_mm is None or not np.isfinite(travel_mm).any():
        return blocks
    return _within_travel(blocks, path, *np.asarray(travel_mm, dtype=float))


def read_on_machine(path: str | Path, flavor: str, profile: MachineProfile, lines: Iterable[bytes] | None = None,
                    within_travel: bool = False) -> Iterator[Block]:
    """``read_gcode`` in ``profile``'s frame: its home (G28) and its LinuxCNC work offsets, and
    with ``within_travel`` its travel (a move beyond it refused)."""
    travel_mm = profile.travel_mm("".join(AXES)) if within_travel else None
    return read_gcode(path, flavor, profile.home_mm, travel_mm, lines, profile.work_offsets_mm)


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


def _blocks(path: str | Path, flavor: str, home_mm, lines: Iterable[bytes] | None, work_offsets_mm) -> Iterator[Block]:
    try:
        handle = open(path, "rb") if lines is None else contextlib.nullcontext(lines)
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    reader = Reader(path, flavor, home_mm, work_offsets_mm)
    line = reader.line
    with handle as source:
        for line_no, raw in enumerate(source, 1):
            block = line(line_no, raw)
            if block.__class__ is Block:
                yield block
            elif block is not None:  # a spline's lines, held until its end
                yield from block
        reader.splines.unended()
