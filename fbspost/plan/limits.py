"""The planner's limits: those in force block by block, and those of pieces and junctions.

Takes the profile and the limit changes of the blocks (``blocks.PlannerLimits``); gives a row of
the limits in force per block (``LimitState.row``), the cruise limits and accelerations of
pieces by the per-axis rules (``axis_piece_limits``) and the largest speeds at the junctions
between them (``junction_limits``, Klipper's Move.calc_junction; ``jerk_junction_limits``,
RepRapFirmware's DDA::MatchSpeeds); and the limits LinuxCNC gives an axis the profile leaves out
(``given_or_slowest``).
"""
from __future__ import annotations

import math

import numpy as np

from ..profile import MachineProfile
from ..read.blocks import AXES, OTHER_AXES

_NA = len(AXES)
_E = AXES.index("E")
# RepRapFirmware 3.5's instantaneous speed changes (M566) where neither the program nor the profile
# gives one (Configuration.h DefaultZInstantDv, DefaultEInstantDv; DefaultAxisInstantDv the others);
# X and Y take the square corner velocity in force
REPRAP_JERK_MM_S = {"Z": 10.0, "E": 5.0}
REPRAP_AXIS_JERK_MM_S = 15.0


def given_or_slowest(profile: MachineProfile, names: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The velocity (mm/s) and acceleration (mm/s^2) limits of each axis of ``names``: the
    profile's, else the slowest given axis' (of X Y Z, else of all). LinuxCNC's INI has finite
    limits for every axis, and without any a move of an axis the profile leaves out (Z on an XY
    stage) never ends."""
    given = [profile.axes[a] for a in "XYZ" if a in profile.axes] or list(profile.axes.values())
    axes = [profile.axes.get(a) for a in names]
    return (tuple(a.max_velocity_mm_s if a else min(g.max_velocity_mm_s for g in given) for a in axes),
            tuple(a.max_acceleration_mm_s2 if a else min(g.max_acceleration_mm_s2 for g in given) for a in axes))


class LimitState:
    """The planner settings as the blocks change them; ``row()`` is one row of the state table:
    accel, travel accel (NaN: none), planner max velocity, junction deviation, axis max velocity
    (4), axis max acceleration (4), square corner velocity (classic jerk: Marlin's M205 X Y, RRF's
    M566 X Y), accel_to_decel (Klipper's smoothing; accel elsewhere).

    max_velocity starts at the speed along the path the firmware caps (``profile.path_velocity_mm_s``:
    Klipper's max_velocity, LinuxCNC's MAX_LINEAR_VELOCITY). Klipper: accel_to_decel is
    accel * (1 - minimum_cruise_ratio), or, with the profile's max_accel_to_decel (klippy before
    2024), min(that, accel), SET_VELOCITY_LIMIT ACCEL_TO_DECEL changing it (MINIMUM_CRUISE_RATIO
    unknown there); in the newer Klipper, ACCEL_TO_DECEL sets the ratio 1 - min(1, it / accel)."""

    def __init__(self, profile: MachineProfile, firmware: str | None = None):
        self.accel = float(profile.planner_acceleration_mm_s2)
        self.travel_accel = math.nan
        self.max_velocity = profile.path_velocity_mm_s(firmware)
        self.klipper = firmware == "klipper"
        self.cruise_ratio = profile.firmware.minimum_cruise_ratio
        self.accel_to_decel = profile.firmware.max_accel_to_decel_mm_s2  # None: the ratio rules
        self.scv = float(profile.planner_square_corner_velocity_mm_s)
        self.direct_jd: float | None = None  # Marlin M205 J, until a square corner velocity is set
        self.axis_v = np.full(_NA, math.inf)
        self.axis_a = np.full(_NA, math.inf)
        for i, name in enumerate(AXES):
            if name in profile.axes:
                self.axis_v[i] = profile.axes[name].max_velocity_mm_s
                self.axis_a[i] = profile.axes[name].max_acceleration_mm_s2
        if firmware == "linuxcnc":  # as LinuxCNC's INI: finite limits for every axis (given_or_slowest)
            names = "XYZ" + OTHER_AXES
            columns = [AXES.index(a) for a in names]
            (self.axis_v[columns], self.axis_a[columns]) = given_or_slowest(profile, names)

    def apply(self, limits, line_no: int) -> None:
        def positive(value, what, zero_ok=False):
            if not (math.isfinite(value) and (value > 0 or zero_ok and value == 0)):
                raise ValueError(f"line {line_no}: {what} must be {'>=' if zero_ok else '>'} 0, got {value!r}")
            return float(value)

        if limits.acceleration_mm_s2 is not None:
            self.accel = positive(limits.acceleration_mm_s2, "acceleration")
        if limits.travel_acceleration_mm_s2 is not None:
            self.travel_accel = positive(limits.travel_acceleration_mm_s2, "travel acceleration")
        if limits.max_velocity_mm_s is not None:
            self.max_velocity = positive(limits.max_velocity_mm_s, "max velocity")
        if limits.square_corner_velocity_mm_s is not None:
            self.scv = positive(limits.square_corner_velocity_mm_s, "square corner velocity", zero_ok=True)
            self.direct_jd = None
        if limits.junction_deviation_mm is not None and not self.klipper:
            self.direct_jd = positive(limits.junction_deviation_mm, "junction deviation", zero_ok=True)
        self._apply_smoothing(limits)
        if self.klipper:  # Klipper knows no M201 / M203 / M205 J
            return
        for name, value in limits.axis_max_velocity_mm_s.items():
            if name in AXES:
                self.axis_v[AXES.index(name)] = positive(value, f"{name} max velocity")
        for name, value in limits.axis_max_acceleration_mm_s2.items():
            if name in AXES:
                self.axis_a[AXES.index(name)] = positive(value, f"{name} max acceleration")

    def _apply_smoothing(self, limits) -> None:
        ratio, to_decel = limits.minimum_cruise_ratio, limits.accel_to_decel_mm_s2
        if self.accel_to_decel is not None:  # klippy before 2024
            self.accel_to_decel = to_decel if to_decel is not None else self.accel_to_decel
        elif ratio is not None:
            self.cruise_ratio = ratio
        elif to_decel is not None:
            self.cruise_ratio = 1.0 - min(1.0, to_decel / self.accel)

    def row(self) -> list[float]:
        jd = self.direct_jd
        if jd is None:  # Klipper's _calc_junction_deviation, with the accel in force
            jd = self.scv**2 * (math.sqrt(2.0) - 1.0) / self.accel
        if not self.klipper:
            to_decel = self.accel
        elif self.accel_to_decel is None:
            to_decel = self.accel * (1.0 - self.cruise_ratio)
        else:
            to_decel = min(self.accel_to_decel, self.accel)
        return [self.accel, self.travel_accel, self.max_velocity, jd, *self.axis_v, *self.axis_a, self.scv, to_decel]



def junction_limits(unit_prev: np.ndarray, unit_next: np.ndarray, jd_prev, jd_next, accel_prev, accel_next,
                    delta_prev, delta_next, cruise_v2_prev, cruise_v2_next) -> np.ndarray:
    """Largest squared speed at junctions between XYZ pieces (Klipper's Move.calc_junction):
    the cruise speeds, and for a real corner the junction-deviation and centripetal limits."""
    cos_theta = -np.einsum("ij,ij->i", unit_prev, unit_next)
    sin_d2 = np.sqrt(np.maximum(0.5 * (1.0 - cos_theta), 0.0))
    cos_d2 = np.sqrt(np.maximum(0.5 * (1.0 + cos_theta), 0.0))
    one_minus_sin = 1.0 - sin_d2
    limit = np.minimum(cruise_v2_prev, cruise_v2_next)
    corner = (one_minus_sin > 0.0) & (cos_d2 > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_jd = sin_d2 / one_minus_sin
        quarter_tan = 0.25 * sin_d2 / cos_d2
        corner_limit = np.minimum.reduce([r_jd * jd_next * accel_next, r_jd * jd_prev * accel_prev,
                                          delta_next * quarter_tan, delta_prev * quarter_tan])
    return np.where(corner, np.minimum(limit, corner_limit), limit)



def reprap_jerk_mm_s(scv_mm_s: np.ndarray) -> np.ndarray:
    """(n, len(AXES)) RepRapFirmware's M566 per drive: X and Y ``scv_mm_s`` (per row), the others its defaults."""
    jerk = np.array([REPRAP_JERK_MM_S.get(a, REPRAP_AXIS_JERK_MM_S) for a in AXES]) * np.ones((len(scv_mm_s), 1))
    jerk[:, :2] = np.asarray(scv_mm_s)[:, None]
    return jerk


def jerk_junction_limits(unit_prev, unit_next, jerk_mm_s, cruise_v2_prev, cruise_v2_next, meld) -> np.ndarray:
    """Largest squared speed at junctions by RepRapFirmware's rule (DDA::MatchSpeeds): on every
    drive, E included, the change of its speed per unit of path speed (``unit``: per mm of
    length) at most its ``jerk_mm_s`` (M566, the next piece's), and both cruise speeds; 0 where
    the pieces do not ``meld`` (jerk policy P0: a printing move, a travel, an extrude-only move)."""
    step = np.abs(unit_next - unit_prev)
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = np.where(step > 0, jerk_mm_s / step, np.inf).min(axis=1)
    return np.where(meld, np.minimum(np.minimum(cruise_v2_prev, cruise_v2_next), cap * cap), 0.0)


def axis_piece_limits(delta, length, extrude_only, feed, planner_v, accel_print, accel_travel, axis_v, axis_a,
                      xy_accel_only: bool = False):
    """(unit, cruise limit, accel, feed clamped) of pieces by the per-axis rules (not Klipper's);
    ``xy_accel_only`` (RepRapFirmware): M204's accelerations only for pieces that move X or Y."""
    unit = delta / length[:, None]
    unit[extrude_only, :3] = 0.0  # along E (or LinuxCNC's other axes) alone
    abs_unit = np.abs(unit)
    with np.errstate(divide="ignore"):
        axis_v_limit = np.where(abs_unit > 0, axis_v / abs_unit, np.inf).min(axis=1, initial=np.inf)
        axis_a_limit = np.where(abs_unit > 0, axis_a / abs_unit, np.inf).min(axis=1, initial=np.inf)
    max_v = np.minimum(np.minimum(feed, planner_v), axis_v_limit)
    clamped = np.isfinite(feed) & (axis_v_limit < feed)  # as the controller does (a G0 means it)
    extrudes = delta[:, _E] > 0
    accel = np.where(extrudes | np.isnan(accel_travel), accel_print, accel_travel)
    if xy_accel_only:  # (an axis without a limit keeps M204's)
        accel = np.where((delta[:, 0] != 0) | (delta[:, 1] != 0) | ~np.isfinite(axis_a_limit), accel, np.inf)
    return unit, max_v, np.minimum(accel, axis_a_limit), clamped

