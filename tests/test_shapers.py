"""Klipper's input shapers against closed forms: what a shaped step leaves of an oscillator's
vibration (simulated with scipy, not computed from the impulses), the ZV/ZVD/MZV formulas and
MZV's defining equations, and shaping a ramp exactly."""
import math

import numpy as np
import pytest

from fbspost.firmware.shapers import SHAPERS, klipper_shaper, shape
from fbspost.profile import Mode
from reference import simulate_lsim

FINE_S = 1e-5  # the step simulations' sample period


def residual_ratio(shaper, frequency_hz, damping):
    """Vibration a shaped step leaves on a unit-DC oscillator at (frequency, damping), over what an
    unshaped step at the time of the last impulse leaves (Singhose's V, Klipper's measure)."""
    w = 2 * math.pi * frequency_hz
    mode = Mode(frequency_hz, damping, w * w, 0.0)
    t = np.arange(int(0.3 / FINE_S)) * FINE_S
    start = 0.05
    shaped = sum(a * (t >= start + tau) for a, tau in zip(shaper.amplitudes, shaper.times_s, strict=True))
    plain = (t >= start + shaper.lag_s).astype(float)
    after = t > start + shaper.lag_s + 1e-3
    # After the last impulse both are exp(-d w t) (C cos w_d t + S sin w_d t): fit C and S.
    wd = w * math.sqrt(1 - damping**2)
    basis = np.exp(-damping * w * t[after])[:, None] * np.column_stack([np.cos(wd * t[after]), np.sin(wd * t[after])])
    amplitude = [np.hypot(*np.linalg.lstsq(basis, simulate_lsim([mode], FINE_S, u)[after] - 1.0, rcond=None)[0])
                 for u in (shaped, plain)]
    return amplitude[0] / amplitude[1]


@pytest.mark.parametrize("name, expected, tolerance", [
    ("zv", 0.0, 0.003), ("mzv", 0.0, 0.003), ("zvd", 0.0, 0.003), ("2hump_ei", 0.0, 0.005),
    ("ei", 0.05, 0.004), ("3hump_ei", 0.05, 0.004)])
@pytest.mark.parametrize("damping", [0.0, 0.1])
def test_vibration_left_at_the_design_mode(name, expected, tolerance, damping):
    """Zero for the zero-vibration shapers and 2-hump EI (zero at its centre), Klipper's 5 %
    tolerance for EI and 3-hump EI (their middle hump)."""
    shaper = klipper_shaper(name, 40.0, damping)
    assert residual_ratio(shaper, 40.0, damping) == pytest.approx(expected, abs=tolerance)


def test_shapers_suppress_less_away_from_the_design_frequency():
    """ZV at 40 Hz on a 50 Hz mode: V = |cos(pi/2 * 50/40)| for an undamped mode, closed form."""
    shaper = klipper_shaper("zv", 40.0, 0.0)
    assert residual_ratio(shaper, 50.0, 0.0) == pytest.approx(abs(math.cos(math.pi / 2 * 50 / 40)), abs=0.003)


@pytest.mark.parametrize("name", SHAPERS)
@pytest.mark.parametrize("frequency_hz, damping", [(25.7, 0.021), (48.0, 0.08), (36.0, 0.15)])
def test_amplitudes_sum_to_one_and_times_are_centred(name, frequency_hz, damping):
    shaper = klipper_shaper(name, frequency_hz, damping)
    assert shaper.amplitudes.sum() == pytest.approx(1.0, abs=1e-12)
    assert (shaper.amplitudes > 0).all()
    assert shaper.amplitudes @ shaper.times_s == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.diff(shaper.times_s) > 0)
    # Klipper's total durations, in damped periods (2-hump: 1.5, 3-hump: 2 undamped periods at d = 0).
    periods = {"zv": 0.5, "mzv": 0.75, "zvd": 1.0, "ei": 1.0, "2hump_ei": 1.5, "3hump_ei": 2.0}[name]
    damped_period = 1 / (frequency_hz * math.sqrt(1 - damping**2))
    assert shaper.lead_s + shaper.lag_s == pytest.approx(periods * damped_period, rel=0.12 if "hump" in name else 1e-12)


def test_zv_zvd_closed_forms():
    f, d = 40.0, 0.1
    k = math.exp(-d * math.pi / math.sqrt(1 - d * d))
    half = 0.5 / (f * math.sqrt(1 - d * d))
    zv, zvd = klipper_shaper("zv", f, d), klipper_shaper("zvd", f, d)
    np.testing.assert_allclose(zv.amplitudes, np.array([1, k]) / (1 + k), rtol=1e-12)
    np.testing.assert_allclose(zv.times_s - zv.times_s[0], [0, half], rtol=1e-12)
    np.testing.assert_allclose(zvd.amplitudes, np.array([1, 2 * k, k * k]) / (1 + k) ** 2, rtol=1e-12)
    np.testing.assert_allclose(zvd.times_s - zvd.times_s[0], [0, half, 2 * half], rtol=1e-12)


def test_mzv_solves_klippers_equations():
    """Klipper's get_mzv_coeffs (n = 3, t = 0.75): sum 1 and zeros of the undamped shaper at 1 and
    1 + 1/tau times the frequency, tau = t (n - 2) / (n - 2 t - 1); then damped by K^i."""
    n, t, f, d = 3, 0.75, 40.0, 0.1
    tau = t * (n - 2) / (n - 2 * t - 1)
    times = np.arange(n) * t / (n - 1)
    rows, rhs = [np.ones(n)], [1.0]
    for i in range(n - 1):
        w = 2 * math.pi * (1 + i / tau) * times
        rows += [np.cos(w), np.sin(w)]
        rhs += [0.0, 0.0]
    a = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    df = math.sqrt(1 - d * d)
    a = a * math.exp(-2 * t * d * math.pi / ((n - 1) * df)) ** np.arange(n)
    mzv = klipper_shaper("mzv", f, d)
    np.testing.assert_allclose(mzv.amplitudes, a / a.sum(), rtol=1e-9)
    np.testing.assert_allclose(mzv.times_s - mzv.times_s[0], times / (f * df), rtol=1e-12)


def test_refuses_damping_beyond_klippers_range():
    with pytest.raises(ValueError, match="0.2"):
        klipper_shaper("3hump_ei", 40.0, 0.25)


def test_shaping_a_ramp_is_exact():
    """A ramp between rests, sampled at 1 kHz, shaped: sum_i a_i x(t - t_i) of the continuous
    ramp, at delays that are not multiples of the period."""
    period = 1e-3
    t = np.arange(400) * period
    ramp = lambda time: np.clip((time - 0.1) / 0.2, 0, 1) * 5.0  # noqa: E731
    shaper = klipper_shaper("ei", 37.3, 0.05)
    expected = sum(a * ramp(t - tau) for a, tau in zip(shaper.amplitudes, shaper.times_s, strict=True))
    both = shape(np.column_stack([ramp(t), -ramp(t)]), period, shaper)
    np.testing.assert_allclose(both[:, 0], expected, atol=1e-12)
    np.testing.assert_allclose(both[:, 1], -expected, atol=1e-12)
