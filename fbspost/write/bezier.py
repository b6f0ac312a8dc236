"""Cubic Bézier G5 blocks fitted to a sampled command, within a tolerance.

Takes the command (n samples on a uniform time grid, machine mm; X and Y first, then any
further columns such as Z and E), the tolerance and the block length limits in samples; gives
contiguous blocks that start and end exactly on command samples, each a cubic Bézier curve in
XY, written ``G5 I J P Q X Y [Z E] F`` with (I, J) = p1 - start, (P, Q) = p2 - end and
F = length_mm / duration, or a G1 block where no curve can carry the block's time.

The controller's model (Marlin and LinuxCNC G5, G17 plane): the tool moves along the curve at
the constant feed F, so at time fraction tau of a block it is at arc-length fraction tau of
the curve. Further columns move linearly in the Bézier parameter u, not in arc length: that is
what Marlin does (planner_bezier.cpp interpolates Z and E with the curve parameter, with a
FIXME saying so); LinuxCNC has no E and rejects Z words in G5, so a LinuxCNC writer gives only
XY, or keeps Z moves out of G5 blocks itself. Neither controller follows the exact curve:
Marlin cuts it into chords (at least 5, up to 0.1 mm off the curve), LinuxCNC into 16 biarcs.

A block is a G5 block when the curve point at arc-length fraction tau_k is within the
tolerance of the command's XY, and every further column within the tolerance of its linear
interpolation in that point's u_k, at every sample k and at every midpoint between samples (so
that a curve cannot slip away between them; see _Fitter), and the curve is at least
``min_length_mm`` long: a shorter one cannot carry the block's time (at zero XY length the
controller would time the block by E). Otherwise it is a G1 block when every column is within
the tolerance of its linear interpolation in time: XY at rest while Z or E move, or a dwell.
The caller writes those as G1 (G4 where nothing moves), and may write any G5 block whose
control points lie on the chord's thirds (a straight line) as G1.

Blocks are chosen greedily, each as long as the tolerance allows within [min_samples,
max_samples]; where even min_samples exceed the tolerance, the minimum wins (``error_mm``
tells by how much). Each candidate is fitted by least squares for p1 and p2 with the end
points fixed, in the arc-length parameterization (Gauss-Newton from the linear fit at the time
fractions), on at most 33 of its points; the chosen block is then checked at every point. For
speed the command is cut into chunks searched in lock step, one numpy pass per candidate in
every chunk; the search is then redone across each chunk edge, from the block before it to the
second after it, and kept where it takes fewer blocks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Search
_CHUNKS = 4096  # lock-step lanes: enough to amortize numpy's per-call cost
_MIN_CHUNK = 256  # samples (unless max_samples is less): a chunk edge can still cost a block
_GROW = 2.0  # largest growth of a passing candidate's length
_ALONG = 2.0  # tolerances: candidates whose distance along the path is further from linear in time
#               than this are not fitted
# Fit
_FIT_STEPS = 32  # a longer candidate is fitted on this many half-sample steps, evenly spread
_MAX_STEPS = 4  # Gauss-Newton steps after the linear fit, at most (_MAX_STEPS_LONG: blocks
_MAX_STEPS_LONG = 16  # fitted on _FIT_STEPS + 1 points, which are few and may need more)
_DAMPING = 1e-2  # Levenberg-Marquardt damping of the first step, relative to the normal matrix's trace,
_DECAY = 0.3  # and its factor from step to step
_GOOD = 0.5  # tolerances: a fit stops at errors below this (_GOOD_LONG: blocks fitted on _FIT_STEPS + 1
_GOOD_LONG = 0.01  # points, whose curve seeds the search's next candidate),
_SETTLE = 1e-3  # at steps below this,
_PROGRESS = 0.8  # or when its error shrank by less than this factor in _PATIENCE steps (twice that for
_PATIENCE = 2  # blocks fitted on _FIT_STEPS + 1 points)
_RETRY = 5.0  # tolerances: a long block that missed by at most this is fitted again, undamped
_REGULARIZATION = 1e-9  # relative pull of p1, p2 towards the chord's thirds: decides blocks of 1 or 2 steps
# Check
_GRID = 32  # the arc length is inverted on this many equal parameter steps per curve
# Gauss-Legendre on [0, 1], 3 nodes: exact for speeds polynomial of degree 5 in u; on a step h of
# u the error is below h^7 max|d^6 speed / du^6| / 2016000, and the speed of a passing curve is smooth.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(3)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


@dataclass(frozen=True)
class G5Blocks:
    """Blocks covering samples 0 .. n-1: block i runs from sample ``starts[i]`` to ``ends[i]``."""

    ends: np.ndarray  # (m,) sample index of each block's end; starts are 0 and ends[:-1]
    p1_mm: np.ndarray  # (m, 2) first control point, absolute XY
    p2_mm: np.ndarray  # (m, 2) second control point, absolute XY
    curve: np.ndarray  # (m,) True: G5 block; False: G1 block (p1, p2 then on the chord's thirds)
    length_mm: np.ndarray  # (m,) XY length of the curve (G1: of the chord): F = length / duration
    error_mm: np.ndarray  # (m,) largest deviation over the block's samples, midpoints and columns

    @property
    def starts(self) -> np.ndarray:
        return np.concatenate([[0], self.ends[:-1]]).astype(self.ends.dtype)


def fit_g5(command_mm: np.ndarray, tolerance_mm: float, min_samples: int = 1, max_samples: int = 2000,
           min_length_mm: float = 1e-3, step_mm: float = 0.0) -> G5Blocks:
    """G5 (and, where needed, G1) blocks for ``command_mm`` (n, d >= 2; X, Y first), see the module.
    ``step_mm``: the written resolution of I J P Q; the curves are checked as written, rounded to
    it (a short curve that turns back is timed by an arc length that rounding changes a lot)."""
    command = np.asarray(command_mm, dtype=float)
    n = len(command)
    if command.ndim != 2 or command.shape[1] < 2:
        raise ValueError("command_mm must be (n, d >= 2), X and Y first")
    if not 1 <= min_samples <= max_samples:
        raise ValueError("need 1 <= min_samples <= max_samples")
    if not tolerance_mm > 0:
        raise ValueError("tolerance_mm must be positive")
    if n < 2:
        empty = np.zeros((0, 2))
        return G5Blocks(np.zeros(0, np.int64), empty, empty, np.zeros(0, bool), np.zeros(0), np.zeros(0))
    fitter = _Fitter(command, tolerance_mm, min_length_mm, step_mm)
    chunk = max(-(-(n - 1) // _CHUNKS), min(max_samples, _MIN_CHUNK))
    edges = np.append(np.arange(0, n - 1, chunk), n - 1)
    limits = (tolerance_mm, min_samples, max_samples)
    starts, ends, fit = _search(fitter, edges[:-1], edges[1:], edges[1:] == n - 1, *limits)
    for parity in (0, 1):  # neighbouring edges' windows may overlap: every other edge at a time
        starts, ends, fit = _search_across(fitter, starts, ends, fit, edges[1 + parity:-1:2], n, *limits)
    curve = (fit.curve_mm <= tolerance_mm) | (fit.curve_mm <= fit.line_mm)
    polish = np.flatnonzero(curve & (2 * (ends - starts) > _FIT_STEPS) & (fit.line_mm > tolerance_mm))
    if polish.size:  # long fitted curves
        fit.put(polish, fitter.polish(starts[polish], ends[polish], fit.take(polish)))
    line = fitter.line(starts, ends)
    q = np.where(curve, fit.q, line)  # a G1 block reports the straight line
    chord = np.hypot(*(command[ends, :2] - command[starts, :2]).T)
    return G5Blocks(ends, q[:2].T.copy(), q[2:].T.copy(), curve, np.where(curve, fit.length_mm, chord),
                    np.where(curve, fit.curve_mm, fit.line_mm))


@dataclass
class _Fit:
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

    def take(self, index) -> _Fit:
        return _Fit(self.q[:, index], *(getattr(self, name)[index] for name in self.ENTRIES))

    def put(self, index, other: _Fit, other_index=slice(None)) -> None:
        self.q[:, index] = other.q[:, other_index]
        for name in self.ENTRIES:
            getattr(self, name)[index] = getattr(other, name)[other_index]


def _allowed_lengths(rest, g, open_end, min_samples: int, max_samples: int) -> tuple:
    """Block lengths ``g`` with ``rest`` samples left clipped to [shortest, longest] and moved off
    tails shorter than min_samples (unless ``open_end``); and the shortest."""
    cannot_split = (rest < 2 * min_samples) & (rest <= max_samples) & ~open_end
    shortest = np.where(cannot_split, rest, np.minimum(min_samples, rest))
    g = np.clip(g, shortest, np.minimum(max_samples, rest))
    tail = rest - g
    short_tail = (tail > 0) & (tail < min_samples) & ~open_end
    return np.where(short_tail, np.maximum(rest - min_samples, shortest), g), shortest


def _next_length(low, high, err_low, err_high, tolerance_mm: float) -> np.ndarray:
    """The next candidate length from the bracket [longest pass ``low``, shortest fail ``high``]
    (0: none yet) and their errors."""
    with np.errstate(all="ignore"):
        grow = low * np.clip((tolerance_mm / err_low) ** 0.5, 1.25, _GROW)  # no failure yet
        shrink = high * np.clip((tolerance_mm / err_high) ** 0.5, 0.25, 0.8)  # no pass yet
        # Both known: log(error) linear in log(length), solved for the tolerance.
        p = np.maximum(np.log(err_high / err_low) / np.log(high / low), 0.5)
        between = low * (tolerance_mm / err_low) ** (1.0 / p)
    margin = np.maximum(1, (high - low) // 8)
    between = np.clip(np.nan_to_num(between), low + margin, high - margin)
    g = np.where((low > 0) & (high > 0), between, np.where(high > 0, shrink, np.maximum(grow, low + 1)))
    return np.nan_to_num(g).astype(np.int64)


def _search(fitter, pos, stop, open_end, tolerance_mm, min_samples, max_samples):
    """Greedy blocks from each ``pos`` to its ``stop``, all of these lanes in lock step.

    Each lane searches its block's length: from the previous block's length it grows until a
    candidate fails, then narrows the bracket [longest pass, shortest fail], each next candidate
    guessed from the errors at the bracket's ends (error ~ length^p, p from the two), until it
    is closed. Candidates are judged on their fitted points; the chosen one is then checked at
    every point, and the search goes on below it if it fails there. A lane's last block leaves
    no tail shorter than min_samples, unless the lane is ``open_end`` (the data's end).
    """
    lanes = len(pos)
    pos = pos.copy()
    lo = np.zeros(lanes, np.int64)  # longest passing length (0: none yet)
    hi = np.zeros(lanes, np.int64)  # shortest failing length (0: none yet)
    err_lo, err_hi = np.zeros(lanes), np.zeros(lanes)
    cand = np.full(lanes, 4 * min_samples, np.int64)
    best_steps = np.zeros(lanes, np.int64)  # length of the candidate in best (0: none)
    best = _Fit(np.zeros((4, lanes)), np.zeros(lanes), np.zeros(lanes), np.zeros(lanes), np.zeros(lanes, bool))
    out_start, out_end, out_fit = [], [], []

    def allowed(lane, g):
        return _allowed_lengths(stop[lane] - pos[lane], g, open_end[lane], min_samples, max_samples)

    def next_length(lane):
        g = _next_length(lo[lane], hi[lane], err_lo[lane], err_hi[lane], tolerance_mm)
        return allowed(lane, g)[0]

    active = np.flatnonzero(pos < stop)
    cand[active] = allowed(active, cand[active])[0]
    while active.size:
        c = cand[active]
        fit = fitter.screen(pos[active], pos[active] + c, best.take(active), best_steps[active])
        err = fit.error_mm
        shortest = allowed(active, c)[1]
        forced = (err > tolerance_mm) & (c == shortest)  # the minimum wins over the tolerance
        passed = (err <= tolerance_mm) | forced
        best.put(active[passed], fit, passed)
        best_steps[active[passed]] = c[passed]
        lo[active[passed]], err_lo[active[passed]] = c[passed], err[passed]
        hi[active[~passed]], err_hi[active[~passed]] = c[~passed], err[~passed]

        low, high = lo[active], hi[active]
        nxt = next_length(active)
        top = np.minimum(max_samples, stop[active] - pos[active])
        done = forced | ((low > 0) & (((high > 0) & ((high - low <= 1) | (nxt >= high)))
                                      | (low == top) | (nxt <= low)))
        cand[active] = nxt

        fin = active[done]
        unchecked = fin[~best.exact[fin]]
        if unchecked.size:
            best.put(unchecked, fitter.check(pos[unchecked], pos[unchecked] + lo[unchecked], best.q[:, unchecked]))
        bad = (best.error_mm[fin] > tolerance_mm) & (lo[fin] > allowed(fin, lo[fin])[1])
        retry, fin = fin[bad], fin[~bad]
        if retry.size:  # failed on the samples between the fitted ones: search below
            hi[retry], err_hi[retry], lo[retry] = lo[retry], best.error_mm[retry], 0
            cand[retry] = next_length(retry)
        if fin.size:
            out_start.append(pos[fin].copy())
            out_end.append(pos[fin] + lo[fin])
            out_fit.append(best.take(fin))
            pos[fin] += lo[fin]
            cand[fin] = allowed(fin, lo[fin])[0]  # the next block starts from this one's length
            lo[fin] = hi[fin] = best_steps[fin] = 0
        active = active[pos[active] < stop[active]]

    starts = np.concatenate(out_start)
    order = np.argsort(starts, kind="stable")
    fits = _Fit(np.concatenate([f.q for f in out_fit], axis=1),
                *(np.concatenate([getattr(f, name) for f in out_fit]) for name in _Fit.ENTRIES))
    return starts[order], np.concatenate(out_end)[order], fits.take(order)


def _search_across(fitter, starts, ends, fit, edges, n, tolerance_mm, min_samples, max_samples):
    """Search again across chunk edges: from the start of the block before each edge to the end
    of the second block after it, kept where it takes fewer blocks (a chunk's first block starts
    at its edge, not where the greedy search from the chunk before would have started it)."""
    right = np.searchsorted(starts, edges)
    right = right[starts[np.minimum(right, len(starts) - 1)] == edges]  # still a block boundary
    left, far = right - 1, np.minimum(right + 1, len(starts) - 1)
    keep = np.ones(len(left), bool)
    keep[1:] = starts[left[1:]] >= ends[far[:-1]]  # windows apart
    left, far = left[keep], far[keep]
    if not left.size:
        return starts, ends, fit
    new_starts, new_ends, new_fit = _search(fitter, starts[left], ends[far], ends[far] == n - 1,
                                            tolerance_mm, min_samples, max_samples)
    window = np.searchsorted(starts[left], new_starts, side="right") - 1  # each new block's window
    fewer = np.bincount(window, minlength=len(left)) < far - left + 1
    old = np.ones(len(starts), bool)
    for a, b in zip(left[fewer], far[fewer], strict=True):
        old[a:b + 1] = False
    new = fewer[window]
    order = np.argsort(np.concatenate([starts[old], new_starts[new]]), kind="stable")
    merged = _Fit(np.concatenate([fit.q[:, old], new_fit.q[:, new]], axis=1),
                  *(np.concatenate([getattr(fit, name)[old], getattr(new_fit, name)[new]]) for name in _Fit.ENTRIES))
    return (np.concatenate([starts[old], new_starts[new]])[order], np.concatenate([ends[old], new_ends[new]])[order],
            merged.take(order))


def _ragged(counts):
    """For blocks of ``counts`` entries laid end to end: each block's first entry, each entry's
    block and its index within the block."""
    first = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=first[1:])
    block = np.repeat(np.arange(len(counts)), counts)
    return first, block, np.arange(int(counts.sum())) - first[block]


class _Fitter:
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
        first, block, i = _ragged(counts)
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

    def screen(self, starts: np.ndarray, ends: np.ndarray, prior: _Fit | None = None,
               prior_steps: np.ndarray | None = None) -> _Fit:
        """Fits judged on at most _FIT_STEPS + 1 of each block's points (samples and
        midpoints), evenly spread.

        A block whose straight line, linear in time, is within the tolerance keeps it (the
        curve with p1, p2 at the chord's thirds moves exactly so). A block whose distance along
        the command's path is further than _ALONG tolerances from linear in time is not fitted:
        a curve at constant speed moves its own arc length linearly in time, and the path
        through the samples follows that to within about the sample errors (on a sliced print
        this skipped 1 % of the candidates a fit would have passed). The others are fitted
        (see _fit_curves), from the linear least-squares fit or, where given, from the curve
        ``prior`` fitted to the first ``prior_steps`` steps of the same start, stretched along
        itself to the block's length (the search's candidates share their start: a sub-curve
        or extension of a curve is the same polynomial, so a constant-speed curve's fit carries
        over, where the linear fit can start far from it).
        """
        pts, first, block, idx, exact = self.fit_points(starts, ends, _FIT_STEPS)
        line = self.line(starts, ends)
        line_max = _line_error(pts, first)
        chord = np.hypot(*(self.xy[:, ends] - self.xy[:, starts]))
        fit = _Fit(line, chord, np.where(line_max <= self.tolerance_mm, line_max, np.inf), line_max, exact)
        path, path0, path3 = self.path[idx], self.path[2 * starts], self.path[2 * ends]
        along = np.maximum.reduceat(np.abs(path - path0[block] - pts[0] * (path3 - path0)[block]), first)
        fit_them = (line_max > self.tolerance_mm) & (along <= _ALONG * self.tolerance_mm)
        counts = _counts(first, pts.shape[1])

        def refit(subset, start=None, damping=_DAMPING):
            """Fit the blocks ``subset`` from ``start`` (None: the linear fit); keep what is better."""
            q, length, err = _fit_curves(np.compress(subset[block], pts, axis=1), counts[subset],
                                         line[:, subset], self.tolerance_mm, q=start, damping=damping)
            better = err < fit.curve_mm[subset]
            where = np.flatnonzero(subset)[better]
            fit.q[:, where], fit.length_mm[where], fit.curve_mm[where] = q[:, better], length[better], err[better]

        warm = np.zeros_like(fit_them) if prior is None else fit_them & (prior_steps > 0) & (prior.curve_mm < np.inf)
        if (fit_them & ~warm).any():
            refit(fit_them & ~warm)
        if warm.any():
            prior_end = self.xy[:, starts[warm] + prior_steps[warm]]
            refit(warm, _stretch(self.xy[:, starts[warm]], prior.q[:, warm], prior_end,
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

    def polish(self, starts: np.ndarray, ends: np.ndarray, fit: _Fit) -> _Fit:
        """Fits carried on to convergence by undamped Gauss-Newton steps from ``fit`` (damping
        helps the search's many short, nearly straight candidates, but slows the last digits),
        kept where the check finds them better."""
        pts, first, _, _, _ = self.fit_points(starts, ends, _FIT_STEPS)
        q, _, _ = _fit_curves(pts, _counts(first, pts.shape[1]), self.line(starts, ends), self.tolerance_mm,
                              q=fit.q, damping=0.0, good=0.0)
        better = self.check(starts, ends, q)
        keep = ~(better.curve_mm < fit.curve_mm)
        better.put(keep, fit, keep)
        return better

    def check(self, starts: np.ndarray, ends: np.ndarray, q: np.ndarray) -> _Fit:
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
        nodes = (grid[:-1, None] + _GL_X / _GRID).ravel()
        s = np.zeros((nb, _GRID + 1))
        np.cumsum(_speeds(a, b, c, nodes).reshape(nb, _GRID, len(_GL_X)) @ _GL_W / _GRID, axis=1, out=s[:, 1:])
        sigma = _speeds(a, b, c, grid)
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
            for x, w in zip(_GL_X, _GL_W, strict=True):
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
        curve_max = np.maximum.reduceat(_xy_error(bx_u, by_u, pts) + np.abs(s_u - target), first)
        for ce, e0, e3 in pts[_EXTRAS:].reshape(-1, 3, len(u)):
            curve_max = np.maximum(curve_max, np.maximum.reduceat(np.abs(e0 + (e3 - e0) * u - ce), first))
        curve_max[~(length >= self.min_length_mm)] = np.inf
        return _Fit(q, length, curve_max, _line_error(pts, first), np.ones(nb, bool))


def _counts(first, total):
    """Entries per block, from each block's first entry and the total."""
    return np.diff(np.append(first, total))


def _fit_curves(pts, counts, line, tolerance_mm, q=None, damping=_DAMPING, good=None):
    """Least-squares curves with fixed end points, in the arc-length parameterization, through
    blocks of ``counts`` points ``pts`` (rows as in _Fitter.fit_points); gives p1, p2 (rows p1x,
    p1y, p2x, p2y), the length and the error bound.

    Start from ``q`` or the linear least-squares fit at the time fractions tau_k, then take
    Gauss-Newton steps on (p1, p2) for the points' distances from the curve points at their
    arc-length fractions, moving each point's parameter u_k along by a Newton step on
    s(u_k) = tau_k L. An iterate's error bound is |B(u_k) - c_k| + |s(u_k) - tau_k L| (the curve
    point at arc-length fraction tau_k is that far along the curve from B(u_k)), s by
    Gauss-Legendre on each step of u. The steps are damped (Levenberg-Marquardt, ``damping``
    times the normal matrix's trace, decaying by _DECAY a step): a short, nearly straight
    block hardly determines where its control points lie along the chord, and undamped steps
    there jump far. Each block keeps its best iterate and stops once that is within ``good``
    tolerances, once its steps fall below _SETTLE tolerances, once it makes too little
    progress (_PROGRESS), or after _MAX_STEPS (_MAX_STEPS_LONG for blocks
    fitted on _FIT_STEPS + 1 points: they are few, and may need more steps).
    """
    nb = len(counts)
    first, block, _ = _ragged(counts)
    long = counts > _FIT_STEPS
    max_steps = np.where(long, _MAX_STEPS_LONG, _MAX_STEPS)
    good = np.where(long, _GOOD_LONG, _GOOD) if good is None else np.full(nb, good)
    reparameterize = 0 if q is None else 2  # Newton steps on u alone
    max_steps = max_steps + reparameterize
    q = _linear_fit(pts[:7], first, line) if q is None else q.copy()
    u = pts[0].copy()
    best_q, best_err, best_len = q.copy(), np.full(nb, np.inf), np.zeros(nb)
    ids, settled = np.arange(nb), np.zeros(nb, bool)
    history = []  # best errors after each step
    with np.errstate(all="ignore"):  # curves of (nearly) zero length: their errors become nan or inf
        for step in range(int(max_steps.max()) + 1):
            tau, cx, cy, X0, Y0, X3, Y3 = pts[:7]
            last = first + counts - 1
            P1x, P1y, P2x, P2y = np.take(q, block, axis=1)
            ax, bx, cx3 = 3.0 * (P1x - X0), 6.0 * (P2x - 2.0 * P1x + X0), 3.0 * (X3 - 3.0 * P2x + 3.0 * P1x - X0)
            ay, by, cy3 = 3.0 * (P1y - Y0), 6.0 * (P2y - 2.0 * P1y + Y0), 3.0 * (Y3 - 3.0 * P2y + 3.0 * P1y - Y0)
            S = _arc_integrals(u, (ax, bx, cx3, ay, by, cy3), first, block)
            length = S[0, last]
            ds = S[0] - tau * length[block]
            bx_u = X0 + u * (ax + u * (0.5 * bx + u * cx3 / 3.0))
            by_u = Y0 + u * (ay + u * (0.5 * by + u * cy3 / 3.0))
            rx, ry = bx_u - cx, by_u - cy
            err = _xy_error(bx_u, by_u, pts) + np.abs(ds)
            for ce, e0, e3 in pts[_EXTRAS:].reshape(-1, 3, len(u)):
                err = np.maximum(err, np.abs(e0 + (e3 - e0) * u - ce))  # Marlin: linear in u
            block_err = np.maximum.reduceat(err, first)
            better = block_err < best_err[ids]  # false for nan
            where = ids[better]
            best_q[:, where], best_err[where], best_len[where] = q[:, better], block_err[better], length[better]
            stop = settled | (best_err[ids] <= good[ids] * tolerance_mm) | (step >= max_steps[ids])
            if step >= reparameterize:
                history.append(best_err.copy())
            if len(history) > _PATIENCE:  # a fifth better in _PATIENCE steps (long: twice that), or give up
                window = np.where(long[ids], 2 * _PATIENCE, _PATIENCE)
                window = np.minimum(window, len(history) - 1)
                earlier = np.array(history)[len(history) - 1 - window, ids]
                stop |= best_err[ids] > _PROGRESS * earlier
            if stop.all():
                break

            dx, dy = ax + u * (bx + u * cx3), ay + u * (by + u * cy3)  # B'(u)
            sigma = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12 * length[block] + 1e-300)
            if step < reparameterize:  # bring the time fractions to the given curve's arc length first
                u = _monotone(u - ds / sigma, first, last, block)
                continue
            h = tau * np.take(S[1:, last], block, axis=1) - S[1:]  # sigma * du_k / dq_j
            normal = _normal_equations(u, (rx, ry), (dx / sigma, dy / sigma), ds, h, first)
            delta = _solve(normal, q, line[:, ids], damping * _DECAY ** (step - reparameterize))
            q = q + delta
            du = (np.einsum("jk,jk->k", h, np.take(delta, block, axis=1)) - ds) / sigma
            u = _monotone(u + du, first, last, block)
            settled = np.abs(delta).max(axis=0) <= _SETTLE * tolerance_mm  # evaluate once more, then stop
            if stop.any():  # drop the stopped blocks
                keep, keep_pts = ~stop, ~stop[block]
                ids, q, settled, counts = ids[keep], q[:, keep], settled[keep], counts[keep]
                pts, u = np.compress(keep_pts, pts, axis=1), u[keep_pts]
                first, block, _ = _ragged(counts)
    return best_q, best_len, best_err


def _normal_equations(u, residual, tangent, ds, h, first) -> np.ndarray:
    """_fit_curves' Gauss-Newton system per block (its unique entries, then the right-hand side)
    for the points' residuals at parameters ``u``, moved to their arc-length fractions to first
    order (``ds`` along the unit ``tangent``); ``h``: sigma * du_k / dq_j."""
    tx, ty = tangent
    rx = residual[0] - tx * ds  # to first order, the residual at the arc-length fraction
    ry = residual[1] - ty * ds
    w = 1.0 - u
    b1, b2 = 3.0 * u * w * w, 3.0 * u * u * w
    jx, jy = tx * h, ty * h
    jx[0] += b1
    jx[2] += b2
    jy[1] += b1
    jy[3] += b2
    return np.add.reduceat(np.concatenate([jx[_I] * jx[_J] + jy[_I] * jy[_J], jx * rx + jy * ry]), first, axis=1)


# Pairs (i, j), i <= j, of the 4 x 4 normal matrix of (p1x, p1y, p2x, p2y).
_I, _J = np.triu_indices(4)


def _stretch(p0, q, p3, length_mm):
    """Control points (rows p1x, p1y, p2x, p2y) of the curve (p0, q, p3) continued along itself,
    or cut short, to the arc length ``length_mm``: the same cubic on [0, U], s(U) = length_mm
    (Newton steps, 8-node Gauss-Legendre on [0, U]), by blossoming."""
    d0, d1, d2 = q[:2] - p0, q[2:] - q[:2], p3 - q[2:]
    a, b, c = 3.0 * d0, 6.0 * (d1 - d0), 3.0 * (d0 - 2.0 * d1 + d2)
    x, w = np.polynomial.legendre.leggauss(8)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    big_u = np.clip(length_mm / np.maximum(_speeds(a, b, c, x) @ w, 1e-300), 0.05, 4.0)
    for _ in range(3):
        s = big_u * (_speeds(a, b, c, big_u[:, None] * x) @ w)
        speed = np.maximum(_speeds(a, b, c, big_u[:, None])[:, 0], 1e-300)
        big_u = np.clip(big_u - (s - length_mm) / speed, 0.05, 4.0)
    p1 = (1.0 - big_u) * p0 + big_u * q[:2]
    p2 = (1.0 - big_u) ** 2 * p0 + 2.0 * big_u * (1.0 - big_u) * q[:2] + big_u ** 2 * q[2:]
    return np.concatenate([p1, p2])


_EXTRAS = 9  # first row of the further columns in the points' rows (see _Fitter.fit_points)


def _xy_error(x, y, pts):
    """Distance of (x, y) from each point's XY: the nearer of its cubic and its linear midpoint."""
    d1 = (x - pts[1]) ** 2 + (y - pts[2]) ** 2
    d2 = (x - pts[7]) ** 2 + (y - pts[8]) ** 2
    return np.sqrt(np.minimum(d1, d2))


def _line_error(pts, first):
    """Largest error of each block's straight line, linear in time, over its points ``pts``
    (rows as in _Fitter.fit_points)."""
    tau, cx, cy, X0, Y0, X3, Y3 = pts[:7]
    err = _xy_error(X0 + (X3 - X0) * tau, Y0 + (Y3 - Y0) * tau, pts)
    for ce, e0, e3 in pts[_EXTRAS:].reshape(-1, 3, len(tau)):
        err = np.maximum(err, np.abs(e0 + (e3 - e0) * tau - ce))
    return np.maximum.reduceat(err, first)


def _linear_fit(pts, first, line):
    """p1, p2 (rows p1x, p1y, p2x, p2y) minimizing the distances of the points from B(tau_k)."""
    u, cx, cy, X0, Y0, X3, Y3 = pts
    w = 1.0 - u
    b1, b2 = 3.0 * u * w * w, 3.0 * u * u * w
    b0, b3 = w * w * w, u * u * u
    rx = cx - b0 * X0 - b3 * X3
    ry = cy - b0 * Y0 - b3 * Y3
    a11, a12, a22, r1x, r1y, r2x, r2y = np.add.reduceat(
        np.stack([b1 * b1, b1 * b2, b2 * b2, b1 * rx, b1 * ry, b2 * rx, b2 * ry]), first, axis=1)
    zero = np.zeros_like(a11)
    normal = np.array([a11, zero, a12, zero, a11, zero, a12, a22, zero, a22,
                       -r1x, -r1y, -r2x, -r2y])
    return _solve(normal, np.zeros_like(line), line)


def _solve(normal, q, line, damping=0.0):
    """Gauss-Newton step from ``normal`` (10 upper-triangle entries of J^T J, then J^T r, per
    block), pulled by a relative _REGULARIZATION towards the chord's thirds (the straight line
    at constant speed), which decides p1, p2 where the samples cannot (blocks of 1 or 2 steps)."""
    nb = normal.shape[1]
    a = np.zeros((nb, 4, 4))
    a[:, _I, _J] = normal[:10].T
    a[:, _J, _I] = normal[:10].T
    trace = np.trace(a, axis1=1, axis2=2)
    lam = _REGULARIZATION * trace + 1e-300
    a[:, np.arange(4), np.arange(4)] += (lam + damping * trace)[:, None]
    rhs = -(normal[10:] + lam * (q - line)).T
    with np.errstate(invalid="ignore"):
        return np.linalg.solve(a, rhs[..., None])[..., 0].T


def curve_lengths(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray) -> np.ndarray:
    """XY arc lengths of the cubic Béziers whose control points are the rows (XY) of p0 .. p3,
    within about 1e-6 of each: for a writer, which times the curve it rounded (a slow block's
    time error shifts all the motion after it).

    Gauss-Legendre on 16 and on 32 equal steps of u; where they differ by more than 1e-8, the
    speed nearly vanishes somewhere (a kink, where the fit's _GRID steps may be 1e-4 off): 512
    steps there.
    """
    d0, d1, d2 = (p1 - p0).T, (p2 - p1).T, (p3 - p2).T
    a, b, c = 3.0 * d0, 6.0 * (d1 - d0), 3.0 * (d0 - 2.0 * d1 + d2)

    def lengths(rows, steps):
        nodes = ((np.arange(steps)[:, None] + _GL_X) / steps).ravel()
        return _speeds(a[:, rows], b[:, rows], c[:, rows], nodes) @ np.tile(_GL_W, steps) / steps

    everything = slice(None)
    length = lengths(everything, 32)
    kinked = np.flatnonzero(np.abs(length - lengths(everything, 16)) > 1e-8 * length)
    for i in range(0, len(kinked), _CHUNKS // 16):  # (rows, nodes) temporaries of the others' size
        length[kinked[i:i + _CHUNKS // 16]] = lengths(kinked[i:i + _CHUNKS // 16], 512)
    return length


def _speeds(a, b, c, u):
    """|B'(u)| of every block (rows) at the parameters u (columns); B' = a + u (b + u c)."""
    dx = a[0][:, None] + u * (b[0][:, None] + u * c[0][:, None])
    dy = a[1][:, None] + u * (b[1][:, None] + u * c[1][:, None])
    return np.sqrt(dx * dx + dy * dy)


def _monotone(u, first, last, block):
    """Parameters clipped to [0, 1], non-decreasing in each block, 0 and 1 at its ends."""
    u = np.maximum.accumulate(np.clip(u, 0.0, 1.0) + block) - block
    u[first], u[last] = 0.0, 1.0
    return u


def _arc_integrals(u, coef, first, block):
    """From the block's start to each u_k: the arc length s and its derivatives by p1x, p1y,
    p2x, p2y (integrals of the unit tangent times the Bernstein derivatives), by Gauss-Legendre
    on each step of u."""
    ax, bx, cx, ay, by, cy = coef
    prev = np.empty_like(u)
    prev[1:] = u[:-1]
    prev[first] = u[first]  # no step before a block's first sample
    step = u - prev
    acc = np.zeros((5, len(u)))
    for x, w in zip(_GL_X, _GL_W, strict=True):
        v = prev + x * step
        dx, dy = ax + v * (bx + v * cx), ay + v * (by + v * cy)
        sigma = np.sqrt(dx * dx + dy * dy)
        acc[0] += w * sigma
        wt = w / np.maximum(sigma, 1e-300)
        d1, d2 = 3.0 * (1.0 - v) * (1.0 - 3.0 * v) * wt, 3.0 * v * (2.0 - 3.0 * v) * wt  # Bernstein b1', b2'
        acc[1] += dx * d1
        acc[2] += dy * d1
        acc[3] += dx * d2
        acc[4] += dy * d2
    acc *= step
    np.cumsum(acc, axis=1, out=acc)
    return acc - np.take(acc[:, first], block, axis=1)
