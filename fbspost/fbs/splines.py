"""B-spline knot vectors and basis matrices, with time in seconds.

Takes a knot vector, a degree m and sample times; gives the sparse basis matrix N (command =
N p, patent Eq. 2) and the matrices N_r of its r-th time derivative (Eq. 7, units 1/s^r).
Knot vectors: uniform clamped (patent Eq. 4, scaled to a duration), uniform unclamped (the
sliding windows of limited look-ahead: every span looks the same) and any non-decreasing
vector given by the caller.
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline


def clamped_uniform_knots(n_control: int, degree: int, duration_s: float = 1.0) -> np.ndarray:
    """Patent Eq. 4 for n + 1 = ``n_control`` control points, scaled from [0, 1] to [0, duration_s]."""
    n, m = n_control - 1, degree
    if n < m:
        raise ValueError(f"a degree-{m} B-spline needs at least {m + 1} control points")
    k = np.arange(m + n + 2)
    g = np.clip((k - m) / (n - m + 1), 0.0, 1.0)
    return g * duration_s


def uniform_knots(n_control: int, degree: int, spacing_s: float, first_knot: int = 0) -> np.ndarray:
    """Unclamped uniform knots t_i = (first_knot + i) spacing_s; basis j lives on [t_j, t_(j+m+1)].

    The offset counts whole spans so that the knot at time 0, if any, is exactly 0: a sample at
    t = 0 must not fall a rounding error outside the spline's base interval.
    """
    return spacing_s * (first_knot + np.arange(n_control + degree + 1))


def derivative_coefficients(knots: np.ndarray, degree: int) -> sparse.csr_matrix:
    """The matrix D with q = D p: the control points of the derivative (degree m-1, knots[1:-1])."""
    knots = np.asarray(knots, dtype=float)
    n_control = len(knots) - degree - 1
    span = knots[degree + 1:degree + n_control] - knots[1:n_control]
    c = np.divide(degree, span, out=np.zeros_like(span), where=span > 0)
    return sparse.diags([-c, c], [0, 1], shape=(n_control - 1, n_control), format="csr")


def basis_matrix(knots: np.ndarray, degree: int, times_s: np.ndarray, derivative: int = 0) -> sparse.csr_matrix:
    """N_r: row i holds the r-th derivative of every basis function at ``times_s[i]``.

    ``times_s`` must lie within [knots[degree], knots[-degree-1]], where the basis is complete.
    """
    if not 0 <= derivative <= degree:
        raise ValueError(f"derivative order must be in [0, {degree}]")
    knots = np.asarray(knots, dtype=float)
    chain = sparse.identity(len(knots) - degree - 1, format="csr")
    for r in range(derivative):
        inner = knots[r:len(knots) - r]
        chain = derivative_coefficients(inner, degree - r) @ chain
    inner = knots[derivative:len(knots) - derivative]
    x = np.asarray(times_s, dtype=float)
    return (BSpline.design_matrix(x, inner, degree - derivative) @ chain).tocsr()
