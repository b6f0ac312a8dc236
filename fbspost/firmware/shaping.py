"""Input shaping as the firmwares run it, through whole motor steps: the baseline FBS must beat.

Takes one axis of a firmware's plan (positions in mm sampled every ``period_s``, e.g.
``marlin.MarlinRun.positions_mm``), the axis' steps per mm and the shaper's settings; gives the
axis' shaped position in whole steps on the same samples (held at the first and last sample
before and after them). Read from the firmwares' sources (November 2026), not copied:

- **Marlin INPUT_SHAPING_X/Y** (``M593 X F.. D..``, stepper.cpp / stepper.h: ``ShapeParams``,
  ``ShapingQueue``, ``PULSE_PREP_SHAPING``, ``shaping_isr``): a ZV shaper on the axis' *steps*.
  Every step the planner's Bresenham gives adds +-factor1 to a second Bresenham counter at once
  and is queued to add +-factor2 ``delay`` later (factor1 + factor2 = 128, factor2 from a cubic
  in the damping ratio, floored; delay = half the *undamped* period in whole timer ticks); the
  counter steps the motor whenever it reaches +-64 and gives back 128. So the motor is at
  (factor1 n(t) + factor2 n(t - delay)) / 128 steps, rounded, n the unshaped step count:
  *not centred* (Klipper shifts its impulses to a zero mean time): each axis runs late by its
  own factor2 / 128 x delay, and axes with different frequencies fall out of step.
  Not modelled: the queue's early release when it is full (sized for the top step rate), the
  TMC2208 half-step hysteresis.
- **Marlin FT_MOTION** (ft_motion/shaping.cpp): ZV, ZVD, ZVDD, ZVDDD, MZV, EI, 2HEI, 3HEI on its
  own trajectory at FTM_FS (1 kHz): echo times rounded to whole samples (``Ni``), amplitudes
  from K = exp(-zeta pi / sqrt(1 - zeta^2)) (EI's with vibration tolerance ``vtol``); each axis
  shifted back by its centroid rounded to a sample, and every axis then delayed by the largest
  centroid (``largest_delay_samples``: a common delay, left out here), so the axes stay in step.
  Its stepper then rounds to whole steps. Here the trajectory is the plan given.
- **RepRapFirmware M593** (AxisShaper.cpp ``Configure``): one shaper for every axis, its
  cumulative coefficients and durations (ZVD, ZVDD, ZVDDD, MZV, EI2, EI3) as the impulses
  (amplitudes the coefficients' steps, times the durations' sums), uncentred but common to all
  axes, so the path keeps its shape. RRF applies them by replacing each move's acceleration
  and deceleration phases with segments (``PlanShaping``: overlapped for short moves, none where
  the acceleration would fall under M593 L); that per-move planning is not modelled: here the
  impulses are convolved with the whole plan, as on a move long enough for all of them.

Whole steps (``whole_steps``): the count Marlin's Bresenham gives an axis, floor(x spm + 1/2)
(its delta_error starts at half a step); used for RRF's steps too.
"""
from __future__ import annotations

import math

import numpy as np

from ..read.blocks import AXES
from .marlin import lround
from .shapers import HUMP_AMPLITUDES, HUMP_TIMES, Shaper, shape

STEPPER_TIMER_RATE_HZ = 2_000_000  # Marlin's STEPPER_TIMER_RATE on AVR (F_CPU / 8) and most 32-bit HALs
FTM_FS_HZ = 1000  # FT_MOTION's trajectory rate (FTM_FS)
FTM_VTOL = 0.05  # FTM_SHAPING_V_TOL: the EI shapers' vibration tolerance
FT_MOTION_SHAPERS = ("zv", "zvd", "zvdd", "zvddd", "mzv", "ei", "2hei", "3hei")
REPRAP_SHAPERS = ("zvd", "zvdd", "zvddd", "mzv", "ei2", "ei3")
_HALF = 64  # Marlin's shaping counter steps at +-64 of 128
JUMP_MM = 1.0  # between two samples: no axis moves so far (1 m/s at 1 kHz)


def whole_steps(positions_mm: np.ndarray, steps_per_mm: float) -> np.ndarray:
    """``positions_mm`` at the whole step the stepper is on: floor(x spm + 1/2) / spm."""
    return np.floor(np.asarray(positions_mm, dtype=float) * steps_per_mm + 0.5) / steps_per_mm


def stepper_positions(samples_mm: np.ndarray, steps_per_mm: dict[str, float]) -> np.ndarray:
    """Rows of X Y Z E ... (``blocks.AXES``) with X Y Z on their whole steps (``whole_steps``) where
    ``steps_per_mm`` has them; E as given (it only says which samples print)."""
    out = np.array(samples_mm, dtype=float)
    for axis in ("X", "Y", "Z"):
        if axis in steps_per_mm:
            out[:, AXES.index(axis)] = whole_steps(out[:, AXES.index(axis)], steps_per_mm[axis])
    return out


def staircase_positions(samples_mm: np.ndarray, steps_per_mm: dict[str, float], points: int = 20) -> np.ndarray:
    """Rows of X Y Z E ... as ``stepper_positions``, but X Y Z each the mean, over its sample's
    period (centred on it), of the whole step it is on along the motion linear between samples,
    ``points`` to a period: the staircase a stepper runs (a step where the motion crosses a half
    step), as a mode sampled at that period feels it. ``stepper_positions`` holds each sample's own
    step for the period, which aliases a fast axis' step rate (several a period) into the modes'
    band: a bias against motion whose speed changes from block to block. A jump of more than
    ``JUMP_MM`` between samples is a position set, not motion: held."""
    out = np.array(samples_mm, dtype=float)
    u = (np.arange(points) - (points - 1) / 2.0) / points  # (of a period, about the sample)
    for axis in ("X", "Y", "Z"):
        if axis in steps_per_mm:
            x = out[:, AXES.index(axis)]
            before, after = np.append(x[0], x[:-1]), np.append(x[1:], x[-1])
            before = np.where(np.abs(x - before) > JUMP_MM, x, before)
            after = np.where(np.abs(after - x) > JUMP_MM, x, after)
            fine = x[:, None] + np.where(u < 0.0, u * (x - before)[:, None], u * (after - x)[:, None])
            out[:, AXES.index(axis)] = whole_steps(fine, steps_per_mm[axis]).mean(axis=1)
    return out


def marlin_zv_factors(zeta: float) -> tuple[int, int]:
    """(factor1, factor2) of 128: the share of each step Marlin moves at once and ``delay`` later
    (``set_shaping_damping_ratio``: K / (1 + K) fitted by a cubic, floored)."""
    if zeta <= 0.0:
        factor2 = 64
    elif zeta >= 1.0:
        factor2 = 0
    else:
        factor2 = math.floor(64.44056192 - 99.02008832 * zeta - 7.58095488 * zeta**2 + 43.073216 * zeta**3)
    return 128 - factor2, factor2


def marlin_zv_delay_s(frequency_hz: float, timer_rate_hz: int = STEPPER_TIMER_RATE_HZ) -> float:
    """The echo's delay: half the undamped period, truncated to timer ticks (``set_shaping_frequency``)."""
    return int((timer_rate_hz // 2) / frequency_hz) / timer_rate_hz


def marlin_zv(positions_mm: np.ndarray, period_s: float, steps_per_mm: float, frequency_hz: float,
              zeta: float) -> np.ndarray:
    """One axis shaped by Marlin's INPUT_SHAPING (``M593 F D``), in whole steps (module docstring).
    The counter's state is closed form: the motor is within half a step of (factor1 n(t) + factor2
    n(t - delay)) / 128; exactly half a step (a tie) is the step taken, up if the counter last rose
    (of updates within one sample, the echoes first)."""
    factor1, factor2 = marlin_zv_factors(zeta)
    x = np.asarray(positions_mm, dtype=float)
    t = np.arange(len(x)) * period_s
    now = np.floor(x * steps_per_mm + 0.5).astype(np.int64)
    late = np.floor(np.interp(t - marlin_zv_delay_s(frequency_hz), t, x) * steps_per_mm + 0.5).astype(np.int64)
    counter = factor1 * now + factor2 * late
    # The direction of the counter's last update; within one sample the echoes come first.
    moved = np.diff(now, prepend=now[:1])
    moved = np.where(moved != 0, moved, np.diff(late, prepend=late[:1]))
    last = np.maximum.accumulate(np.where(moved != 0, np.arange(len(x)), 0))
    falling_tie = (moved[last] < 0) & (np.mod(counter, 128) == _HALF)
    return (np.floor_divide(counter + _HALF, 128) - falling_tie) / steps_per_mm


def marlin_zv_shaper(frequency_hz: float, zeta: float) -> Shaper:
    """Marlin's ZV as impulses (before the steps): factor1 / 128 now, factor2 / 128 ``delay`` later."""
    factor1, factor2 = marlin_zv_factors(zeta)
    return Shaper("marlin_zv", frequency_hz, zeta, np.array([factor1, factor2]) / 128.0,
                  np.array([0.0, marlin_zv_delay_s(frequency_hz)]))


def _k(zeta: float) -> float:
    return math.exp(-zeta * math.pi / math.sqrt(1.0 - zeta * zeta))


def ft_motion_amplitudes(name: str, zeta: float, vtol: float = FTM_VTOL) -> tuple[np.ndarray, float]:
    """(amplitudes summing to 1, the echoes' spacing in damped periods) of FT_MOTION's ``name``
    (``set_axis_shaping_A`` and ``set_axis_shaping_N``)."""
    k = _k(zeta)
    if name in ("zv", "zvd", "zvdd", "zvddd"):
        order = ("zv", "zvd", "zvdd", "zvddd").index(name) + 1
        a = [math.comb(order, i) * k**i for i in range(order + 1)]  # (1 + K)^order's terms
    elif name == "mzv":
        a = [1.0, math.sqrt(2.0) * k, k * k]
    elif name == "ei":
        a0 = 0.25 * (1.0 + vtol)
        a = [a0, 0.5 * (1.0 - vtol) * k, a0 * k * k]
    elif name == "2hei":
        v2 = vtol * vtol
        x = (v2 * (math.sqrt(1.0 - v2) + 1.0)) ** (1.0 / 3.0)
        a0 = (3.0 * x * x + 2.0 * x + 3.0 * v2) / (16.0 * x)
        a1 = (0.5 - a0) * k
        a = [a0, a1, a1 * k, a0 * k**3]
    elif name == "3hei":
        a0 = 0.0625 * (1.0 + 3.0 * vtol + 2.0 * math.sqrt(2.0 * (vtol + 1.0) * vtol))
        a1 = 0.25 * (1.0 - vtol) * k
        a = [a0, a1, (0.5 * (1.0 + vtol) - 2.0 * a0) * k * k, a1 * k * k, a0 * k**4]
    else:
        raise ValueError(f"unknown FT_MOTION shaper {name!r}: expected one of {', '.join(FT_MOTION_SHAPERS)}")
    a = np.asarray(a, dtype=float)
    return a / a.sum(), 0.375 if name == "mzv" else 0.5


def ft_motion_shaper(name: str, frequency_hz: float, zeta: float, rate_hz: float = FTM_FS_HZ) -> Shaper:
    """FT_MOTION's ``name`` as impulses: echoes a whole number of trajectory samples apart
    (lround of the spacing), shifted back by the centroid rounded to a sample."""
    amplitudes, spacing = ft_motion_amplitudes(name, zeta)
    index = int(lround(spacing / (frequency_hz * math.sqrt(1.0 - zeta * zeta)) * rate_hz)) * np.arange(len(amplitudes))
    index = index + int(lround(-float(amplitudes @ index)))  # Ni[0]: the centroid
    return Shaper(f"ft_{name}", frequency_hz, zeta, amplitudes, index / rate_hz)


def reprap_shaper(name: str, frequency_hz: float, zeta: float) -> Shaper:
    """RepRapFirmware's M593 P``name`` as impulses from the start of an acceleration: the steps of
    its cumulative coefficients, at the sums of its durations (``AxisShaper::Configure``)."""
    damped_period_s = 1.0 / (frequency_hz * math.sqrt(1.0 - zeta * zeta))
    k = _k(zeta)
    z = np.array([1.0, zeta, zeta * zeta, zeta**3])
    if name in ("zvd", "zvdd", "zvddd"):
        order = ("zvd", "zvdd", "zvddd").index(name) + 2
        steps = np.array([math.comb(order, i) * k**i for i in range(order + 1)]) / (1.0 + k) ** order
        durations = np.full(order, 0.5 * damped_period_s)
    elif name == "mzv":  # RRF's MZV is Klipper's: K to the 3/4
        km = math.exp(-zeta * 0.75 * math.pi / math.sqrt(1.0 - zeta * zeta))
        a1 = 1.0 - 0.5 * math.sqrt(2.0)
        steps = np.array([a1, (math.sqrt(2.0) - 1.0) * km, a1 * km * km])
        steps = steps / steps.sum()
        durations = np.full(2, 0.375 * damped_period_s)
    elif name in ("ei2", "ei3"):
        # Klipper's hump EI fits (the same papers' tables), but the last amplitude is 1 minus the
        # others (RRF's coefficients climb to 1) and the times are in damped periods.
        klipper = {"ei2": "2hump_ei", "ei3": "3hump_ei"}[name]
        rise = np.asarray(HUMP_AMPLITUDES[klipper])[:-1] @ z
        steps = np.append(rise, 1.0 - rise.sum())
        durations = np.diff(np.asarray(HUMP_TIMES[klipper]) @ z) * damped_period_s
    else:
        raise ValueError(f"unknown RepRapFirmware shaper {name!r}: expected one of {', '.join(REPRAP_SHAPERS)}")
    return Shaper(f"rrf_{name}", frequency_hz, zeta, steps, np.concatenate([[0.0], np.cumsum(durations)]))


def shaped_steps(positions_mm: np.ndarray, period_s: float, steps_per_mm: float, shaper: Shaper) -> np.ndarray:
    """One axis through the impulses of ``shaper`` (FT_MOTION's, RRF's), then the stepper's whole steps."""
    return whole_steps(shape(positions_mm, period_s, shaper), steps_per_mm)
