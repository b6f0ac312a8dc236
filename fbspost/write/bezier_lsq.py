"""The least-squares cubic Bézier curves with fixed ends, in the arc-length parameterization.

Takes blocks of points laid end to end (rows as in ``bezier_fitter.Fitter.fit_points``: time
fractions, the command's XY, the ends, further columns); gives their curves' control points,
lengths and error bounds (``fit_curves``: damped Gauss-Newton from the linear fit or a given
curve), the straight lines' errors (``line_error``), curves continued along themselves
(``stretch``) and the arc-length integrals they rest on (``curve_speeds``, ``_arc_integrals``,
by Gauss-Legendre).
"""
from __future__ import annotations

import numpy as np

# Fit
FIT_STEPS = 32  # a longer candidate is fitted on this many half-sample steps, evenly spread
_MAX_STEPS = 4  # Gauss-Newton steps after the linear fit, at most (_MAX_STEPS_LONG: blocks
_MAX_STEPS_LONG = 16  # fitted on FIT_STEPS + 1 points, which are few and may need more)
DAMPING = 1e-2  # Levenberg-Marquardt damping of the first step, relative to the normal matrix's trace,
_DECAY = 0.3  # and its factor from step to step
_GOOD = 0.5  # tolerances: a fit stops at errors below this (_GOOD_LONG: blocks fitted on FIT_STEPS + 1
_GOOD_LONG = 0.01  # points, whose curve seeds the search's next candidate),
_SETTLE = 1e-3  # at steps below this,
_PROGRESS = 0.8  # or when its error shrank by less than this factor in _PATIENCE steps (twice that for
_PATIENCE = 2  # blocks fitted on FIT_STEPS + 1 points)



_REGULARIZATION = 1e-9  # relative pull of p1, p2 towards the chord's thirds: decides blocks of 1 or 2 steps



# Gauss-Legendre on [0, 1], 3 nodes: exact for speeds polynomial of degree 5 in u; on a step h of
# u the error is below h^7 max|d^6 speed / du^6| / 2016000, and the speed of a passing curve is smooth.
GL_X, GL_W = np.polynomial.legendre.leggauss(3)
GL_X, GL_W = 0.5 * (GL_X + 1.0), 0.5 * GL_W



def ragged(counts):
    """For blocks of ``counts`` entries laid end to end: each block's first entry, each entry's
    block and its index within the block."""
    first = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=first[1:])
    block = np.repeat(np.arange(len(counts)), counts)
    return first, block, np.arange(int(counts.sum())) - first[block]



def entries_per_block(first, total):
    """Entries per block, from each block's first entry and the total."""
    return np.diff(np.append(first, total))



def fit_curves(pts, counts, line, tolerance_mm, q=None, damping=DAMPING, good=None):
    """Least-squares curves with fixed end points, in the arc-length parameterization, through
    blocks of ``counts`` points ``pts`` (rows as in Fitter.fit_points); gives p1, p2 (rows p1x,
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
    fitted on FIT_STEPS + 1 points: they are few, and may need more steps).
    """
    nb = len(counts)
    first, block, _ = ragged(counts)
    long = counts > FIT_STEPS
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
            err = xy_error(bx_u, by_u, pts) + np.abs(ds)
            for ce, e0, e3 in pts[EXTRAS:].reshape(-1, 3, len(u)):
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
                first, block, _ = ragged(counts)
    return best_q, best_len, best_err



def _normal_equations(u, residual, tangent, ds, h, first) -> np.ndarray:
    """fit_curves' Gauss-Newton system per block (its unique entries, then the right-hand side)
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



def stretch(p0, q, p3, length_mm):
    """Control points (rows p1x, p1y, p2x, p2y) of the curve (p0, q, p3) continued along itself,
    or cut short, to the arc length ``length_mm``: the same cubic on [0, U], s(U) = length_mm
    (Newton steps, 8-node Gauss-Legendre on [0, U]), by blossoming."""
    d0, d1, d2 = q[:2] - p0, q[2:] - q[:2], p3 - q[2:]
    a, b, c = 3.0 * d0, 6.0 * (d1 - d0), 3.0 * (d0 - 2.0 * d1 + d2)
    x, w = np.polynomial.legendre.leggauss(8)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    big_u = np.clip(length_mm / np.maximum(curve_speeds(a, b, c, x) @ w, 1e-300), 0.05, 4.0)
    for _ in range(3):
        s = big_u * (curve_speeds(a, b, c, big_u[:, None] * x) @ w)
        speed = np.maximum(curve_speeds(a, b, c, big_u[:, None])[:, 0], 1e-300)
        big_u = np.clip(big_u - (s - length_mm) / speed, 0.05, 4.0)
    p1 = (1.0 - big_u) * p0 + big_u * q[:2]
    p2 = (1.0 - big_u) ** 2 * p0 + 2.0 * big_u * (1.0 - big_u) * q[:2] + big_u ** 2 * q[2:]
    return np.concatenate([p1, p2])



EXTRAS = 9  # first row of the further columns in the points' rows (see Fitter.fit_points)



def xy_error(x, y, pts):
    """Distance of (x, y) from each point's XY: the nearer of its cubic and its linear midpoint."""
    d1 = (x - pts[1]) ** 2 + (y - pts[2]) ** 2
    d2 = (x - pts[7]) ** 2 + (y - pts[8]) ** 2
    return np.sqrt(np.minimum(d1, d2))


def line_error(pts, first):
    """Largest error of each block's straight line, linear in time, over its points ``pts``
    (rows as in Fitter.fit_points)."""
    tau, cx, cy, X0, Y0, X3, Y3 = pts[:7]
    err = xy_error(X0 + (X3 - X0) * tau, Y0 + (Y3 - Y0) * tau, pts)
    for ce, e0, e3 in pts[EXTRAS:].reshape(-1, 3, len(tau)):
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



def curve_speeds(a, b, c, u):
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
    for x, w in zip(GL_X, GL_W, strict=True):
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

