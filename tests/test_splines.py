"""Tests of fbspost.fbs.splines against independent truths.

Truths used: patent Eq. 4 (knots) and Eq. 10 (initial derivative) written out here,
scipy.interpolate.BSpline(...).derivative(r) evaluated on random coefficients, partition of
unity, and the closed forms of constant and linear control points on uniform knots.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.interpolate import BSpline

from fbspost.fbs.splines import basis_matrix, clamped_uniform_knots, uniform_knots


def eq4_knots(n: int, m: int) -> list[float]:
    """Patent Eq. 4, k = 0 .. m + n + 1, piecewise as printed."""
    g = []
    for k in range(m + n + 2):
        if k <= m:
            g.append(0.0)
        elif k <= n:
            g.append((k - m) / (n - m + 1))
        else:
            g.append(1.0)
    return g


@pytest.mark.parametrize("n_control,m", [(4, 3), (5, 3), (12, 3), (10, 5), (7, 1), (3, 2), (20, 4)])
@pytest.mark.parametrize("duration", [1.0, 2.5])
def test_clamped_knots_eq4(n_control, m, duration):
    """clamped_uniform_knots(n + 1, m, D) = D * Eq. 4."""
    knots = clamped_uniform_knots(n_control, m, duration)
    truth = np.array(eq4_knots(n_control - 1, m)) * duration
    assert knots.shape == truth.shape
    np.testing.assert_allclose(knots, truth, rtol=1e-15, atol=0)


def scipy_reference(knots, m, x, r, coeffs):
    """r-th derivative of sum_j c_j N_j(x) by scipy's own BSpline."""
    spline = BSpline(np.asarray(knots, float), coeffs, m)
    return spline.derivative(r)(x) if r else spline(x)


def check_against_scipy(knots, m, x, rng, n_coeff_sets=3):
    n_control = len(knots) - m - 1
    coeffs = rng.normal(size=(n_control, n_coeff_sets))
    for r in range(m + 1):
        N = basis_matrix(knots, m, x, r)
        assert N.shape == (len(x), n_control)
        truth = scipy_reference(knots, m, x, r, coeffs)
        got = N @ coeffs
        scale = np.max(np.abs(truth)) + 1e-300
        np.testing.assert_allclose(got, truth, rtol=0, atol=1e-9 * scale, err_msg=f"r={r}")


@pytest.mark.parametrize("m", [1, 2, 3, 4, 5])
def test_basis_matrix_clamped_vs_scipy(m):
    """Clamped uniform knots on [0, 0.8]: N_r @ c equals BSpline(knots, c, m).derivative(r), r = 0..m,
    at a dense grid including both ends."""
    rng = np.random.default_rng(m)
    knots = clamped_uniform_knots(11, m, 0.8)
    x = np.concatenate([np.linspace(0.0, 0.8, 401), rng.uniform(0, 0.8, 50)])
    check_against_scipy(knots, m, x, rng)


@pytest.mark.parametrize("m", [1, 3, 5])
def test_basis_matrix_uniform_vs_scipy(m):
    """Unclamped uniform knots (spacing 10 ms, first knot 30 spans = 0.3 s): same check inside [t_m, t_{-m-1}]."""
    rng = np.random.default_rng(10 + m)
    knots = uniform_knots(9, m, 0.01, 30)
    np.testing.assert_allclose(knots, 0.3 + 0.01 * np.arange(9 + m + 1), rtol=1e-14)
    x = np.linspace(knots[m], knots[-m - 1], 333)
    check_against_scipy(knots, m, x, rng)


@st.composite
def knot_vectors(draw):
    """Random non-decreasing knot vectors: strictly increasing interior, ends clamped or not."""
    m = draw(st.integers(1, 5))
    n_control = draw(st.integers(m + 1, m + 8))
    n_knots = n_control + m + 1
    clamped = draw(st.booleans())
    n_free = n_knots - 2 * m if clamped else n_knots
    gaps = draw(st.lists(st.floats(0.05, 3.0), min_size=n_free - 1, max_size=n_free - 1))
    start = draw(st.floats(-5.0, 5.0))
    free = start + np.concatenate([[0.0], np.cumsum(gaps)])
    knots = np.concatenate([[free[0]] * m, free, [free[-1]] * m]) if clamped else free
    assert len(knots) == n_knots
    return knots, m


@settings(max_examples=40, deadline=None)
@given(kv=knot_vectors(), seed=st.integers(0, 2**32 - 1))
def test_basis_matrix_random_knots_vs_scipy(kv, seed):
    """Random non-uniform knots: N_r @ c = BSpline(...).derivative(r)(x) for all r <= m, at random
    points and at every knot of the base interval."""
    knots, m = kv
    lo, hi = knots[m], knots[-m - 1]
    assume(hi > lo)
    rng = np.random.default_rng(seed)
    inner = knots[(knots >= lo) & (knots <= hi)]
    x = np.concatenate([rng.uniform(lo, hi, 40), inner])
    check_against_scipy(knots, m, x, rng, n_coeff_sets=2)


@settings(max_examples=30, deadline=None)
@given(kv=knot_vectors())
def test_partition_of_unity(kv):
    """Rows of N_0 sum to 1 in the base interval; rows of N_r (r >= 1) sum to 0 (constant has no slope)."""
    knots, m = kv
    lo, hi = knots[m], knots[-m - 1]
    x = np.linspace(lo, hi, 57)
    np.testing.assert_allclose(np.asarray(basis_matrix(knots, m, x, 0).sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-12)
    for r in range(1, m + 1):
        N = basis_matrix(knots, m, x, r)
        row_scale = np.asarray(abs(N).sum(axis=1)).ravel()
        np.testing.assert_allclose(np.asarray(N.sum(axis=1)).ravel(), 0.0, rtol=0, atol=1e-12 * row_scale.max())


@pytest.mark.parametrize("n_control,m", [(4, 3), (8, 3), (15, 3), (9, 4), (12, 5), (6, 2)])
def test_eq10_initial_derivative(n_control, m):
    """Patent Eq. 10: on clamped uniform knots over [0, 1], x'(0) = m (n - m + 1)(p_1 - p_0), n + 1 points;
    and the curve starts at p_0 (clamping)."""
    rng = np.random.default_rng(n_control * 10 + m)
    knots = clamped_uniform_knots(n_control, m, 1.0)
    n = n_control - 1
    p = rng.normal(size=n_control)
    d1 = (basis_matrix(knots, m, [0.0], 1) @ p)[0]
    assert d1 == pytest.approx(m * (n - m + 1) * (p[1] - p[0]), rel=1e-12)
    assert (basis_matrix(knots, m, [0.0], 0) @ p)[0] == pytest.approx(p[0], rel=1e-14)
    # scaled to a duration D the derivative scales by 1/D (time in seconds)
    knots_d = clamped_uniform_knots(n_control, m, 0.25)
    assert (basis_matrix(knots_d, m, [0.0], 1) @ p)[0] == pytest.approx(m * (n - m + 1) * (p[1] - p[0]) / 0.25,
                                                                        rel=1e-12)


@pytest.mark.parametrize("m", [1, 2, 3, 5])
def test_uniform_constant_and_linear(m):
    """Uniform knots: equal control points give that constant (all derivatives 0); p_j = j gives
    x(t) = (t - t0)/h - (m + 1)/2 (Greville abscissae), slope 1/h, higher derivatives 0."""
    h, t0, n_control = 0.002, 0.1, 12
    knots = uniform_knots(n_control, m, h, 50)  # first knot at 50 spans = t0
    t = np.linspace(knots[m], knots[-m - 1], 211)
    const = np.full(n_control, 3.7)
    lin = np.arange(n_control, dtype=float)
    np.testing.assert_allclose(basis_matrix(knots, m, t, 0) @ const, 3.7, rtol=1e-13)
    np.testing.assert_allclose(basis_matrix(knots, m, t, 0) @ lin, (t - t0) / h - (m + 1) / 2, rtol=0, atol=1e-10)
    np.testing.assert_allclose(basis_matrix(knots, m, t, 1) @ lin, 1.0 / h, rtol=1e-10)
    for r in range(1, m + 1):
        np.testing.assert_allclose(basis_matrix(knots, m, t, r) @ const, 0.0, rtol=0, atol=1e-9 / h**r)
    for r in range(2, m + 1):
        np.testing.assert_allclose(basis_matrix(knots, m, t, r) @ lin, 0.0, rtol=0, atol=1e-9 / h**r)


@pytest.mark.parametrize("r", [-1, 4, 7])
def test_basis_matrix_bad_derivative(r):
    """A derivative order outside [0, m] is a ValueError."""
    with pytest.raises(ValueError):
        basis_matrix(clamped_uniform_knots(6, 3), 3, [0.5], r)


@pytest.mark.parametrize("n_control,m", [(3, 3), (1, 1), (4, 5)])
def test_clamped_knots_too_few_points(n_control, m):
    """Fewer than m + 1 control points cannot carry a degree-m B-spline: ValueError."""
    with pytest.raises(ValueError):
        clamped_uniform_knots(n_control, m)
    clamped_uniform_knots(m + 1, m)  # the minimum is accepted


@pytest.mark.parametrize("spacing_samples, period_s", [(21, 1e-4), (27, 1e-4), (9, 1e-3), (43, 1e-3)])
def test_knot_at_time_zero_is_exact(spacing_samples, period_s):
    """Spacings whose products round badly (e.g. 5 * 0.0021) still put a knot exactly at t = 0, so
    a sample at t = 0 lies inside the base interval and the basis there sums to one."""
    m = 5
    knots = uniform_knots(m + 8, m, spacing_samples * period_s, first_knot=-m)
    assert knots[m] == 0.0
    row = basis_matrix(knots, m, [0.0]).toarray()
    assert abs(row.sum() - 1.0) < 1e-14
