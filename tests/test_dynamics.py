"""Tests of fbspost.fbs.dynamics.AxisDynamics against independent truths.

Truths used: the closed-form step response of one second-order mode, scipy.signal.lsim of the
continuous modal state space built here, scipy.signal.freqs / freqresp, closed-form poles,
a root of G on the real axis found with scipy.optimize.brentq, brute-force state stepping,
and the exact zero-order-hold impulse response from scipy.linalg.expm.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import linalg, optimize, signal

from fbspost.fbs.dynamics import AxisDynamics
from fbspost.profile import Mode, load_profile

PATENT = load_profile("patent-xy-stage")
BEDSLINGER = load_profile("bedslinger-example")
LOADED_AXES = [("patent", "X"), ("patent", "Y"), ("bedslinger", "X"), ("bedslinger", "Y")]


def modes_of(profile_name: str, axis: str):
    return {"patent": PATENT, "bedslinger": BEDSLINGER}[profile_name].axes[axis].modes


def continuous_ss(modes):
    """Block-diagonal continuous state space of sum_i (a_i + b_i s)/(s^2 + 2 z_i w_i s + w_i^2)."""
    blocks, bs, cs = [], [], []
    for m in modes:
        w, z = 2 * math.pi * m.frequency_hz, m.damping
        blocks.append(np.array([[0.0, 1.0], [-w * w, -2 * z * w]]))
        bs.append([0.0, 1.0])
        cs.append([m.alpha, m.beta])
    return linalg.block_diag(*blocks), np.concatenate(bs)[:, None], np.concatenate(cs)[None, :]


def G(modes, s):
    """Eq. 1 of the patent evaluated at complex s, written out here."""
    s = np.asarray(s, dtype=complex)
    total = 0
    for m in modes:
        w = 2 * math.pi * m.frequency_hz
        total = total + (m.alpha + m.beta * s) / (s * s + 2 * m.damping * w * s + w * w)
    return total


def closed_form_step(mode: Mode, t: np.ndarray) -> np.ndarray:
    """Step response of (a + b s)/(s^2 + 2 z w s + w^2), underdamped."""
    w, z, a, b = 2 * math.pi * mode.frequency_hz, mode.damping, mode.alpha, mode.beta
    wd = w * math.sqrt(1 - z * z)
    e = np.exp(-z * w * t)
    return (a / w**2 * (1 - e * (np.cos(wd * t) + z / math.sqrt(1 - z * z) * np.sin(wd * t)))
            + b / wd * e * np.sin(wd * t))


STEP_MODES = [
    Mode(30.0, 0.05, (2 * math.pi * 30.0) ** 2, 0.0),
    Mode(12.0, 0.3, 4000.0, 40.0),
    Mode(80.0, 0.7, 1.5e5, -200.0),
]


@pytest.mark.parametrize("T", [1e-4, 1e-3])
@pytest.mark.parametrize("mode", STEP_MODES, ids=["30Hz-b0", "12Hz-b40", "80Hz-b-200"])
def test_step_response_closed_form(mode, T):
    """filter(ones) is the ZOH step response: y[k] equals the continuous step response at t = k T."""
    n = int(round(0.6 / T))
    t = np.arange(n) * T
    truth = closed_form_step(mode, t)
    y = AxisDynamics([mode], T).filter(np.ones(n))
    assert y[0] == 0.0
    peak = np.max(np.abs(truth))
    np.testing.assert_allclose(y, truth, rtol=0, atol=1e-10 * peak)


def test_step_response_two_modes_is_sum():
    """Two modes in parallel: the step response is the sum of the two closed forms."""
    T, n = 1e-4, 5000
    t = np.arange(n) * T
    truth = closed_form_step(STEP_MODES[0], t) + closed_form_step(STEP_MODES[1], t)
    y = AxisDynamics(STEP_MODES[:2], T).filter(np.ones(n))
    np.testing.assert_allclose(y, truth, rtol=0, atol=1e-10 * np.max(np.abs(truth)))


def minimum_jerk(t, t0, duration, x0, x1):
    tau = np.clip((t - t0) / duration, 0.0, 1.0)
    return x0 + (x1 - x0) * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)


@pytest.mark.parametrize("axis", ["X", "Y"])
def test_simulate_matches_lsim(axis):
    """simulate(command) equals scipy.signal.lsim of the continuous modal model, started at rest at
    command[0], with each coarse sample held over its period (repeated on a 10x finer grid)."""
    modes = PATENT.axes[axis].modes
    T, fine = 1.0 / PATENT.sample_rate_hz, 10
    n = 3000
    t = np.arange(n) * T
    command = (minimum_jerk(t, 0.02, 0.08, 5.0, 15.0) + minimum_jerk(t, 0.15, 0.05, 0.0, -3.0)
               + 0.2 * np.sin(2 * np.pi * 40 * t) * (t > 0.22) * np.sin(np.pi * np.clip((t - 0.22) / 0.05, 0, 1)) ** 2)
    A, B, C = continuous_ss(modes)
    # rest at command[0]: position states u0 / w^2, velocity states 0
    x0 = np.concatenate([[command[0] / (2 * math.pi * m.frequency_hz) ** 2, 0.0] for m in modes])
    t_fine = np.arange(n * fine) * (T / fine)
    _, y_fine, _ = signal.lsim((A, B, C, np.zeros((1, 1))), np.repeat(command, fine), t_fine, X0=x0, interp=False)
    truth = y_fine[::fine]
    y = AxisDynamics(modes, T).simulate(command)
    amplitude = np.ptp(command)
    np.testing.assert_allclose(y, truth, rtol=0, atol=1e-9 * amplitude)
    assert np.max(np.abs(y - command)) > 1e-3 * amplitude  # the dynamics are not trivially identity


@pytest.mark.parametrize("profile_name,axis", LOADED_AXES)
def test_dc_gain_and_long_step(profile_name, axis):
    """Normalized profiles: DC gain 1, a 10 s step settles at 1, G(0) = 1."""
    modes = modes_of(profile_name, axis)
    dyn = AxisDynamics(modes, 1e-3)
    assert dyn.dc_gain == pytest.approx(1.0, abs=1e-12)
    y = dyn.filter(np.ones(10_000))
    assert y[-1] == pytest.approx(1.0, abs=1e-6)
    assert abs(G(modes, 0.0) - 1) < 1e-12  # the test's own formula agrees
    assert abs(dyn.frequency_response(0.0) - 1) < 1e-12


@pytest.mark.parametrize("profile_name,axis", LOADED_AXES)
def test_frequency_response_vs_scipy(profile_name, axis):
    """frequency_response(f) = sum of scipy.signal.freqs of each mode = scipy.signal.freqresp of the
    block-diagonal continuous system."""
    modes = modes_of(profile_name, axis)
    f = np.array([0.5, 5.0, 17.86, 20.52, 36.0, 42.55, 48.0, 100.0, 400.0])
    w = 2 * np.pi * f
    by_freqs = sum(signal.freqs([m.beta, m.alpha], [1.0, 2 * m.damping * m.omega_rad_s, m.omega_rad_s**2],
                                worN=w)[1] for m in modes)
    A, B, C = continuous_ss(modes)
    with warnings.catch_warnings():  # the tf conversion warns about a zero leading numerator coefficient
        warnings.simplefilter("ignore", signal.BadCoefficients)
        _, by_freqresp = signal.freqresp(signal.StateSpace(A, B, C, np.zeros((1, 1))), w=w)
    got = AxisDynamics(modes, 1e-4).frequency_response(f)
    scale = np.abs(by_freqs)
    assert np.all(np.abs(got - by_freqs) <= 1e-12 * np.maximum(scale, 1e-3))
    assert np.all(np.abs(got - by_freqresp) <= 1e-9 * np.maximum(scale, 1e-3))


@pytest.mark.parametrize("axis,expected", [("X", 230.9), ("Y", 151.1)])
def test_right_half_plane_zero(axis, expected):
    """Each patent axis has exactly one RHP zero (X ~ +230.9, Y ~ +151.1 rad/s); it is where G(s),
    evaluated here, vanishes, and brentq on real s finds the same root."""
    modes = PATENT.axes[axis].modes
    zeros = AxisDynamics(modes, 1e-4).zeros()
    assert len(zeros) == 2 * len(modes) - 1  # sum(beta) != 0: numerator of degree 2M - 1
    rhp = zeros[zeros.real > 0]
    assert len(rhp) == 1
    z = rhp[0]
    assert abs(z.imag) < 1e-9 and abs(z.real - expected) < 0.1
    root = optimize.brentq(lambda s: G(modes, s).real, 50.0, 1000.0, xtol=1e-12)
    assert z.real == pytest.approx(root, rel=1e-9)
    # every returned zero is a zero of G relative to its DC value 1
    for zero in zeros:
        assert abs(G(modes, zero)) < 1e-8 * abs(G(modes, 0.0))


def test_zeros_of_single_mode():
    """One mode (a + b s)/(...): zero at -a/b; none when b = 0."""
    m = Mode(30.0, 0.1, 2e4, 50.0)
    np.testing.assert_allclose(AxisDynamics([m], 1e-3).zeros(), [-2e4 / 50.0], rtol=1e-12)
    assert len(AxisDynamics([Mode(30.0, 0.1, 2e4, 0.0)], 1e-3).zeros()) == 0


@pytest.mark.parametrize("profile_name,axis", LOADED_AXES)
def test_poles_closed_form(profile_name, axis):
    """Poles are -z w +/- j w sqrt(1 - z^2) for each mode."""
    modes = modes_of(profile_name, axis)
    truth = np.concatenate([[complex(-m.damping * w, s * w * math.sqrt(1 - m.damping**2)) for s in (1, -1)]
                            for m in modes for w in [2 * math.pi * m.frequency_hz]])
    got = AxisDynamics(modes, 1e-4).poles()

    def key(p):
        return round(p.real, 6), round(p.imag, 6)

    np.testing.assert_allclose(sorted(got, key=key), sorted(truth, key=key), rtol=1e-12)


@pytest.mark.parametrize("profile_name,axis", LOADED_AXES)
@pytest.mark.parametrize("x0", [0.0, 1.0, -37.5, 250.0])
def test_rest_state_is_fixed_point(profile_name, axis, x0):
    """rest_state(x0) is a fixed point of x -> A x + B x0 and its output C x is x0."""
    modes = modes_of(profile_name, axis)
    dyn = AxisDynamics(modes, 1.0 / {"patent": PATENT, "bedslinger": BEDSLINGER}[profile_name].sample_rate_hz)
    s = dyn.rest_state(x0)
    scale = max(abs(x0), 1.0)
    np.testing.assert_allclose(dyn.A @ s + dyn.B * x0, s, rtol=1e-12, atol=1e-15 * scale)
    assert abs(dyn.C @ s - x0) < 1e-9 * scale
    # and it is the continuous rest state (position states x0/w^2, velocities 0): ZOH keeps equilibria
    cont = np.concatenate([[x0 / (2 * math.pi * m.frequency_hz) ** 2, 0.0] for m in modes])
    np.testing.assert_allclose(s, cont, rtol=1e-8, atol=1e-12 * scale)


@pytest.mark.parametrize("profile_name,axis", [("patent", "X"), ("bedslinger", "Y")])
def test_block_matrices_vs_brute_force(profile_name, axis):
    """free_response_matrix / input_to_state_matrix / markov against stepping x[k+1] = A x + B u,
    y = C x from a random state with random inputs."""
    rng = np.random.default_rng(7)
    dyn = AxisDynamics(modes_of(profile_name, axis), 1e-3)
    n = 150
    x0 = rng.normal(size=dyn.n_states)
    u = rng.normal(size=n)
    x = x0.copy()
    y = np.empty(n)
    for k in range(n):
        y[k] = dyn.C @ x
        x = dyn.A @ x + dyn.B * u[k]
    free = dyn.free_response_matrix(n)
    h = dyn.markov(n)
    h_brute = np.array([0.0] + [dyn.C @ np.linalg.matrix_power(dyn.A, k - 1) @ dyn.B for k in range(1, n)])
    scale = np.max(np.abs(y))
    np.testing.assert_allclose(h, h_brute, rtol=0, atol=1e-12 * np.max(np.abs(h_brute)))
    np.testing.assert_allclose(free @ x0 + np.convolve(h_brute, u)[:n], y, rtol=0, atol=1e-11 * scale)
    final = np.linalg.matrix_power(dyn.A, n) @ x0 + dyn.input_to_state_matrix(n) @ u
    np.testing.assert_allclose(final, x, rtol=0, atol=1e-11 * np.max(np.abs(x)))
    assert free.shape == (n, dyn.n_states) and dyn.input_to_state_matrix(n).shape == (dyn.n_states, n)


def exact_zoh_impulse(mode: Mode, T: float, n: int) -> np.ndarray:
    """h[0] = 0, h[k] = C e^{A (k-1) T} (int_0^T e^{A s} ds) B, integral from expm of [[A, B], [0, 0]] T."""
    w, z = 2 * math.pi * mode.frequency_hz, mode.damping
    A = np.array([[0.0, 1.0], [-w * w, -2 * z * w]])
    B = np.array([0.0, 1.0])
    C = np.array([mode.alpha, mode.beta])
    aug = np.zeros((3, 3))
    aug[:2, :2] = A * T
    aug[:2, 2] = B * T
    gamma = linalg.expm(aug)[:2, 2]
    phis = linalg.expm(A[None] * (np.arange(n - 1) * T)[:, None, None])  # e^{A (k-1) T}, k = 1..n-1
    return np.concatenate([[0.0], C @ phis @ gamma])


@pytest.mark.slow
@settings(max_examples=30, deadline=None)
@given(freq=st.floats(5.0, 200.0), damping=st.floats(0.01, 0.9), dc=st.floats(0.1, 3.0),
       beta=st.floats(-50.0, 50.0))
def test_markov_equals_exact_zoh_impulse(freq, damping, dc, beta):
    """For any single mode at T = 1 ms, markov(n) is the exact ZOH impulse response (expm truth)."""
    T, n = 1e-3, 120
    alpha = dc * (2 * math.pi * freq) ** 2
    mode = Mode(freq, damping, alpha, beta)
    truth = exact_zoh_impulse(mode, T, n)
    h = AxisDynamics([mode], T).markov(n)
    assert h[0] == 0.0
    np.testing.assert_allclose(h, truth, rtol=0, atol=1e-10 * np.max(np.abs(truth)))


def test_no_modes_rejected():
    """An axis without modes has no model: ValueError."""
    with pytest.raises(ValueError):
        AxisDynamics([], 1e-3)


def test_zeros_ignore_cancelled_leading_coefficient():
    """Betas that cancel (0.1 + 0.2 - 0.3 rounds to 5.6e-17) leave a numerator of lower degree:
    no spurious zero near infinity. The remaining zeros make the summed G(s) vanish."""
    modes = [Mode(20.0, 0.1, 15000.0, 0.1), Mode(35.0, 0.2, 30000.0, 0.2), Mode(50.0, 0.05, 60000.0, -0.3)]
    dyn = AxisDynamics(modes, 1e-4)
    zeros = dyn.zeros()
    assert zeros.size == 2 * len(modes) - 2
    assert np.abs(zeros).max() < 1e4

    def g(s):
        return sum(
            (m.alpha + m.beta * s) / (s * s + 2 * m.damping * m.omega_rad_s * s + m.omega_rad_s**2) for m in modes
        )

    for z in zeros:
        assert abs(g(z)) < 1e-8 * abs(g(0.0))


@pytest.mark.parametrize("period", [0.0, -1e-4])
def test_sample_period_must_be_positive(period):
    with pytest.raises(ValueError):
        AxisDynamics([Mode(20.0, 0.1, 15791.4, 0.0)], period)


def test_empty_inputs():
    dyn = AxisDynamics([Mode(20.0, 0.1, 15791.4, 0.0)], 1e-4)
    assert dyn.simulate([]).size == 0 and dyn.markov(0).size == 0


def test_response_in_pieces_is_the_simulation():
    """The response to a command given in pieces (empty ones among them) is the response to the
    whole command: the modes' states carry over exactly."""
    dynamics = AxisDynamics(PATENT.axes["Y"].modes, 1e-4)
    command = np.cumsum(np.random.default_rng(5).normal(size=5000)) * 1e-3 + 3.0
    step = dynamics.response(command[0])
    cuts = [0, 0, 17, 17, 1000, 1001, 4321, 5000]
    pieces = np.concatenate([step(command[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)])
    assert np.array_equal(pieces, dynamics.simulate(command))


def test_zeros_of_modes_with_and_without_beta():
    """A mode without beta beside one with it (a mass and a belt on one axis): G vanishes at every
    zero returned (G summed from the modes, written out here), three of them (the numerator's
    degree: beta s times the other denominator; np.polymul dropped the first mode's 0 and crashed)."""
    modes = (Mode(40.0, 0.05, 63165.0, 0.0), Mode(80.0, 0.03, 50000.0, 30.0))
    zeros = AxisDynamics(modes, 1e-3).zeros()

    def g(s):
        return sum((m.alpha + m.beta * s) / (s * s + 2 * m.damping * m.omega_rad_s * s + m.omega_rad_s**2)
                   for m in modes)

    assert len(zeros) == 3
    scale = abs(g(1j * modes[0].omega_rad_s))
    for z in zeros:
        assert abs(g(z)) < 1e-9 * scale
