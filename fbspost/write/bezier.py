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
that a curve cannot slip away between them; see Fitter), and the curve is at least
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

from .bezier_fitter import CandidateFit, Fitter
from .bezier_lsq import FIT_STEPS, GL_W, GL_X, curve_speeds

# Search
_CHUNKS = 4096  # lock-step lanes: enough to amortize numpy's per-call cost
_MIN_CHUNK = 256  # samples (unless max_samples is less): a chunk edge can still cost a block
_GROW = 2.0  # largest growth of a passing candidate's length


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
    fitter = Fitter(command, tolerance_mm, min_length_mm, step_mm)
    chunk = max(-(-(n - 1) // _CHUNKS), min(max_samples, _MIN_CHUNK))
    edges = np.append(np.arange(0, n - 1, chunk), n - 1)
    limits = (tolerance_mm, min_samples, max_samples)
    starts, ends, fit = _search(fitter, edges[:-1], edges[1:], edges[1:] == n - 1, *limits)
    for parity in (0, 1):  # neighbouring edges' windows may overlap: every other edge at a time
        starts, ends, fit = _search_across(fitter, starts, ends, fit, edges[1 + parity:-1:2], n, *limits)
    curve = (fit.curve_mm <= tolerance_mm) | (fit.curve_mm <= fit.line_mm)
    polish = np.flatnonzero(curve & (2 * (ends - starts) > FIT_STEPS) & (fit.line_mm > tolerance_mm))
    if polish.size:  # long fitted curves
        fit.put(polish, fitter.polish(starts[polish], ends[polish], fit.take(polish)))
    line = fitter.line(starts, ends)
    q = np.where(curve, fit.q, line)  # a G1 block reports the straight line
    chord = np.hypot(*(command[ends, :2] - command[starts, :2]).T)
    return G5Blocks(ends, q[:2].T.copy(), q[2:].T.copy(), curve, np.where(curve, fit.length_mm, chord),
                    np.where(curve, fit.curve_mm, fit.line_mm))


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
    best = CandidateFit(np.zeros((4, lanes)), np.zeros(lanes), np.zeros(lanes), np.zeros(lanes), np.zeros(lanes, bool))
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
    fits = CandidateFit(np.concatenate([f.q for f in out_fit], axis=1),
                        *(np.concatenate([getattr(f, name) for f in out_fit]) for name in CandidateFit.ENTRIES))
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
    merged = CandidateFit(np.concatenate([fit.q[:, old], new_fit.q[:, new]], axis=1),
                          *(np.concatenate([getattr(fit, name)[old], getattr(new_fit, name)[new]])
                            for name in CandidateFit.ENTRIES))
    return (np.concatenate([starts[old], new_starts[new]])[order], np.concatenate([ends[old], new_ends[new]])[order],
            merged.take(order))


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
        nodes = ((np.arange(steps)[:, None] + GL_X) / steps).ravel()
        return curve_speeds(a[:, rows], b[:, rows], c[:, rows], nodes) @ np.tile(GL_W, steps) / steps

    everything = slice(None)
    length = lengths(everything, 32)
    kinked = np.flatnonzero(np.abs(length - lengths(everything, 16)) > 1e-8 * length)
    for i in range(0, len(kinked), _CHUNKS // 16):  # (rows, nodes) temporaries of the others' size
        length[kinked[i:i + _CHUNKS // 16]] = lengths(kinked[i:i + _CHUNKS // 16], 512)
    return length
