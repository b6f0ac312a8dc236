"""Klipper's planner rules, as vector functions for the planner (``planner.PlanStream``).

Takes the linear pieces of a program (their displacement, length, feed and the limits in force)
and gives what klippy's ``toolhead.Move`` makes of them, in klippy's own operation order:

- ``piece_limits``: the cruise limit and acceleration of each piece. A kinematic move runs at
  min(feed, max_velocity) with the toolhead's accel; an extrude-only move (XYZ below 1e-9 mm)
  at its feed with no accel limit of its own. Moves with Z are limited by max_z_velocity and
  max_z_accel times move_d / |dZ| (kinematics/cartesian.py). Moves with E that do not move X or
  Y, or that retract, are limited by max_extrude_only_velocity / _accel divided by |dE| per mm
  (kinematics/extruder.py check_move).
- ``junction_limits``: Move.calc_junction between kinematic moves: 0 at a reversal (cos theta
  > 0.999999), the junction-deviation and centripetal limits with cos theta clamped at
  -0.999999 (a straight junction of short moves is limited too), the extruder's
  instantaneous_corner_velocity / |change of E per mm|, both cruise limits.
- ``cruise_speeds``: MoveQueue.flush's speeds once the look-ahead passes are done: the junction
  speeds S (the usual passes) and the smoothed ones Sm (the same passes over 2 d
  accel_to_decel, which is how minimum_cruise_ratio lowers the peak of short moves); a move
  that can accelerate in the smoothed plan peaks at most at the smoothed peak of the next move
  that sets it, a move that only decelerates in it cruises at its start speed (klippy's
  "delayed" moves).

Units: mm, s, mm/s, (mm/s)^2.
"""
from __future__ import annotations

import math

import numpy as np

STRAIGHT_COS = 0.999999  # klippy: a junction this close to a reversal stops; the clamp of the other end
EXTRUDE_ONLY_ACCEL = 99999999.9  # klippy's accel of an extrude-only move before the extruder limits it
# klippy's sequential passes give exactly equal squared speeds where a move accelerates or
# decelerates fully in the smoothed plan, and branch on that equality; the planner's vectorized
# passes equal them to a few ulps of their running sums (< 1e-7 (mm/s)^2 over a scan chunk):
# closer than this counts as equal
CLOSE_V2 = 1e-6


def constants(profile) -> tuple[tuple[float, float], tuple[float, float], float]:
    """(max_z_velocity, max_z_accel), (max_extrude_only_velocity, _accel), instantaneous_corner_velocity
    of ``profile`` (a ``MachineProfile``). Klipper caps the Z limits at max_velocity and the
    configured max_accel (the profile's planner acceleration), and has none without a Z axis."""
    z = profile.axes.get("Z")
    z_limits = (math.inf, math.inf) if z is None else (
        min(z.max_velocity_mm_s, profile.toolhead_max_velocity_mm_s),
        min(z.max_acceleration_mm_s2, profile.planner_acceleration_mm_s2))
    e_limits = (profile.extrude_only_velocity_mm_s, profile.extrude_only_accel_mm_s2)
    return z_limits, e_limits, profile.firmware.instantaneous_corner_velocity_mm_s


def piece_limits(delta: np.ndarray, length: np.ndarray, extrude_only: np.ndarray, feed: np.ndarray,
                 max_velocity: np.ndarray, accel: np.ndarray, z_limits: tuple[float, float],
                 e_limits: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit, max_v, accel) of pieces with displacement ``delta`` (m, 4: X Y Z E) and ``length``
    (XYZ or |dE|): unit = delta * (1 / length) (klippy's axes_r), the cruise limit and the
    acceleration after Move.limit_speed by the Z and extruder rules."""
    inv = 1.0 / length
    unit = delta * inv[:, None]
    unit[extrude_only, :3] = 0.0
    max_v = np.where(extrude_only, feed, np.minimum(feed, max_velocity))
    accel = np.where(extrude_only, EXTRUDE_ONLY_ACCEL, accel)
    with np.errstate(divide="ignore"):
        z = ~extrude_only & (delta[:, 2] != 0.0)
        z_ratio = length / np.abs(delta[:, 2])
        max_v = np.where(z, np.minimum(max_v, z_limits[0] * z_ratio), max_v)
        accel = np.where(z, np.minimum(accel, z_limits[1] * z_ratio), accel)
        e_rate = unit[:, 3]
        limited = (delta[:, 3] != 0.0) & ((extrude_only | (delta[:, 0] == 0.0) & (delta[:, 1] == 0.0)) | (e_rate < 0.0))
        inv_e = 1.0 / np.abs(e_rate)
        max_v = np.where(limited, np.minimum(max_v, e_limits[0] * inv_e), max_v)
        accel = np.where(limited, np.minimum(accel, e_limits[1] * inv_e), accel)
    return unit, max_v, accel


def junction_limits(unit_prev, unit_next, jd_prev, jd_next, accel_prev, accel_next, length_prev, length_next,
                    cruise_v2_prev, cruise_v2_next, corner_velocity_mm_s: float) -> np.ndarray:
    """Largest squared speed at junctions between kinematic moves (klippy's Move.calc_junction
    without the forward limit, which the planner's forward pass applies)."""
    cos_theta = -(unit_next[:, 0] * unit_prev[:, 0] + unit_next[:, 1] * unit_prev[:, 1]
                  + unit_next[:, 2] * unit_prev[:, 2])
    reversal = cos_theta > STRAIGHT_COS
    cos_theta = np.maximum(cos_theta, -STRAIGHT_COS)
    sin_d2 = np.sqrt(0.5 * (1.0 - cos_theta))
    r_jd = sin_d2 / (1.0 - sin_d2)
    tan_d2 = sin_d2 / np.sqrt(0.5 * (1.0 + cos_theta))
    diff_r = unit_next[:, 3] - unit_prev[:, 3]
    with np.errstate(divide="ignore"):
        extruder = np.where(diff_r != 0.0, (corner_velocity_mm_s / np.abs(diff_r)) ** 2, cruise_v2_next)
    limit = np.minimum.reduce([r_jd * jd_next * accel_next, r_jd * jd_prev * accel_prev,
                               0.5 * length_next * tan_d2 * accel_next, 0.5 * length_prev * tan_d2 * accel_prev,
                               extruder, cruise_v2_next, cruise_v2_prev])
    return np.where(reversal, 0.0, limit)


def _segmented_cummin(values: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Running minimum of ``values`` restarting where ``segment`` changes (exact: min only)."""
    out = values.copy()
    shift = 1
    while shift < out.size:
        same = segment[shift:] == segment[:-shift]
        out[shift:] = np.where(same, np.minimum(out[shift:], out[:-shift]), out[shift:])
        shift *= 2
    return out


def cruise_speeds(start_v2: np.ndarray, smoothed_v2: np.ndarray, delta_v2: np.ndarray, smooth_delta_v2: np.ndarray,
                  cruise_v2: np.ndarray, carry_v2: float) -> tuple[np.ndarray, ...]:
    """(start, cruise, end squared speed, decided-by-itself, carry) of n pieces from the look-ahead's
    junction speeds ``start_v2`` and ``smoothed_v2`` (n + 1 junctions each, the last one after
    the last piece; the piece after it, if any, assumed to accelerate). ``carry_v2`` is the
    cruise a decelerating run continued from the piece before these (klippy's peak_cruise_v2
    there). A piece is decided by itself when it sets a peak or only decelerates: every piece
    before such a piece is decided with it; ``carry`` is what the next call needs after piece i."""
    n = cruise_v2.size
    s0, s1 = start_v2[:-1], start_v2[1:]
    sm0, sm1 = smoothed_v2[:-1], smoothed_v2[1:]
    reach_sm = sm1 + smooth_delta_v2
    accel = sm0 < reach_sm - CLOSE_V2
    accel_next = np.append(accel[1:], True)
    sets_peak = accel & ((sm0 + smooth_delta_v2 > sm1 + CLOSE_V2) | ~accel_next)
    peak = np.minimum(cruise_v2, (sm0 + reach_sm) * 0.5)
    index = np.where(sets_peak, np.arange(n), n)
    nearest = np.minimum.accumulate(index[::-1])[::-1]
    peak_ahead = np.append(peak, 0.0)[nearest]
    cruise = np.minimum(np.minimum((s0 + (s1 + delta_v2)) * 0.5, cruise_v2), peak_ahead)
    # decelerating runs: the peak of the accelerating piece before them, then each start speed
    run_start = ~accel & np.append(True, accel[:-1])
    before = np.append(carry_v2, peak[:-1])
    seeded = np.where(run_start, np.minimum(s0, before), s0)
    decel = _segmented_cummin(seeded, np.where(accel, -1 - np.arange(n), np.cumsum(accel)))
    cruise = np.where(accel, cruise, decel)
    carry = np.where(accel, peak, decel)
    return np.minimum(s0, cruise), cruise, np.minimum(s1, cruise), sets_peak | ~accel, carry
