"""The modal fit: modes to a measured frequency response.

Takes a frequency response (frequencies in Hz, complex G(j 2 pi f)), optionally weights (the
coherence), a mode count and a time offset and clock error to fit; gives a ``Fit`` (the modes,
the offset and clock error found, the fit's error per mode count, each mode's uncertainty).
``fit_frf``: relaxed vector fitting for the poles, a linear solve for the numerators, a nonlinear
least-squares refinement; the automatic count (see ``identify``'s docstring) and the plausibility
of a fit's modes (``_plausible``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage, optimize

from ..fbs.dynamics import modal_response
from ..profile import Mode

MODE_COUNT_GAIN = 1.25  # one more mode must divide the RMS error by more than this to be kept
DAMPING_BOUNDS = (1e-5, 0.999)  # the fit's damping stays within these
VALLEY_TIE = 0.005  # minima of the zeros' trade-off with the time offset this close in cost are a tie
PLAUSIBLE_SHARE = 0.01
PLAUSIBLE_DAMPING = 0.9  # the automatic count skips a fit with a mode damped more (the patent stage: 0.54 at most)
_VF_ITERATIONS = 30
_DISTINCT = 1e-3  # minima whose responses differ less than this share of the peak are one


@dataclass(frozen=True)
class Fit:
    """Modes fitted to a frequency response, with the error of the fit over the measured band."""

    modes: tuple[Mode, ...]  # as fitted: DC gain sum(alpha / w^2) not normalized
    delay_s: float  # time offset removed from the measurement (0 unless fitted)
    clock_error: float  # the recording's clock rate's relative error found by the fit (with clock_times_s)
    rms_error: float  # RMS of |fitted - measured| over the band / max |measured|
    max_error: float  # max of the same
    errors_by_count: dict[int, float]  # mode count -> RMS error, for every count tried
    # per mode, the standard deviation of its frequency and of its damping relative to the value,
    # from the fit's covariance (``_relative_sd``)
    frequency_sd: tuple[float, ...] = ()
    damping_sd: tuple[float, ...] = ()
    # the valley's other minimum lowest in cost (``_along_the_valley``): its cost over this fit's
    # (inf: none found), and the largest difference of its response from this fit's over the band / peak
    rival_cost: float = math.inf
    rival_error: float = 0.0

    def response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """The fitted model G(j 2 pi f), without the delay."""
        return modal_response(self.modes, frequency_hz)


def fit_frf(frequency_hz: np.ndarray, response: np.ndarray, n_modes: int | None = None, max_modes: int = 8,
            weights: np.ndarray | None = None, fit_delay: bool = False,
            clock_times_s: np.ndarray | None = None) -> Fit:
    """Fit ``n_modes`` modes (or the automatic count, see the module) to ``response`` at
    ``frequency_hz``. The residuals are relative to the measured |G| at each frequency, times
    ``weights`` (>= 0, one per frequency, e.g. the coherence); ``fit_delay`` also fits a time
    offset tau, the measurement being G(s) exp(-s tau); ``clock_times_s`` (with it: when the
    recording holds each frequency, ``Recording.excited_at_s``) also a relative error e of the
    recording's clock rate, exp(-s (tau + e t)): a clock off by e is late by e t at time t."""
    f = np.asarray(frequency_hz, dtype=float)
    h = np.asarray(response, dtype=complex)
    # Residuals relative to each measured |G| (the least-squares estimate for noise proportional
    # to the response) and scaled by the peak: accurate at the anti-resonances and the low
    # frequencies, where a compensator inverts the model, as well as at the peaks.
    relative = np.abs(h).max() / np.maximum(np.abs(h), 1e-6 * np.abs(h).max())
    weights = relative * (1.0 if weights is None else np.asarray(weights, dtype=float))
    w_ref = 2 * np.pi * f[-1]  # frequencies scaled by the top of the band, responses by the peak
    s, peak = 1j * (2 * np.pi * f) / w_ref, np.abs(h).max()
    hn = h / peak
    delays = None  # rows: each delay parameter's multiple at each frequency (scaled)
    if fit_delay:
        delays = np.ones((1, len(f)))
        if clock_times_s is not None:
            clock_scale_s = max(float(np.max(np.abs(clock_times_s))), 1e-9)
            delays = np.vstack([delays, np.asarray(clock_times_s, dtype=float) / clock_scale_s])

    fits, xs = {}, {}

    def fit(n):
        tau0 = _delay_guess(s, hn, weights, n) if fit_delay else None
        keep(n, _fit_count(s, hn, weights, n, delays, tau0, xs.get(n - 1)))

    def keep(n, x):
        xs[n] = x
        error = np.abs(_model(xs[n], s, n, delays) - hn)[weights > 0]
        wn, zeta, a, b = xs[n][:n] * w_ref, xs[n][n:2 * n], xs[n][2 * n:3 * n], xs[n][3 * n:4 * n]
        order = np.argsort(wn)
        modes = tuple(Mode(wn[i] / (2 * np.pi), zeta[i], peak * a[i] * wn[i] ** 2, peak * b[i] * wn[i])
                      for i in order)
        sd = _relative_sd(xs[n], s, hn, weights, n, delays)
        delay, clock = (xs[n][4 * n] / w_ref if fit_delay else 0.0,
                        xs[n][4 * n + 1] / (w_ref * clock_scale_s) if clock_times_s is not None else 0.0)
        fits[n] = Fit(modes, delay, clock, float(np.sqrt(np.mean(error**2))), float(error.max()), {},
                      tuple(sd[:n][order]), tuple(sd[n:2 * n][order]))

    if n_modes:
        fit(n_modes)
        chosen = n_modes
    else:
        for n in range(1, max_modes + 1):
            fit(n)
            chosen = _chosen_count({k: v.rms_error if _plausible(v, f[-1]) else math.inf for k, v in fits.items()},
                                   max_modes)
            if chosen:
                break
        else:  # (no count of only plausible modes: the best, which assess_fit refuses)
            chosen = min(fits, key=lambda k: fits[k].rms_error)
    rival = {}
    if fit_delay:
        x, rival_x, rival_cost = _along_the_valley(xs[chosen], s, hn, weights, chosen, delays)
        keep(chosen, x)
        if rival_x is not None:
            rival = dict(rival_cost=rival_cost, rival_error=_response_change(x, rival_x, s, chosen))
    return replace(fits[chosen], errors_by_count={n: v.rms_error for n, v in fits.items()}, **rival)


def _chosen_count(errors: dict[int, float], max_modes: int) -> int | None:
    """The smallest count n whose RMS error neither n + 1 nor n + 2 modes (up to max_modes)
    divide by more than MODE_COUNT_GAIN; None while those are not all fitted yet. A count whose
    error is inf (a fit with a mode that is not one, ``_plausible``) is never chosen."""
    for n in sorted(errors):
        following = [m for m in (n + 1, n + 2) if m <= max_modes]
        if any(m not in errors for m in following):
            return None
        if math.isfinite(errors[n]) and (not following
                                         or errors[n] <= MODE_COUNT_GAIN * min(errors[m] for m in following)):
            return n
    return None


def _plausible(fit: Fit, top_hz: float) -> bool:
    """Whether every mode of ``fit`` is a resonance: none nearly critically damped (two real poles,
    which with a partner of opposite sign stand in for a slow trend of the response, the
    recording's timing or a filter: seen on simulated recordings, a pair at 85 Hz of damping 0.996
    and 0.999 whose 0.1% less error made FBS worse than no compensation on the machine), none at
    the fit's lowest damping (undetermined), and none
    at the band's top (``top_hz``) whose own peak is under PLAUSIBLE_SHARE of the response's (one at 119.9 Hz of
    0.1% soaked up what was left of a recording's clock there; the patent stage's Y has a real one
    of 1% inside the band)."""
    peaks = [abs(modal_response((m,), np.array([m.frequency_hz]))[0]) for m in fit.modes]
    whole = np.abs(modal_response(fit.modes, np.array([m.frequency_hz for m in fit.modes]))).max()
    return all(1.01 * DAMPING_BOUNDS[0] < m.damping < PLAUSIBLE_DAMPING
               and (peak >= PLAUSIBLE_SHARE * whole or m.frequency_hz < 0.98 * top_hz)
               for m, peak in zip(fit.modes, peaks, strict=True))


def _fit_count(s, hn, weights, n, delays, tau0, previous):
    """The parameters (w, zeta, a, b per mode, then the delays' if fitted: tau and the clock's
    error; scaled) of the best fit with exactly ``n`` modes to ``hn``, refined from two starts:
    the poles of vector fitting, and the ``n - 1`` modes of ``previous`` (their parameters) with
    one more where their residual is largest. ``tau0``: the scaled time offset to start from."""
    fit_delay = delays is not None
    start_delays = np.zeros(len(delays)) if fit_delay else np.zeros(0)
    if fit_delay:
        start_delays[0] = tau0
    starts = [(_vector_fit(s, hn * _delay_factor(start_delays, s, delays, -1) if fit_delay else hn, weights, n),
               start_delays)]
    if previous is not None:
        m = n - 1
        # where the complex residual, averaged over neighbouring frequencies, is largest: noise
        # averages out there, a missing mode does not
        residual = weights * (_model(previous, s, m, delays) - hn)
        w_new = s.imag[
            np.argmax(
                np.abs(ndimage.uniform_filter1d(residual.real, 15) + 1j * ndimage.uniform_filter1d(residual.imag, 15))
            )
        ]
        w_prev, zeta_prev = previous[:m], previous[m:2 * m]
        poles = np.append(w_prev * (-zeta_prev + 1j * np.sqrt(1 - zeta_prev**2)), w_new * (-0.01 + 1j))
        starts.append((poles, previous[4 * m:]))
    results = []
    for poles, delay in starts:
        wn, zeta = np.abs(poles), np.clip(-poles.real / np.abs(poles), 1e-4, 0.99)
        a, b = _numerators(s, hn * _delay_factor(delay, s, delays, -1) if fit_delay else hn, weights, wn, zeta)
        results.append(_refine(np.concatenate([wn, zeta, a, b, delay]), s, hn, weights, n, delays))
    return min(results, key=lambda r: r.cost).x


def _along_the_valley(x, s, hn, weights, n, delays):
    """(the best of the fit ``x`` (with a time offset) and its refinements from two other points
    of the valley it lies in. The zeros and the time offset both set the low-frequency phase (its
    first-order term is sum (b - 2 zeta a) / w - tau sum a), so a recording's fit can have two
    nearly equal minima along that valley: also start from its points with no zeros (a mass
    pushed by a force) and with a belt's zeros (b = 2 zeta a), the time offset moved to keep the
    term. Of minima whose costs are within VALLEY_TIE of the lowest, the one with the smallest time
    offset: the recording is aligned on the sweep and its clock (``frf_from_recording``), so what
    is left of the offset is the machine's own delay, which a controller and an accelerometer keep
    to a fraction of a millisecond, and the axis' net low-frequency lead, none for belts, while a
    belt's zero traded for an offset moves it by 2 beta / alpha, about 1 ms (seen on simulated
    recordings: the zeros' signs flipped within 0.2% of the cost, and FBS with them was 6 times
    worse on the machine). Only a near tie: a stage whose zeros give it a net lead
    (tests/data/truth-stage.toml's X, 0.91 ms) leaves that much offset, and with a tie of 10% its
    minimum, 1.6% to 5.8% lower, lost to one at a third of the offset with the zeros rotated, 20%
    off the truth's response; the other minimum lowest in cost, whose response differs from the best's
    (None: none), and its cost over the best's)."""
    wn, zeta, a, b = (x[i * n:(i + 1) * n] for i in range(4))
    if not abs(np.sum(a)) > 0:  # no DC gain: no term to keep
        return x, None, math.inf
    found = [(float(np.sum(_residual(x, s, hn, weights, n, delays) ** 2)) / 2, x)]
    for b_start in (np.zeros(n), 2 * zeta * a):
        delay = x[4 * n:].copy()
        delay[0] += np.sum((b_start - b) / wn) / np.sum(a)
        result = _refine(np.concatenate([wn, zeta, a, b_start, delay]), s, hn, weights, n, delays)
        found.append((result.cost, result.x))
    lowest = min(cost for cost, _ in found)
    cost, best = min((c for c in found if c[0] <= (1 + VALLEY_TIE) * lowest), key=lambda c: abs(c[1][4 * n]))
    others = [c for c in found if _response_change(best, c[1], s, n) > _DISTINCT]
    if not others:
        return best, None, math.inf
    rival_cost, rival = min(others, key=lambda c: c[0])
    return best, rival, rival_cost / cost - 1.0


def _response_change(x, other, s, n) -> float:
    """The largest difference of ``other``'s response from ``x``'s (their modes, without the
    delays) over the band, relative to the peak of ``x``'s."""
    g = _model(x[:4 * n], s, n, None)
    return float(np.abs(_model(other[:4 * n], s, n, None) - g).max() / np.abs(g).max())


def _refine(x0, s, hn, weights, n, delays):
    """The nonlinear least-squares refinement of the parameters from ``x0`` (scipy's result):
    natural frequencies within the band, dampings within DAMPING_BOUNDS."""
    free = 2 * n + (0 if delays is None else len(delays))  # a, b and the delays: unbounded
    lower = np.concatenate([np.full(n, s.imag.min()), np.full(n, DAMPING_BOUNDS[0]), np.full(free, -np.inf)])
    upper = np.concatenate([np.full(n, s.imag.max()), np.full(n, DAMPING_BOUNDS[1]), np.full(free, np.inf)])
    return optimize.least_squares(
        lambda x: _residual(x, s, hn, weights, n, delays), np.clip(x0, lower + 1e-12, upper - 1e-12),
        jac=lambda x: _jacobian(x, s, weights, n, delays), bounds=(lower, upper), x_scale="jac",
        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100 * len(x0))


def _residual(x, s, hn, weights, n, delays):
    """The weighted complex residual of the parameters ``x`` as real numbers (real parts, then
    imaginary parts)."""
    r = weights * (_model(x, s, n, delays) - hn)
    return np.concatenate([r.real, r.imag])


def _jacobian(x, s, weights, n, delays):
    """d _residual / d x."""
    d = weights[:, None] * _model_derivatives(x, s, n, delays)
    return np.vstack([d.real, d.imag])


def _relative_sd(x, s, hn, weights, n, delays):
    """Standard deviation of each parameter of the solution ``x`` relative to its value: the
    covariance of weighted least squares, (J^T J)^-1 times the residual variance (sum of squares
    over the degrees of freedom), J the Jacobian at the solution. Exact to first order for
    independent noise whose standard deviation the weights are inversely proportional to; inf
    for a parameter the data does not determine (J^T J singular)."""
    used = np.concatenate([weights > 0, weights > 0])
    jac = _jacobian(x, s, weights, n, delays)[used]
    r = _residual(x, s, hn, weights, n, delays)[used]
    variance = float(r @ r) / max(1, jac.shape[0] - jac.shape[1])
    scale = np.linalg.norm(jac, axis=0)  # columns scaled to norm 1: the parameters' units differ widely
    scale[scale == 0] = 1.0
    _, singular, vt = np.linalg.svd(jac / scale, full_matrices=False)
    with np.errstate(divide="ignore"):
        inverse = np.where(singular > singular[0] * 1e-12, 1 / singular**2, np.inf)
    sd = np.sqrt(variance * (vt.T**2 @ inverse)) / scale
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(sd), sd / np.abs(x), np.inf)


def _model(x, s, n, delays):
    """Sum of (a w^2 + b w s)/(s^2 + 2 zeta w s + w^2) in scaled s; a, b dimensionless gains;
    times the delays' factor if fitted."""
    wn, zeta, a, b = (x[i * n:(i + 1) * n, None] for i in range(4))
    g = ((a * wn**2 + b * wn * s) / (s * s + 2 * zeta * wn * s + wn**2)).sum(axis=0)
    return g if delays is None else g * _delay_factor(x[4 * n:], s, delays)


def _delay_factor(parameters, s, delays, sign=1):
    """exp(-sign s sum_k parameters_k delays_k): the delays' factor at each frequency."""
    return np.exp(-sign * s * (parameters @ delays))


def _model_derivatives(x, s, n, delays):
    """d _model / d x, one column per parameter."""
    wn, zeta, a, b = (x[i * n:(i + 1) * n] for i in range(4))
    s_ = s[:, None]
    den = s_ * s_ + 2 * zeta * wn * s_ + wn**2
    num = a * wn**2 + b * wn * s_
    d_w = (2 * a * wn + b * s_) / den - num * (2 * zeta * s_ + 2 * wn) / den**2
    d_zeta = -num * 2 * wn * s_ / den**2
    columns = np.hstack([d_w, d_zeta, wn**2 / den, wn * s_ / den])
    if delays is None:
        return columns
    delay = _delay_factor(x[4 * n:], s, delays)[:, None]
    g = (num / den).sum(axis=1, keepdims=True)
    return np.hstack([columns * delay, -s_ * delays.T * g * delay])


def _basis(s, wn, zeta):
    """Columns 1/(s^2 + 2 zeta w s + w^2) w^2 and s w / (same): the numerators' unknowns a, b."""
    den = s[:, None] ** 2 + 2 * zeta * wn * s[:, None] + wn**2
    return np.hstack([wn**2 / den, wn * s[:, None] / den])


def _numerators(s, h, weights, wn, zeta):
    """Least-squares a, b of every mode for fixed poles."""
    basis = weights[:, None] * _basis(s, wn, zeta)
    rhs = weights * h
    ab = np.linalg.lstsq(np.vstack([basis.real, basis.imag]), np.concatenate([rhs.real, rhs.imag]), rcond=None)[0]
    return ab[:len(wn)], ab[len(wn):]


def _vector_fit(s, h, weights, n_pairs, poles=None, iterations=_VF_ITERATIONS):
    """Upper-half-plane poles of ``n_pairs`` stable complex-conjugate pairs within the band
    fitted to h(s) by relaxed vector fitting, from ``poles`` (default: lightly damped, spread
    over the band): each iteration solves sigma h ~ p for p and the relaxed sigma (both with the
    current poles) and moves the poles to the zeros of sigma."""
    band = (s.imag.min(), s.imag.max())
    if poles is None:
        w0 = np.linspace(*band, n_pairs + 2)[1:-1]
        poles = -0.01 * w0 + 1j * w0
    k = len(s)
    for _ in range(iterations):
        phi = _pair_basis(s, poles)
        sw = weights[:, None]
        a = np.hstack([sw * phi, -(sw * h[:, None]) * phi, -(weights * h)[:, None]])
        rows = np.vstack([a.real, a.imag])
        rhs = np.zeros(2 * k)
        # relaxation: the real part of sigma summed over the band is k (not sigma's d fixed at 1)
        scale = np.linalg.norm(weights * h) / k
        relax = np.concatenate([np.zeros(2 * n_pairs), scale * phi.real.sum(axis=0), [scale * k]])
        x = np.linalg.lstsq(np.vstack([rows, relax]), np.concatenate([rhs, [scale * k]]), rcond=None)[0]
        c_sigma, d_sigma = x[2 * n_pairs:4 * n_pairs], x[-1]
        if abs(d_sigma) < 1e-8:
            d_sigma = math.copysign(1e-8, d_sigma)
        state, b = _pair_realization(poles)
        zeros = np.linalg.eigvals(state - np.outer(b, c_sigma) / d_sigma)
        poles = _stable_pairs(zeros, n_pairs, band)
    return poles


def _pair_basis(s, poles):
    """Real-coefficient basis of each pair p, p*: 1/(s-p) + 1/(s-p*) and j/(s-p) - j/(s-p*)."""
    a, b = 1 / (s[:, None] - poles), 1 / (s[:, None] - poles.conj())
    return np.hstack([a + b, 1j * (a - b)])


def _pair_realization(poles):
    """(A, b) whose c^T (sI - A)^-1 b is the pair basis with coefficients c (real form)."""
    n = len(poles)
    state = np.zeros((2 * n, 2 * n))
    b = np.zeros(2 * n)
    for i, p in enumerate(poles):  # states ordered [re_0..re_n-1, im_0..im_n-1], as the basis
        state[i, i] = state[n + i, n + i] = p.real
        state[i, n + i], state[n + i, i] = p.imag, -p.imag
        b[i] = 2.0
    return state, b


def _stable_pairs(roots, n_pairs, band):
    """``n_pairs`` upper-half-plane poles from the 2 n_pairs roots: unstable ones mirrored into
    the left half plane; real roots, which the model has no term for, joined two by two into the
    pair of their product and sum (kept underdamped); natural frequencies outside ``band``
    moved to its nearer edge (a mode outside the measurement is not identified: there it would
    only stand in for other effects, such as the recording's time offset)."""
    roots = -np.abs(roots.real) + 1j * roots.imag
    upper = list(roots[roots.imag > 1e-9])
    real = np.sort(roots[np.abs(roots.imag) <= 1e-9].real)
    for r1, r2 in zip(real[::2], real[1::2], strict=False):  # (an odd one left over is dropped)
        w = math.sqrt(r1 * r2)
        zeta = min(0.95, -(r1 + r2) / (2 * w))
        upper.append(w * (-zeta + 1j * math.sqrt(1 - zeta * zeta)))
    upper = np.array(sorted(upper, key=lambda p: abs(p))[:n_pairs])
    return upper * np.clip(np.abs(upper), *band) / np.abs(upper)


def _delay_guess(s, h, weights, n_modes):
    """The time offset (scaled) whose removal lets vector fitting fit best, on a grid."""
    best = (np.inf, 0.0)
    poles = None
    for tau in np.linspace(-6.0, 6.0, 41):  # +-6 / w_ref: about one period of the top frequency
        hd = h * np.exp(s * tau)
        poles = _vector_fit(s, hd, weights, n_modes, poles, iterations=10)  # warm: the last tau's poles
        wn, zeta = np.abs(poles), -poles.real / np.abs(poles)
        a, b = _numerators(s, hd, weights, wn, zeta)
        err = np.linalg.norm(weights * ((_basis(s, wn, zeta) @ np.concatenate([a, b])) - hd))
        best = min(best, (err, tau))
    return best[1]
