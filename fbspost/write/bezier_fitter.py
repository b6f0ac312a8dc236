"""The candidate G5 blocks of one command, fitted and checked (``bezier.fit_g5``'s search asks).

Takes the command (rows of samples, X and Y first), the tolerance and the shortest curve; gives
for batches of candidate blocks [start, end] their fits judged on a few of their points
(``Fitter.screen``), carried on to convergence (``polish``) and their errors at every sample
and midpoint (``check``), as ``CandidateFit``: control points, lengths, errors of the curve and of the
straight line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bezier_lsq import (
    DAMPING,
    EXTRAS,
    FIT_STEPS,
    GL_W,
    GL_X,
    curve_speeds,
    entries_per_block,
    fit_curves,
    line_error,
    ragged,
    stretch,
    xy_error,
)

_ALONG = 2.0  # tolerances: candidates whose distance along the path is further from linear in time
#               than this are not fitted



_RETRY = 5.0  # tolerances: a long block that missed by at most this is fitted again, undamped



_GRID = 32  # the arc length is inverted on this many equal parameter steps per curve



@dataclass
class CandidateFit:
    """Fitted candidate blocks, one column or entry per block."""

    q: np.ndarray  # (4, b): p1x, p1y, p2x, p2y
    length_mm: np.ndarray  # XY arc length of the curve
    curve_mm: np.ndarray  # largest error of the curve (inf: shorter than min_length_mm)
    line_mm: np.ndarray  # largest error of the straight line, linear in time
    exact: np.ndarray  # the errors are over all of the block's points (else: over the fitted ones)

    ENTRIES = ("length_mm", "curve_mm", "line_mm", "exact")

    @property
    def error_mm(self) -> np.ndarray:
        return np.minimum(self.curve_mm, self.line_mm)

    def take(self, index) -> CandidateFit:
        return CandidateFit(self.q[:, index], *(getattr(self, name)[index] for name in self.ENTRIES))

    def put(self, index, other: CandidateFit, other_index=slice(None)) -> None:
        self.q[:, index] = other.q[:, other_index]
        for name in self.ENTRIES:
            getattr(self, name)[index] = getattr(other, name)[other_index]



class Fitter:
    """Fits and checks batches of candidate blocks [start, end] of one command."""

    def __init__(self, command: np.ndarray, tolerance_mm: float, min_length_mm: float, step_mm: float = 0.0):
        """Points to fit and check at: the samples and the midpoints between them (half index
        2k: sample k; 2k + 1: halfway to sample k + 1), so that a curve cannot slip away from
        the command between samples. An XY midpoint may be met by cubic interpolation
        (quadratic at the data's ends), standing for a smooth command, or by linear
        interpolation, for a command with corners (where the cubic overshoots): the error there
        is the distance to the nearer. The further columns' midpoints are linear."""
        n = len(command)
        self.xy = np.ascontiguousarray(command[:, :2].T)
        mid = 0.5 * (command[:-1] + command[1:])
        if n >= 3:
            mid[:, :2] = np.concatenate([
                (3.0 * command[:1, :2] + 6.0 * command[1:2, :2] - command[2:3, :2]) / 8.0,
                (9.0 * (command[1:-2, :2] + command[2:-1, :2]) - command[:-3, :2] - command[3:, :2]) / 16.0,
                (3.0 * command[-1:, :2] + 6.0 * command[-2:-1, :2] - command[-3:-2, :2]) / 8.0])
        half = np.empty((2 * n - 1, command.shape[1]))
        half[0::2], half[1::2] = command, mid
        self.half = [np.ascontiguousarray(half[:, i]) for i in range(command.shape[1])]
        half[1::2, :2] = 0.5 * (command[:-1, :2] + command[1:, :2])
        self.chords = [np.ascontiguousarray(half[:, i]) for i in range(2)]  # XY with linear midpoints
        # Distance along the path through the samples (and the midpoints), from the first sample.
        self.path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(half[:, :2], axis=0).T))])
        self.tolerance_mm = tolerance_mm
        self.min_length_mm = min_length_mm
        self.step_mm = step_mm

    def points(self, starts, ends, most):
        """Up to ``most`` + 1 points of each block, evenly spread on its half-sample grid, laid
        end to end: each block's first point, each point's block, its time fraction and its
        half index; and whether a block's points are all of its half-sample points."""
        half_steps = 2 * (ends - starts)
        counts = np.minimum(half_steps, most) + 1
        first, block, i = ragged(counts)
        j = i * half_steps[block] // (counts - 1)[block]
        return first, block, j / half_steps[block], 2 * starts[block] + j, half_steps <= most

    def line(self, starts, ends) -> np.ndarray:
        """Control points (rows p1x, p1y, p2x, p2y) of the chord at constant speed: its thirds."""
        p0, p3 = self.xy[:, starts], self.xy[:, ends]
        return np.concatenate([p0 + (p3 - p0) / 3.0, p3 - (p3 - p0) / 3.0])

    def fit_points(self, starts, ends, most):
        """Up to ``most`` + 1 points of each block (see points) as rows: tau, the command's XY
        (cubic midpoints), the block's end points, the command's XY with linear midpoints, then
        (value, start, end) per further column; and the layout."""
        first, block, tau, idx, exact = self.points(starts, ends, most)
        ends_xy = [*np.take(self.xy[:, starts], block, axis=1), *np.take(self.xy[:, ends], block, axis=1)]
        extras = [(e[idx], e[2 * starts][block], e[2 * ends][block]) for e in self.half[2:]]
        pts = np.array([tau, self.half[0][idx], self.half[1][idx], *ends_xy, self.chords[0][idx], self.chords[1][idx],
                        *sum(extras, ())])
        return pts, first, block, idx, exact

    def screen(self, starts: np.ndarray, ends: np.ndarray, prior: CandidateFit | None = None,
               prior_steps: np.ndarray | None = None) -> CandidateFit:
        """Fits judged on at most FIT_STEPS + 1 of each block's points (samples and
        midpoints), evenly spread.

        A block whose straight line, linear in time, is within the tolerance keeps it (the
        curve with p1, p2 at the chord's thirds moves exactly so). A block whose distance along
        the command's path is further than _ALONG tolerances from linear in time is not fitted:
        a curve at constant speed moves its own arc length linearly in time, and the path
        through the samples follows that to within about the sample errors (on a sliced print
        this skipped 1 % of the candidates a fit would have passed). The others are fitted
        (see fit_curves), from the linear least-squares fit or, where given, from the curve
        ``prior`` fitted to the first ``prior_steps`` steps of the same start, stretched along
        itself to the block's length (the search's candidates share their start: a sub-curve
        or extension of a curve is the same polynomial, so a constant-speed curve's fit carries
        over, where the linear fit can start far from it).
        """
        pts, first, block, idx, exact = self.fit_points(starts, ends, FIT_STEPS)
        line = self.line(starts, ends)
        line_max = line_error(pts, first)
        chord = np.hypot(*(self.xy[:, ends] - self.xy[:, starts]))
        fit = CandidateFit(line, chord, np.where(line_max <= self.tolerance_mm, line_max, np.inf), line_max, exact)
        path, path0, path3 = self.path[idx], self.path[2 * starts], self.path[2 * ends]
        along = np.maximum.reduceat(np.abs(path - path0[block] - pts[0] * (path3 - path0)[block]), first)
        fit_them = (line_max > self.tolerance_mm) & (along <= _ALONG * self.tolerance_mm)
        counts = entries_per_block(first, pts.shape[1])

        def refit(subset, start=None, damping=DAMPING):
            """Fit the blocks ``subset`` from ``start`` (None: the linear fit); keep what is better."""
            q, length, err = fit_curves(np.compress(subset[block], pts, axis=1), counts[subset],
                                        line[:, subset], self.tolerance_mm, q=start, damping=damping)
            better = err < fit.curve_mm[subset]
            where = np.flatnonzero(subset)[better]
            fit.q[:, where], fit.length_mm[where], fit.curve_mm[where] = q[:, better], length[better], err[better]

        warm = np.zeros_like(fit_them) if prior is None else fit_them & (prior_steps > 0) & (prior.curve_mm < np.inf)
        if (fit_them & ~warm).any():
            refit(fit_them & ~warm)
        if warm.any():
            prior_end = self.xy[:, starts[warm] + prior_steps[warm]]
            refit(warm, stretch(self.xy[:, starts[warm]], prior.q[:, warm], prior_end,
                                prior.length_mm[warm] * (ends - starts)[warm] / prior_steps[warm]))
        # Long blocks that missed, once more: from the linear fit where the prior led astray, by
        # undamped steps from their best curve where they missed by at most _RETRY tolerances.
        missed = fit_them & ~exact & (fit.curve_mm > self.tolerance_mm)
        if (missed & warm).any():
            refit(missed & warm)
        again = missed & ~warm & (fit.curve_mm <= _RETRY * self.tolerance_mm)
        if again.any():
            refit(again, fit.q[:, again], damping=0.0)
        fit.curve_mm[~(fit.length_mm >= self.min_length_mm)] = np.inf  # too short to carry the block's time
        return fit

    def polish(self, starts: np.ndarray, ends: np.ndarray, fit: CandidateFit) -> CandidateFit:
        """Fits carried on to convergence by undamped Gauss-Newton steps from ``fit`` (damping
        helps the search's many short, nearly straight candidates, but slows the last digits),
        kept where the check finds them better."""
        pts, first, _, _, _ = self.fit_points(starts, ends, FIT_STEPS)
        q, _, _ = fit_curves(pts, entries_per_block(first, pts.shape[1]), self.line(starts, ends), self.tolerance_mm,
                             q=fit.q, damping=0.0, good=0.0)
        better = self.check(starts, ends, q)
        keep = ~(better.curve_mm < fit.curve_mm)
        better.put(keep, fit, keep)
        return better

    def check(self, starts: np.ndarray, ends: np.ndarray, q: np.ndarray) -> CandidateFit:
        """Errors of the curves ``q`` at every point (samples and midpoints) of their blocks.

        The arc length is tabulated on _GRID equal steps of u and inverted at each point's
        tau_k L by monotone cubic Hermite interpolation (slopes 1 / speed) and a Newton step.
        The inversion's miss |s(u_k) - tau_k L|, s integrated again from the table's node, is
        added to the distance |B(u_k) - c_k|: the error bounds the distance from the curve point
        at arc-length fraction tau_k, up to the quadrature's error.
        """
        nb = len(starts)
        p0, p3 = self.xy[:, starts], self.xy[:, ends]
        if self.step_mm:  # as written: the offsets from the ends rounded
            q = np.concatenate([p0 + np.rint((q[:2] - p0) / self.step_mm) * self.step_mm,
                                p3 + np.rint((q[2:] - p3) / self.step_mm) * self.step_mm])
        d0, d1, d2 = q[:2] - p0, q[2:] - q[:2], p3 - q[2:]
        a, b, c = 3.0 * d0, 6.0 * (d1 - d0), 3.0 * (d0 - 2.0 * d1 + d2)  # B'(u) = a + u (b + u c), (2, nb)
        grid = np.arange(_GRID + 1) / _GRID
        nodes = (grid[:-1, None] + GL_X / _GRID).ravel()
        s = np.zeros((nb, _GRID + 1))
        np.cumsum(curve_speeds(a, b, c, nodes).reshape(nb, _GRID, len(GL_X)) @ GL_W / _GRID, axis=1, out=s[:, 1:])
        sigma = curve_speeds(a, b, c, grid)
        length = s[:, -1]

        pts, first, block, _, _ = self.fit_points(starts, ends, 2 * int((ends - starts).max()))
        tau, cx, cy, x0, y0 = pts[:5]
        offset = np.zeros(nb)
        np.cumsum(length[:-1] + 1.0, out=offset[1:])  # keeps blocks apart in one sorted key
        target = tau * length[block]
        j = np.searchsorted((s + offset[:, None]).ravel(), target + offset[block], side="right") - 1
        j = np.clip(j - block * (_GRID + 1), 0, _GRID - 1)
        flat = block * (_GRID + 1) + j  # into the (nb, _GRID + 1) tables
        s0, s1 = s.ravel().take(flat), s.ravel().take(flat + 1)
        h = s1 - s0
        with np.errstate(all="ignore"):
            t = np.clip(np.where(h > 0, (target - s0) / h, 0.0), 0.0, 1.0)
            # Slopes du/dt capped at 3 du (Fritsch-Carlson): monotone where the speed nearly vanishes.
            m0 = np.minimum(h / sigma.ravel().take(flat), 3.0 / _GRID)
            m1 = np.minimum(h / sigma.ravel().take(flat + 1), 3.0 / _GRID)
        t2, t3 = t * t, t * t * t
        u0 = grid[j]
        u = u0 + (3 * t2 - 2 * t3) / _GRID + (t3 - 2 * t2 + t) * m0 + (t3 - t2) * m1
        (ax, ay), (bx, by), (c2x, c2y) = (np.take(v, block, axis=1) for v in (a, b, c))

        def arc(u):  # s(u), from the table's node u0
            s_u = s0.copy()
            for x, w in zip(GL_X, GL_W, strict=True):
                v = u0 + x * (u - u0)
                dx, dy = ax + v * (bx + v * c2x), ay + v * (by + v * c2y)
                s_u += w * (u - u0) * np.sqrt(dx * dx + dy * dy)
            return s_u

        dx, dy = ax + u * (bx + u * c2x), ay + u * (by + u * c2y)
        with np.errstate(all="ignore"):  # one Newton step on the interpolated parameter
            u = np.clip(u - np.nan_to_num((arc(u) - target) / np.sqrt(dx * dx + dy * dy)), u0, u0 + 1.0 / _GRID)
        s_u = arc(u)
        bx_u = x0 + u * (ax + u * (0.5 * bx + u * c2x / 3.0))
        by_u = y0 + u * (ay + u * (0.5 * by + u * c2y / 3.0))
        curve_max = np.maximum.reduceat(xy_error(bx_u, by_u, pts) + np.abs(s_u - target), first)
        for ce, e0, e3 in pts[EXTRAS:].reshape(-1, 3, len(u)):
            curve_max = np.maximum(curve_max, np.maximum.reduceat(np.abs(e0 + (e3 - e0) * u - ce), first))
        curve_max[~(length >= self.min_length_mm)] = np.inf
        return CandidateFit(q, length, curve_max, line_error(pts, first), np.ones(nb, bool))

