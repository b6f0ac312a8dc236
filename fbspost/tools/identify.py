"""Axis models from measurements: fit modes to a frequency response, or estimate them coarsely
from what Klipper users already have.

Takes a measured frequency response (CSV ``frequency_hz,real,imag`` or
``frequency_hz,magnitude,phase_deg``, commanded to actual position, or commanded to measured
acceleration: the same ratio), an accelerometer recording of ``fbspost excite``'s sweep, Klipper's
``calibrate_shaper`` CSV or a ``printer.cfg``; gives ``profile.Mode`` tuples for one axis, with
the fit error.

The fit (``fit_frf``): relaxed vector fitting (Gustavsen and Semlyen) with complex-conjugate pole
pairs, unstable poles flipped into the left half plane, gives the poles of each mode count; a
linear least-squares solve gives each mode's numerator alpha + beta s (no direct term, zeros
free: right-half-plane zeros are kept); a nonlinear least-squares refinement of (frequency,
damping, alpha, beta), and of a time offset and the clock's error for recordings
(``fit_recording``), on the complex residual relative to
the measured |G| at each frequency, gives the result (for a recording, the chosen count is also
refined from two more starts: its zeros trade off against the time offset). Without a mode
count, every count up to ``max_modes`` is fitted from 1 up, and the smallest count n is kept
whose RMS error (relative to the peak) neither n + 1 nor n + 2 modes divide by more than
``MODE_COUNT_GAIN`` (two, so that a close pair of modes, which one more mode alone may not fit,
is still found). Each mode's frequency and damping get a standard deviation from the fit's
covariance; ``assess_fit`` says whether the fit is usable (its error, the coherence, the
dampings, the modes' places in the band, that uncertainty) and gives the tolerances to write.
The coarse estimates are base-excited modes by default (``coarse_mode``).

Malformed files raise ``InputError`` naming the file and line.
"""
from __future__ import annotations

import configparser
import csv
import io
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage, optimize, signal

from ..errors import InputError
from ..fbs.dynamics import modal_response
from ..profile import AxisProfile, FirmwareProfile, MachineProfile, Mode, format_profile, parse_profile

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
MODE_COUNT_GAIN = 1.25  # one more mode must divide the RMS error by more than this to be kept
KLIPPER_DEFAULT_DAMPING = 0.1  # Klipper's damping_ratio_x/y when printer.cfg does not set it
DAMPING_BOUNDS = (1e-5, 0.999)  # the fit's damping stays within these
VALLEY_TIE = 0.1  # minima of the zeros' trade-off with the time offset this close in cost are a tie
PLAUSIBLE_SHARE = 0.01
PLAUSIBLE_DAMPING = 0.9  # the automatic count skips a fit with a mode damped more (the patent stage: 0.54 at most)
COARSE_FORMS = ("base", "mass")  # the model of a coarse estimate's mode (coarse_mode)
_VF_ITERATIONS = 30


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

    def response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """The fitted model G(j 2 pi f), without the delay."""
        return modal_response(self.modes, frequency_hz)


# ---- reading a measured frequency response ------------------------------------------------------

def read_frf_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(frequency_hz, complex response) from a CSV with the header ``frequency_hz,real,imag`` or
    ``frequency_hz,magnitude,phase_deg`` (magnitude a plain ratio, not dB); frequencies > 0 and
    strictly increasing."""
    header, rows = _read_numeric_csv(path, {("frequency_hz", "real", "imag"),
                                            ("frequency_hz", "magnitude", "phase_deg")})
    data = np.array([values for _, values in rows])
    lines = [line for line, _ in rows]
    frequency_hz = data[:, 0]
    for i in range(len(frequency_hz)):
        if frequency_hz[i] <= 0:
            raise InputError(path, lines[i], f"frequency {frequency_hz[i]:g} Hz must be > 0")
        if i and frequency_hz[i] <= frequency_hz[i - 1]:
            raise InputError(path, lines[i], f"frequencies must increase: {frequency_hz[i]:g} Hz after "
                                             f"{frequency_hz[i - 1]:g} Hz")
    if header[1] == "real":
        response = data[:, 1] + 1j * data[:, 2]
    else:
        if (data[:, 1] < 0).any():
            i = int(np.argmax(data[:, 1] < 0))
            raise InputError(path, lines[i], "magnitude must be >= 0 (a ratio, not dB)")
        response = data[:, 1] * np.exp(1j * np.radians(data[:, 2]))
    if len(frequency_hz) < 8:
        raise InputError(path, None, f"{len(frequency_hz)} frequencies: at least 8 are needed for a fit")
    return frequency_hz, response


def _read_numeric_csv(path, headers: set[tuple[str, ...]], comment: str | None = None):
    """The header (one of ``headers``, cells stripped, extra trailing cells ignored) and the rows as
    (line number, the header's columns as floats); blank lines skipped, lines starting with
    ``comment`` skipped (a header may start with it)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    expected = " or ".join(",".join(h) for h in sorted(headers))
    header, width, rows = None, 0, []
    for lineno, row in enumerate(csv.reader(io.StringIO(text)), start=1):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        if header is None:
            names = tuple(c.lstrip(comment or "") for c in cells)
            header = next((h for h in headers if names[:len(h)] == h), None)
            if header is None:
                if comment and cells[0].startswith(comment):
                    continue
                raise InputError(path, lineno, f"header {','.join(cells)!r}: expected {expected}")
            width = len(header)
            continue
        if comment and cells[0].startswith(comment):
            continue
        if len(cells) < width:
            raise InputError(path, lineno, f"expected {width} values, got {len(cells)}")
        try:
            values = [float(c) for c in cells[:width]]
        except ValueError:
            raise InputError(path, lineno, f"not a number in {','.join(cells[:width])!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(path, lineno, "values must be finite")
        rows.append((lineno, values))
    if header is None:
        raise InputError(path, 1, f"empty file: expected the header {expected}")
    if not rows:
        raise InputError(path, None, "no data rows")
    return header, rows


# ---- the fit ------------------------------------------------------------------------------------

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
    if fit_delay:
        keep(chosen, _along_the_valley(xs[chosen], s, hn, weights, chosen, delays))
    return replace(fits[chosen], errors_by_count={n: v.rms_error for n, v in fits.items()})


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
    """The best of the fit ``x`` (with a time offset) and its refinements from two other points
    of the valley it lies in. The zeros and the time offset both set the low-frequency phase (its
    first-order term is sum (b - 2 zeta a) / w - tau sum a), so a recording's fit can have two
    nearly equal minima along that valley: also start from its points with no zeros (a mass
    pushed by a force) and with a belt's zeros (b = 2 zeta a), the time offset moved to keep the
    term. Of minima whose costs are within VALLEY_TIE of the lowest, the one with the smallest time
    offset: the recording is aligned on the sweep and its clock (``frf_from_recording``), so what
    is left of the offset is the machine's own delay, which a controller and an accelerometer keep
    to a fraction of a millisecond, while a belt's zero traded for an offset moves it by 2 beta /
    alpha, about 1 ms (seen on simulated recordings: the zeros' signs flipped within 0.2% of the
    cost, and FBS with them was 6 times worse on the machine)."""
    wn, zeta, a, b = (x[i * n:(i + 1) * n] for i in range(4))
    if not abs(np.sum(a)) > 0:  # no DC gain: no term to keep
        return x
    found = [(float(np.sum(_residual(x, s, hn, weights, n, delays) ** 2)) / 2, x)]
    for b_start in (np.zeros(n), 2 * zeta * a):
        delay = x[4 * n:].copy()
        delay[0] += np.sum((b_start - b) / wn) / np.sum(a)
        result = _refine(np.concatenate([wn, zeta, a, b_start, delay]), s, hn, weights, n, delays)
        found.append((result.cost, result.x))
    lowest = min(cost for cost, _ in found)
    return min((c for c in found if c[0] <= (1 + VALLEY_TIE) * lowest), key=lambda c: abs(c[1][4 * n]))[1]


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


# ---- how far to trust a fit ----------------------------------------------------------------------
# Good fits give errors far below these: the noisy FRFs of tests/test_identify.py (1% noise) an RMS
# error of 0.07 to 0.23% of the peak and a largest one of 1.5 to 2.1%; simulated recordings of
# excite's sweep 0.04 to 0.35% and 0.3 to 2.6%, with a mean coherence of 0.99. A sweep the
# firmware re-timed (the recording is not of the program) gave 31% and 100%, coherence 0.72.
# Refused: an error of 10% of the peak is twice the residual vibration Klipper's shapers are
# designed to leave (5%: SHAPER_VIBRATION_REDUCTION = 20 in its shaper_defs.py), so compensation
# with that model cannot be expected to beat them; a largest error of half the peak means a mode
# missed or a recording of something else; a mean coherence below 0.8 means a fifth of the
# measured power is not the axis' response to the program.
# Warned: errors ten times the simulated recordings' (3%, 20%), a tenth of the power unexplained.
WARN_RMS_ERROR, REFUSE_RMS_ERROR = 0.03, 0.10  # RMS error over the band / peak |G|
WARN_MAX_ERROR, REFUSE_MAX_ERROR = 0.20, 0.50  # largest error / peak |G|
WARN_COHERENCE, REFUSE_COHERENCE = 0.90, 0.80  # mean coherence over the band
LOW_DAMPING = 0.005  # below machine axes' (Klipper assumes 0.1 for a printer; the patent stage's lowest: 0.007)
DC_GAIN_RANGE = (0.5, 2.0)  # a position axis follows a slow command: the fit's DC gain is near 1
# The tolerances written: 3 standard deviations (99.7% of a normal estimate within them), at least
# what a machine drifts by between measurement and use (temperature, belt tension, the print's
# mass: a few % of frequency; damping, which friction sets, more), and at most what robust FBS
# covers: with 13% and 20% and wider it lost to the best shaper on two prints of three (robust.md).
COVERAGE = 3.0
MIN_FREQUENCY_TOLERANCE, MIN_DAMPING_TOLERANCE = 0.02, 0.05
MAX_TOLERANCE = 0.20
# A coarse estimate has no uncertainty of its own: README's values for a machine not measured.
COARSE_FREQUENCY_TOLERANCE, COARSE_DAMPING_TOLERANCE = 0.10, 0.16


@dataclass(frozen=True)
class Trust:
    """What ``assess_fit`` found: problems that make a fit unusable (``refusals``) or doubtful
    (``warnings``), each a short phrase, and the relative tolerances to write for the axis."""

    refusals: tuple[str, ...]
    warnings: tuple[str, ...]
    frequency_spread: float  # COVERAGE standard deviations relative to the value, the largest over the modes
    damping_spread: float
    frequency_tolerance: float  # the spread, at least the floor, at most MAX_TOLERANCE
    damping_tolerance: float


def assess_fit(fit: Fit, frequency_hz: np.ndarray, coherence: np.ndarray | None = None) -> Trust:
    """How far to trust ``fit`` of a response measured at ``frequency_hz`` (with ``coherence``
    where known): its error, the coherence, each mode's damping and place in the band, and the
    uncertainty of its frequencies and dampings (see the thresholds above)."""
    refusals, warnings = [], []
    error = f"RMS error {100 * fit.rms_error:.3g}% and max {100 * fit.max_error:.3g}% of the peak"
    if fit.rms_error > REFUSE_RMS_ERROR or fit.max_error > REFUSE_MAX_ERROR:
        refusals.append(f"{error} (usable: under {100 * REFUSE_RMS_ERROR:g}% and {100 * REFUSE_MAX_ERROR:g}%)")
    elif fit.rms_error > WARN_RMS_ERROR or fit.max_error > WARN_MAX_ERROR:
        warnings.append(f"{error} (good fits: under {100 * WARN_RMS_ERROR:g}% and {100 * WARN_MAX_ERROR:g}%)")
    if coherence is not None:
        mean = float(np.mean(coherence))
        phrase = f"mean coherence {mean:.2f}: {100 * (1 - mean):.0f}% of the measured power is not the response"
        if mean < REFUSE_COHERENCE:
            refusals.append(phrase)
        elif mean < WARN_COHERENCE:
            warnings.append(phrase)
    f_lo, f_hi = frequency_hz[0], frequency_hz[-1]
    for i, m in enumerate(fit.modes, start=1):
        if not DAMPING_BOUNDS[0] * 1.01 < m.damping < DAMPING_BOUNDS[1] * 0.99:
            refusals.append(f"mode {i}'s damping {m.damping:.3g} is at the fit's bound")
        elif m.damping < LOW_DAMPING:
            warnings.append(f"mode {i}'s damping {m.damping:.3g} is below machines' ({LOW_DAMPING:g})")
        # its resonance spans f (1 +- zeta): nearer an end than that it is only partly measured
        margin = m.frequency_hz * min(max(m.damping, 0.01), 0.05)
        if m.frequency_hz - f_lo < margin or f_hi - m.frequency_hz < margin:
            warnings.append(f"mode {i} at {m.frequency_hz:.4g} Hz is at the end of the band "
                            f"{f_lo:.4g}..{f_hi:.4g} Hz: measure a wider one")
    dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in fit.modes)
    if not DC_GAIN_RANGE[0] < dc_gain < DC_GAIN_RANGE[1]:
        warnings.append(f"the fit's DC gain is {dc_gain:.3g}, not about 1")
    spreads = []
    for what, sds in (("frequency", fit.frequency_sd), ("damping", fit.damping_sd)):
        spreads.append(COVERAGE * max(sds, default=0.0))
        if spreads[-1] > MAX_TOLERANCE:
            by = f"by {100 * spreads[-1]:.3g}% ({COVERAGE:g} standard deviations)" if math.isfinite(spreads[-1]) else ""
            refusals.append(f"mode {int(np.argmax(sds)) + 1}'s {what} is uncertain {by or 'wholly'}, more than "
                            f"the {100 * MAX_TOLERANCE:g}% robust FBS covers")
    tolerances = [min(max(spread, floor), MAX_TOLERANCE)
                  for spread, floor in zip(spreads, (MIN_FREQUENCY_TOLERANCE, MIN_DAMPING_TOLERANCE), strict=True)]
    return Trust(tuple(refusals), tuple(warnings), *spreads, *tolerances)


# ---- Klipper's measurements: coarse one-mode estimates ------------------------------------------

def klipper_psd_mode(path: str | Path, axis: str, form: str = "base") -> tuple[Mode, float, float]:
    """One mode of ``form`` (``coarse_mode``) from the ``psd_<axis>`` column of Klipper's
    calibrate_shaper CSV (header ``freq,psd_x,psd_y,psd_z,psd_xyz,...``; the shaper columns
    after it are ignored): the frequency of the PSD peak and the damping from its half-power
    band f1..f2 (where the PSD, a power, falls to half the peak), zeta = (f2 - f1) / (2 f0).
    Gives (mode, f1, f2)."""
    column = f"psd_{axis.lower()}"
    if column not in ("psd_x", "psd_y", "psd_z"):
        raise InputError(path, None, f"no PSD column for axis {axis} (calibrate_shaper has psd_x, psd_y, psd_z)")
    _, rows = _read_numeric_csv(path, {("freq", "psd_x", "psd_y", "psd_z", "psd_xyz")})
    data = np.array([values for _, values in rows])
    freq_hz, psd = data[:, 0], data[:, ("psd_x", "psd_y", "psd_z").index(column) + 1]
    lines = [line for line, _ in rows]
    bad = np.flatnonzero(np.diff(freq_hz) <= 0)
    if bad.size:
        raise InputError(path, lines[bad[0] + 1], "frequencies must increase")
    peak = int(np.argmax(psd))
    if not psd[peak] > 0:
        raise InputError(path, None, f"{column} has no positive value")
    half = psd[peak] / 2
    below = np.flatnonzero(psd[:peak] < half)
    above = np.flatnonzero(psd[peak:] < half)
    if not below.size or not above.size:
        raise InputError(path, None, f"{column}: the peak at {freq_hz[peak]:g} Hz does not fall to half power "
                                     "on both sides within the file's band: no damping estimate")
    i, j = below[-1], peak + above[0]  # the crossings, interpolated linearly in the PSD
    f1 = float(np.interp(half, [psd[i], psd[i + 1]], [freq_hz[i], freq_hz[i + 1]]))
    f2 = float(np.interp(half, [psd[j], psd[j - 1]], [freq_hz[j], freq_hz[j - 1]]))
    f0 = float(freq_hz[peak])
    return coarse_mode(f0, (f2 - f1) / (2 * f0), form), f1, f2


def klipper_cfg_modes(path: str | Path, form: str = "base") -> dict[str, Mode]:
    """One mode of ``form`` (``coarse_mode``) per axis (X, Y) from the ``[input_shaper]`` section
    of a Klipper printer.cfg: ``shaper_freq_x/y`` and ``damping_ratio_x/y`` (Klipper's default
    0.1; see ``_klipper_config`` for the SAVE_CONFIG block). Gives {axis: mode} for the axes that
    have a frequency."""
    sections, lines = _klipper_config(path)
    if "input_shaper" not in sections:
        raise InputError(path, None, "no [input_shaper] section (nor one in the #*# SAVE_CONFIG block)")
    values = sections["input_shaper"]
    modes = {}
    for axis in ("x", "y"):
        if f"shaper_freq_{axis}" not in values:
            continue
        frequency = _cfg_number(path, lines, values, f"shaper_freq_{axis}")
        damping = (_cfg_number(path, lines, values, f"damping_ratio_{axis}")
                   if f"damping_ratio_{axis}" in values else KLIPPER_DEFAULT_DAMPING)
        if not frequency > 0 or not 0 < damping < 1:
            raise InputError(path, lines.get(f"shaper_freq_{axis}"),
                             f"shaper_freq_{axis} must be > 0 and damping_ratio_{axis} in (0, 1)")
        modes[axis.upper()] = coarse_mode(frequency, damping, form)
    if not modes:
        raise InputError(path, None, "[input_shaper] has neither shaper_freq_x nor shaper_freq_y")
    return modes


def klipper_cfg_machine(path: str | Path, profile: MachineProfile) -> MachineProfile:
    """``profile`` with what a Klipper printer.cfg says of the firmware fbspost writes for: the
    flavor, ``[printer]`` max_accel (the planner's acceleration), max_velocity,
    square_corner_velocity and minimum_cruise_ratio where given, and ``[input_shaper]``'s
    frequencies (what the output restores after switching shaping off)."""
    sections, lines = _klipper_config(path)
    printer, shaper = sections.get("printer", {}), sections.get("input_shaper", {})
    number = {key: _cfg_number(path, lines, printer, key) for key in
              ("max_accel", "max_velocity", "square_corner_velocity", "minimum_cruise_ratio") if key in printer}
    shaping = {axis.upper(): _cfg_number(path, lines, shaper, f"shaper_freq_{axis}") for axis in "xy"
               if f"shaper_freq_{axis}" in shaper}
    firmware = replace(profile.firmware, flavor="klipper", shaper_frequency_hz={**profile.firmware.shaper_frequency_hz,
                                                                                **shaping},
                       max_velocity_mm_s=number.get("max_velocity", profile.firmware.max_velocity_mm_s),
                       minimum_cruise_ratio=number.get("minimum_cruise_ratio", profile.firmware.minimum_cruise_ratio))
    return replace(profile, firmware=firmware,
                   planner_acceleration_mm_s2=number.get("max_accel", profile.planner_acceleration_mm_s2),
                   planner_square_corner_velocity_mm_s=number.get("square_corner_velocity",
                                                                  profile.planner_square_corner_velocity_mm_s))


def _klipper_config(path: str | Path) -> tuple[dict[str, dict[str, str]], dict[str, int]]:
    """The sections of a Klipper printer.cfg ({section: {key: value}}, the SAVE_CONFIG block's
    ``#*#`` lines at the end, where SHAPER_CALIBRATE saves, overriding the main part as in
    Klipper) and the line of each key, for messages."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    # The main part and the SAVE_CONFIG block, each with the other's lines blank (so configparser's
    # line numbers are the file's); the block's lines before its first section are its banner.
    main, saved, in_section = [], [], False
    for line in text.splitlines():
        block = line.startswith("#*#")
        content = line[3:] if block else ""
        in_section = in_section or (block and content.strip().startswith("["))
        main.append("" if block else line)
        saved.append(content if in_section else "")
    sections: dict[str, dict[str, str]] = {}
    for part in ("\n".join(main), "\n".join(saved)):
        parser = configparser.RawConfigParser(strict=True, inline_comment_prefixes=("#", ";"))
        try:
            parser.read_string(part, source=str(path))
        except configparser.Error as exc:
            raise InputError(
                path, getattr(exc, "lineno", None), f"not a Klipper config: {exc.message.splitlines()[0]}"
            ) from None
        for name in parser.sections():
            sections.setdefault(name, {}).update(parser[name])
    keys = {key for values in sections.values() for key in values}
    lines = {}
    for number, line in enumerate(text.splitlines(), start=1):
        key = line.removeprefix("#*#").split(":", 1)[0].split("=", 1)[0].strip().lower()
        if key in keys:
            lines[key] = number
    return sections, lines


def _cfg_number(path, lines, values, key):
    try:
        value = float(values[key])
    except ValueError:
        raise InputError(path, lines.get(key), f"{key}: not a number: {values[key]!r}") from None
    if not math.isfinite(value):
        raise InputError(path, lines.get(key), f"{key} must be finite")
    return value


def coarse_mode(frequency_hz: float, damping: float, form: str = "base") -> Mode:
    """The single mode of DC gain 1 at ``frequency_hz`` and ``damping``: ``form`` "base", a
    belt- or screw-driven axis, excited through its drive's stiffness and damping, (2 zeta w s +
    w^2) / (s^2 + 2 zeta w s + w^2) (alpha = w^2, beta = 2 zeta w: a zero); "mass", a mass
    pushed by a force, w^2 / (s^2 + 2 zeta w s + w^2) (beta = 0)."""
    w = 2 * math.pi * frequency_hz
    if form not in COARSE_FORMS:
        raise ValueError(f"unknown coarse form {form!r}: expected one of {', '.join(COARSE_FORMS)}")
    return Mode(frequency_hz, damping, w * w, 2 * damping * w if form == "base" else 0.0)


# ---- an accelerometer recording of fbspost excite's sweep ----------------------------------------

@dataclass(frozen=True)
class Recording:
    """The frequency response estimated from a recording of a sweep, over the sweep's band."""

    frequency_hz: np.ndarray
    response: np.ndarray  # H1 = S_xy / S_xx, commanded to measured acceleration
    coherence: np.ndarray
    offset_s: float  # the recording's time of the sweep's start (with the plant's delay, see fit)
    inverted: bool  # the accelerometer axis pointed against the machine axis: sign flipped
    sample_rate_hz: float  # in the machine's time
    clock_rate: float = 1.0  # the recording's seconds per second of the machine's (from the sweep's clock mark)
    excited_at_s: np.ndarray | None = None  # per frequency, when the command holds it (s from the sweep's start)


def read_accel_log(path: str | Path, column: str) -> tuple[np.ndarray, np.ndarray]:
    """(times_s, acceleration) of ``column`` from an accelerometer CSV: header
    ``time_s,accel_x,accel_y,accel_z`` or Klipper's raw ``#time,accel_x,accel_y,accel_z``
    (lines starting with ``#`` before it skipped); times strictly increasing."""
    headers = {("time_s", "accel_x", "accel_y", "accel_z"), ("time", "accel_x", "accel_y", "accel_z")}
    header, rows = _read_numeric_csv(path, headers, comment="#")
    if column not in header[1:]:
        raise InputError(path, None, f"no column {column!r} (the columns are {', '.join(header)})")
    data = np.array([values for _, values in rows])
    bad = np.flatnonzero(np.diff(data[:, 0]) <= 0)
    if bad.size:
        raise InputError(path, rows[bad[0] + 1][0], "times must increase")
    if len(data) < 1000:
        raise InputError(path, None, f"{len(data)} samples: too short a recording for a sweep")
    return data[:, 0], data[:, header.index(column)]


CLOCK_REFIT = 1e-6  # a clock rate the fit finds off by more than this: the response again at its rate


def fit_recording(times_s: np.ndarray, accel: np.ndarray, sweep, n_modes: int | None = None,
                  max_modes: int = 8) -> tuple[Recording, Fit, float]:
    """(the response, the fit, the clock mark's rate) of an accelerometer recording of ``sweep``
    (``frf_from_recording``, ``fit_frf`` with the time offset and the clock's error): where the fit
    finds the clock mark's rate off by more than CLOCK_REFIT (the mark's 5 Hz passages time it to
    about 70 us at 100 mm/s^2 of noise: 3 ppm over a 30 s sweep, 10 over 12 s; the phase of the
    whole band times it far better), the response again at the rate found and fitted again; the
    Fit's clock_error is then what is left of it."""
    recording = frf_from_recording(times_s, accel, sweep)
    mark_rate = recording.clock_rate
    for _ in range(2):
        fit = fit_frf(recording.frequency_hz, recording.response, n_modes, max_modes, weights=recording.coherence,
                      fit_delay=True, clock_times_s=recording.excited_at_s)
        if abs(fit.clock_error) <= CLOCK_REFIT:
            break
        recording = frf_from_recording(times_s, accel, sweep, recording.clock_rate * (1.0 + fit.clock_error))
    return recording, fit, mark_rate


def frf_from_recording(times_s: np.ndarray, accel: np.ndarray, sweep, clock_rate: float | None = None) -> Recording:
    """The frequency response from the measured acceleration ``accel`` at ``times_s`` (its own
    time base) and the commanded motion of ``sweep`` (``excite.Sweep``): the recording is put on a
    uniform grid at its mean rate; the commanded acceleration, band-limited alike, is aligned with
    it by cross-correlation (both low-passed at _ALIGN_LOW_PASS times the band's start) and its
    clock rate found (``_clock_rate``; ``clock_rate``: known);
    then ``_whole_record_frf`` of the program from a second before it to a second after it ends."""
    fs = (len(times_s) - 1) / (times_s[-1] - times_s[0])
    grid = times_s[0] + np.arange(len(times_s)) / fs
    measured = np.interp(grid, times_s, accel)
    measured -= measured.mean()
    duration_s = sweep.times_s[-1]
    # Aligned on the sweep's first octave only: well below the modes the axis follows its command
    # (G ~ 1), while near a mode the response lags by up to half a period and its ringing
    # dominates the correlation.
    octave_s = duration_s * math.log(2) / math.log(sweep.end_hz / sweep.start_hz)
    octave = np.arange(int(octave_s * fs) + 1) / fs
    # both low-passed far below the modes: a sweep of pulses (LinuxCNC's, from rest to rest at its
    # acceleration) excites the modes at every pulse, whose ringing matched the pulses 41 ms off
    low = signal.butter(4, _ALIGN_LOW_PASS * sweep.start_hz, fs=fs, output="sos")
    measured_low = signal.sosfiltfilt(low, measured)
    template = signal.sosfiltfilt(low, _commanded_acceleration(sweep, octave, fs))
    offset_s, inverted = _aligned(measured_low, grid, template)
    rate = clock_rate or 1.0
    if sweep.mark_s or clock_rate:
        rate = clock_rate or _clock_rate(measured, grid, fs, sweep, offset_s)
        # again on the recording's clock: a template on the machine's was 1.45 ms off at 100 ppm
        near_s = (offset_s - 0.01, offset_s + 0.01)
        template = signal.sosfiltfilt(low, _commanded_acceleration(sweep, octave / rate, fs * rate))
        offset_s, inverted = _aligned(measured_low, grid, template, near_s)
    keep = (grid >= offset_s - 1.0) & (grid <= offset_s + rate * (duration_s + 1.0))
    y = -measured[keep] if inverted else measured[keep]
    fs_machine = fs * rate  # the recording's samples per second of the machine's
    x = _commanded_acceleration(sweep, (grid[keep] - offset_s) / rate, fs_machine)
    f, response, coherence = _whole_record_frf(x, y, fs_machine, sweep.start_hz, sweep.end_hz)
    return Recording(f, response, coherence, offset_s, bool(inverted), fs_machine, rate,
                     _excited_at_s(x, fs_machine, f) - 1.0)


def _excited_at_s(x: np.ndarray, fs: float, frequency_hz: np.ndarray) -> np.ndarray:
    """When ``x`` (sampled at ``fs`` from time 0) holds each of ``frequency_hz``: the mean time
    of its short-time spectrum's power there (half-second Hann windows). A sweep holds each
    frequency at one time (the clock mark's repeat: at two, whose mean this is)."""
    f, t_s, spectrum = signal.stft(x, fs=fs, nperseg=int(0.5 * fs))
    power = np.abs(spectrum) ** 2
    at_s = (power @ t_s) / np.maximum(power.sum(axis=1), 1e-300)
    return np.interp(frequency_hz, f, at_s)


FRF_RESOLUTION = 0.002  # relative width of the bands the response is averaged over (a tenth of
#                         the half-width of a mode of damping 0.02: what a peak keeps of its shape)
_FRF_BINS = 3  # at least this many spectral lines per band: the coherence needs more than one


def _whole_record_frf(x: np.ndarray, y: np.ndarray, fs: float, start_hz: float, end_hz: float):
    """(frequencies Hz, H, coherence) from ``x`` and ``y`` sampled at ``fs``, each from rest to
    rest: their whole spectra, so that Y = G X holds line by line (the sweep excites each
    frequency once, and a lightly damped mode rings for seconds after: Welch's windowed segments
    weigh its input and its ringing differently, which biased the phase enough for a belt's zero
    to read as a time offset: Y's zero 0 for 21 on a simulated recording). H1 = S_xy / S_xx and
    the coherence over bands of FRF_RESOLUTION of their frequency, at least _FRF_BINS lines,
    between ``start_hz`` and ``end_hz``."""
    n = sp_fft.next_fast_len(len(x))
    spectrum_x, spectrum_y = sp_fft.rfft(x, n), sp_fft.rfft(y, n)
    f = sp_fft.rfftfreq(n, 1.0 / fs)
    step_hz = f[1]
    edges = [int(math.ceil(start_hz / step_hz))]
    while f[edges[-1]] < end_hz:
        edges.append(edges[-1] + max(_FRF_BINS, int(round(FRF_RESOLUTION * f[edges[-1]] / step_hz))))
    edges = np.array(edges[:-1] if edges[-1] >= len(f) else edges)

    def summed(values):
        return np.add.reduceat(values[:edges[-1]], edges[:-1])

    s_xx, s_yy = summed(np.abs(spectrum_x) ** 2), summed(np.abs(spectrum_y) ** 2)
    s_xy = summed(np.conj(spectrum_x) * spectrum_y)
    weights = np.abs(spectrum_x) ** 2
    centre_hz = summed(weights * f) / s_xx
    return centre_hz, s_xy / s_xx, np.abs(s_xy) ** 2 / (s_xx * s_yy)


def _clock_rate(measured: np.ndarray, grid: np.ndarray, fs: float, sweep, offset_s: float) -> float:
    """The recording's seconds per second of the machine's, from the sweep's clock mark: its first
    passage again at the end, both found in the recording (``measured`` on ``grid``, ``fs``
    samples per second, the sweep starting near ``offset_s``) with the same template, so the
    axis' lag is the same both times; the mark within 1000 ppm of where a clock of the machine's
    rate would put it."""
    duration_s = sweep.times_s[-1]
    # In the recording low-passed, all alike, below the modes: no blocks' corners (1 kHz) there,
    # what the axis' modes would let through of them would align the passages block by block
    low = signal.butter(4, _MARK_LOW_PASS * sweep.start_hz, fs=fs, output="sos")
    # (cut from the whole command low-passed, as the recording is: not low-passed alone, whose
    # ends the filter would shape otherwise)
    machine_s = np.arange(-int(fs), int((duration_s + 1.0) * fs)) / fs  # (from the rest before it)
    first = slice(int(fs), int(fs) + int(_MARK_TEMPLATE_S * fs))
    # where the mark is in the command itself (the header's time is the program's as written,
    # the firmware's plan may differ by milliseconds), from its positions, exact copies of the
    # first passage's (the accelerations' block corners match a block off as well); from that
    # passage as found alike: a correlation over a window that cuts a growing signal peaks off
    # its lag (here by 0.35 ms), the same for both passages
    position = sweep.position(machine_s) - sweep.positions_mm[0]
    passages = [_aligned(position, machine_s, position[first], (at_s - 0.05, at_s + 0.05))[0]
                for at_s in (0.0, sweep.mark_s)]
    mark_s = passages[1] - passages[0]
    template = signal.sosfiltfilt(low, _commanded_acceleration(sweep, machine_s, fs))[first]
    measured_low = signal.sosfiltfilt(low, measured)
    start_at_s, _ = _aligned(measured_low, grid, template, (offset_s - 0.05, offset_s + 0.05))
    reach_s = 1e-3 * mark_s + 1.0 / fs
    window_s = (start_at_s + mark_s - reach_s, start_at_s + mark_s + reach_s)
    mark_at_s, _ = _aligned(measured_low, grid, template, window_s)
    return (mark_at_s - start_at_s) / mark_s


_MARK_TEMPLATE_S = 1.3  # the mark's part well before its fade (at 1.5 s)
_MARK_LOW_PASS = 2.5  # times the band's start, Hz: the mark's passage, far below the modes
# times the band's start, Hz: the sweep's first passage, for its start; below the third harmonic
# of the band's start (a sweep of pulses has all odd harmonics as strong as its fundamental)
_ALIGN_LOW_PASS = 1.5


def _aligned(measured: np.ndarray, grid: np.ndarray, template: np.ndarray,
             window_s: tuple[float, float] | None = None) -> tuple[float, bool]:
    """(the recording's time where ``template`` starts, whether it is inverted there): the peak of
    |normalized cross-correlation|, between samples by a parabola through three, within ``window_s`` (the
    template's start times searched; default anywhere)."""
    if len(measured) < len(template):
        raise ValueError("the recording is shorter than the sweep")
    # normalized by the recording's energy under the template at each lag: a signal that grows
    # (a sweep's acceleration rises with its frequency) pulls a plain correlation's peak later
    # (by 0.9 ms on excite's first octave)
    energy = np.cumsum(np.concatenate([[0.0], measured**2]))
    under = energy[len(template):] - energy[:-len(template)]
    corr = signal.correlate(measured, template, mode="valid", method="fft") / np.sqrt(np.maximum(under, 1e-300))
    fs = 1.0 / (grid[1] - grid[0])
    lo, hi = 0, len(corr)
    if window_s is not None:
        lo = max(lo, int(math.floor((window_s[0] - grid[0]) * fs)))
        hi = min(hi, int(math.ceil((window_s[1] - grid[0]) * fs)) + 1)
    if lo >= hi:
        raise ValueError("the recording ends before the sweep's clock mark")
    k = lo + int(np.argmax(np.abs(corr[lo:hi])))
    inverted = corr[k] < 0
    if 0 < k < len(corr) - 1:
        c0, c1, c2 = corr[k - 1:k + 2] * (-1 if inverted else 1)
        k += 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2)
    return grid[0] + k / fs, bool(inverted)


def _commanded_acceleration(sweep, times_s: np.ndarray, fs: float, oversample: int = 8) -> np.ndarray:
    """The sweep's commanded acceleration at ``times_s`` (uniform at ``fs``): second differences
    of the piecewise-linear command on a grid ``oversample`` times finer, low-passed at 0.4 fs
    without phase shift (the corners of the blocks would alias into the band)."""
    fine = times_s[0] + np.arange(len(times_s) * oversample) / (oversample * fs)
    accel = np.gradient(np.gradient(sweep.position(fine), fine), fine)
    sos = signal.butter(8, 0.4 * fs, fs=oversample * fs, output="sos")
    return signal.sosfiltfilt(sos, accel)[::oversample]


# ---- the result: a profile, a plot ---------------------------------------------------------------

NEW_PROFILE_DEFAULTS = {  # what a new profile gets unless given: a printer-like machine at 1 kHz
    "sample_rate": 1000.0, "planner_acceleration": 3000.0, "square_corner_velocity": 5.0,
    "max_velocity": 300.0, "max_acceleration": 10000.0,
}


def profile_with_axes(base: MachineProfile | None, axes_modes: dict[str, tuple[Mode, ...]], note: str,
                      options: dict, name: str) -> MachineProfile:
    """``base`` (a ``MachineProfile``, or None for a new one) with the axes of ``axes_modes``
    replaced or added: modes normalized to a DC gain of 1; an axis' limits from ``options``
    (the keys of NEW_PROFILE_DEFAULTS and max_jerk; None: not given) where given, else from
    ``base``'s axis, else the defaults (no jerk limit); ``note`` is added to the description."""
    def pick(key, existing):
        given = options.get(key)
        return given if given is not None else existing if existing is not None else NEW_PROFILE_DEFAULTS[key]

    axes = dict(base.axes) if base else {}
    for axis_name, modes in axes_modes.items():
        old = axes.get(axis_name)
        dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in modes)
        normalized = tuple(
            replace(m, frequency_hz=float(m.frequency_hz), damping=float(m.damping), alpha=float(m.alpha / dc_gain),
                    beta=float(m.beta / dc_gain))
            for m in modes
        )
        axes[axis_name] = AxisProfile(
            axis_name,
            pick("max_velocity", old and old.max_velocity_mm_s),
            pick("max_acceleration", old and old.max_acceleration_mm_s2),
            options.get("max_jerk") or (old.max_jerk_mm_s3 if old else None),
            normalized)
    description = f"{base.description}; {note}" if base and base.description else note
    return MachineProfile(
        base.name if base else name, description, "",
        pick("sample_rate", base and base.sample_rate_hz),
        pick("planner_acceleration", base and base.planner_acceleration_mm_s2),
        pick("square_corner_velocity", base and base.planner_square_corner_velocity_mm_s),
        axes, base.firmware if base else FirmwareProfile(), base.home_mm if base else (0.0, 0.0, 0.0))


def profile_text(profile: MachineProfile, path: str | Path) -> str:
    """The TOML text of ``profile``, checked as ``load_profile`` will check the file ``path``
    (``ProfileError`` before anything is written)."""
    text = format_profile(profile)
    parse_profile(tomllib.loads(text), str(path))
    return text


def plot_png(frequency_hz: np.ndarray, measured: np.ndarray, fitted: np.ndarray, title: str) -> bytes:
    """A PNG of measured and fitted magnitude and phase against frequency."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8, 6.5), constrained_layout=True)
    magnitude, phase = figure.subplots(2, 1, sharex=True)
    for data, style, label in ((measured, ".", "measured"), (fitted, "-", "fitted model")):
        magnitude.semilogy(frequency_hz, np.abs(data), style, markersize=2, label=label)
        phase.plot(frequency_hz, np.degrees(np.unwrap(np.angle(data))), style, markersize=2, label=label)
    magnitude.set_ylabel("|G| (actual / commanded)")
    magnitude.set_title(title)
    magnitude.legend()
    phase.set_ylabel("phase (deg)")
    phase.set_xlabel("frequency (Hz)")
    for ax in (magnitude, phase):
        ax.grid(True, which="both", alpha=0.3)
    out = io.BytesIO()
    FigureCanvasAgg(figure).print_png(out)
    return out.getvalue()
