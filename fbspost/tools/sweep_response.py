"""The frequency response from an accelerometer recording of ``fbspost excite``'s sweep.

Takes the recording (its times and one axis' acceleration, ``measurements.read_accel_log``) and
the sweep (``excite.Sweep``); gives a ``Recording`` (``frf_from_recording``: the response, its
coherence, the sweep's start in the recording, its clock's rate from the sweep's clock mark, when
each frequency was excited), and with the fit (``fit_recording``) the modes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft
from scipy import signal

from .modal_fit import Fit, fit_frf


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
    first = slice(int(fs) + int(_MARK_SETTLED_S * fs), int(fs) + int(_MARK_TEMPLATE_S * fs))
    # where the mark is in the command itself (the header's time is the program's as written,
    # the firmware's plan may differ by milliseconds), from its positions, exact copies of the
    # first passage's (the accelerations' block corners match a block off as well); from that
    # passage as found alike: a correlation over a window that cuts a growing signal peaks off
    # its lag (here by 0.35 ms), the same for both passages
    position = sweep.position(machine_s) - sweep.positions_mm[0]
    passages = [_aligned(position, machine_s, position[first], (at_s - 0.05, at_s + 0.05))[0]
                for at_s in (_MARK_SETTLED_S, sweep.mark_s + _MARK_SETTLED_S)]
    mark_s = passages[1] - passages[0]
    template = signal.sosfiltfilt(low, _commanded_acceleration(sweep, machine_s, fs))[first]
    measured_low = signal.sosfiltfilt(low, measured)
    start_at_s, _ = _aligned(measured_low, grid, template,
                             (offset_s + _MARK_SETTLED_S - 0.05, offset_s + _MARK_SETTLED_S + 0.05))
    reach_s = 1e-3 * mark_s + 1.0 / fs
    window_s = (start_at_s + mark_s - reach_s, start_at_s + mark_s + reach_s)
    mark_at_s, _ = _aligned(measured_low, grid, template, window_s)
    return (mark_at_s - start_at_s) / mark_s


_MARK_TEMPLATE_S = 1.3  # the mark's part well before its fade (at 1.5 s) ...
# ... from here on: before it, the axis still rings from what precedes the mark (LinuxCNC's sweep
# returns to its start in one block at the axis' acceleration right before it), which through the
# low-pass took the mark 47 ppm off on a 10 s sweep of a 23 Hz mode of damping 0.07 (7 from here)
_MARK_SETTLED_S = 0.3
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
