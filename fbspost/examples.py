"""Reference trajectories: the patent's butterfly (Temple Fay's butterfly curve).

Takes a size and the planner's limits; gives sample times and x, y positions on a uniform grid.
"""
from __future__ import annotations

import numpy as np

BUTTERFLY_PARAMETER_END = 12.0 * np.pi


def butterfly_curve(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x = sin t (e^cos t - 2 cos 4t - sin^5(t/12)), y = cos t (same), in curve units."""
    r = np.exp(np.cos(theta)) - 2.0 * np.cos(4.0 * theta) - np.sin(theta / 12.0) ** 5
    return np.sin(theta) * r, np.cos(theta) * r


def _parameter(times_s: np.ndarray, rate: float, ramp_s: float, duration_s: float) -> np.ndarray:
    """Curve parameter for a parameter rate that rises from 0 to ``rate`` and back along
    C2 (smootherstep) ramps of ``ramp_s``, so the motion starts and ends at rest."""

    def ramp_area(u):  # integral over [0, u] of the smootherstep 6u^5 - 15u^4 + 10u^3
        u = np.clip(u, 0.0, 1.0)
        return u**6 - 3 * u**5 + 2.5 * u**4

    u_up = times_s / ramp_s
    rising = ramp_s * np.where(u_up < 1.0, ramp_area(u_up), u_up - 0.5)
    u_down = np.clip((duration_s - times_s) / ramp_s, 0.0, 1.0)
    falling = ramp_s * (0.5 - u_down + ramp_area(u_down))
    return rate * (rising - falling)


def butterfly(sample_rate_hz: float = 10000.0, size_mm: float = 1.0, max_speed_mm_s: float = 100.0,
              max_acceleration_mm_s2: float = 5000.0, ramp_s: float = 0.1):
    """The butterfly scaled by ``size_mm`` per curve unit and timed as fast as the planner allows.

    The path speed and the path acceleration (vector magnitudes) stay within the limits; the
    motion starts at (0, x) at rest and ends at rest. Returns (times_s, x_mm, y_mm).
    """
    fine = np.linspace(0.0, BUTTERFLY_PARAMETER_END, 200001)
    h = fine[1] - fine[0]
    x, y = butterfly_curve(fine)
    d1 = np.hypot(np.gradient(x, h), np.gradient(y, h))
    d2 = np.hypot(np.gradient(np.gradient(x, h), h), np.gradient(np.gradient(y, h), h))
    rate = min(max_speed_mm_s / (size_mm * d1.max()), np.sqrt(max_acceleration_mm_s2 / (size_mm * d2.max())))
    while True:  # the ramps add tangential acceleration: slow down until the sampled plan complies
        duration_s = BUTTERFLY_PARAMETER_END / rate + ramp_s
        n = int(np.ceil(duration_s * sample_rate_hz))
        times_s = np.arange(n + 1) / sample_rate_hz
        duration_s = times_s[-1]
        rate = BUTTERFLY_PARAMETER_END / (duration_s - ramp_s)
        xs, ys = butterfly_curve(_parameter(times_s, rate, ramp_s, duration_s))
        xs, ys = size_mm * xs, size_mm * ys
        dt = 1.0 / sample_rate_hz
        speed = np.hypot(np.diff(xs), np.diff(ys)) / dt
        accel = np.hypot(np.diff(xs, 2), np.diff(ys, 2)) / dt**2
        worst = max(speed.max() / max_speed_mm_s, np.sqrt(accel.max() / max_acceleration_mm_s2))
        if worst <= 1.0:
            return times_s, xs, ys
        rate /= worst * 1.0005
