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

Its parts: ``measurements.py`` (the files read: responses, recordings, Klipper's CSV and cfg),
``sweep_response.py`` (a recording of the sweep to a response), ``modal_fit.py`` (the fit),
``fit_trust.py`` (its checks and tolerances); here, the profile written and the plot.
"""
from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..profile import AxisProfile, FirmwareProfile, MachineProfile, Mode, format_profile, parse_profile

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

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
