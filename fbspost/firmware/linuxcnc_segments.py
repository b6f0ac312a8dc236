"""The segments of LinuxCNC 2.9's trajectory planner (``linuxcnc_tp``) and what they are made from.

Takes a program's MOVE blocks (``blocks.Block``) and the INI's limits (``LinuxCNCConfig``); gives
one ``Tc`` (a TC_STRUCT: a line, a G2/G3 as chords, or a blend arc) per block that moves, with its
limits and terminal condition (``segment``, the mode a line sets: ``line_mode``), its position
along its path (``Tc.at``) and its accelerations, and the velocities both the queue and the
servo cycle use (``max_target``, ``parabolic_velocities``). Units: mm, s.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..plan.limits import given_or_slowest
from ..profile import MachineProfile
from ..read.blocks import EXTRA_AXES, OTHER_AXES, Block

_XYZ = slice(0, 3)
_OTHER = list(EXTRA_AXES)  # A B C U V W (E, column 3, is no LinuxCNC axis)
_CART_FUZZ = 1e-10  # posemath's CART_FUZZ: below it a line's part has no length (tmag_zero)
STOP, EXACT, PARABOLIC, TANGENT = "stop", "exact", "parabolic", "tangent"
ACC_TAN = 0.5  # BLEND_ACC_RATIO_TANGENTIAL
BLEND_MODE = re.compile(rb"[Gg]\s*0*6\s*(4|1\s*\.\s*1|1)(?![\d.])((?:\s*[PpQq]\s*[-+]?[\d.]+)*)")


@dataclass(frozen=True)
class LinuxCNCConfig:
    """The INI's limits and the TP's settings (LinuxCNC's defaults; ``from_profile``: the
    profile's ``[firmware]`` ones, ``profile.LinuxCNCSettings``)."""

    axis_velocity_mm_s: tuple[float, float, float]  # [AXIS_X/Y/Z] MAX_VELOCITY
    axis_acceleration_mm_s2: tuple[float, float, float]  # [AXIS_X/Y/Z] MAX_ACCELERATION
    # [AXIS_A/B/C/U/V/W] MAX_VELOCITY and MAX_ACCELERATION (deg or mm; inf: not limited)
    other_velocity: tuple[float, ...] = (math.inf,) * 6
    other_acceleration: tuple[float, ...] = (math.inf,) * 6
    max_linear_velocity_mm_s: float = math.inf  # [TRAJ] MAX_LINEAR_VELOCITY
    servo_period_s: float = 0.001  # [EMCMOT] SERVO_PERIOD 1000000 ns
    optimization_depth: int = 50  # [TRAJ] ARC_BLEND_OPTIMIZATION_DEPTH
    gap_cycles: float = 4.0  # [TRAJ] ARC_BLEND_GAP_CYCLES
    ramp_frequency_hz: float = 100.0  # [TRAJ] ARC_BLEND_RAMP_FREQ
    kink_ratio: float = 0.1  # [TRAJ] ARC_BLEND_KINK_RATIO
    arc_blends: bool = True  # [TRAJ] ARC_BLEND_ENABLE
    startup_tolerance_mm: float = 0.0  # the G64 P the machine starts in (RS274NGC_STARTUP_CODE)

    @classmethod
    def from_profile(cls, profile: MachineProfile, **changes) -> LinuxCNCConfig:
        (velocity, acceleration), (other_velocity, other_acceleration) = (given_or_slowest(profile, "XYZ"),
                                                                          given_or_slowest(profile, OTHER_AXES))
        ini = profile.firmware.linuxcnc  # (ARC_BLEND_FALLBACK_ENABLE: in the INI the bench runs, not modelled)
        return cls(**{"axis_velocity_mm_s": velocity, "axis_acceleration_mm_s2": acceleration,
                      "other_velocity": other_velocity, "other_acceleration": other_acceleration,
                      "servo_period_s": ini.servo_period_s, "optimization_depth": ini.arc_blend_optimization_depth,
                      "gap_cycles": float(ini.arc_blend_gap_cycles), "ramp_frequency_hz": ini.arc_blend_ramp_freq_hz,
                      "kink_ratio": ini.arc_blend_kink_ratio, "arc_blends": ini.arc_blend_enable,
                      "startup_tolerance_mm": ini.g64_p_mm, "max_linear_velocity_mm_s": ini.max_linear_velocity_mm_s,
                      **changes})


@dataclass
class Tc:
    """One TC_STRUCT: a line (or a G2/G3 as chords) or a blend arc, and its run-time state."""

    start: np.ndarray  # (NA,)
    end: np.ndarray
    path: np.ndarray  # (k, 3) XYZ points along the segment (a line: its two ends)
    line: int  # the program block it comes from
    reqvel: float
    maxvel: float
    maxaccel: float
    term: str
    tolerance: float
    rapid: bool = False
    rotary: bool = False  # A B C or U V W move (tpRotaryMotionCheck): neither tangent nor blend arc
    arc_radius: float = math.inf  # the tightest radius of a G2/G3 or of a blend arc
    nominal: float = 0.0
    target: float = 0.0
    kink_vel: float = -1.0
    kink_reduce: float = 0.0
    kink_reduce_prev: float = 0.0
    blend_prev: bool = False
    finalized: bool = False
    finalvel: float = 0.0
    acc_ratio_tan: float = ACC_TAN
    at_max: bool = False
    # run time
    ramp: bool = False
    active: bool = False
    progress: float = 0.0
    currentvel: float = 0.0
    cycle_s: float = 0.0
    splitting: bool = False
    term_vel: float = 0.0
    blending: bool = False
    on_final_decel: bool = False
    vel_at_blend_start: float = 0.0
    blend_vel: float = 0.0
    lengths: np.ndarray = field(default_factory=lambda: np.zeros(1))
    circle: tuple | None = None  # blend arc: (center, u, w, length of the consumed line before it)

    def set_path(self, path: np.ndarray) -> None:
        self.path = path
        self.lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        self.target = float(self.lengths[-1])

    @property
    def arc(self) -> bool:
        return math.isfinite(self.arc_radius)

    def at(self, s: float) -> np.ndarray:
        """The NA position at progress ``s`` (XYZ along the path, other axes in proportion)."""
        frac = s / self.target if self.target > 0 else 1.0
        out = self.start + (self.end - self.start) * frac
        if self.circle is not None:  # a blend arc, after the line it consumed
            center, u, w, line_mm = self.circle
            if s >= line_mm:
                angle = (s - line_mm) / self.arc_radius
                out[_XYZ] = center + self.arc_radius * (math.cos(angle) * u + math.sin(angle) * w)
                return out
        out[_XYZ] = [np.interp(s, self.lengths, self.path[:, i]) for i in range(3)]
        return out

    def start_unit(self) -> np.ndarray:
        return unit(self.path[1] - self.path[0])

    def end_unit(self) -> np.ndarray:
        return unit(self.path[-1] - self.path[-2])

    def overall_accel(self) -> float:
        """tcGetOverallMaxAccel: reduced by a kink, halved in a parabolic blend."""
        scale = 1.0 - max(self.kink_reduce, self.kink_reduce_prev)
        if self.blend_prev or self.term == PARABOLIC:
            scale *= 0.5
        return self.maxaccel * scale

    def tangential_accel(self) -> float:
        return self.overall_accel() * (self.acc_ratio_tan if self.arc else 1.0)


def unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def along(bounds: np.ndarray, u: np.ndarray) -> float:
    """The largest magnitude along unit ``u`` within per-axis ``bounds`` (emccanon)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.where(np.abs(u) > 1e-12, bounds / np.abs(u), np.inf).min())


def find_v_peak(accel: float, length: float) -> float:
    """findVPeak: the top of a triangle from rest to rest over ``length``."""
    return math.sqrt(accel * length)


def max_target(tc: Tc, config: LinuxCNCConfig) -> float:
    """tpGetMaxTargetVel (feed override 1): F within the segment's and the machine's limits."""
    return min(tc.reqvel, tc.maxvel, config.max_linear_velocity_mm_s)


def parabolic_velocities(tc: Tc, nexttc: Tc, v_this: float, v_next: float) -> tuple[float, float, float]:
    """tpComputeBlendVelocity: (this, next, net tangent) velocities of a parabolic blend."""
    acc_this, acc_next = tc.tangential_accel(), nexttc.tangential_accel()
    reach_this = min(_triangle(tc), v_this)
    reach_next = min(_triangle(nexttc), v_next)
    if reach_this <= 0 or reach_next <= 0:
        return 0.0, 0.0, 0.0
    t_blend = min(min(tc.target / reach_this, nexttc.target / reach_next),
                  max(reach_this / acc_this, reach_next / acc_next))
    b_this, b_next = min(reach_this, t_blend * acc_this), min(reach_next, t_blend * acc_next)
    theta = math.acos(max(-1.0, min(1.0, -float(tc.end_unit() @ nexttc.start_unit())))) / 2.0
    if tc.tolerance > 0 and math.cos(theta) > math.cos(math.pi / 2.0 - 1e-3):
        limit = 2.0 * math.sqrt(acc_this * tc.tolerance / math.cos(theta))
        b_this, b_next = min(b_this, limit), min(b_next, limit)
    return b_this, b_next, math.sin(theta) * (b_this + b_next) / 2.0


def _triangle(tc: Tc) -> float:
    """tpCalculateTriangleVel: half the length while it may still be blended away."""
    return find_v_peak(tc.tangential_accel(), tc.target if tc.finalized else 0.5 * tc.target)


def segment(block: Block, index: int, start: np.ndarray, mode: tuple[str, float],
            config: LinuxCNCConfig) -> list[Tc]:
    """The TC of a MOVE block from ``start`` (none if it does not move)."""
    points = np.where(np.isnan(block.points_mm), start, block.points_mm)
    path = np.vstack([start[None, _XYZ], points[:, _XYZ]])
    pieces = np.diff(path, axis=0)
    lengths = np.linalg.norm(pieces, axis=1)
    rest = float(np.linalg.norm((points[-1] - start)[3:]))
    rotary = bool(np.any(np.abs((points[-1] - start)[_OTHER]) > _CART_FUZZ))
    if lengths.sum() < 1e-12 and rest < 1e-12:
        return []
    vel, acc = _straight_limits(pieces, lengths, (points[-1] - start)[_OTHER], config)
    rapid = math.isinf(block.feed_mm_s)
    tc = Tc(start, points[-1], path, index, vel if rapid else min(block.feed_mm_s, vel), vel, acc,
            mode[0], mode[1], rapid=rapid, rotary=rotary, arc_radius=_radius(path) if len(points) > 1 else math.inf)
    tc.set_path(path)
    if tc.target < 1e-12:  # only axes besides X Y Z: their length, XYZ still
        tc.lengths, tc.target = np.array([0.0, rest]), rest
        tc.path = path[[0, -1]]
    return [tc]


def _straight_limits(pieces: np.ndarray, lengths: np.ndarray, other: np.ndarray,
                     config: LinuxCNCConfig) -> tuple[float, float]:
    """emccanon's getStraightVelocity / getStraightAcceleration: the fastest F and acceleration
    along the move with every moving axis within its limits; the A B C U V W axes' share of the
    XYZ length where XYZ move, else along their own length (the feed's length then)."""
    other_mm = float(np.linalg.norm(other))
    moving = [unit(p) for p, n in zip(pieces, lengths, strict=True) if n > 1e-12]
    if not moving:  # only the other axes: their own direction
        share = other / other_mm
        return along(np.array(config.other_velocity), share), along(np.array(config.other_acceleration), share)
    share = other / float(lengths.sum())
    vel = min(min(along(np.array(config.axis_velocity_mm_s), u) for u in moving),
              along(np.array(config.other_velocity), share))
    acc = min(min(along(np.array(config.axis_acceleration_mm_s2), u) for u in moving),
              along(np.array(config.other_acceleration), share))
    return vel, acc


def _radius(path: np.ndarray) -> float:
    """The tightest circumradius of consecutive chord triples (a G2/G3 read as chords)."""
    a, b, c = path[:-2], path[1:-1], path[2:]
    ab, bc, ca = (np.linalg.norm(x, axis=1) for x in (b - a, c - b, a - c))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = ab * bc * ca / (2.0 * area2)
    r = r[np.isfinite(r)]
    return float(r.min()) if r.size else 1e12


def line_mode(raw: bytes, mode: tuple[str, float]) -> tuple[str, float]:
    """G61 (exact path), G61.1 (exact stop), G64 [P tolerance] (blend) as a line sets them."""
    found = BLEND_MODE.search(raw.split(b";")[0])
    if not found:
        return mode
    code = found.group(1).replace(b" ", b"")
    if code != b"4":
        return (EXACT if code == b"1" else STOP), 0.0
    p = re.search(rb"[Pp]\s*([-+]?[\d.]+)", found.group(2))
    return PARABOLIC, float(p.group(1)) if p else 0.0
