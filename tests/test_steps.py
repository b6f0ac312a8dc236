"""Block ends in whole steps (fbspost/firmware/steps.py). Truths: the modes' differential equation
integrated numerically (scipy's solve_ivp, with the squared position error as a state), the
axis' exact discrete model (dynamics.AxisDynamics) on a fine grid, and the closed forms of
rounding (floor and ceil; first-order feedback keeps the error sum within half a step)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fbspost.fbs.dynamics import AxisDynamics
from fbspost.firmware.steps import FedBackRounding, ModalRounding, crossing_ends
from fbspost.profile import load_profile

TWO_MODES = load_profile("printer-two-mode").axes["X"].modes  # 52 Hz + 96 Hz
RHP_ZERO = load_profile("patent-xy-stage").axes["X"].modes  # beta != 0: a right-half-plane zero


def _integrated(modes, z0, errors, duration_s, horizon_s):
    """The modes driven by an error ramping linearly through ``errors`` (one per ``duration_s``,
    then held at the last), from modal state ``z0``: the state at each knot and the integral of
    the squared position error up to each knot and to ``horizon_s``."""
    n = 2 * len(modes)

    def error_at(t):
        return np.interp(t, duration_s * np.arange(len(errors)), errors)

    def rates(t, x):
        u, z, out = error_at(t), x[:n], np.empty(n + 1)
        y = 0.0
        for i, m in enumerate(modes):
            w, d = m.omega_rad_s, m.damping
            out[2 * i], out[2 * i + 1] = z[2 * i + 1], u - w * w * z[2 * i] - 2 * d * w * z[2 * i + 1]
            y += m.alpha * z[2 * i] + m.beta * z[2 * i + 1]
        out[n] = y * y
        return out

    knots = duration_s * np.arange(1, len(errors))
    ramps = solve_ivp(rates, (0.0, knots[-1]), np.append(z0, 0.0), method="DOP853", rtol=1e-11, atol=1e-16,
                      t_eval=knots, max_step=duration_s / 8)  # (steps short of the ramps' kinks)
    tail = solve_ivp(rates, (knots[-1], horizon_s), ramps.y[:, -1], method="DOP853", rtol=1e-10, atol=1e-16)
    return ramps.y[:n].T, np.append(ramps.y[n], tail.y[n, -1])


@pytest.mark.parametrize("duration_us", [1700, 800_000])
@pytest.mark.parametrize("modes", [TWO_MODES, RHP_ZERO], ids=["two-modes", "rhp-zero"])
def test_block_matrices_are_the_modes_integrated(modes, duration_us):
    """The modal state after a block, the error energy over it, and over it and after it with the
    error ramped back to zero over as long a block, as quadratic forms in [z0, e0, e1]. A block
    of 0.8 s too: Van Loan's exponential over it gave X's energy -1.6e13 (a 1.1 s block in the
    3-copy stacked gear: the lattice's ends then swung X by 270 m)."""
    rounding = ModalRounding(modes)
    n = rounding.n
    rng = np.random.default_rng(3)
    scale = np.repeat([1.0 / m.omega_rad_s ** 2 for m in modes], 2) * np.tile([1.0, 300.0], len(modes))
    z0 = rng.normal(size=n) * scale
    e0, e1 = 0.37, -0.81
    xi = np.concatenate([z0, [e0, e1]])
    to_state, this, total = rounding.block(duration_us)
    slowest = min(m.damping * m.omega_rad_s for m in modes)
    states, energy = _integrated(modes, z0, [e0, e1, 0.0], duration_us * 1e-6, 2e-6 * duration_us + 15.0 / slowest)
    assert to_state @ xi == pytest.approx(states[0], rel=1e-7, abs=1e-9 * np.abs(states[0]).max())
    assert xi @ this @ xi == pytest.approx(energy[0], rel=1e-6)
    assert xi @ total @ xi == pytest.approx(energy[-1], rel=1e-6)


def _slow_curve(n_blocks: int) -> np.ndarray:
    """Block ends in steps of a curve at 1 kHz: 20 mm of a 3 Hz swing and a 5 mm/s drift, 80 steps/mm."""
    t = np.arange(n_blocks) * 1e-3
    return 80.0 * (20.0 * np.sin(2 * np.pi * 3.0 * t) + 5.0 * t)


def _felt_um(modes, counts: np.ndarray, wanted: np.ndarray) -> float:
    """RMS of the axis' position error (um, 80 steps/mm) from the rounding error joined linearly
    between the block ends (1 ms), simulated exactly at 10 kHz."""
    error = np.concatenate([[0.0], counts - wanted]) / 80.0 * 1e3
    fine = np.interp(np.arange(10 * (len(error) - 1) + 1) / 10.0, np.arange(len(error)), error)
    return float(np.sqrt(np.mean(AxisDynamics(modes, 1e-4).simulate(fine) ** 2)))


def test_modal_rounding_leaves_the_axis_least_error():
    """Every count is the floor or the ceiling of its end; the position error the modes make of
    them is well under first-order feedback's and plain rounding's (measured: 0.94, 1.47 and
    3.37 um); the same counts whether the run is rounded at once or in two calls."""
    wanted = _slow_curve(2000)
    durations = np.full(len(wanted), 1e-3)
    modal = ModalRounding(TWO_MODES)
    counts, states = modal.round(wanted, durations, np.zeros(modal.size))
    assert np.all((counts == np.floor(wanted)) | (counts == np.ceil(wanted)))
    fed, _ = FedBackRounding().round(wanted, durations, np.zeros(1))
    felt = {name: _felt_um(TWO_MODES, c, wanted) for name, c in
            (("modal", counts), ("fed back", fed), ("plain", np.rint(wanted)))}
    print(felt)
    assert felt["modal"] < 0.75 * felt["fed back"] and felt["modal"] < 0.4 * felt["plain"]
    first, middle = modal.round(wanted[:700], durations[:700], np.zeros(modal.size))
    rest, _ = modal.round(wanted[700:], durations[700:], middle[-1])
    assert np.array_equal(np.concatenate([first, rest]), counts)


def test_fed_back_rounding_never_drifts():
    """Each count within a step of its end, the running sum of the errors within half a step."""
    wanted = _slow_curve(3000) * 0.013  # slow: many ends between the same two steps
    counts, errors = FedBackRounding().round(wanted, np.full(len(wanted), 1e-3), np.zeros(1))
    assert np.abs(counts - wanted).max() < 1.0
    assert np.abs(np.cumsum(counts - wanted)).max() <= 0.5 + 1e-9
    assert errors[-1, 0] == pytest.approx(np.sum(counts - wanted))


def test_crossing_ends_on_a_straight_line():
    """X at 1.7 steps per ms, Y at 0.4 (1 step per unit, rows every ms, kept rows 4, 8 and 10):
    each kept end but the last moves to where X reaches its nearest whole step, t = step / 1.7
    ms (closed form), Y there at 0.4 t; the last stays."""
    t_s = np.arange(11) * 1e-3
    units = np.column_stack([1700.0 * t_s, 400.0 * t_s, np.zeros(11)])
    times, ends = crossing_ends(t_s, units, np.array([1.0, 1.0, 0.0]), np.array([4, 8, 10]))
    wanted_s = np.array([7.0 / 1.7e3, 14.0 / 1.7e3, 0.010])  # 6.8 -> 7, 13.6 -> 14; the last at 17
    assert times == pytest.approx(wanted_s, abs=1e-15)
    assert ends[:, 0] == pytest.approx([7.0, 14.0, 17.0], abs=1e-12)
    assert ends[:, 1] == pytest.approx(400.0 * wanted_s, abs=1e-12)


@pytest.mark.slow  # (30 s under load: 13 simulations of 1.3 s at 20 kHz)
def test_lattice_solves_the_chords_least_squares():
    """The lattice's ends, taken at their optimum (no whole steps), are the least-squares solution
    found by brute force: the chords' hat functions (and the wanted motion's own chord error)
    simulated by scipy's lsim at 20 kHz through the modes, the error after the last end ramped
    back to zero over as long a block, the chord's energy and slope weighed as the module says
    (steps.CHORD_WEIGHT, SLOPE_WEIGHT_S2), solved by numpy's lstsq; and taken on whole steps,
    every block moving the minimum (6 steps)."""
    from scipy import signal

    from fbspost.firmware import steps
    from reference import continuous_model

    rng = np.random.default_rng(5)
    knots_s = np.cumsum(rng.uniform(0.004, 0.012, 12))  # 12 blocks, all in one stretch and its look-ahead
    assert knots_s[-1] < 2 * steps.HORIZON_S
    times_s = np.linspace(0.0, knots_s[-1], 61)
    wanted = 80.0 * (25.0 * times_s + 0.04 * np.sin(2 * np.pi * 52.0 * times_s))  # steps: 25 mm/s and a swing
    lattice = ModalRounding(TWO_MODES).lattice(times_s, wanted, knots_s, np.zeros(5))
    solved = np.empty(len(knots_s))
    for k in range(len(knots_s)):
        solved[k] = lattice.best(k)[0]
        lattice.take(k, solved[k])

    fs = 20000.0
    t = np.arange(0.0, knots_s[-1] + 1.2, 1.0 / fs)
    end_s = knots_s[-1] + (knots_s[-1] - knots_s[-2])  # the ramp back to zero after the last end
    at_knots = np.interp(knots_s, times_s, wanted)

    def error(offsets):  # the chord through wanted + offsets minus the wanted, then the ramp back
        chord = np.interp(t, np.append(0.0, knots_s), np.append(wanted[0], at_knots + offsets))
        e = np.where(t <= knots_s[-1], chord - np.interp(t, times_s, wanted), 0.0)
        return np.where((t > knots_s[-1]) & (t < end_s), offsets[-1] * (end_s - t) / (end_s - knots_s[-1]), e)

    inside = t <= knots_s[-1]
    rows = []
    for column in [np.zeros(len(knots_s))] + list(np.eye(len(knots_s))):
        e = error(column)
        _, y, _ = signal.lsim(continuous_model(TWO_MODES), e, t)
        slope = np.gradient(e, 1.0 / fs)
        rows.append(np.concatenate([y, np.sqrt(steps.CHORD_WEIGHT) * e[inside],
                                    np.sqrt(steps.SLOPE_WEIGHT_S2) * slope[inside]]) / np.sqrt(fs))
    base, hats = rows[0], np.column_stack(rows[1:]) - rows[0][:, None]
    brute, *_ = np.linalg.lstsq(hats, -base, rcond=None)
    assert solved - at_knots == pytest.approx(brute, abs=0.01 * np.abs(brute).max())  # (measured: 0.004)

    lattice = ModalRounding(TWO_MODES).lattice(times_s, wanted, knots_s, np.zeros(5))
    steps.lattice_counts([lattice], np.zeros(len(knots_s), bool), 6)
    assert np.all(np.abs(np.diff(np.append(wanted[0], lattice.counts))) >= 6)
    assert np.all(lattice.counts == np.rint(lattice.counts))
