"""The FBS optimizer against independent truths: scipy's simulation of the continuous model, a
brute-force least-squares and QP solve of the same problem written out here, and the patent's
butterfly on its own stage."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import linalg, optimize, sparse
from scipy.interpolate import BSpline

from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.limited_qp import LimitedQP
from fbspost.fbs.optimizer import AxisCompensator, compensate_axis
from fbspost.fbs.settings import AxisLimits, FBSSettings
from fbspost.fbs.windows import Window
from fbspost.profile import load_profile
from fbspost.tools.examples import butterfly
from reference import finite_derivative_max, rms, simulate_lsim

PATENT = load_profile("patent-xy-stage")
T = 1.0 / PATENT.sample_rate_hz
SKIP = int(0.05 / T)  # the must-show metric starts after the first 50 ms


@pytest.fixture(scope="module")
def butterfly_xy():
    _, x, y = butterfly(sample_rate_hz=PATENT.sample_rate_hz, size_mm=0.8)
    return {"X": x, "Y": y}


@pytest.fixture(scope="module")
def butterfly_results(butterfly_xy):
    """Limited and complete look-ahead, with the profile's limits, on both axes."""
    out = {}
    for axis, desired in butterfly_xy.items():
        dynamics = AxisDynamics(PATENT.axes[axis].modes, T)
        limits = AxisLimits.from_profile(PATENT.axes[axis])
        out[axis] = {mode: compensate_axis(desired, dynamics, limits, lookahead=mode)
                     for mode in ("limited", "complete")}
    return out


def tracking_rms(axis, desired, command):
    return rms((desired - simulate_lsim(PATENT.axes[axis].modes, T, command))[SKIP:])


def smooth_move(distance_mm, duration_s, rest_s, period_s):
    """Minimum-jerk point-to-point move followed by a rest (closed form, starts and ends at rest)."""
    t = np.arange(int(round((duration_s + rest_s) / period_s)) + 1) * period_s
    s = np.clip(t / duration_s, 0.0, 1.0)
    return distance_mm * (10 * s**3 - 15 * s**4 + 6 * s**5)


# ---- must show: the butterfly on the patent stage ---------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("axis", ["X", "Y"])
def test_butterfly_error_at_most_2_percent_within_limits(butterfly_xy, butterfly_results, axis):
    desired = butterfly_xy[axis]
    result = butterfly_results[axis]["limited"]
    command = result.command_mm
    before = tracking_rms(axis, desired, desired)
    after = tracking_rms(axis, desired, command)
    assert after <= 0.02 * before, f"{axis}: {after / before:.3%} of the uncompensated RMS"
    assert result.windows > 10  # the look-ahead really was limited
    assert finite_derivative_max(command, 1, T) <= 100.0 * (1 + 1e-6)
    assert finite_derivative_max(command, 2, T) <= 8000.0 * (1 + 1e-6)
    # Same duration, starts at rest at the first desired position, ends exactly at the last.
    assert command.shape == desired.shape
    assert command[0] == desired[0] and command[-1] == desired[-1]
    assert not result.warnings


@pytest.mark.slow
@pytest.mark.parametrize("axis", ["X", "Y"])
def test_limited_lookahead_matches_complete(butterfly_xy, butterfly_results, axis):
    desired = butterfly_xy[axis]
    limited = tracking_rms(axis, desired, butterfly_results[axis]["limited"].command_mm)
    complete = tracking_rms(axis, desired, butterfly_results[axis]["complete"].command_mm)
    assert butterfly_results[axis]["complete"].windows == 1
    assert abs(limited - complete) <= 0.01 * complete


@pytest.mark.slow
def test_binding_limit_no_worse_than_best_clipped_solution(butterfly_xy, butterfly_results):
    """Y's stop needs more than 8000 mm/s^2 unconstrained. The QP meets the limit to 1e-6 and
    tracks at least as well as the best blend of the unconstrained command with the desired
    trajectory that meets the limits (the blend factor found by bisection here)."""
    axis, desired = "Y", butterfly_xy["Y"]
    dynamics = AxisDynamics(PATENT.axes[axis].modes, T)
    free = compensate_axis(desired, dynamics, AxisLimits()).command_mm
    assert finite_derivative_max(free, 2, T) > 8000.0 * 1.5  # the limit really binds

    def feasible(lam):
        u = desired + lam * (free - desired)
        return finite_derivative_max(u, 1, T) <= 100.0 and finite_derivative_max(u, 2, T) <= 8000.0

    lo, hi = 0.0, 1.0
    assert feasible(lo)
    for _ in range(50):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if feasible(mid) else (lo, mid)
    clipped = desired + lo * (free - desired)
    constrained = butterfly_results[axis]["limited"].command_mm
    assert finite_derivative_max(constrained, 2, T) <= 8000.0 * (1 + 1e-6)
    assert finite_derivative_max(constrained, 2, T) >= 8000.0 * (1 - 1e-5)  # active, to OSQP's tolerance
    assert tracking_rms(axis, desired, constrained) <= tracking_rms(axis, desired, clipped)


@pytest.mark.slow
def test_jerk_limit_binds_inside_windows(butterfly_xy):
    """A jerk limit just above the desired trajectory's own jerk binds in regular windows too
    (with knots twice as dense as the default, whose command has more jerk to limit)."""
    axis, desired = "X", butterfly_xy["X"]
    dynamics = AxisDynamics(PATENT.axes[axis].modes, T)
    dense = FBSSettings(knot_spacing_samples=FBSSettings().resolve(dynamics).knot_spacing_samples // 2)
    jerk_limit = 1.1 * finite_derivative_max(desired, 3, T)
    free = compensate_axis(desired, dynamics, AxisLimits(), dense).command_mm
    assert finite_derivative_max(free[:-10000], 3, T) > 2 * jerk_limit
    result = compensate_axis(desired, dynamics, AxisLimits({1: 100.0, 2: 8000.0, 3: jerk_limit}), dense)
    assert result.qp_windows >= 2
    assert finite_derivative_max(result.command_mm, 3, T) <= jerk_limit * (1 + 1e-6)
    before = tracking_rms(axis, desired, desired)
    assert tracking_rms(axis, desired, result.command_mm) <= 0.05 * before


# ---- the formulation against a brute-force solve ----------------------------------------------

def brute_force_problem(desired, modes, settings, period_s):
    """The optimizer's problem written out densely: free control points p_0.. on uniform knots,
    p_i = x0 before the start, command held after the end, the settle rows weighted, the
    derivative-tracking rows, and the end conditions u(t_E) = x_E, u'(t_E) = u''(t_E) = 0."""
    m, k, settle = settings.degree, settings.knot_spacing_samples, settings.settle_samples
    last = desired.size - 1
    h = k * period_s
    n_free = last // k + 1
    knots = h * (np.arange(n_free + 2 * m + 1) - m)  # control points i = -m .. n_free-1
    rows = np.minimum(np.arange(last + 1 + settle), last) * period_s
    basis = BSpline.design_matrix(rows, knots, m).toarray()
    x0, x_end = desired[0], desired[-1]
    target = np.concatenate([desired, np.full(settle, x_end)])
    base = simulate_lsim(modes, period_s, basis[:, :m] @ np.full(m, x0))
    filtered = np.column_stack([simulate_lsim(modes, period_s, basis[:, j]) for j in range(m, m + n_free)])
    weights = np.ones(target.size)
    weights[last + 1:] = settings.settle_weight
    a_rows, b_rows = [weights[:, None] * filtered], [weights * (target - base)]
    for r, alpha in enumerate(settings.derivative_weights, start=1):
        a_rows.append(alpha * np.diff(filtered, r, axis=0) / period_s**r)
        b_rows.append(alpha * np.diff(target - base, r) / period_s**r)
    t_end = last * period_s
    eq = np.array([[BSpline.basis_element(knots[j:j + m + 2], extrapolate=False).derivative(r)(t_end)
                    if knots[j] <= t_end <= knots[j + m + 1] else 0.0 for j in range(m + n_free)]
                   for r in range(settings.end_rest_order + 1)])
    eq = np.nan_to_num(eq)
    eq_rhs = np.zeros(settings.end_rest_order + 1)
    eq_rhs[0] = x_end
    eq_rhs -= eq[:, :m] @ np.full(m, x0)
    return (np.vstack(a_rows), np.concatenate(b_rows), eq[:, m:], eq_rhs,
            lambda p: basis[:last + 1] @ np.concatenate([np.full(m, x0), p]))


def test_complete_lookahead_equals_brute_force_least_squares():
    axis = PATENT.axes["X"]
    desired = smooth_move(3.0, 0.12, 0.03, T)
    settings = FBSSettings(knot_spacing_samples=25, settle_samples=400, settle_weight=0.5,
                           derivative_weights=(2e-3,))
    dynamics = AxisDynamics(axis.modes, T)
    ours = compensate_axis(desired, dynamics, AxisLimits(), settings, lookahead="complete").command_mm
    a, b, c, d, command = brute_force_problem(desired, axis.modes, settings.resolve(dynamics), T)
    # Equality-constrained least squares through the null space of the end conditions.
    particular = np.linalg.lstsq(c, d, rcond=None)[0]
    _, _, vt = np.linalg.svd(c)
    null = vt[c.shape[0]:].T
    z = np.linalg.lstsq(a @ null, b - a @ particular, rcond=None)[0]
    truth = command(particular + null @ z)
    assert np.abs(ours - truth).max() <= 1e-7 * np.ptp(desired)


def qp_move(limits):
    """Y's 2 mm move, complete look-ahead, under ``limits`` (AxisLimits): (desired, its settings
    resolved, the unconstrained command, ours)."""
    axis = PATENT.axes["Y"]
    desired = smooth_move(2.0, 0.1, 0.03, T)
    dynamics = AxisDynamics(axis.modes, T)
    settings = FBSSettings(knot_spacing_samples=40, settle_samples=300)
    free = compensate_axis(desired, dynamics, AxisLimits(), settings, lookahead="complete").command_mm
    ours = compensate_axis(desired, dynamics, limits(free), settings, lookahead="complete")
    assert ours.qp_windows == 1 and not ours.warnings
    return desired, settings.resolve(dynamics), free, ours.command_mm


def assert_kkt(desired, settings, ours, active_rows):
    """``ours`` satisfies the KKT conditions of the written-out problem (so it is the global optimum
    of this convex QP): the objective's gradient is cancelled by nonnegative multipliers on the
    active rows and free ones on the end conditions (found by NNLS here). ``active_rows(jac, p,
    base)``: the active rows (samples by control points), each signed to point out of the feasible set."""
    a, b, c, d, command = brute_force_problem(desired, PATENT.axes["Y"].modes, settings, T)
    n = c.shape[1]
    base = command(np.zeros(n))
    jac = np.column_stack([command(e) - base for e in np.eye(n)])  # samples per control point
    p = np.linalg.lstsq(jac, ours - base, rcond=None)[0]
    assert np.abs(command(p) - ours).max() < 1e-9
    # End conditions (position, velocity, acceleration rows), each relative to its own scale.
    assert np.all(np.abs(c @ p - d) <= 1e-9 * np.ptp(desired) * np.abs(c).sum(axis=1))
    active = active_rows(jac, p, base)
    assert len(active) >= 1
    gradient = 2 * a.T @ (a @ p - b)
    # grad + sum lam_i G_i + c^T mu = 0, lam >= 0, mu = mu+ - mu-.
    directions = np.hstack([active.T, c.T, -c.T])
    scale = np.abs(directions).max(axis=0)
    directions, scale = directions[:, scale > 0], scale[scale > 0]  # (samples at rest before the move: fixed)
    _, residual = optimize.nnls(directions / scale, -gradient, maxiter=50 * directions.shape[1])
    assert residual <= 1e-6 * np.linalg.norm(gradient)


def test_constrained_solve_is_the_qp_optimum():
    """Acceleration limited to 70% of what the unconstrained command uses: our command meets the
    limit and is the QP's optimum (``assert_kkt``)."""
    desired, settings, free, ours = qp_move(lambda free: AxisLimits({2: 0.7 * finite_derivative_max(free, 2, T)}))
    limit = 0.7 * finite_derivative_max(free, 2, T)
    assert finite_derivative_max(ours, 2, T) <= limit * (1 + 1e-6)

    def accel_rows(jac, p, base):
        """Acceleration rows over the samples, the rest before the start and the hold after the end."""
        n = jac.shape[1]
        padded_jac = np.vstack([np.zeros((2, n)), jac, np.repeat(jac[-1:], 2, axis=0)])
        padded_base = np.concatenate([[desired[0]] * 2, base, [base[-1]] * 2])
        rows, offset = np.diff(padded_jac, 2, axis=0) / T**2, np.diff(padded_base, 2) / T**2
        accel = rows @ p + offset
        assert np.abs(accel).max() <= limit * (1 + 1e-6)
        active = np.abs(accel) >= limit * (1 - 1e-6)
        return np.sign(accel[active])[:, None] * rows[active]

    assert_kkt(desired, settings, ours, accel_rows)


def test_travel_rows_hold_and_the_command_is_the_qp_optimum():
    """The travel 0..2 mm, where the desired move 0 -> 2 mm goes (the unconstrained command goes
    beyond 2 mm to cancel Y's modes): our command stays within it and is the QP's optimum with the
    travel as inequalities on the samples (``assert_kkt``)."""
    desired, settings, free, ours = qp_move(lambda free: AxisLimits(position_mm=(0.0, 2.0)))
    assert free.max() > 2.05
    assert -1e-7 <= ours.min() and ours.max() <= 2.0 + 1e-7
    assert_kkt(desired, settings, ours, lambda jac, p, base: np.vstack([jac[ours >= 2.0 - 1e-6],
                                                                        -jac[ours <= 1e-6]]))


@pytest.mark.parametrize("travel_mm", [(0.0, 2.0), (0.0, np.inf), (-np.inf, 2.0)], ids=["both", "min", "max"])
def test_travel_holds_window_by_window(travel_mm):
    """Three strokes 0 -> 2 -> 0 mm on X, limited look-ahead (15 windows), the travel at the
    strokes' own ends (the unconstrained command goes 12 um below 0 and beyond 2 mm): every sample
    within it to the optimizer's tolerance (relative to half the band, 500 mm where an end is open),
    and the tracking error (scipy's simulation) still under a fifth of the uncompensated one."""
    axis = PATENT.axes["X"]
    stroke = np.concatenate([smooth_move(2.0, 0.1, 0.2, T), 2.0 - smooth_move(2.0, 0.1, 0.3, T)])
    desired = np.tile(stroke, 3)
    dynamics = AxisDynamics(axis.modes, T)
    free = compensate_axis(desired, dynamics, AxisLimits()).command_mm
    assert free.min() < -0.01 and free.max() > 2.01
    limits = AxisLimits(position_mm=travel_mm)
    result = compensate_axis(desired, dynamics, limits)
    slack = 1e-7 * limits.position_half_mm
    assert result.windows >= 10 and not result.warnings
    assert travel_mm[0] - slack <= result.command_mm.min() and result.command_mm.max() <= travel_mm[1] + slack
    assert tracking_rms("X", desired, result.command_mm) < 0.2 * tracking_rms("X", desired, desired)


# ---- behaviour at the edges -------------------------------------------------------------------

def test_constant_trajectory_is_returned_unchanged():
    dynamics = AxisDynamics(PATENT.axes["X"].modes, T)
    desired = np.full(5000, 12.5)
    assert np.array_equal(compensate_axis(desired, dynamics, AxisLimits()).command_mm, desired)


def test_trajectory_shorter_than_a_window():
    """A 20 ms move: a single (final) window, still at rest at both ends, still much better."""
    axis = PATENT.axes["X"]
    desired = smooth_move(0.2, 0.02, 0.0, T)
    result = compensate_axis(desired, AxisDynamics(axis.modes, T), AxisLimits.from_profile(axis))
    assert result.windows == 1
    assert result.command_mm[-1] == desired[-1] and result.command_mm[0] == desired[0]
    assert finite_derivative_max(result.command_mm, 2, T) <= 8000.0 * (1 + 1e-6)


def test_output_limit_binds_on_modelled_motion():
    """A limit on the modelled output's velocity, below what the tracked motion would need, holds
    on the output simulated by scipy (to the tolerance of the exact discretization)."""
    axis = PATENT.axes["X"]
    desired = smooth_move(2.0, 0.08, 0.05, T)
    dynamics = AxisDynamics(axis.modes, T)
    settings = FBSSettings(knot_spacing_samples=40)
    free = compensate_axis(desired, dynamics, AxisLimits(), settings)
    out_free = simulate_lsim(axis.modes, T, free.command_mm)
    limit = 0.9 * finite_derivative_max(out_free, 1, T)
    result = compensate_axis(desired, dynamics, AxisLimits(output={1: limit}), settings)
    assert result.qp_windows >= 1
    out = simulate_lsim(axis.modes, T, result.command_mm)
    assert finite_derivative_max(out, 1, T) <= limit * (1 + 1e-6)


def test_printer_profile_at_1khz_compensates_a_move():
    """The bundled printer profile at its own 1 kHz grid: a 40 mm move at ~150 mm/s, 20x better."""
    profile = load_profile("bedslinger-example")
    period_s = 1.0 / profile.sample_rate_hz
    desired = smooth_move(40.0, 0.45, 0.2, period_s)
    for name, axis in ((n, a) for n, a in profile.axes.items() if a.modes):
        result = compensate_axis(desired, AxisDynamics(axis.modes, period_s), AxisLimits.from_profile(axis))
        before = rms(desired - simulate_lsim(axis.modes, period_s, desired))
        after = rms(desired - simulate_lsim(axis.modes, period_s, result.command_mm))
        assert after <= before / 20, name
        assert finite_derivative_max(result.command_mm, 2, period_s) <= axis.max_acceleration_mm_s2 * (1 + 1e-6)


def test_settings_are_chosen_from_the_dynamics_and_overridable():
    dynamics = AxisDynamics(PATENT.axes["X"].modes, T)
    auto = FBSSettings().resolve(dynamics)
    highest = max(m.frequency_hz for m in PATENT.axes["X"].modes)
    assert auto.knot_spacing_samples == int(PATENT.sample_rate_hz / (6 * highest))
    # Look-ahead: the RHP zero at +230.9 rad/s decays by 1e-6 in ln(1e6)/230.9 s, or one period
    # of the lowest mode (20.52 Hz), whichever is longer.
    lookahead_s = max(np.log(1e6) / 230.9, 1 / 20.52)
    assert auto.overlap_spans == pytest.approx(lookahead_s / (auto.knot_spacing_samples * T), abs=1.01)
    manual = FBSSettings(knot_spacing_samples=7, commit_spans=11, overlap_spans=13).resolve(dynamics)
    assert (manual.knot_spacing_samples, manual.commit_spans, manual.overlap_spans) == (7, 11, 13)


def test_bad_desired_trajectory_is_rejected():
    dynamics = AxisDynamics(PATENT.axes["X"].modes, T)
    for bad in (np.array([]), np.array([0.0, np.nan, 1.0]), np.zeros((3, 2))):
        with pytest.raises(ValueError):
            compensate_axis(bad, dynamics, AxisLimits())


@pytest.mark.parametrize("machine, axis_name, spacing", [("bedslinger-example", "Y", 9), ("patent-xy-stage", "X", 21)])
def test_knot_spacings_whose_products_round_badly(machine, axis_name, spacing):
    """Spacings where -m*K*T + m*K*T != 0 in floating point (9 samples at 1 kHz, 21 at 10 kHz)."""
    profile = load_profile(machine)
    period_s = 1.0 / profile.sample_rate_hz
    axis = profile.axes[axis_name]
    desired = smooth_move(10.0, 0.3, 0.2, period_s)
    result = compensate_axis(desired, AxisDynamics(axis.modes, period_s), AxisLimits.from_profile(axis),
                             FBSSettings(knot_spacing_samples=spacing))
    before = rms(desired - simulate_lsim(axis.modes, period_s, desired))
    assert rms(desired - simulate_lsim(axis.modes, period_s, result.command_mm)) < before / 5


@pytest.mark.parametrize("spans", [7, 11, 73])
def test_run_ending_on_a_knot_whose_time_rounds_low(spans):
    """Y of the patent stage (K = 38 samples at 10 kHz): a run whose last sample is the final
    window's last knot, where (spans * K) * T > (K * T) * spans in floating point (the sample an
    ulp past the spline's end; a 5-axis program's short run crashed there). Compensated, at rest
    at both ends, better than the original (scipy's simulation)."""
    axis = PATENT.axes["Y"]
    dynamics = AxisDynamics(axis.modes, T)
    k = FBSSettings().resolve(dynamics).knot_spacing_samples
    assert k == 38 and (spans * k) * T > (k * T) * spans
    desired = 0.5 * (1.0 - np.cos(np.pi * np.arange(spans * k + 1) / (spans * k)))
    result = compensate_axis(desired, dynamics, AxisLimits.from_profile(axis))
    assert result.command_mm[0] == desired[0] and result.command_mm[-1] == desired[-1]
    before = rms(desired - simulate_lsim(axis.modes, T, desired))
    assert rms(desired - simulate_lsim(axis.modes, T, result.command_mm)) < before


def test_motion_too_short_to_shape_is_returned_as_planned():
    """Five samples of motion cannot satisfy the end conditions with a free point to spare."""
    dynamics = AxisDynamics(PATENT.axes["X"].modes, T)
    desired = np.array([0.0, 0.001, 0.003, 0.004, 0.004])
    assert np.array_equal(compensate_axis(desired, dynamics, AxisLimits()).command_mm, desired)


@pytest.mark.slow
def test_limits_that_cannot_be_met_are_reported():
    """60 mm to cover in the 0.5 s between the start and the last sample against a 100 mm/s
    limit: no command can meet it (it starts at rest and must end there), and the result says
    where."""
    axis = PATENT.axes["X"]
    desired = smooth_move(60.0, 0.4, 0.1, T)
    assert 60.0 / (desired.size * T) > 100.0
    result = compensate_axis(desired, AxisDynamics(axis.modes, T), AxisLimits({1: 100.0}))
    assert result.warnings and result.warnings[0].startswith("window from sample")
    assert "could not be met" in result.warnings[0]


def kkt_certified(H, g, A, offset, p, E=None, e=None, residual_tol=1e-8):
    """Whether ``p`` is the optimum of min 1/2 p'Hp - g'p s.t. |A p + offset| <= 1 (and E p = e):
    it meets every row, and the gradient is cancelled by nonnegative multipliers on the rows at
    their bounds and free ones on E (found by NNLS here)."""
    E = np.zeros((0, len(p))) if E is None else E
    value = A @ p + offset
    active = np.abs(value) >= 1 - 1e-9
    gradient = H @ p - g
    directions = np.hstack([(np.sign(value[active])[:, None] * A[active]).T, E.T, -E.T])
    scale = np.maximum(np.abs(directions).max(axis=0, initial=0.0), 1e-300)
    _, residual = optimize.nnls(directions / scale, -gradient, maxiter=50 * directions.shape[1] + 100)
    return (np.abs(value).max() <= 1 + 1e-7 and active.any() and (not len(E) or np.allclose(E @ p, e, atol=1e-12))
            and residual <= residual_tol * max(1.0, np.linalg.norm(g)))


class Problem(SimpleNamespace):
    """A window as the solvers see it (a subclass, so that its QP can hold a weak proxy of it)."""


def random_window(seed, equalities):
    """A random problem min 1/2 p'Hp - g'p s.t. |A p + offset| <= 1 (and E p = e, as in a final
    window) whose limits bind, as the solvers see it: a window with its factorization."""
    rng = np.random.default_rng(seed)
    n, rows = 8, 30
    root = rng.standard_normal((n, n))
    H = root @ root.T + 0.1 * np.eye(n)
    A = rng.standard_normal((rows, n)) * (rng.random((rows, n)) < 0.4)
    offset = rng.uniform(-0.5, 0.5, rows)
    g = rng.standard_normal(n) * 5
    E, e = rng.standard_normal((equalities, n)), rng.uniform(-0.2, 0.2, equalities)
    kkt = np.block([[H, E.T], [E, np.zeros((equalities, equalities))]])
    window = Problem(A_free=sparse.csc_matrix(A), n_free=n, H=H, E=E if equalities else None,
                     factor=linalg.lu_factor(kkt) if equalities else linalg.cho_factor(H))
    window.violation = Window.violation.__get__(window)
    window.qp = LimitedQP(window)
    p_free = np.linalg.solve(kkt, np.concatenate([g, e]))[:n]
    assert np.abs(A @ p_free + offset).max() > 1  # the limits bind
    return window, H, g, A, offset, E, e, p_free


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("solver, equalities", [("active_set", 0), ("active_set", 2), ("least_distance", 0)])
def test_dual_active_set_step_is_the_qp_optimum(seed, solver, equalities):
    """The QP step on random problems, by either solver (Goldfarb-Idnani on the factored window,
    DAQP on its least-distance form): its point is KKT-certified (so the optimum), and no
    feasible point SLSQP finds is better."""
    window, H, g, A, offset, E, e, p_free = random_window(seed, equalities)
    ours = getattr(window.qp, solver)(p_free, offset)
    assert kkt_certified(H, g, A, offset, ours, E, e)

    def objective(p):
        return 0.5 * p @ H @ p - g @ p

    def rows_of(p):
        return np.concatenate([1 - (A @ p + offset), 1 + (A @ p + offset)])

    constraints = [{"type": "ineq", "fun": rows_of, "jac": lambda p: np.vstack([-A, A])}]
    if equalities:
        constraints.append({"type": "eq", "fun": lambda p: E @ p - e, "jac": lambda p: E})
    reference = optimize.minimize(objective, p_free, jac=lambda p: H @ p - g, method="SLSQP", constraints=constraints)
    if rows_of(reference.x).min() >= -1e-9 and np.allclose(E @ reference.x, e, atol=1e-9):
        assert objective(ours) <= objective(reference.x) + 1e-9 * abs(objective(reference.x))


def corner_moves(period_s, moves=12, distance_mm=3.0, speed_mm_s=60.0, accel_mm_s2=3000.0):
    """Back-and-forth moves that stop at every corner, each a trapezoid in velocity (acceleration
    steps at its corners, as a planner writes them), by exact integration of the acceleration."""
    ramp = int(round(speed_mm_s / accel_mm_s2 / period_s))
    cruise = int(round((distance_mm - speed_mm_s**2 / accel_mm_s2) / speed_mm_s / period_s))
    one = np.concatenate([np.full(ramp, accel_mm_s2), np.zeros(cruise), np.full(ramp, -accel_mm_s2)])
    accel = np.concatenate([np.tile(np.concatenate([one, -one]), moves // 2), np.zeros(200)])
    velocity = np.concatenate([[0.0], np.cumsum(accel)]) * period_s
    return np.concatenate([[0.0], np.cumsum(velocity[:-1] + 0.5 * accel * period_s) * period_s])


def test_daqp_is_the_optimum_of_the_hard_cases_corner_windows(monkeypatch):
    """The corner windows of printer-two-mode's X axis (52 + 96 Hz) with a knot at every sample
    (the hardest windows: 120 points, 240 limit rows, cond(H) ~ 1e12): DAQP's point is
    KKT-certified on every window whose limits bind, and its objective is Goldfarb-Idnani's (an
    exact method) to 1e-9."""
    axis = load_profile("printer-two-mode").axes["X"]
    dynamics = AxisDynamics(axis.modes, 1e-3)
    windows = []
    constrained = Window.constrained
    monkeypatch.setattr(Window, "constrained", lambda self, target, p_fixed, offset, end_values, warm: windows.append(
        (self, target, offset, warm)) or constrained(self, target, p_fixed, offset, end_values, warm))
    result = AxisCompensator(dynamics, AxisLimits.from_profile(axis), FBSSettings(knot_spacing_samples=1))(
        corner_moves(1e-3)
    )
    regular = [w for w in windows if w[0].E is None]
    assert len(regular) >= 8 and not result.warnings
    for window, target, offset, warm in regular[:8]:
        A, g = window.A_free.toarray(), window.gradient(target)
        daqp_p, exact_p = window.qp.least_distance(warm, offset), window.qp.active_set(warm, offset)
        assert kkt_certified(window.H, g, A, offset, daqp_p, residual_tol=1e-6)

        def objective(p, window=window, g=g):
            return 0.5 * p @ window.H @ p - g @ p

        assert abs(objective(daqp_p) - objective(exact_p)) <= 1e-9 * abs(objective(exact_p))


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_stream_in_pieces_equals_the_whole_run_bit_for_bit(seed):
    """A run pushed in random pieces (some empty, some a single sample) gives exactly the samples
    of the run in one piece, with the limits binding in places; each push gives only samples
    that are final, in order."""
    axis = PATENT.axes["X"]
    dynamics = AxisDynamics(axis.modes, T)
    there_and_back = np.concatenate([smooth_move(2.0, 0.06, 0.3, T), 2.0 - smooth_move(2.0, 0.06, 0.3, T)[1:]])
    desired = np.tile(there_and_back, 4)
    compensator = AxisCompensator(dynamics, AxisLimits({1: 100.0, 2: 8000.0}))
    whole = compensator(desired)
    assert whole.qp_windows >= 1 and whole.windows >= 3
    rng = np.random.default_rng(seed)
    cuts = np.sort(rng.choice(np.arange(desired.size), 12, replace=False))
    cuts = np.concatenate([[0], cuts, cuts[:2], [cuts[3] + 1], [desired.size]])
    cuts.sort()
    stream, pieces = compensator.stream(), []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        pieces.append(stream.push(desired[a:b]))
        assert sum(p.size for p in pieces) <= b
    result = stream.finish()
    streamed = np.concatenate(pieces + [result.command_mm])
    assert np.array_equal(streamed, whole.command_mm)
    assert (result.windows, result.qp_windows) == (whole.windows, whole.qp_windows)

