"""The reader's motion: G0/G1, G2/G3 arcs and G5 cubic Beziers, in machine mm.

Takes a line's motion mode and words (``words.Words``) and the machine state (``state.State``:
the position it moves, the offsets and modes it reads); gives the line's ``Block``: G0/G1
(``Motion.fast_move`` for the common line straight from its bytes, else ``Motion.move``), arcs
and Beziers cut into linear pieces within CHORD_TOLERANCE_MM, and LinuxCNC's G33 timed by the
spindle (``commands.Spindle``).
"""
from __future__ import annotations

import math

import numpy as np

from .blocks import AXES, CHORD_TOLERANCE_MM, DEGREES, OTHER_AXES, Block, Kind
from .state import INCH

PLANES = {17.0: (0, 1, 2, "I", "J"), 18.0: (2, 0, 1, "K", "I"), 19.0: (1, 2, 0, "J", "K")}
_TWO_PI = 2.0 * math.pi
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(5)


class Motion:
    """G0-G3, G5 and G33 lines: what it holds of its own is the previous G5's P and Q (a G5 right
    after a G5 may leave out I and J); it moves the state's position."""

    def __init__(self, words, state, spindle):
        self.words, self.state, self.spindle = words, state, spindle
        self.last_bezier_pq = None  # (P, Q) of the previous G5, mm

    def fast_move(self, n, raw, g, f1, x, y, z, e, f2) -> Block | None:
        """G0/G1 matched by ``words.FAST_G01``: the same as move(), or None to take the general path."""
        words, state = self.words, self.state
        if f1 is not None:
            if f2 is not None:
                return None
            f2 = f1
        scale = INCH if state.inches else 1.0
        if f2 is not None:
            feed = float(f2)
            if feed <= 0.0:
                raise words.error(n, f"feed F{f2.decode()} must be positive")
            state.feed = feed * scale / 60.0
        motion = 1 if g == b"1" else 0
        state.motion = motion
        start = state.pos
        target = start[:]
        off = state.off
        if state.abs_xyz:
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
            if state.cnc:
                return None
            target[3] = float(e) * scale + off[3] if state.eabs else target[3] + float(e) * scale
        elif x is None and y is None and z is None:
            return Block(n, raw, Kind.PASS, state.modal, np.array(start))
        state.pos = target
        feed = math.inf if (motion == 0 and state.cnc) else state.feed
        if feed is None or ((x is not None and start[0] != start[0]) or (y is not None and start[1] != start[1])
                            or (z is not None and start[2] != start[2]) or (e is not None and start[3] != start[3])):
            return Block(n, raw, Kind.STOP, state.modal, np.array(target), feed_mm_s=feed)  # from an unknown start
        if target == start:  # (unnamed axes hold the very same float objects, NaN included)
            return Block(n, raw, Kind.PASS, state.modal, np.array(target))
        both = np.array((target, target))  # one allocation: row 0 the position, row 1 the piece
        return Block(n, raw, Kind.MOVE, state.modal, both[0], both[1:], feed)

    def move(self, n, raw, motion, params, dups, junk, scale, stop) -> Block:
        words, state = self.words, self.state
        for a in AXES:
            if a in params:
                words.number(n, a, params[a])  # "X", "Xnan", "X1.2.3": name the word first
        if junk is not None:
            raise words.error(n, junk)
        if dups:
            raise words.error(n, f"{''.join(sorted(dups))} given twice")
        if not state.cnc:
            for a in OTHER_AXES:
                if a in params:
                    raise words.error(n, f"axis {a}: only X Y Z E are supported")
        named = False
        start = state.pos
        target = start[:]
        off = state.off
        for i in state.frame:
            v = params.get(AXES[i])
            if v is not None:
                x = words.number(n, AXES[i], v) * (1.0 if i in DEGREES else scale)
                target[i] = x + off[i] if state.abs_xyz else target[i] + x
                named = True
        v = params.get("E")
        if v is not None:
            if state.cnc:
                raise words.error(n, f"E{v}: LinuxCNC refuses an E word on a motion line (a number has no "
                                     "exponent there: 1e5 reads as 1, then E5)")
            x = words.number(n, "E", v) * scale
            target[3] = x + off[3] if state.eabs else target[3] + x
            named = True

        if motion != 5:
            self.last_bezier_pq = None  # LinuxCNC: only a G5 right after a G5 may omit I and J
        if motion == 0 and state.cnc:
            feed = math.inf
        else:
            feed = state.feed

        if motion == 33:
            return self.spindle.synced(n, raw, params, start, target, scale, state)
        if motion >= 2:
            if not named and motion == 5:
                raise words.error(n, "G5 needs an end point")
        elif not named:
            return state.block(n, raw, Kind.PASS)  # e.g. "G1 F1800": a feed change

        # the axes this move moves: the named ones, and both axes of an arc's or a Bezier's plane
        moving = [i for i, a in enumerate(AXES) if a in params]
        if motion >= 2:
            moving += PLANES[state.plane][:2]
        known = all(start[i] == start[i] for i in moving)
        if motion == 2 or motion == 3:
            points = _arc(words, state, n, motion, params, start, target, scale, known)
        elif motion == 5:
            points = self.bezier(n, params, start, target, scale, known)
        else:
            points = None
        state.pos = target
        if not known or stop or feed is None:
            return Block(n, raw, Kind.STOP, state.modal, np.array(target), feed_mm_s=feed)
        if motion <= 1:
            if target == start:  # (unnamed axes hold the very same float objects, NaN included)
                return Block(n, raw, Kind.PASS, state.modal, np.array(target))
            points = np.array([target])
        elif points is None:
            return Block(n, raw, Kind.PASS, state.modal, np.array(target))
        return Block(n, raw, Kind.MOVE, state.modal, np.array(target), points, feed)

    def bezier(self, n, params, start, target, scale, known):
        """The pieces of a G5 cubic Bezier in the XY plane (None when the start is unknown)."""
        words, state = self.words, self.state
        if state.plane != 17:
            raise words.error(n, "G5 is only supported in the XY plane (G17)")
        vals = {}
        for letter in "IJPQ":
            v = params.get(letter)
            vals[letter] = words.number(n, letter, v) * scale if v is not None else None
        if vals["I"] is None and vals["J"] is None and state.cnc:
            if self.last_bezier_pq is None:
                raise words.error(n, "the first G5 needs I and J")
            vals["I"], vals["J"] = -self.last_bezier_pq[0], -self.last_bezier_pq[1]
        elif (vals["I"] is None) != (vals["J"] is None) and state.cnc:
            raise words.error(n, "G5 needs both I and J or neither")
        if state.cnc and (vals["P"] is None or vals["Q"] is None):
            raise words.error(n, "G5 needs P and Q")
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


def _arc(words, state, n, motion, params, start, target, scale, known):
    """The pieces of a G2/G3 arc (None when nothing moves); checks the words even if unknown."""
    a, b, lin, ia, ib = PLANES[state.plane]
    if "R" in params:
        if ia in params or ib in params:
            raise words.error(n, f"an arc with both R and {ia}/{ib}")
        r = words.number(n, "R", params["R"]) * scale
        if not known:
            return None
        u0, v0, u1, v1 = start[a], start[b], target[a], target[b]
        du, dv = u1 - u0, v1 - v0
        d = math.hypot(du, dv)
        if d == 0.0:
            raise words.error(n, "an R arc must end away from its start")
        if abs(r) < 0.5 * d * (1.0 - 1e-6):
            raise words.error(n, f"arc radius {abs(r):.6g} mm is shorter than half the chord ({0.5 * d:.6g} mm)")
        h = math.sqrt(max(r * r - 0.25 * d * d, 0.0))
        e = -1.0 if (motion == 2) != (r < 0.0) else 1.0
        cu = 0.5 * (u0 + u1) - e * h * dv / d
        cv = 0.5 * (v0 + v1) + e * h * du / d
        full = False
    else:
        iv, jv = params.get(ia), params.get(ib)
        if iv is None and jv is None:
            raise words.error(n, f"an arc needs {ia}/{ib} (center) or R (radius)")
        oi = words.number(n, ia, iv) * scale if iv is not None else 0.0
        oj = words.number(n, ib, jv) * scale if jv is not None else 0.0
        if not state.abs_ijk and oi == 0.0 and oj == 0.0:
            raise words.error(n, f"arc center {ia}=0 {ib}=0: the radius is zero")
        if not known:
            return None
        u0, v0, u1, v1 = start[a], start[b], target[a], target[b]
        if state.abs_ijk:
            cu, cv = oi + state.off[a], oj + state.off[b]
        else:
            cu, cv = u0 + oi, v0 + oj
        full = math.hypot(u1 - u0, v1 - v0) <= 1e-9
    r0 = math.hypot(u0 - cu, v0 - cv)
    r1 = math.hypot(u1 - cu, v1 - cv)
    if r0 <= 1e-9:
        raise words.error(n, "the arc's center is its start: the radius is zero")
    if abs(r1 - r0) > 0.002 and abs(r1 - r0) > 1e-3 * r0:
        raise words.error(n, f"the arc's end is {abs(r1 - r0):.4g} mm off its circle (radius {r0:.6g} mm)")
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
    if turns is not None and (state.cnc or state.flavor == "marlin"):
        # LinuxCNC: P turns in all (P1 = the arc alone); Marlin: P full circles, then the arc
        p = words.number(n, "P", turns)
        first = 1 if state.cnc else 0
        if p < first or p != int(p):
            raise words.error(n, f"arc turns P{turns} must be a whole number >= {first}")
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


def _along(start: list[float], target: list[float], frac: np.ndarray) -> np.ndarray:
    """(len(frac), len(AXES)): every axis moved linearly from ``start`` to ``target`` by ``frac``."""
    start = np.asarray(start)
    return start + (np.asarray(target) - start) * np.asarray(frac)[:, None]
