"""Klipper's input shapers, to compare with FBS.

Takes a shaper name (``SHAPERS``), a frequency and a damping ratio; gives its impulses as Klipper
builds them (klippy/extras/shaper_defs.py: ZV, MZV, ZVD, EI with 5 % vibration tolerance, 2- and
3-hump EI), normalized to sum 1 and shifted so their amplitude-weighted mean time is zero
(Klipper's ``shift_pulses`` in chelper/kin_shaper.c): the shaped motion starts ``lead_s`` before
the plan and ends ``lag_s`` after it. ``shape`` applies a shaper to sampled positions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SHAPERS = ("zv", "mzv", "zvd", "ei", "2hump_ei", "3hump_ei")
VIBRATION_TOLERANCE = 0.05  # Klipper's SHAPER_VIBRATION_REDUCTION = 20
# Klipper's largest damping ratio each shaper is defined for (its INPUT_SHAPERS table).
MAX_DAMPING = {"zv": 0.99, "mzv": 0.99, "zvd": 0.99, "ei": 0.4, "2hump_ei": 0.3, "3hump_ei": 0.2}

# The hump EI shapers are fits in the damping ratio d: a row (c0, c1, c2, c3) is c0 + c1 d + c2
# d^2 + c3 d^3; times in periods of the shaper frequency (undamped), amplitudes before normalizing.
HUMP_TIMES = {
    "2hump_ei": ((0.0, 0.0, 0.0, 0.0), (0.49890, 0.16270, -0.54262, 6.16180),
                 (0.99748, 0.18382, -1.58270, 8.17120), (1.49920, -0.09297, -0.28338, 1.85710)),
    "3hump_ei": ((0.0, 0.0, 0.0, 0.0), (0.49974, 0.23834, 0.44559, 12.4720),
                 (0.99849, 0.29808, -2.36460, 23.3990), (1.49870, 0.10306, -2.01390, 17.0320),
                 (1.99960, -0.28231, 0.61536, 5.40450)),
}
HUMP_AMPLITUDES = {
    "2hump_ei": ((0.16054, 0.76699, 2.26560, -1.22750), (0.33911, 0.45081, -2.58080, 1.73650),
                 (0.34089, -0.61533, -0.68765, 0.42261), (0.15997, -0.60246, 1.00280, -0.93145)),
    "3hump_ei": ((0.11275, 0.76632, 3.29160, -1.44380), (0.23698, 0.61164, -2.57850, 4.85220),
                 (0.30008, -0.19062, -2.14560, 0.13744), (0.23775, -0.73297, 0.46885, -2.08650),
                 (0.11244, -0.45439, 0.96382, -1.46000)),
}


@dataclass(frozen=True)
class Shaper:
    name: str
    frequency_hz: float
    damping: float
    amplitudes: np.ndarray  # sum 1
    times_s: np.ndarray  # ascending; Klipper's: sum(amplitudes * times_s) = 0 (firmware_shapers' need not be)

    @property
    def lead_s(self) -> float:
        """How much earlier than the plan the shaped motion starts."""
        return float(-self.times_s[0])

    @property
    def lag_s(self) -> float:
        """How much later than the plan the shaped motion ends."""
        return float(self.times_s[-1])


def klipper_shaper(name: str, frequency_hz: float, damping: float) -> Shaper:
    """The shaper ``name`` for a mode at ``frequency_hz`` with damping ratio ``damping``."""
    if name not in SHAPERS:
        raise ValueError(f"unknown shaper {name!r}: expected one of {', '.join(SHAPERS)}")
    if not frequency_hz > 0:
        raise ValueError(f"shaper frequency must be > 0 Hz, got {frequency_hz!r}")
    if not 0 <= damping <= MAX_DAMPING[name]:
        raise ValueError(f"{name} is defined for damping ratios 0 to {MAX_DAMPING[name]:g}, got {damping:g}")
    df = math.sqrt(1.0 - damping**2)
    t_d = 1.0 / (frequency_hz * df)  # damped period
    k = math.exp(-damping * math.pi / df)  # decay over half a damped period
    if name == "zv":
        a, t = [1.0, k], [0.0, 0.5 * t_d]
    elif name == "zvd":
        a, t = [1.0, 2.0 * k, k * k], [0.0, 0.5 * t_d, t_d]
    elif name == "mzv":  # zeros at the frequency and 5/3 of it, impulses 3/8 damped period apart
        km = k**0.75
        a, t = [1.0 - math.sqrt(0.5), (math.sqrt(2.0) - 1.0) * km, (1.0 - math.sqrt(0.5)) * km * km], \
            [0.0, 0.375 * t_d, 0.75 * t_d]
    elif name == "ei":
        v, d = VIBRATION_TOLERANCE, damping
        a1 = (0.24968 + 0.24961 * v) + ((0.80008 + 1.23328 * v) + (0.49599 + 3.17316 * v) * d) * d
        a3 = (0.25149 + 0.21474 * v) + ((-0.83249 + 1.41498 * v) + (0.85181 - 4.90094 * v) * d) * d
        t2 = 0.4999 + (((0.46159 + 8.57843 * v) * v)
                       + (((4.26169 - 108.644 * v) * v) + ((1.75601 + 336.989 * v) * v) * d) * d) * d
        a, t = [a1, 1.0 - a1 - a3, a3], [0.0, t2 * t_d, t_d]
    else:
        powers = damping ** np.arange(4)
        a = np.asarray(HUMP_AMPLITUDES[name]) @ powers
        t = np.asarray(HUMP_TIMES[name]) @ powers / frequency_hz
    amplitudes = np.asarray(a, dtype=float) / np.sum(a)
    times = np.asarray(t, dtype=float)
    return Shaper(name, float(frequency_hz), float(damping), amplitudes, times - amplitudes @ times)


def shape(positions_mm: np.ndarray, period_s: float, shaper: Shaper) -> np.ndarray:
    """``sum_i a_i x(t - t_i)`` on the samples' grid, x the samples joined by straight lines (so
    exact for a piecewise-linear-in-time motion; for the planner's piecewise-quadratic one the
    error is that of linear interpolation, under a T^2/8 of the acceleration). Rows are samples,
    columns axes. The samples must rest at least ``lead_s`` at the start and ``lag_s`` at the end
    (the motion is held at its first and last sample beyond them)."""
    positions_mm = np.asarray(positions_mm, dtype=float)
    columns = positions_mm.reshape(len(positions_mm), -1)
    t = np.arange(len(positions_mm)) * period_s
    out = np.zeros_like(columns)
    for a, delay in zip(shaper.amplitudes, shaper.times_s, strict=True):
        for j in range(columns.shape[1]):
            out[:, j] += a * np.interp(t - delay, t, columns[:, j])
    return out.reshape(positions_mm.shape)
