"""The reader's LinuxCNC splines: G5.1, and G5.2 ... G5.3 and G6.2 NURBS, as LinuxCNC evaluates them.

Takes a spline's lines (their words, ``words.Words``) and the machine state (``state.State``:
where the curve starts, the offsets, the feed); gives, at the spline's end, every line held
with its share of the curve (``Splines``: the open spline, a ``_Spline``, is what it holds), the
curve cut into pieces within CHORD_TOLERANCE_MM, every knot a chord's end; ``nurbs_points``
evaluates a NURBS (``nurbs_additional_functions.cc``).
"""
from __future__ import annotations

import math

import numpy as np

from .blocks import CHORD_TOLERANCE_MM, OTHER_AXES, Block, Kind


class Splines:
    """The splines' lines: an open G5.2 or G6.2 NURBS holds its lines until its end."""

    def __init__(self, words, state):
        self.words, self.state = words, state
        self.spline = None  # an open G5.2 or G6.2 NURBS: its lines are held until its end

    def hold(self, block: Block) -> None:
        """A comment or blank line inside the open NURBS: given with the NURBS' lines."""
        self.spline.lines.append(block)

    def unended(self) -> None:
        """At the program's end: an InputError if a NURBS is still open."""
        if self.spline is not None:
            first = self.spline.lines[0][0]
            if self.spline.knots is not None:
                raise self.words.error(first, f"G6.2 NURBS never ended ({self.spline.order} lines of its last knot "
                                              "alone, K, end it)")
            raise self.words.error(first, "G5.2 without G5.3 (the NURBS is never ended)")

    def spline_line(self, n, raw, motion, params, dups, junk, scale):
        """A G5.1 (its block), or a G5.2 or G6.2 NURBS line: held (None) until the NURBS' end
        gives every line's block."""
        words, state = self.words, self.state
        if junk is not None:
            raise words.error(n, junk)
        if dups:
            raise words.error(n, f"{''.join(sorted(dups))} given twice")
        if state.plane != 17:
            raise words.error(n, f"G{motion:g} splines are only supported in the XY plane (G17)")
        for a in "Z" + OTHER_AXES:
            if a in params:
                raise words.error(n, f"G{motion:g} splines move X and Y only: {a} is not allowed")
        if self.spline is not None and (self.spline.knots is not None) != (motion == 6.2):
            raise words.error(n, f"G{motion:g} inside a {'G6.2' if self.spline.knots is not None else 'G5.2'} NURBS")
        if motion == 5.1 and self.spline is not None:  # (LinuxCNC's rs274 refuses the program too)
            raise words.error(n, "G5.1 inside a G5.2 NURBS: end the NURBS with G5.3 first")
        if motion == 6.2:
            return self.g62_line(n, raw, params, scale)
        if motion == 5.3:
            if self.spline is None:
                raise words.error(n, "G5.3 without G5.2 first")
            return self._end(self.spline, n, raw)
        if ("X" in params) != ("Y" in params):
            raise words.error(n, "a spline's control point needs both X and Y")
        xy = None
        if "X" in params:
            xy = [words.number(n, a, params[a]) * scale for a in "XY"]
            xy = [v + state.off[i] if state.abs_xyz else state.pos[i] + v for i, v in enumerate(xy)]
        if motion == 5.1:
            if xy is None or "I" not in params or "J" not in params:
                raise words.error(n, "G5.1 needs X, Y, I and J")
            i, j = (words.number(n, a, params[a]) * scale for a in "IJ")
            x0, y0 = state.pos[0], state.pos[1]
            return self._end(_Spline([(x0, y0, 1.0), (x0 + i, y0 + j, 1.0), (*xy, 1.0)], 3, [(n, raw)]))
        weight = words.number(n, "P", params["P"]) if "P" in params else None
        if self.spline is None:  # G5.2: the first control point is where the tool is
            order = words.number(n, "L", params["L"]) if "L" in params else 3.0
            if order != int(order) or order < 3:
                order = 3.0  # LinuxCNC uses L only above 3
            w0 = weight if xy is None and weight is not None and weight > 0.0 else 1.0
            self.spline = _Spline([(state.pos[0], state.pos[1], w0)], int(order), [])
            if xy is None:
                self.spline.lines.append((n, raw))
                return None
        elif xy is None:
            raise words.error(n, "a NURBS control point needs X and Y")
        if weight is None or weight <= 0.0:
            raise words.error(n, "a NURBS control point needs a positive weight P")
        self.spline.points.append((*xy, weight))
        self.spline.lines.append((n, raw))
        return None

    def g62_line(self, n, raw, params, scale):
        """A line of a G6.2 NURBS (LinuxCNC 2.10): the first gives the order P; each a knot K, and
        a control point X Y with its weight R, or (the last ``order`` lines) a knot alone."""
        words, state = self.words, self.state
        if not state.abs_xyz:
            raise words.error(n, "G6.2 in incremental distance mode (G91) is not supported")
        if "K" not in params:
            raise words.error(n, "every G6.2 line needs its knot K")
        spline = self.spline
        if spline is None:
            order = words.number(n, "P", params["P"]) if "P" in params else None
            if order is None or order != int(order) or order < 2:
                raise words.error(n, "the first G6.2 line needs its order P, an integer of at least 2")
            if "X" not in params or "Y" not in params:
                raise words.error(n, "the first G6.2 line needs its first control point (X Y R)")
            first = [words.number(n, a, params[a]) * scale + state.off[i] for i, a in enumerate("XY")]
            if math.dist(first, state.pos[:2]) > 1e-9:  # NaN (unknown start) passes: copied at rest
                raise words.error(n, "a G6.2 NURBS starts at its first control point: X Y must be where the tool is")
            spline = self.spline = _Spline([], int(order), [], knots=[])
        if ("X" in params) != ("Y" in params):
            raise words.error(n, "a G6.2 control point needs both X and Y")
        if "X" in params:
            if len(spline.knots) > len(spline.points):
                raise words.error(n, "a G6.2 control point after the knots that end the NURBS")
            weight = words.number(n, "R", params["R"]) if "R" in params else 0.0
            if weight <= 0.0:
                raise words.error(n, "a G6.2 control point needs a positive weight R")
            spline.points.append((*(words.number(n, a, params[a]) * scale + state.off[i] for i, a in enumerate("XY")),
                                  weight))
        spline.knots.append(words.number(n, "K", params["K"]))
        spline.lines.append((n, raw))
        if len(spline.knots) == len(spline.points) + spline.order:
            return self._end(spline)
        return None

    def _end(self, spline: _Spline, n: int | None = None, raw: bytes | None = None) -> list[Block] | Block:
        """``spline`` ended (by the line ``n``, ``raw``, if given): no NURBS is open any more."""
        self.spline = None
        return spline.end(self.words, self.state, n, raw)


class _Spline:
    """A LinuxCNC spline being read: control points (x, y, weight) in machine mm, its order, its
    knots (G6.2; None: LinuxCNC's uniform ones), and its lines: (line number, bytes) of the
    spline's own lines, Blocks of comments between them."""

    def __init__(self, points, order, lines, knots=None):
        self.points, self.order, self.lines, self.knots = points, order, lines, knots

    def end(self, words, state, n: int | None = None, raw: bytes | None = None) -> list[Block] | Block:
        """Every held line's block: the curve's pieces shared among the spline's own lines."""
        if n is not None:
            self.lines.append((n, raw))
        ctrl = np.array(self.points)
        if len(ctrl) < self.order:
            raise words.error(self.lines[-1][0], f"a NURBS of order {self.order} needs at least {self.order} "
                                                 f"control points, this one has {len(ctrl)}")
        start = state.pos
        knots = None if self.knots is None else self.checked_knots(words)
        target = start[:]
        target[0], target[1] = ctrl[-1, 0], ctrl[-1, 1]
        state.pos = target
        own = [i for i, line in enumerate(self.lines) if line.__class__ is not Block]
        moves = start[0] == start[0] and start[1] == start[1] and state.feed is not None
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
                out.append(Block(line[0], line[1], Kind.MOVE, state.modal, at, piece, state.feed))
            else:
                out.append(Block(line[0], line[1], Kind.STOP, state.modal, np.array(target)))
        return out[0] if len(out) == 1 else out

    def checked_knots(self, words) -> np.ndarray:
        """The G6.2 knots, which must not decrease and begin and end ``order`` times alike (the
        curve runs from its first control point to its last)."""
        knots, k, line = np.array(self.knots), self.order, self.lines[-1][0]
        if np.any(np.diff(knots) < 0.0):
            raise words.error(line, "G6.2 knots K must not decrease")
        if np.ptp(knots[:k]) or np.ptp(knots[-k:]) or knots[0] == knots[-1]:
            raise words.error(line, f"G6.2 knots must begin with {k} equal knots and end with {k} greater "
                                    f"equal ones (P{k}: the curve from its first control point to its last)")
        return knots


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
