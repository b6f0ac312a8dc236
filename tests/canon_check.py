"""No silently wrong output for LinuxCNC programs, checked against LinuxCNC's own interpreter.

``path_problems``: the program fbspost compensated (the expansion, or the original when it
needed none), re-read by fbspost's reader with compensation off, against rs274's canonical moves
of the original: every point the reader gives lies on a canonical move (a line, or an arc: its
radius and its axis' travel, or a G5/G5.1 spline as rs274 evaluates it, ``rs274_splines``: its
Bezier curve in Bernstein form), moving forward through them, and every canonical move's end is
among the reader's points, in order.
``command_problems``: rs274 run on fbspost's output gives the same non-motion canonical calls
(spindle, coolant, tools, dwells, I/O, messages, stops, program end, probe on/off, spindle
synchronization with its pitch), in order, as on the original, besides the dwells fbspost adds
(the unused end of a run's settle margin), and the same probes' targets.
The canonical geometry here is evaluated on its own (not with fbspost.read.expand's code).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fbspost.read.blocks import AXES, Kind
from fbspost.read.expand import MOTION_CALLS, STATE_CALLS, canonical_calls
from fbspost.read.gcode import read_gcode

_PLANE_AXES = {"CANON_PLANE_XY": (0, 1, 2), "CANON_PLANE_YZ": (1, 2, 0), "CANON_PLANE_XZ": (2, 0, 1)}


def canonical_moves(calls, with_tool: bool) -> tuple[list[tuple], float, list[np.ndarray]]:
    """rs274's moves as (start, end, arc) in mm (degrees), X Y Z A B C, with the G92 (and tool
    length) offsets added; arc = (centre, first, second, axis, turns) or None. Also the largest
    unit (mm) seen and the probes' targets (a probe ends where it stops: the next move's start
    is not compared)."""
    scale, unit, g92, tool = 1.0, 1.0, np.zeros(6), np.zeros(6)
    plane, pos, moves, last_pq, probes = "CANON_PLANE_XY", np.zeros(6), [], None, []

    def values(args):  # X Y Z in the program's unit, A B C in degrees
        return np.array([float(a) for a in args[:6]] + [0.0] * (6 - len(args[:6]))) * ([scale] * 3 + [1.0] * 3)

    for name, args in calls:
        if name == "USE_LENGTH_UNITS":
            scale = 25.4 if args[0] == "CANON_UNITS_INCHES" else 1.0
            unit = max(unit, scale)
        elif name == "SET_G92_OFFSET":
            g92 = values(args)
        elif name == "USE_TOOL_LENGTH_OFFSET" and with_tool:
            tool = values(args)
        elif name == "SET_G5X_OFFSET":
            pos = None  # a new frame: the next move's start is not compared
        elif name == "SELECT_PLANE":
            plane = args[0]
        elif name == "STRAIGHT_PROBE":  # (code, axes, x, y, z, ...): rs274_probes
            probes.append(values(args[2:]) + g92 + tool)
            pos = None
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED"):
            end = values(args) + g92 + tool
            moves.append((pos, end, None))
            pos = end
        elif name == "SPLINE_FEED":  # G5/G5.1 (rs274_splines), XY: its Bezier control points
            dx, dy, i, j, p, q = (None if v is None else float(v) * scale for v in args[1:7])
            if args[0] == "G5" and i is None:
                i, j = -last_pq[0], -last_pq[1]
            end = pos.copy()
            end[:2] += [dx, dy]
            ctrl = [pos[:2], pos[:2] + [i, j]] + ([end[:2] + [p, q]] if args[0] == "G5" else []) + [end[:2]]
            last_pq = (p, q) if args[0] == "G5" else None
            moves.append((pos, end, ("bezier", _bezier(np.array(ctrl)))))
            pos = end
        elif name == "ARC_FEED":
            a, b, c = _PLANE_AXES[plane]
            v = [float(x) for x in args]
            end, centre = np.zeros(6), np.zeros(6)
            end[a], end[b], end[c] = v[0], v[1], v[5]
            end[3:] = v[6:9]
            centre[a], centre[b] = v[2], v[3]
            end, centre = end * ([scale] * 3 + [1.0] * 3) + g92 + tool, centre * scale + g92 + tool
            moves.append((pos, end, (centre, a, b, c, int(v[4]))))
            pos = end
    return moves, unit, probes


_XYZABC = [AXES.index(a) for a in "XYZABC"]


def reader_points(program: str | Path) -> list[np.ndarray]:
    """Every position fbspost's reader puts the tool at, in order (X Y Z A B C, NaN where
    unknown: a line fbspost copies as it is, where LinuxCNC's path is its own by construction)."""
    points = []
    for block in read_gcode(program, "linuxcnc"):
        if block.kind is Kind.MOVE:
            points.extend(block.points_mm[:, _XYZABC])
        elif block.kind is Kind.STOP:
            points.append(block.position_mm[_XYZABC])
    return points


def _bezier(ctrl: np.ndarray, count: int = 20001) -> np.ndarray:
    """Points of the Bezier curve of control points ``ctrl`` (Bernstein form), dense."""
    t = np.linspace(0.0, 1.0, count)[:, None]
    d = len(ctrl) - 1
    return sum(math.comb(d, k) * t ** k * (1 - t) ** (d - k) * ctrl[k] for k in range(d + 1))


def _off_polyline(point, line) -> float:
    a, d = line[:-1], np.diff(line, axis=0)
    t = np.clip(((point - a) * d).sum(1) / np.maximum((d * d).sum(1), 1e-300), 0.0, 1.0)
    return float(np.hypot(*(point - a - t[:, None] * d).T).min())


def _off_move(point, start, end, arc) -> float:
    """Distance of ``point`` from the move (NaN coordinates left out)."""
    known = ~np.isnan(point)
    if arc is not None and isinstance(arc[0], str):  # a Bezier: X Y along it, the other axes where they are
        rest = np.nan_to_num((point - end)[2:])
        return math.hypot(_off_polyline(np.nan_to_num(point[:2]), arc[1]) if known[0] and known[1] else 0.0, *rest)
    if arc is None or start is None:
        if start is None:
            return float(np.linalg.norm((point - end)[known]))
        d = end - start
        t = np.clip(np.dot(np.nan_to_num(point - start) * known, d) / max(np.dot(d, d), 1e-300), 0.0, 1.0)
        return float(np.linalg.norm((point - start - t * d)[known]))
    centre, a, b, c, _ = arc
    r0 = math.hypot(start[a] - centre[a], start[b] - centre[b])
    r1 = math.hypot(end[a] - centre[a], end[b] - centre[b])
    r = math.hypot(point[a] - centre[a], point[b] - centre[b])
    radial = max(
        0.0, min(abs(r - r0), abs(r - r1)) if min(r0, r1) <= r <= max(r0, r1) else min(abs(r - r0), abs(r - r1))
    )
    # the arc's axis and A B C move linearly: within their ranges
    lo, hi = np.minimum(start, end)[[c, 3, 4, 5]], np.maximum(start, end)[[c, 3, 4, 5]]
    linear = np.nan_to_num(np.maximum(np.maximum(lo - point[[c, 3, 4, 5]], point[[c, 3, 4, 5]] - hi), 0.0))
    return math.hypot(radial if known[a] and known[b] else 0.0, *linear)


def path_problems(original: str | Path, compensated_input: str | Path, expanded: bool,
                  tool_table: str | Path | None = None, tolerance_mm: float = 1e-3,
                  ini: str | Path | None = None) -> list[str]:
    """Where the reader's path of ``compensated_input`` leaves rs274's path of ``original`` by more
    than ``tolerance_mm`` (plus rs274's printed rounding, 0.0001 of the program's unit)."""
    moves, unit, _ = canonical_moves(canonical_calls(original, tool_table, ini), with_tool=expanded)
    tol = tolerance_mm + 1.5e-4 * unit
    points = reader_points(compensated_input)
    k = 0  # every point on a canonical move, in order
    for p in points:
        if np.isnan(p).all():
            continue  # a line copied as it is
        while k < len(moves) and _off_move(p, *moves[k]) > tol:
            k += 1
        if k == len(moves):
            return [f"point {np.round(p, 4)} is on no canonical move (in order) within {tol * 1e3:.2f} um"]
    j = 0  # every canonical move's end reached, in order
    for k, (_, end, _) in enumerate(moves):
        while j < len(points) and _off_move(points[j], None, end, None) > tol:
            j += 1
        if j == len(points):
            return [f"canonical move {k + 1} ending at {np.round(end, 4)} is never reached (in order)"]
    return []


def _normalized(calls):
    out, scale = [], 1.0
    for name, args in calls:
        if name == "USE_LENGTH_UNITS":
            scale = 25.4 if args[0] == "CANON_UNITS_INCHES" else 1.0
        if name in MOTION_CALLS or name in STATE_CALLS or name in ("START_CHANGE", "CHANGE_TOOL"):
            continue
        if name == "SET_MOTION_CONTROL_MODE":
            args = args[:1]  # its tolerance is in the program's units
        if name == "START_SPEED_FEED_SYNC":  # G33's pitch, in the program's units: mm per revolution, 0.1 um
            args = [f"{float(args[0]) * scale:.4f}", *args[1:]]
        out.append((name, [round(float(a), 6) if _is_number(a) else a for a in args]))
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _without_added_dwells(want, got):
    """``got`` without the dwells fbspost adds (the unused end of a run's settle margin, at
    rest): a dwell of the output that is not the next of the program's calls."""
    kept, i = [], 0
    for call in got:
        if call[0] == "DWELL" and (i >= len(want) or want[i] != call):
            continue
        kept.append(call)
        i += 1
    return kept


def command_problems(original: str | Path, output: str | Path, tool_table: str | Path | None = None,
                     ini: str | Path | None = None) -> list[str]:
    """Differences between the non-motion canonical calls of ``original`` and of ``output``.
    The blending mode (SET_MOTION_CONTROL_MODE) is compared where the programs end: the output
    sets its own around the compensated blocks (transparency) and gives back the program's."""
    calls = [canonical_calls(path, tool_table, ini) for path in (original, output)]
    probes = [canonical_moves(c, with_tool=True) for c in calls]
    if len(probes[0][2]) != len(probes[1][2]):
        return [f"{len(probes[0][2])} probes expected, {len(probes[1][2])} written"]
    tol = 1e-3 + 1.5e-4 * probes[0][1]
    for i, (w, g) in enumerate(zip(probes[0][2], probes[1][2], strict=True)):
        if np.abs(w - g).max() > tol:
            return [f"probe {i + 1}: expected the target {np.round(w, 4)}, got {np.round(g, 4)}"]
    want, got = (_normalized(c) for c in calls)
    modes = [[c for c in calls if c[0] == "SET_MOTION_CONTROL_MODE"][-1:] for calls in (want, got)]
    if modes[0] and modes[0] != modes[1]:
        return [f"the program ends in {modes[0]}, the output in {modes[1]}"]
    want, got = ([c for c in calls if c[0] != "SET_MOTION_CONTROL_MODE"] for calls in (want, got))
    got = _without_added_dwells(want, got)
    for i, (w, g) in enumerate(zip(want, got, strict=True)):
        if w != g:
            return [f"non-motion command {i + 1}: expected {w}, got {g}"]
    if len(want) != len(got):
        return [f"{len(want)} non-motion commands expected, {len(got)} written"]
    return []
