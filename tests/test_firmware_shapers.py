"""The firmwares' input shapers through whole steps against independent truths: Marlin's shaping
counter run step event by step event as stepper.cpp runs it, the factor and delay formulas worked
by hand, a ramp's lag (Marlin's uncentred delay), a step's response as the sum of delayed steps,
the shapers' residual vibration in closed form, and the quantization bound."""
import math

import numpy as np
import pytest

from fbspost.firmware.shapers import shape
from fbspost.firmware.shaping import (
    REPRAP_SHAPERS,
    ft_motion_shaper,
    marlin_zv,
    marlin_zv_delay_s,
    marlin_zv_factors,
    reprap_shaper,
    shaped_steps,
    staircase_positions,
    stepper_positions,
    whole_steps,
)

SPM = 80.0


def marlin_by_events(counts: np.ndarray, echo_samples: int, zeta: float) -> np.ndarray:
    """Marlin's ZV shaping run event by event (stepper.cpp's PULSE_PREP_SHAPING): the motor's step
    count after each sample of the unshaped counts ``counts``, every step's echo ``echo_samples``
    later, a sample's echoes before its steps."""
    factor1, factor2 = marlin_zv_factors(zeta)
    error, motor, out = 0, int(counts[0]), []
    for k in range(len(counts)):
        updates = []
        if k >= echo_samples:
            moved = int(counts[k - echo_samples] - counts[k - echo_samples - 1]) if k > echo_samples else 0
            updates += [math.copysign(factor2, moved)] * abs(moved)
        if k:
            moved = int(counts[k] - counts[k - 1])
            updates += [math.copysign(factor1, moved)] * abs(moved)
        for dividend in updates:
            error += int(dividend)
            if error >= 64:
                error -= 128
                motor += 1
            elif error <= -64:
                error += 128
                motor -= 1
        out.append(motor)
    return np.array(out)


@pytest.mark.parametrize("zeta", [0.0, 0.07, 0.3])
def test_marlin_zv_equals_its_counter_run_step_by_step(zeta):
    """A random walk of up to 4 steps a sample, reversing often, on a grid that puts the echo a
    whole number of samples later: the closed form is Marlin's counter exactly."""
    delay_s = marlin_zv_delay_s(52.0)
    period_s = delay_s / 10
    rng = np.random.default_rng(1)
    counts = np.concatenate([[0] * 12, np.cumsum(rng.integers(-4, 5, 3000)), [0] * 12])
    counts[-12:] = counts[-13]
    shaped = marlin_zv(counts / SPM, period_s, SPM, 52.0, zeta)
    np.testing.assert_array_equal(np.rint(shaped * SPM), marlin_by_events(counts, 10, zeta))


def test_marlin_factors_and_delay_as_the_source_computes_them():
    """factor2 = floor(64.44056192 - 99.02008832 z - 7.58095488 z^2 + 43.073216 z^3), worked by
    hand; 64 at zeta 0; delay = (2 MHz / 2) / F ticks, truncated."""
    assert marlin_zv_factors(0.07) == (71, 57)  # 64.4406 - 6.9314 - 0.0371 + 0.0148 = 57.49
    assert marlin_zv_factors(0.05) == (69, 59)  # 64.4406 - 4.9510 - 0.0190 + 0.0054 = 59.48
    assert marlin_zv_factors(0.1) == (74, 54)  # 64.4406 - 9.9020 - 0.0758 + 0.0431 = 54.51, floored
    assert marlin_zv_factors(0.0) == (64, 64)
    assert marlin_zv_delay_s(52.0) == 19230 / 2e6
    assert marlin_zv_delay_s(34.0) == 29411 / 2e6


def test_marlin_zv_is_late_by_its_own_mean_delay():
    """A ramp at 50 mm/s, shaped, runs behind by factor2 / 128 x delay (not centred: Klipper's
    would be on the ramp), within a step (the unshaped counts' rounding and the motor's), and at
    rest ends where it was commanded."""
    period_s = 1e-4
    t = np.arange(20000) * period_s
    x = np.clip(t - 0.2, 0.0, 1.5) * 50.0
    lag_s = 57 / 128 * marlin_zv_delay_s(52.0)
    shaped = marlin_zv(x, period_s, SPM, 52.0, 0.07)
    steady = (t > 0.25) & (t < 1.65)
    behind = x[steady] - shaped[steady]
    assert np.abs(behind - 50.0 * lag_s).max() <= 1.0 / SPM + 1e-12
    assert shaped[-1] == x[-1] == 75.0
    assert lag_s == pytest.approx(4.282e-3, abs=1e-6)


def test_marlin_zv_step_is_the_sum_of_delayed_steps():
    """A 10 mm jump: 71/128 of it at once and the rest 9.615 ms later, each in whole steps."""
    period_s = 1e-4
    x = np.where(np.arange(3000) >= 1000, 10.0, 0.0)
    shaped = marlin_zv(x, period_s, SPM, 52.0, 0.07)
    echo = 1000 + math.ceil(marlin_zv_delay_s(52.0) / period_s - 1e-9)
    assert set(np.unique(shaped[1000:echo - 1])) == {round(800 * 71 / 128) / SPM}
    assert shaped[echo + 1] == 10.0 and shaped[999] == 0.0


def vibration(shaper, frequency_hz, zeta):
    """|sum a_i e^(s t_i)| over sum a_i e^(zeta w t_i), s = zeta w + j w_d: what a shaped step
    leaves of a mode's ringing, relative to an unshaped one (Singhose's V)."""
    w = 2 * math.pi * frequency_hz
    s = zeta * w + 1j * w * math.sqrt(1 - zeta**2)
    t = shaper.times_s - shaper.times_s[0]
    return abs(np.sum(shaper.amplitudes * np.exp(s * t))) / np.sum(shaper.amplitudes * np.exp(zeta * w * t))


@pytest.mark.parametrize("name, expected", [("zv", 0.0), ("zvd", 0.0), ("zvdd", 0.0), ("zvddd", 0.0),
                                            ("mzv", 0.0), ("ei", 0.05), ("2hei", 0.0), ("3hei", 0.05)])
def test_ft_motion_shapers_cancel_their_mode(name, expected):
    """At 50 Hz the echoes are 10 whole samples of 1 kHz apart (MZV: 7.5 rounded): the zero-
    vibration shapers leave nothing undamped, EI and 3-hump EI their 5 % (a0 - a1 + a2 = vtol),
    2-hump EI nothing at its centre; centred within half a sample."""
    shaper = ft_motion_shaper(name, 50.0, 0.0)
    assert shaper.amplitudes.sum() == pytest.approx(1.0)
    assert abs(shaper.amplitudes @ shaper.times_s) <= 0.5e-3
    if name != "mzv":
        assert vibration(shaper, 50.0, 0.0) == pytest.approx(expected, abs=1e-6)
    assert set(np.round(np.diff(shaper.times_s) * 1e3, 9)) == ({8.0} if name == "mzv" else {10.0})
    damped_hz = 50.0 / math.sqrt(1 - 0.1**2)  # the damped half period 10 whole samples again
    if name != "mzv":
        assert vibration(ft_motion_shaper(name, damped_hz, 0.1), damped_hz, 0.1) == pytest.approx(expected, abs=1e-6)


def test_ft_motion_zv_closed_form():
    """ZV: 1 / (1 + K) and K / (1 + K), K = exp(-zeta pi / sqrt(1 - zeta^2))."""
    k = math.exp(-0.07 * math.pi / math.sqrt(1 - 0.07**2))
    shaper = ft_motion_shaper("zv", 52.0, 0.07)
    np.testing.assert_allclose(shaper.amplitudes, [1 / (1 + k), k / (1 + k)])
    assert np.diff(shaper.times_s)[0] == pytest.approx(round(1e3 / (2 * 52 * math.sqrt(1 - 0.07**2))) * 1e-3)


@pytest.mark.parametrize("name, zeta", [(name, zeta) for name in REPRAP_SHAPERS for zeta in (0.0, 0.1)
                                        if zeta == 0.0 or not name.startswith("ei")])
def test_reprap_shapers_cancel_their_mode(name, zeta):
    """RRF's impulses (from its cumulative coefficients and durations) leave nothing of the
    mode's ringing; the EI fits, undamped, their tolerance at the centre (5 %, within the fit's
    0.1 %). (Damped, RRF times the EI fits in damped periods where they were fitted in undamped
    ones: EI3 at zeta 0.1 leaves 9.5 %.)"""
    shaper = reprap_shaper(name, 40.0, zeta)
    assert shaper.amplitudes.sum() == pytest.approx(1.0) and shaper.times_s[0] == 0.0
    assert vibration(shaper, 40.0, zeta) < (0.051 if name.startswith("ei") else 1e-6)


def test_shaped_steps_are_whole_and_within_half_a_step():
    """Any shaper's output is on the step lattice and within half a step of the ideal shaping."""
    rng = np.random.default_rng(2)
    x = np.cumsum(rng.normal(0.0, 0.05, 5000))
    for shaper in (ft_motion_shaper("ei", 48.0, 0.08), reprap_shaper("mzv", 36.0, 0.06)):
        stepped = shaped_steps(x, 1e-3, SPM, shaper)
        assert np.array_equal(stepped * SPM, np.rint(stepped * SPM))
        assert np.abs(stepped - shape(x, 1e-3, shaper)).max() <= 0.5 / SPM + 1e-12
    assert np.array_equal(whole_steps(np.array([0.00625, -0.00625, 0.0062]), SPM) * SPM, [1.0, 0.0, 0.0])


def test_a_jump_is_not_shaped():
    """A move from an unknown place (the Marlin model puts it in no time) stays one jump: shaped,
    it would be two, the axis stopping between them 60 mm off every path for 9.6 ms."""
    from fbspost.profile import load_profile
    from firmware_results import shaped_plans
    profile = load_profile("printer-two-mode")
    plan = np.zeros((400, 4))
    plan[100:, 0] = 100.0  # a jump on X
    plan[200:, 0] = 100.0 + np.minimum(np.arange(200) * 1e-3 * 50.0, 5.0)  # then a real move
    shapers = {"X": ft_motion_shaper("zv", 52.0, 0.07)}
    (command, padded, _), = shaped_plans(plan, profile, {"zv": shapers},
                                         lambda x, p, s, axis: shaped_steps(x, p, SPM, s)).values()
    jump = np.flatnonzero(np.abs(np.diff(command[:, 0])) > 1.0)
    assert len(jump) == 1 and command[jump[0] + 1, 0] == 100.0
    moving = np.abs(padded[:, 0] - 102.5) < 2.0
    ideal = 100.0 + shape(padded[:, 0] - 100.0, 1e-3, shapers["X"])
    assert np.abs(command[moving, 0] - ideal[moving]).max() <= 0.5 / SPM


def test_reprap_ei2_is_its_cumulative_coefficients():
    """RRF's EI2 undamped, from AxisShaper::Configure worked by hand: coefficients (the
    acceleration's levels) 0.16054, 0.16054 + 0.33911, + 0.34089, then 1; durations 0.49890,
    0.99748 - 0.49890, 1.49920 - 0.99748 periods."""
    shaper = reprap_shaper("ei2", 40.0, 0.0)
    np.testing.assert_allclose(np.cumsum(shaper.amplitudes), [0.16054, 0.49965, 0.84054, 1.0], atol=1e-12)
    np.testing.assert_allclose(shaper.times_s * 40.0, [0.0, 0.49890, 0.99748, 1.49920], atol=1e-12)


def _staircase_mean(a: float, b: float, t0: float, t1: float) -> float:
    """The exact mean over [t0, t1] of floor(a + b t + 1/2), b > 0: the levels between crossings."""
    crossings = [t0, *((k - 0.5 - a) / b for k in range(math.floor(a + b * t0 + 0.5) + 1,
                                                         math.floor(a + b * t1 + 0.5) + 1)), t1]
    return sum(math.floor(a + b * (lo + hi) / 2 + 0.5) * (hi - lo)
               for lo, hi in zip(crossings[:-1], crossings[1:], strict=True)) / (t1 - t0)


def test_staircase_is_each_periods_mean_of_the_steps():
    """An axis at 1.05 steps a sample (the bench's hold of each sample's step aliases that into a
    20-sample sawtooth of half a step): each sample of the staircase is the mean of the whole steps
    over its period, centred on it, to within the 20 points' 1/20 step of the exact integral;
    a jump of 50 mm (a position set) is held, not smeared into the samples beside it."""
    a, b = 0.3, 1.05  # steps, steps per sample
    x = (a + b * np.arange(300.0)) / SPM
    x[200:] += 50.0
    samples = np.zeros((300, 4))
    samples[:, 0] = x
    stair = staircase_positions(samples, {"X": SPM})[:, 0] * SPM
    exact = np.array([_staircase_mean(a, b, i - 0.5, i + 0.5) for i in range(1, 199)])
    assert np.abs(stair[1:199] - exact).max() <= 1.0 / 20 + 1e-9
    held = stepper_positions(samples, {"X": SPM})[:, 0] * SPM
    assert np.abs(stair[199:201] - held[199:201]).max() <= 1.0  # (smeared: 500 steps off)
    # the bench's hold: off the mean by up to half a step
    assert np.abs(held[1:199] - exact).max() > 0.4
