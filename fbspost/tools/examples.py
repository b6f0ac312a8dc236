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


def _program(points_mm: np.ndarray, feeds_mm_min: np.ndarray, title: str) -> str:
    """A LinuxCNC-style program of G1 blocks through ``points_mm``, F written where it changes."""
    lines = [f"({title})", "G21 G90 G17", f"G0 X{points_mm[0, 0]:.4f} Y{points_mm[0, 1]:.4f}"]
    previous = None
    for (x, y), feed in zip(points_mm[1:], feeds_mm_min, strict=True):
        words = f"G1 X{x:.4f} Y{y:.4f}"
        if feed != previous:
            words += f" F{feed:.3f}"
            previous = feed
        lines.append(words)
    lines.append("M2")
    return "\n".join(lines) + "\n"


def butterfly_dense_program(size_mm: float) -> str:
    """The butterfly as 1 ms G1 blocks at the patent stage's planned timing, each with the F that
    gives it its time (what a CAM system with its own interpolator writes)."""
    _, x_mm, y_mm = butterfly(sample_rate_hz=10000.0, size_mm=size_mm)
    dense = np.round(np.column_stack([x_mm, y_mm])[::10], 4)
    lengths = np.hypot(*np.diff(dense, axis=0).T)
    keep = np.concatenate([[True], lengths > 0])  # a block that does not move cannot carry time
    dense = dense[keep]
    durations = np.diff(np.flatnonzero(keep)) * 1e-3
    feeds = np.hypot(*np.diff(dense, axis=0).T) / durations * 60.0
    return _program(dense, np.round(feeds, 3), "butterfly, 1 ms blocks at the patent stage's planned timing")


def butterfly_polyline_program(size_mm: float, chord_mm: float = 0.05, feed_mm_min: float = 6000.0) -> str:
    """The butterfly as chords of ``chord_mm`` at one feed (what a CAM system writes when the
    controller plans the motion)."""
    theta = np.linspace(0.0, BUTTERFLY_PARAMETER_END, 400001)
    cx, cy = butterfly_curve(theta)
    curve = size_mm * np.column_stack([cx, cy])
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(curve, axis=0).T))])
    stations = np.linspace(0.0, arc[-1], int(np.ceil(arc[-1] / chord_mm)) + 1)
    chords = np.column_stack([np.interp(stations, arc, curve[:, 0]), np.interp(stations, arc, curve[:, 1])])
    return _program(
        chords, np.full(len(chords) - 1, feed_mm_min), f"butterfly, {chord_mm:g} mm chords at F{feed_mm_min:g}"
    )
