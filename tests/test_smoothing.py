"""The trajectory robust compensation tracks (fbspost.fbs.smoothing): against numpy's convolution with
the Hann window written out from its formula, a straight line and a rest (kept exactly), any cut of
the run into pieces, and the compensator run on the independently smoothed trajectory."""
import numpy as np

from fbspost.fbs.dynamics import AxisDynamics, ModelSet
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits, FBSSettings
from fbspost.fbs.smoothing import RunSmoother, half_width_samples
from fbspost.job.axes import axis_compensators
from fbspost.job.report import CompensateOptions
from test_optimizer import smooth_move
from test_robust import NOMINAL, ROBUST, T, with_tolerances


def hann(half_width):
    """0.5 (1 + cos(pi j / (r + 1))), j = -r .. r, normalized: zero r + 1 samples either side."""
    j = np.arange(-half_width, half_width + 1)
    w = 0.5 * (1.0 + np.cos(np.pi * j / (half_width + 1)))
    return w / w.sum()


def reference_smoothed(x, half_width):
    """Each sample times the Hann window as wide as the run allows around it, written out."""
    widths = np.minimum(half_width, np.minimum(np.arange(x.size), np.arange(x.size)[::-1]))
    return np.array([np.dot(x[i - w:i + w + 1], hann(w)) for i, w in enumerate(widths)])


def smoothed_whole(x, half_width):
    smoother = RunSmoother(half_width)
    return np.concatenate([smoother.push(x), smoother.finish()])


def corner_run(rng, n=900):
    """A run with rests, straight pieces and sharp turns: random accelerations held for a while."""
    acceleration = np.repeat(rng.normal(0.0, 3000.0, n // 30), 30)
    x = np.cumsum(np.cumsum(acceleration)) * T * T
    return np.concatenate([np.full(40, x[0]), x, np.full(60, x[-1])]) + 12.5


def test_inside_the_run_it_is_the_hann_convolution_and_the_ends_are_kept():
    x = corner_run(np.random.default_rng(1))
    r = 4
    ours = smoothed_whole(x, r)
    truth = np.convolve(x, hann(r), mode="same")
    assert np.abs(ours[r:-r] - truth[r:-r]).max() < 1e-12 * np.abs(x).max()
    assert ours[0] == x[0] and ours[-1] == x[-1]
    # near the ends, each sample's window is as wide as the run allows, centred on it
    assert np.abs(ours - reference_smoothed(x, r)).max() < 1e-12 * np.abs(x).max()


def test_a_straight_line_and_a_rest_are_kept():
    line = 3.0 + 0.0123 * np.arange(500)
    assert np.allclose(smoothed_whole(line, 5), line, rtol=0, atol=1e-12)
    rest = np.full(300, 0.1 + 0.2)  # a value with no exact binary form
    assert np.array_equal(smoothed_whole(rest, 5), rest)  # bit for bit: windows at rest stay exactly at rest


def test_any_cut_gives_the_same_bits():
    rng = np.random.default_rng(2)
    x = corner_run(rng)
    whole = smoothed_whole(x, 4)
    for _ in range(5):
        cuts = np.sort(rng.choice(np.arange(1, x.size), size=12, replace=False))
        smoother = RunSmoother(4)
        pieces = [smoother.push(piece) for piece in np.split(x, cuts)] + [smoother.finish()]
        assert np.array_equal(np.concatenate(pieces), whole)
    short = RunSmoother(4)  # a run shorter than the window
    assert np.array_equal(np.concatenate([short.push(x[:3]), short.finish()]), smoothed_whole(x[:3], 4))


def test_the_window_is_one_period_of_the_highest_mode():
    for frequency_hz in (34.0, 52.0, 96.0, 150.0, 400.0):
        half_width = half_width_samples(frequency_hz, T)
        assert abs(2 * (half_width + 1) * T - 1.0 / frequency_hz) <= T  # zero to zero
    assert half_width_samples(600.0, T) == 0  # no window narrower than the grid


def test_the_compensator_tracks_the_smoothed_trajectory():
    """Complete look-ahead with the window equals the compensator without it on the trajectory
    smoothed by numpy (the ends as the smoother keeps them); limited look-ahead, pushed in pieces,
    equals it whole."""
    desired = np.concatenate([smooth_move(3.0, 0.08, 0.0, T), 3.0 - smooth_move(1.5, 0.05, 0.03, T)[1:]])
    modes = with_tolerances(ROBUST.axes["X"].modes, 0.1, 0.16)
    models = ModelSet.spread(modes, T)
    settings = FBSSettings(settle_samples=60)

    def compensator(lookahead, half_width):
        return AxisCompensator(AxisDynamics(modes, T), AxisLimits(), FBSSettings(
            settle_samples=60, smoothing_half_width=half_width), lookahead, models)

    target = reference_smoothed(desired, 4)
    ours = compensator("complete", 4)(desired).command_mm
    truth = AxisCompensator(AxisDynamics(modes, T), AxisLimits(), settings, "complete", models)(target).command_mm
    assert np.abs(ours - truth).max() < 1e-9
    assert np.abs(ours - compensator("complete", 0)(desired).command_mm).max() > 1e-3  # (it changes the command)

    whole = compensator("limited", 4)(desired).command_mm
    stream = compensator("limited", 4).stream()
    pieces = [stream.push(piece) for piece in np.array_split(desired, 7)]
    assert np.array_equal(np.concatenate(pieces + [stream.finish().command_mm]), whole)


def test_only_robust_compensation_smooths_and_every_axis_alike():
    robust = axis_compensators(ROBUST, CompensateOptions())
    assert {c.settings.smoothing_half_width for c in robust.values()} == {4}  # 96 Hz, on X and on Y
    nominal = axis_compensators(NOMINAL, CompensateOptions())
    assert {c.settings.smoothing_half_width for c in nominal.values()} == {0}
