"""Tests of fbspost.write.bezier against independent truths.

Truths used: curves evaluated here by de Casteljau's construction, their arc length by
scipy.integrate.quad and its inversion by scipy.optimize.brentq (nothing of the module's own
quadrature or inversion); commands built as exact cubic Béziers, straight lines and circles
traversed at constant speed; the classical quarter-circle Bézier (k = 0.5523) and its radial
error 2.7e-4 r as a bound the fit must reach.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from fbspost.write.bezier import fit_g5

TOL_MM = 1e-3


def de_casteljau(points: np.ndarray, u: float) -> np.ndarray:
    """The Bézier curve of control ``points`` at parameter u, by repeated interpolation."""
    p = np.array(points, dtype=float)
    while len(p) > 1:
        p = (1.0 - u) * p[:-1] + u * p[1:]
    return p[0]


def speed(control: np.ndarray, u: float) -> float:
    """|B'(u)|: the hodograph is the quadratic Bézier of 3 (P_i+1 - P_i)."""
    return float(np.linalg.norm(de_casteljau(3.0 * np.diff(control, axis=0), u)))


def arc_length(control: np.ndarray, u: float) -> float:
    return quad(lambda v: speed(control, v), 0.0, u, epsabs=1e-13, epsrel=1e-13, limit=200)[0]


def parameter_at_fraction(control: np.ndarray, fraction: float, length: float) -> float:
    """u with arc_length(u) = fraction * length."""
    if fraction <= 0.0:
        return 0.0
    if fraction >= 1.0:
        return 1.0
    return brentq(lambda u: arc_length(control, u) - fraction * length, 0.0, 1.0, xtol=1e-15)


def constant_speed(control: np.ndarray, steps: int) -> np.ndarray:
    """Samples of the curve traversed at constant speed, ``steps`` equal time steps."""
    length = arc_length(control, 1.0)
    return np.array([de_casteljau(control, parameter_at_fraction(control, k / steps, length))
                     for k in range(steps + 1)])


def independent_errors(command: np.ndarray, blocks) -> np.ndarray:
    """Largest error of each G5 block over its samples, as the controller moves: the curve point
    at arc-length fraction (k - start) / (end - start) against XY, and every further column
    against its linear interpolation in that point's parameter (Marlin). G1 blocks: every
    column linear in time."""
    out = []
    columns = (blocks.starts, blocks.ends, blocks.p1_mm, blocks.p2_mm, blocks.curve)
    for start, end, p1, p2, curve in zip(*columns, strict=True):
        control = np.array([command[start, :2], p1, p2, command[end, :2]])
        length = arc_length(control, 1.0)
        worst = 0.0
        for k in range(start, end + 1):
            fraction = (k - start) / (end - start)
            if curve:
                u = parameter_at_fraction(control, fraction, length)
                xy = de_casteljau(control, u)
            else:
                u = fraction
                xy = command[start, :2] + fraction * (command[end, :2] - command[start, :2])
            extras = command[start, 2:] + u * (command[end, 2:] - command[start, 2:])
            worst = max(worst, np.linalg.norm(xy - command[k, :2]), *np.abs(extras - command[k, 2:]))
        out.append(worst)
    return np.array(out)


def assert_contiguous(blocks, n: int) -> None:
    starts, ends = blocks.starts, blocks.ends
    assert starts[0] == 0 and ends[-1] == n - 1
    assert np.all(ends > starts)
    np.testing.assert_array_equal(starts[1:], ends[:-1])
    assert blocks.p1_mm.shape == blocks.p2_mm.shape == (len(ends), 2)
    assert np.all(np.isfinite(blocks.p1_mm)) and np.all(np.isfinite(blocks.p2_mm))


@pytest.mark.parametrize("control", [
    [[0.0, 0.0], [3.0, 4.0], [8.0, 5.0], [10.0, 0.0]],  # speed varies by a third along it
    [[0.0, 0.0], [4.0, 3.0], [2.0, -3.0], [6.0, 0.5]],  # an inflection
    [[1.0, 1.0], [1.5, 1.2], [2.2, 1.1], [3.0, 1.4]],  # short and flat
])
@pytest.mark.slow
def test_exact_bezier_is_one_block(control):
    """A cubic Bézier traversed at constant speed comes back as one block: its control points
    (to 1e-6 mm) and its length."""
    control = np.array(control)
    command = constant_speed(control, 200)
    blocks = fit_g5(command, TOL_MM)
    assert len(blocks.ends) == 1 and blocks.curve[0]
    np.testing.assert_allclose(blocks.p1_mm[0], control[1], atol=1e-6)
    np.testing.assert_allclose(blocks.p2_mm[0], control[2], atol=1e-6)
    assert blocks.length_mm[0] == pytest.approx(arc_length(control, 1.0), abs=1e-6)
    assert independent_errors(command, blocks)[0] <= 1e-6


def test_straight_line_is_one_block_with_control_points_on_it():
    """A straight line at constant speed, Z and E moving with it: one block, the control points
    on the line between its ends, errors at rounding level."""
    t = np.linspace(0.0, 1.0, 501)
    start, end = np.array([5.0, -2.0, 0.2, 1.0]), np.array([35.0, 18.0, 0.2, 2.5])
    command = start + t[:, None] * (end - start)
    blocks = fit_g5(command, TOL_MM)
    assert len(blocks.ends) == 1 and blocks.curve[0]
    direction = (end - start)[:2] / np.linalg.norm((end - start)[:2])
    for p in (blocks.p1_mm[0], blocks.p2_mm[0]):
        offset = p - start[:2]
        assert abs(offset[0] * direction[1] - offset[1] * direction[0]) < 1e-9  # on the line
        assert 0.0 <= offset @ direction <= np.linalg.norm((end - start)[:2])
    assert blocks.length_mm[0] == pytest.approx(np.linalg.norm((end - start)[:2]), rel=1e-12)
    assert independent_errors(command, blocks)[0] < 1e-9


def circle(radius_mm: float, angle: float, steps: int) -> np.ndarray:
    theta = np.linspace(0.0, angle, steps + 1)
    return radius_mm * np.column_stack([np.cos(theta), np.sin(theta)])


def test_quarter_circle_within_the_classical_bound_is_one_block():
    """The classical quarter-circle Bézier (k = 0.5523) stays within 2.7e-4 r of the circle; a
    fitted curve, free in its end tangents, must do at least as well: a quarter circle whose
    radius makes that bound the tolerance is one block."""
    k = 4.0 / 3.0 * (np.sqrt(2.0) - 1.0)
    classical = np.array([[1.0, 0.0], [1.0, k], [k, 1.0], [0.0, 1.0]])
    radial = [abs(np.linalg.norm(de_casteljau(classical, u)) - 1.0) for u in np.linspace(0.0, 1.0, 1001)]
    assert max(radial) == pytest.approx(2.7e-4, abs=0.05e-4)  # the bound itself
    radius = TOL_MM / 2.7e-4
    command = circle(radius, np.pi / 2, 400)  # 1 kHz at 14.5 mm/s
    blocks = fit_g5(command, TOL_MM)
    assert len(blocks.ends) == 1 and blocks.curve[0]
    assert independent_errors(command, blocks)[0] <= TOL_MM


def test_full_circle_block_count_and_errors():
    """A full circle of 5 mm radius at 50 mm/s, 1 kHz: every sample within the tolerance, and
    a sensible count: the classical bound scales as angle^6, so arcs of at least 85 degrees fit
    (at most 5 blocks), and one curve cannot turn more than a half circle within 1 um."""
    radius = 5.0
    steps = int(round(2 * np.pi * radius / 50.0 * 1000))
    command = circle(radius, 2 * np.pi, steps)
    blocks = fit_g5(command, TOL_MM)
    assert_contiguous(blocks, len(command))
    assert blocks.curve.all()
    assert 3 <= len(blocks.ends) <= 5
    assert np.all(independent_errors(command, blocks) <= TOL_MM)
    assert np.all(blocks.error_mm <= TOL_MM)


def smooth_path(seed: int, samples: int, period_s: float = 1e-3) -> np.ndarray:
    """X, Y: a random smooth curve (a few harmonics, some millimetres) traversed at a speed
    varying between 20 and 60 mm/s; Z constant; E proportional to the distance travelled."""
    rng = np.random.default_rng(seed)
    fine = np.linspace(0.0, 1.0, 20001)
    harmonics = np.arange(1, 4)
    ax, ay = rng.normal(size=(2, 3)) * 8.0 / harmonics
    px, py = rng.uniform(0.0, 2.0 * np.pi, size=(2, 3))
    x = (ax * np.sin(2 * np.pi * np.outer(fine, harmonics) + px)).sum(axis=1)
    y = (ay * np.sin(2 * np.pi * np.outer(fine, harmonics) + py)).sum(axis=1)
    along = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    t = np.arange(samples) * period_s
    speed_mm_s = 40.0 + 20.0 * np.sin(2 * np.pi * 1.3 * t + rng.uniform(0, 2 * np.pi))
    distance = np.concatenate([[0.0], np.cumsum(0.5 * (speed_mm_s[1:] + speed_mm_s[:-1]) * period_s)])
    distance %= along[-1]
    return np.column_stack([np.interp(distance, along, x), np.interp(distance, along, y),
                            np.full(samples, 0.3), 0.033 * distance])


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.slow
def test_smooth_path_with_varying_speed(seed):
    """Every sample of every block within the tolerance, judged independently; the blocks
    contiguous, from the first sample to the last; fewer blocks than samples by far."""
    command = smooth_path(seed, 3000)
    blocks = fit_g5(command, TOL_MM, min_samples=1, max_samples=200)  # several lock-step chunks
    assert_contiguous(blocks, len(command))
    errors = independent_errors(command, blocks)
    assert np.all(errors <= TOL_MM * (1 + 1e-9))
    assert np.all(errors <= blocks.error_mm + 1e-9)  # the module's bound is a bound
    assert len(blocks.ends) < len(command) / 4


def test_min_and_max_samples():
    """No block shorter than min_samples (the last may be), none longer than max_samples, even
    where the tolerance would want otherwise; the error reports what the minimum costs."""
    t = np.arange(2001) * 1e-3
    shaken = np.column_stack([30.0 * t + 0.05 * np.sin(2 * np.pi * 80.0 * t), np.zeros_like(t)])
    blocks = fit_g5(shaken, TOL_MM, min_samples=8, max_samples=50)
    assert_contiguous(blocks, len(shaken))
    lengths = blocks.ends - blocks.starts
    assert np.all(lengths[:-1] >= 8) and np.all(lengths <= 50)
    errors = independent_errors(shaken, blocks)
    assert errors.max() > TOL_MM  # 80 Hz shaking needs blocks shorter than 8 samples
    assert np.all(errors <= blocks.error_mm + 1e-9)  # reported (over samples and midpoints)

    line = np.column_stack([np.linspace(0.0, 100.0, 1001), np.zeros(1001)])
    blocks = fit_g5(line, TOL_MM, min_samples=3, max_samples=120)
    lengths = blocks.ends - blocks.starts
    assert np.all(lengths <= 120) and len(lengths) == int(np.ceil(1000 / 120))


def test_xy_at_rest_is_a_g1_block():
    """Where XY rests while E moves (a retraction), no curve can carry the time: one G1 block
    spans it, and the moves around it are curves."""
    approach = np.column_stack([np.linspace(0.0, 10.0, 201), np.zeros(201), np.zeros(201)])
    retract = np.column_stack([np.full(100, 10.0), np.zeros(100), np.linspace(0.0, -0.8, 101)[1:]])
    leave = np.column_stack([np.full(200, 10.0), np.linspace(0.0, 10.0, 201)[1:], np.full(200, -0.8)])
    command = np.concatenate([approach, retract, leave])
    blocks = fit_g5(command, TOL_MM)
    assert_contiguous(blocks, len(command))
    np.testing.assert_array_equal(blocks.ends, [200, 300, 500])
    np.testing.assert_array_equal(blocks.curve, [True, False, True])
    assert blocks.length_mm[1] == 0.0
    assert np.all(independent_errors(command, blocks) <= 1e-9)


def test_tiny_inputs():
    blocks = fit_g5(np.zeros((1, 2)), TOL_MM)
    assert len(blocks.ends) == 0
    blocks = fit_g5(np.array([[0.0, 0.0], [0.05, 0.0]]), TOL_MM)
    np.testing.assert_array_equal(blocks.ends, [1])
    assert blocks.curve[0] and blocks.length_mm[0] == pytest.approx(0.05)
    with pytest.raises(ValueError):
        fit_g5(np.zeros((5, 2)), TOL_MM, min_samples=0)
    with pytest.raises(ValueError):
        fit_g5(np.zeros(5), TOL_MM)
