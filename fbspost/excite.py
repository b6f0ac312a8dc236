"""Excitation programs for identification: a sine sweep of one axis, and reading one back.

Takes an axis' limits, a centre position, a band, a duration and a block time; gives the G-code
of a logarithmic sine sweep (chirp) of that axis' position about the centre: G1 blocks of equal
time, each with the F that gives it that time (like the dense output of ``compensate``), the
amplitude falling with frequency so that the sampled velocity, acceleration and jerk stay within
the axis' limits, tapered in and out so the motion starts and ends at rest. ``read_sweep``
gives back the commanded motion of such a program (block end times and positions), which
``identify --accel-log`` relates to an accelerometer recording of it.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .profile import AxisProfile
from .trajectory import InputError

_BEGIN = "; fbspost excite: sweep begins"
_END = "; fbspost excite: sweep ends"
_BAND = re.compile(r"; band: ([0-9.]+) Hz to ([0-9.]+) Hz")
_REST_S = 1.0  # dwell before and after the sweep, so a recording holds the rest on both sides
_POSITION_DECIMALS = 6  # 1 nm


@dataclass(frozen=True)
class Sweep:
    """The commanded motion of a sweep program, in the program's time (0 at the sweep's start)."""

    axis: str
    times_s: np.ndarray  # block ends, times_s[0] = 0 at the start position
    positions_mm: np.ndarray
    start_hz: float
    end_hz: float

    def position(self, times_s: np.ndarray) -> np.ndarray:
        """The commanded position at any times (held before the start and after the end)."""
        return np.interp(times_s, self.times_s, self.positions_mm)


def sweep_samples(axis: AxisProfile, centre_mm: float, start_hz: float, end_hz: float, duration_s: float,
                  amplitude_mm: float, block_s: float, ramp_s: float = 0.5) -> np.ndarray:
    """Positions every ``block_s`` from the centre back to the centre: x = c + A(t) sin(phi(t)),
    phi's frequency rising exponentially from start_hz to end_hz over duration_s (and on at the
    same rate over the raised-cosine ramps of ramp_s added before and after, so the whole band
    is swept at full amplitude), A the largest amplitude (at most amplitude_mm) within 90% of
    the axis' limits at the current frequency; then scaled down, if needed, until the finite
    differences of the samples, with the rest before and after, keep every limit."""
    t = np.arange(int(round((duration_s + 2 * ramp_s) / block_s)) + 1) * block_s
    rate = math.log(end_hz / start_hz) / duration_s
    f0 = start_hz * math.exp(-rate * ramp_s)
    phase = 2 * math.pi * f0 * np.expm1(rate * t) / rate
    w = 2 * math.pi * f0 * np.exp(rate * t)
    limits = [(axis.max_velocity_mm_s, 1), (axis.max_acceleration_mm_s2, 2)]
    if axis.max_jerk_mm_s3:
        limits.append((axis.max_jerk_mm_s3, 3))
    # 90% of each limit: the rising frequency and the ramps add a little to the sine's derivatives
    amplitude = np.minimum(amplitude_mm, np.min([0.9 * lim / w**k for lim, k in limits], axis=0))
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip(np.minimum(t, t[-1] - t) / ramp_s, 0.0, 1.0))
    offset = amplitude * ramp * np.sin(phase)
    padded = np.concatenate([[0.0] * 3, offset, [0.0] * 3])
    worst = max(np.abs(np.diff(padded, k)).max() / block_s**k / lim for lim, k in limits)
    return centre_mm + offset / max(1.0, worst * (1 + 1e-9))


def sweep_program(axis: AxisProfile, positions_mm: np.ndarray, block_s: float, start_hz: float, end_hz: float,
                  machine: str) -> str:
    """The G-code of the sampled sweep: move to the start (at a tenth of the axis' maximum
    velocity), dwell, the sweep's G1 blocks, dwell. A block whose written length would be zero
    (at the ramps, the firmware would skip it) is merged into the next, so every written block
    takes the time it is given."""
    name = axis.name
    rounded = np.round(positions_mm, _POSITION_DECIMALS)
    speed = np.abs(np.diff(positions_mm)).max() / block_s
    accel = np.abs(np.diff(positions_mm, 2)).max() / block_s**2
    lines = [
        f"; fbspost excite: a sine sweep of axis {name} for identification ({machine})",
        f"; band: {start_hz:g} Hz to {end_hz:g} Hz, exponential, "
        f"{(len(positions_mm) - 1) * block_s:g} s with the ramps "
        f"in {block_s * 1e3:g} ms blocks, about {rounded[0]:.3f} mm",
        f"; largest amplitude {np.abs(positions_mm - positions_mm[0]).max():.4f} mm, velocity {speed:.4g} mm/s, "
        f"acceleration {accel:.5g} mm/s^2 (the axis' limits: {axis.max_velocity_mm_s:g} mm/s, "
        f"{axis.max_acceleration_mm_s2:g} mm/s^2)",
        "; Home the machine and make sure the axis is free to move there. The firmware's acceleration",
        f"; limit must be at least {math.ceil(accel)} mm/s^2 "
        f"(e.g. Klipper SET_VELOCITY_LIMIT ACCEL=..., Marlin M204 S...)",
        "; and input shaping or other motion filtering off, or it is identified with the machine.",
        "; Record an accelerometer on the moving part during the whole program, then:",
        f";   fbspost identify --accel-log LOG.csv --program THIS.gcode --axis {name} -o PROFILE.toml",
        "G21 ; millimetres",
        "G90 ; absolute positions",
        f"G1 {name}{rounded[0]:.{_POSITION_DECIMALS}f} F{60 * axis.max_velocity_mm_s / 10:.0f}",
        f"G4 P{_REST_S * 1e3:.0f}",
        _BEGIN,
    ]
    last, last_k = rounded[0], 0
    for k in range(1, len(rounded)):
        if rounded[k] == last and k < len(rounded) - 1:
            continue
        if rounded[k] == last:  # the end, still at the start position: a dwell keeps the time
            lines.append(f"G4 P{(k - last_k) * block_s * 1e3:.6f}")
        else:
            feed = 60 * abs(rounded[k] - last) / ((k - last_k) * block_s)
            lines.append(f"G1 {name}{rounded[k]:.{_POSITION_DECIMALS}f} F{_fixed(feed)}")
        last, last_k = rounded[k], k
    lines += [_END, f"G4 P{_REST_S * 1e3:.0f}", ""]
    return "\n".join(lines)


def _fixed(value: float, significant: int = 9) -> str:
    """``value`` in fixed point (G-code has no exponents) with ``significant`` digits."""
    decimals = max(0, significant - 1 - math.floor(math.log10(value)))
    return f"{value:.{decimals}f}"


_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


def read_sweep(path: str | Path, axis: str) -> Sweep:
    """The commanded motion of a program written by ``sweep_program`` for ``axis``: the position
    at the begin marker, then every G1 (time = length / F) and G4 (P ms) up to the end marker."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    position = feed = band = None
    times, positions, inside, ended = [], [], False, False
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if band is None and (match := _BAND.match(stripped)):
            band = float(match[1]), float(match[2])
        if stripped == _BEGIN:
            if position is None:
                raise InputError(path, lineno, f"the sweep begins before any G1 {axis} sets the start position")
            inside, times, positions = True, [0.0], [position]
            continue
        if stripped == _END:
            ended = inside
            break
        words = [(k.upper(), float(v)) for k, v in _WORD.findall(line.split(";", 1)[0])]
        codes = [int(v) for k, v in words if k == "G"]
        if 91 in codes:
            raise InputError(path, lineno, "G91: a sweep program is in absolute positions")
        if 4 in codes and inside:
            dwell_ms = next((v for k, v in words if k == "P"), 0.0)
            times.append(times[-1] + dwell_ms / 1e3)
            positions.append(position)
        elif {0, 1} & set(codes):
            target = next((v for k, v in words if k == axis), None)
            feed = next((v for k, v in words if k == "F"), feed)
            others = [k for k, _ in words if k in "XYZABCUVWE" and k != axis]
            if inside and (others or target is None or not feed):
                raise InputError(path, lineno, f"a sweep block moves {axis} alone, with a feed")
            if target is not None:
                if inside:
                    times.append(times[-1] + abs(target - position) / (feed / 60))
                    positions.append(target)
                position = target
    if not ended:
        raise InputError(path, None, f"no sweep of axis {axis} between '{_BEGIN}' and '{_END}': "
                                     "not a program written by fbspost excite?")
    if band is None:
        raise InputError(path, None, "no '; band: ... Hz to ... Hz' line")
    return Sweep(axis, np.array(times), np.array(positions), *band)
