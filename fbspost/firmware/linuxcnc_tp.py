"""LinuxCNC 2.9's trajectory planner (TP) over a program's moves: the motion the machine makes.

Takes the blocks of a program (``gcode.read_gcode``), a machine profile and a ``LinuxCNCConfig``
(the INI's limits, LinuxCNC's defaults); gives ``LinuxCNCRun``: the TP's position and the
joints' commands every servo period, when each line's motion ends, and the joints' positions on
the profile's sample grid
(``firmware.replan(..., "linuxcnc")`` wraps it as ``FirmwareMotion``).

Modelled from LinuxCNC/linuxcnc src/emc/tp (tp.c, tc.c, blendmath.c of the 2.8/2.9 line as the
code index stores them, read November 2026: trapezoidal planner only; the S-curve PLANNER_TYPE
and its jerk limits came with 2.10) and the INI documentation ([TRAJ] ARC_BLEND_*):
- segments (``tpAddLine``): reqvel F; maxvel and maxaccel the axes' MAX_VELOCITY /
  MAX_ACCELERATION along the move (emccanon), vLimit [TRAJ] MAX_LINEAR_VELOCITY; a rapid asks
  for maxvel. A G2/G3 comes from the reader as chords: one segment here, as LinuxCNC keeps it,
  with ``tcUpdateArcLimits``' normal acceleration share (radius from its chords).
- the short-segment cap: maxvel <= length / servo period when added and finalized
  (``tcClampVelocityByLength``) and <= length / (1.02 period) in the optimizer
  (``tpComputeOptimalVelocity``, TPMIN_SEGMENT_CYCLES): every segment lasts a period or more.
- terminal conditions: G61.1 stop, G61 exact (no blend; tangent if the kink allows), G64 P
  parabolic unless a better blend is found; a rapid next to a feed move stops
  (``handleModeChange``); a turn within 2 degrees of a reversal stops (``tpSetupTangent``).
- ``tpSetupTangent``: a_inst = v_max / T + a; the kink's acceleration per axis over the axis
  limit, below ARC_BLEND_KINK_RATIO (0.1): tangent at v_max, the acceleration reduced by it;
  else kink_vel = v_max ratio / scale and a blend is tried.
- line-line blend arcs (``blendmath``: blendInit3FromLineLine, blendParamKinematics,
  blendComputeParameters, blendCheckConsume): tolerance min(P, lengths / 4) (P 0: lengths / 4),
  h = T / (1 - sin t), d = min(L1, L2, h cos t) with L1 = min(rest of the previous, half its
  length), L2 half the next, a_n = 0.866 a_max in the plane (0.5 a_max along the arc: a blend arc
  keeps BLEND_ACC_RATIO_TANGENTIAL), v_plan = min(sqrt(a_n R), v_goal),
  R_plan = max(v_plan^2 / a_n, the parabolic-equivalent radius); the previous line consumed
  into the arc if its rest takes under ARC_BLEND_GAP_CYCLES (4) periods; the blend kept only if
  its maxvel beats the tangent kink_vel and half the parabolic blend velocity
  (``tpChooseBestBlend``). Arcs next to arcs: tangent or parabolic only (not modelled: LinuxCNC's
  line-arc and arc-arc blend arcs).
- parabolic blends (``tpComputeBlendVelocity``, ``tpUpdateBlend``): both segments at half
  acceleration, the next started when the current decelerates below its blend velocity
  (at most 2 sqrt(a T / cos t)), their motions summed.
- look-ahead (``tpRunOptimization``): after each segment is queued, a backward pass over
  ARC_BLEND_OPTIMIZATION_DEPTH (50) segments, the newest ending at its triangle velocity,
  stopping at the 2nd non-tangent segment or past 4 peaks (TP_OPTIMIZATION_LAZY).
- the servo cycle (``tpRunCycle``): trapezoidal velocity (``findTrapezoidalDesiredVel``), or a
  constant-acceleration ramp for tangent segments under 1 / ARC_BLEND_RAMP_FREQ (10 ms), split
  cycles at segment ends (the next segment runs the rest of the period).
Not modelled: feed override (1.0), spindle sync, naive-CAM merging (Q > 0: the writer sends
Q0), the queue filling while motion runs (the whole run is queued before it starts; the TP's
queue holds 2000 segments), blends into a segment already past a quarter of its length, and
LinuxCNC's half-period first ramp of a G64 corner from rest (its joints half a period later).
The joints get the TP's points through the motion controller's cubic interpolator (cubic.c
at interpolation rate 1, the servo period being the trajectory period): each period the way
point (1/6, 2/3, 1/6) of the three points before the newest, so 2 periods late, a pass-band
2/3 + 1/3 cos(2 pi f T) at frequency f; the first point fills the queue. Between servo periods
the joints' position is interpolated linearly (what a stepgen or drive in position mode does).
A line that stops the machine (G4, M-codes: ``Kind.STOP``) waits for the queue to empty, then its
dwell. Units: mm, s.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..profile import MachineProfile
from ..read.gcode import AXES, Block, Kind

_NA = len(AXES)
_XYZ = slice(0, 3)
STOP, EXACT, PARABOLIC, TANGENT = "stop", "exact", "parabolic", "tangent"
MIN_SEGMENT_CYCLES = 1.02  # tp_types.h TPMIN_SEGMENT_CYCLES
_ACC_TAN, _ACC_NORMAL = 0.5, math.sqrt(0.75)  # BLEND_ACC_RATIO_TANGENTIAL / _NORMAL
_SHARP_CORNER = (math.pi * 2.0 / 180.0) ** 2  # tpSetupTangent: SHARP_CORNER_DEG 2
BLEND_MODE = re.compile(rb"[Gg]\s*0*6\s*(4|1\s*\.\s*1|1)(?![\d.])((?:\s*[PpQq]\s*[-+]?[\d.]+)*)")


@dataclass(frozen=True)
class LinuxCNCConfig:
    """The INI's limits and the TP's settings (LinuxCNC's defaults; ``from_profile``: the
    profile's ``[firmware]`` ones, ``profile.LinuxCNCSettings``)."""

    axis_velocity_mm_s: tuple[float, float, float]  # [AXIS_X/Y/Z] MAX_VELOCITY
    axis_acceleration_mm_s2: tuple[float, float, float]  # [AXIS_X/Y/Z] MAX_ACCELERATION
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
        # An axis the profile leaves out (Z on an XY stage) gets the slowest given axis' limits:
        # the INI has finite ones, and without any a move of that axis alone never ends.
        given = [profile.axes[a] for a in "XYZ" if a in profile.axes] or list(profile.axes.values())
        limits = [profile.axes.get(a) for a in "XYZ"]
        velocity = tuple(a.max_velocity_mm_s if a else min(g.max_velocity_mm_s for g in given) for a in limits)
        acceleration = tuple(a.max_acceleration_mm_s2 if a else min(g.max_acceleration_mm_s2 for g in given)
                             for a in limits)
        ini = profile.firmware.linuxcnc  # (ARC_BLEND_FALLBACK_ENABLE: in the INI the bench runs, not modelled)
        return cls(**{"axis_velocity_mm_s": velocity, "axis_acceleration_mm_s2": acceleration,
                      "servo_period_s": ini.servo_period_s, "optimization_depth": ini.arc_blend_optimization_depth,
                      "gap_cycles": float(ini.arc_blend_gap_cycles), "ramp_frequency_hz": ini.arc_blend_ramp_freq_hz,
                      "kink_ratio": ini.arc_blend_kink_ratio, "arc_blends": ini.arc_blend_enable,
                      "startup_tolerance_mm": ini.g64_p_mm, **changes})


@dataclass
class _Tc:
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
    arc_radius: float = math.inf  # the tightest radius of a G2/G3 or of a blend arc
    nominal: float = 0.0
    target: float = 0.0
    kink_vel: float = -1.0
    kink_reduce: float = 0.0
    kink_reduce_prev: float = 0.0
    blend_prev: bool = False
    finalized: bool = False
    finalvel: float = 0.0
    acc_ratio_tan: float = _ACC_TAN
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
        return _unit(self.path[1] - self.path[0])

    def end_unit(self) -> np.ndarray:
        return _unit(self.path[-1] - self.path[-2])

    def overall_accel(self) -> float:
        """tcGetOverallMaxAccel: reduced by a kink, halved in a parabolic blend."""
        scale = 1.0 - max(self.kink_reduce, self.kink_reduce_prev)
        if self.blend_prev or self.term == PARABOLIC:
            scale *= 0.5
        return self.maxaccel * scale

    def tangential_accel(self) -> float:
        return self.overall_accel() * (self.acc_ratio_tan if self.arc else 1.0)


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def _along(bounds: np.ndarray, u: np.ndarray) -> float:
    """The largest magnitude along unit ``u`` within per-axis ``bounds`` (emccanon)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.where(np.abs(u) > 1e-12, bounds / np.abs(u), np.inf).min())


def _in_plane(bounds: np.ndarray, binormal: np.ndarray) -> float:
    """calculateInscribedDiameter: the bound on any direction in the plane normal to ``binormal``."""
    scales = np.linalg.norm(np.eye(3) - np.outer(binormal, binormal), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.where(scales > 1e-12, bounds / scales, np.inf).min())


def _find_v_peak(accel: float, length: float) -> float:
    """findVPeak: the top of a triangle from rest to rest over ``length``."""
    return math.sqrt(accel * length)


class _Queue:
    """The TP's queue as segments are added (``tpAddLine`` .. ``tpFinalizeAndEnqueue``)."""

    def __init__(self, config: LinuxCNCConfig):
        self.config, self.items = config, []
        self.acc_bound = np.array(config.axis_acceleration_mm_s2, dtype=float)
        self.vel_bound = np.array(config.axis_velocity_mm_s, dtype=float)

    def add(self, tc: _Tc) -> None:
        """Clamp by length, blend with the last segment, finalize it, queue, optimize."""
        T = self.config.servo_period_s
        tc.nominal = tc.target
        tc.maxvel = min(tc.maxvel, tc.target / T)
        prev = self.items[-1] if self.items else None
        if prev is not None:
            tc.blend_prev = prev.term == PARABOLIC
            if prev.rapid != tc.rapid:
                self._set_term(prev, tc, STOP)
            if self.config.arc_blends:
                self._blend(prev, tc)
            self._finalize(prev)
        self.items.append(tc)
        self._optimize()

    @staticmethod
    def _set_term(prev: _Tc, tc: _Tc | None, term: str) -> None:
        """tcSetTermCond: the previous segment's end, and whether the next blends with it."""
        prev.term = term
        if tc is not None:
            tc.blend_prev = term == PARABOLIC

    def _finalize(self, tc: _Tc) -> None:
        """tcFinalizeLength: the short-segment cap again (the length may have changed) and a
        G2/G3's share of normal acceleration (tcUpdateArcLimits: TC_CIRCULAR only; a blend arc,
        TC_SPHERICAL, keeps BLEND_ACC_RATIO_TANGENTIAL)."""
        if tc.finalized:
            return
        tc.maxvel = min(tc.maxvel, tc.target / self.config.servo_period_s)
        if tc.arc and tc.circle is None:
            a_max = tc.overall_accel()
            a_n_cutoff = _ACC_NORMAL * a_max
            if tc.maxvel ** 2 / tc.arc_radius > a_n_cutoff:
                tc.maxvel = math.sqrt(a_n_cutoff * tc.arc_radius)
            else:
                tc.acc_ratio_tan = math.sqrt(1.0 - (tc.maxvel ** 2 / tc.arc_radius / a_max) ** 2)
        tc.finalized = True

    def _tangent(self, prev: _Tc, tc: _Tc) -> str:
        """tpSetupTangent: 'ok' (tangent), 'fail' (no blend) or 'try' (kink too large)."""
        if prev.term == STOP or self.config.optimization_depth < 2:
            return "fail"
        u1, u2 = prev.end_unit(), tc.start_unit()
        if float(np.sum((u1 + u2) ** 2)) < _SHARP_CORNER:  # pmCartCartAntiParallel
            self._set_term(prev, tc, STOP)
            return "fail"
        v_max = min(min(p.maxvel, p.reqvel) for p in (prev, tc))
        a_inst = v_max / self.config.servo_period_s + tc.maxaccel
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(np.isfinite(self.acc_bound), np.abs(a_inst * (u2 - u1)) / self.acc_bound, 0.0)
        scale_max = float(scale.max())
        if prev.arc or tc.arc:
            scale_max /= _ACC_TAN
        ratio = self.config.kink_ratio
        if scale_max < ratio:
            self._set_term(prev, tc, TANGENT)
            self._kink(prev, tc, v_max, scale_max)
            return "ok"
        self._kink(prev, tc, v_max * ratio / scale_max, ratio)
        return "try"

    @staticmethod
    def _kink(prev: _Tc, tc: _Tc, kink_vel: float, reduce: float) -> None:
        """tcSetKinkProperties (reduce < 0: tcRemoveKinkProperties)."""
        prev.kink_vel = kink_vel
        prev.kink_reduce = max(reduce, prev.kink_reduce) if reduce >= 0 else 0.0
        tc.kink_reduce_prev = max(reduce, tc.kink_reduce_prev) if reduce >= 0 else 0.0

    def _blend(self, prev: _Tc, tc: _Tc) -> None:
        """tpHandleBlendArc: tangent, a blend arc, or the best of parabolic and tangent."""
        if self._tangent(prev, tc) != "try":
            return
        if prev.term == PARABOLIC and not (prev.arc or tc.arc or prev.finalized):
            arc = self._line_blend(prev, tc)
            if arc is not None:
                return
        self._choose(prev, tc, None)

    def _choose(self, prev: _Tc, tc: _Tc, arc: _Tc | None) -> str:
        """tpChooseBestBlend by performance: parabolic / 2, the tangent kink_vel, the arc's maxvel."""
        if prev.term in (STOP, EXACT):
            return "none"
        parabolic = _parabolic_velocities(prev, tc, _max_target(prev, self.config), _max_target(tc, self.config))[2]
        perf = [parabolic / 2.0, prev.kink_vel, arc.maxvel if arc is not None else 0.0]
        best = ("parabolic", "tangent", "arc")[int(np.argmax(perf))]
        if best != "tangent":
            self._kink(prev, tc, -1.0, -1.0)
        if best == "parabolic":
            self._set_term(prev, tc, PARABOLIC)
        elif best == "tangent":
            self._set_term(prev, tc, TANGENT)
        return best

    def _line_blend(self, prev: _Tc, tc: _Tc) -> _Tc | None:
        """tpCreateLineLineBlend: the blend arc between two lines, queued if it is the best blend."""
        u1, u2 = prev.end_unit(), tc.start_unit()
        theta = math.acos(max(-1.0, min(1.0, -float(u1 @ u2)))) / 2.0
        phi = math.pi - 2.0 * theta
        binormal, normal = _unit(np.cross(u1, u2)), _unit(u2 - u1)
        tolerance = _blend_tolerance(prev, tc)
        a_max = _in_plane(self.acc_bound, binormal)
        a_n = _ACC_NORMAL * a_max
        v_req = max(prev.reqvel, tc.reqvel)
        phi_eff = min(phi, 0.49 * math.pi)
        v1 = min(prev.maxvel, tc.maxvel / math.cos(phi_eff))
        v2 = min(tc.maxvel, prev.maxvel / math.cos(phi_eff))
        altitude = v1 * v2 * math.sin(phi) / float(np.linalg.norm(u2 * v2 - u1 * v1))
        v_goal = min(v_req, max(altitude, _in_plane(self.vel_bound, binormal)))
        d_geom = min(prev.target, 0.5 * prev.nominal, 0.5 * tc.target,
                     math.cos(theta) * tolerance / (1.0 - math.sin(theta)))
        r_geom = math.tan(theta) * d_geom
        v_plan = min(math.sqrt(a_n * r_geom), v_goal)
        a_par = 0.5 * a_max  # the parabolic-equivalent radius (blendComputeParameters)
        s_blend = min(math.sqrt(2.0 * a_par * d_geom), v_plan) / a_par * v_plan
        radius = max(v_plan ** 2 / a_n, min(s_blend / phi, r_geom))
        if radius < 1e-12 or radius * phi < 1e-6:
            return None
        d_plan = radius / math.tan(theta)
        corner = prev.path[-1]
        arc_start, arc_end = corner - u1 * d_plan, corner + u2 * d_plan
        center = corner + normal * radius / math.sin(theta)
        rest = prev.target - d_plan
        consume = rest / v_plan < self.config.gap_cycles * self.config.servo_period_s
        u = _unit(arc_start - center)
        w = _unit(arc_end - center - u * float(u @ (arc_end - center)))
        points = np.vstack([prev.path[:1], arc_start, arc_end]) if consume else np.vstack([arc_start, arc_end])
        arc = _Tc(prev.at(prev.target - (prev.target if consume else d_plan)), tc.at(d_plan), points, prev.line,
                  v_req, v_plan, a_max, TANGENT, prev.tolerance, arc_radius=radius)
        line_mm = rest if consume else 0.0
        arc.circle = (center, u, w, line_mm)
        arc.lengths = np.array([0.0, line_mm, line_mm + radius * phi])[-len(points):]
        arc.target = arc.nominal = line_mm + radius * phi
        self._finalize(arc)
        if self._choose(prev, tc, arc) != "arc":
            return None
        if consume:
            self.items.pop()
        else:
            _trim(prev, arc_start, at_end=True)
            prev.term = TANGENT
        _trim(tc, arc_end, at_end=False)
        tc.blend_prev = False
        self.items.append(arc)
        return arc

    def _optimize(self) -> None:
        """tpRunOptimization: the backward pass from the newest segment."""
        items, config = self.items, self.config
        hit_peaks, non_tangent = 0, False
        for x in range(1, config.optimization_depth + 2):
            ind = len(items) - x
            if ind < 1:
                return
            tc, prev = items[ind], items[ind - 1]
            if prev.term != TANGENT:
                if non_tangent:
                    return
                non_tangent = True
                continue
            if not tc.finalized:  # up to half of it may be blended away: stop at its middle
                prev.finalvel = min(prev.maxvel, _find_v_peak(tc.tangential_accel(), tc.target),
                                    _max_target(tc, config))
                if prev.kink_vel >= 0:
                    prev.finalvel = min(prev.finalvel, prev.kink_vel)
                tc.finalvel = 0.0
            else:
                self._optimal_velocity(tc, prev)
            if tc.at_max:
                hit_peaks += 1
            if hit_peaks > 4:  # TP_OPTIMIZATION_CUTOFF
                return

    def _optimal_velocity(self, tc: _Tc, prev: _Tc) -> None:
        """tpComputeOptimalVelocity: the previous segment's final velocity, and the sample-rate cap."""
        vs_back = math.sqrt(tc.finalvel ** 2 + 2.0 * tc.tangential_accel() * tc.target)
        limit = min(tc.maxvel, prev.maxvel if prev.kink_vel < 0 else min(prev.maxvel, prev.kink_vel))
        if vs_back >= limit:
            vs_back = limit
            prev.at_max = True
        prev.finalvel = vs_back
        tc.maxvel = min(tc.maxvel, tc.target / (self.config.servo_period_s * MIN_SEGMENT_CYCLES))


def _blend_tolerance(prev: _Tc, tc: _Tc) -> float:
    """tcFindBlendTolerance: P, or a quarter of a segment (P 0 and the limit either way)."""
    t1 = prev.tolerance or 0.25 * prev.nominal
    t2 = tc.tolerance or 0.25 * tc.nominal
    return min(t1, t2, 0.25 * prev.nominal, 0.25 * tc.nominal)


def _trim(tc: _Tc, point: np.ndarray, at_end: bool) -> None:
    """tcConnectBlendArc: a line shortened to end (or start) at ``point``."""
    path = np.array([tc.path[0], point]) if at_end else np.array([point, tc.path[-1]])
    lo, hi = (0.0, tc.target - float(np.linalg.norm(tc.path[-1] - point))) if at_end else \
        (float(np.linalg.norm(point - tc.path[0])), tc.target)
    tc.start, tc.end = tc.at(lo), tc.at(hi)
    tc.set_path(path)


def _max_target(tc: _Tc, config: LinuxCNCConfig) -> float:
    """tpGetMaxTargetVel (feed override 1): F within the segment's and the machine's limits."""
    return min(tc.reqvel, tc.maxvel, config.max_linear_velocity_mm_s)


def _parabolic_velocities(tc: _Tc, nexttc: _Tc, v_this: float, v_next: float) -> tuple[float, float, float]:
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


def _triangle(tc: _Tc) -> float:
    """tpCalculateTriangleVel: half the length while it may still be blended away."""
    return _find_v_peak(tc.tangential_accel(), tc.target if tc.finalized else 0.5 * tc.target)


def _final_vel(tc: _Tc, nexttc: _Tc | None, config: LinuxCNCConfig) -> float:
    """tpGetRealFinalVel: the optimizer's final velocity within both targets; 0 unless tangent."""
    if tc.term != TANGENT:
        return 0.0
    return min(tc.finalvel, _max_target(tc, config), _max_target(nexttc, config) if nexttc else 0.0)


def _trapezoid_accel(tc: _Tc, nexttc: _Tc | None, config: LinuxCNCConfig) -> tuple[float, float]:
    """tpCalculateTrapezoidalAccel (findTrapezoidalDesiredVel): (acceleration, desired velocity)."""
    a_max, dt = tc.tangential_accel(), max(tc.cycle_s, 1e-12)
    v_final, dx = _final_vel(tc, nexttc, config), tc.target - tc.progress
    half = a_max * dt * 0.5
    discr = v_final ** 2 + a_max * (2.0 * dx - tc.currentvel * dt) + half ** 2
    desired = -half + (math.sqrt(discr) if discr > half ** 2 else 0.0)
    target = _max_target(tc, config)
    newvel = max(-target, min(desired, target))
    return max(-a_max, min((newvel - tc.currentvel) / dt, a_max)), desired


def _ramp_accel(tc: _Tc, nexttc: _Tc | None, config: LinuxCNCConfig) -> tuple[float, float] | None:
    """tpCalculateRampAccel: constant acceleration to the final velocity over the rest."""
    v_final = _final_vel(tc, nexttc, config)
    if v_final < 1e-8:
        return None
    v_avg = 0.5 * (tc.currentvel + v_final)
    dt = max((tc.target - tc.progress) / v_avg, 1e-16) if v_avg > 1e-8 else 1e-16
    a_max = tc.tangential_accel()
    return max(-a_max, min((v_final - tc.currentvel) / dt, a_max)), v_final


def _update(tc: _Tc, nexttc: _Tc | None, config: LinuxCNCConfig) -> None:
    """tpUpdateCycle: one period (or its split part) of ``tc``; then tpCheckEndCondition."""
    if not tc.blending:
        tc.vel_at_blend_start = tc.currentvel
    step = _ramp_accel(tc, nexttc, config) if tc.ramp and tc.term == TANGENT else None
    acc, desired = step or _trapezoid_accel(tc, nexttc, config)
    v_next = tc.currentvel + acc * tc.cycle_s
    if v_next < 0.0:  # tcUpdateDistFromAccel
        v_next = 0.0
        if tc.target - tc.progress < tc.currentvel * tc.cycle_s:
            tc.progress = tc.target
    else:
        tc.progress = min(tc.progress + (v_next + tc.currentvel) * 0.5 * tc.cycle_s, tc.target)
    tc.currentvel = v_next
    tc.on_final_decel = abs(desired - v_next) < 1e-8 and acc < 0.0
    _check_end(tc, nexttc, config)


def _check_end(tc: _Tc, nexttc: _Tc | None, config: LinuxCNCConfig) -> None:
    """checkEndCondition: if the segment ends within the next period, split that period."""
    T, dtg, v = config.servo_period_s, tc.target - tc.progress, tc.currentvel
    v_f = _final_vel(tc, nexttc, config)
    v_avg = 0.5 * (v + v_f)
    dt = 0.5e-12
    if v_avg > 1e-8:
        dt = max(dt, dtg / v_avg)
    elif dtg > v_avg * T and dtg > 1e-12:
        return
    a = (v_f - v) / max(dt, 1e-12)
    a_max = tc.tangential_accel()
    if abs(a) > a_max:
        a = math.copysign(a_max, a)
        disc = (v / a) ** 2 + 2.0 / a * dtg
        if disc < 0:
            return
        dt = -v / a if disc < 1e-24 else -v / a + math.copysign(math.sqrt(disc), a)
        v_f = v + dt * a
    if dt < T:
        tc.splitting, tc.cycle_s, tc.term_vel = True, (0.0 if dt < 1e-12 else dt), v_f


def _activate(tc: _Tc, config: LinuxCNCConfig) -> None:
    """tpActivateSegment: short tangent feed segments ramp (ARC_BLEND_RAMP_FREQ)."""
    ends = tc.currentvel + min(tc.finalvel, _max_target(tc, config))
    seconds = 2.0 * (tc.target - tc.progress) / ends if ends > 0 else math.inf
    tc.ramp = seconds < 1.0 / config.ramp_frequency_hz and not tc.rapid and tc.term == TANGENT
    tc.active, tc.blending, tc.on_final_decel = True, False, False


def _cycle(queue: list[_Tc], position: np.ndarray, config: LinuxCNCConfig) -> tuple[np.ndarray, float | None]:
    """tpRunCycle: one servo period. Returns the new position and, if the front segment ended,
    when within the period (s)."""
    T = config.servo_period_s
    tc = queue[0]
    nexttc = queue[1] if len(queue) > 1 else None
    if not tc.active:
        _activate(tc, config)
    moved = []
    if tc.splitting:  # tpHandleSplitCycle: tc reaches its end, the next takes the rest
        moved.append((tc, tc.progress))
        tc.progress = tc.target
        if nexttc is not None and tc.term in (TANGENT, PARABOLIC):
            if tc.term == TANGENT:
                nexttc.cycle_s, nexttc.currentvel = T - tc.cycle_s, tc.term_vel
            moved.append((nexttc, nexttc.progress))
            _update(nexttc, queue[2] if len(queue) > 2 else None, config)
        ended = tc.cycle_s
    else:
        tc.cycle_s = T
        moved.append((tc, tc.progress))
        _update(tc, nexttc, config)
        if tc.term == PARABOLIC and nexttc is not None:
            tc.blend_vel, nexttc.blend_vel, _ = _parabolic_velocities(
                tc, nexttc, _max_target(tc, config), _max_target(nexttc, config))
            tc.blending |= tc.on_final_decel and tc.currentvel < tc.blend_vel
            if tc.blending:  # tpUpdateBlend: the next segment runs at the same time
                nexttc.cycle_s = T
                moved.append((nexttc, nexttc.progress))
                _update(nexttc, None, config)
        ended = None
    for seg, before in moved:
        position = position + seg.at(seg.progress) - seg.at(before)
    return position, ended


@dataclass
class LinuxCNCRun:
    """What LinuxCNC does with a program (see the module docstring)."""

    servo_period_s: float
    cycle_positions_mm: np.ndarray  # (n, NA) the TP's position at t = k * period
    joint_positions_mm: np.ndarray  # (n + 3, NA) the joints' commands at t = k * period (the interpolator's)
    line_time_s: np.ndarray  # (lines,) when the joints end each line's motion (else reach it)
    duration_s: float  # until the joints are at rest

    def positions_mm(self, sample_rate_hz: float) -> np.ndarray:
        """(n, NA) positions at t = k / sample_rate_hz through the end, linear between periods."""
        return self.at(np.arange(math.floor(self.duration_s * sample_rate_hz) + 2) / sample_rate_hz)

    def at(self, t: np.ndarray) -> np.ndarray:
        """(len(t), NA) the joints' positions at the times ``t`` (s), linear between periods."""
        grid = np.arange(len(self.joint_positions_mm)) * self.servo_period_s
        return np.column_stack([np.interp(t, grid, self.joint_positions_mm[:, i]) for i in range(_NA)])


INTERPOLATOR_DELAY_PERIODS = 2  # cubic.c: the way point of x0 x1 x2, x3 the newest point


def interpolated(tp_mm: np.ndarray) -> np.ndarray:
    """The joints' commands (n + 3, NA) for the TP's points ``tp_mm`` (n, NA) every period: at
    period k (p[k-3] + 4 p[k-2] + p[k-1]) / 6, the first point before the start, the last after
    the end (at rest from period n + 2 on)."""
    padded = np.vstack([tp_mm[:1]] * 3 + [tp_mm] + [tp_mm[-1:]] * 2)
    return (padded[:-2] + 4.0 * padded[1:-1] + padded[2:]) / 6.0


def _segment(block: Block, index: int, start: np.ndarray, mode: tuple[str, float],
             config: LinuxCNCConfig) -> list[_Tc]:
    """The TC of a MOVE block from ``start`` (none if it does not move)."""
    points = np.where(np.isnan(block.points_mm), start, block.points_mm)
    path = np.vstack([start[None, _XYZ], points[:, _XYZ]])
    pieces = np.diff(path, axis=0)
    lengths = np.linalg.norm(pieces, axis=1)
    rest = float(np.linalg.norm((points[-1] - start)[3:]))
    if lengths.sum() < 1e-12 and rest < 1e-12:
        return []
    moving = [_unit(p) for p, n in zip(pieces, lengths, strict=True) if n > 1e-12] or [np.ones(3) / math.sqrt(3)]
    vel = min(_along(np.array(config.axis_velocity_mm_s), u) for u in moving)
    acc = min(_along(np.array(config.axis_acceleration_mm_s2), u) for u in moving)
    rapid = math.isinf(block.feed_mm_s)
    tc = _Tc(start, points[-1], path, index, vel if rapid else min(block.feed_mm_s, vel), vel, acc,
             mode[0], mode[1], rapid=rapid, arc_radius=_radius(path) if len(points) > 1 else math.inf)
    tc.set_path(path)
    if tc.target < 1e-12:  # only axes besides X Y Z: their length, XYZ still
        tc.lengths, tc.target = np.array([0.0, rest]), rest
        tc.path = path[[0, -1]]
    return [tc]


def _radius(path: np.ndarray) -> float:
    """The tightest circumradius of consecutive chord triples (a G2/G3 read as chords)."""
    a, b, c = path[:-2], path[1:-1], path[2:]
    ab, bc, ca = (np.linalg.norm(x, axis=1) for x in (b - a, c - b, a - c))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = ab * bc * ca / (2.0 * area2)
    r = r[np.isfinite(r)]
    return float(r.min()) if r.size else 1e12


def _mode(raw: bytes, mode: tuple[str, float]) -> tuple[str, float]:
    """G61 (exact path), G61.1 (exact stop), G64 [P tolerance] (blend) as a line sets them."""
    found = BLEND_MODE.search(raw.split(b";")[0])
    if not found:
        return mode
    code = found.group(1).replace(b" ", b"")
    if code != b"4":
        return (EXACT if code == b"1" else STOP), 0.0
    p = re.search(rb"[Pp]\s*([-+]?[\d.]+)", found.group(2))
    return PARABOLIC, float(p.group(1)) if p else 0.0


def _drain(queue: list[_Tc], position: np.ndarray, config: LinuxCNCConfig, out: list,
           line_time: np.ndarray) -> np.ndarray:
    """Run the queued segments to rest, appending each period's position to ``out``."""
    slowest_s = sum(tc.target / max(min(tc.reqvel, tc.maxvel), 1e-9) for tc in queue)
    guard = 1e4 + 10 * len(queue) + 4.0 * slowest_s / config.servo_period_s
    while queue:
        position, ended = _cycle(queue, position, config)
        out.append(position)
        if ended is not None:
            line_time[queue[0].line] = (len(out) - 2) * config.servo_period_s + ended
            queue.pop(0)
        if guard < 0:
            raise RuntimeError("linuxcnc_tp: the planner does not reach the end of its queue")
        guard -= 1
    return position


def run_linuxcnc(blocks: list[Block], profile: MachineProfile, config: LinuxCNCConfig | None = None) -> LinuxCNCRun:
    """``blocks`` queued to LinuxCNC's TP and run (see the module docstring)."""
    config = config or LinuxCNCConfig.from_profile(profile)
    T = config.servo_period_s
    position = np.zeros(_NA)
    out, queue = [position], _Queue(config)
    line_time = np.full(len(blocks), np.nan)
    mode = (PARABOLIC, config.startup_tolerance_mm)  # LinuxCNC starts in G64 (P: its startup code's)
    for index, block in enumerate(blocks):
        mode = _mode(block.raw, mode)
        if block.kind is Kind.STOP:  # waits for the motion to end, then its dwell
            position = _drain(queue.items, out[-1], config, out, line_time)
            position = np.where(np.isnan(block.position_mm), position, block.position_mm)
            out.extend([position] * int(math.ceil(block.dwell_s / T - 1e-9)))
            out[-1] = position
        elif block.kind is Kind.MOVE and block.points_mm is not None:
            for tc in _segment(block, index, position, mode, config):
                queue.add(tc)
                position = tc.end
        line_time[index] = (len(out) - 1) * T
    _drain(queue.items, out[-1], config, out, line_time)
    joints = interpolated(np.array(out))
    # a line blended away (consumed by a blend arc) or without motion: when the motion before it ends
    return LinuxCNCRun(T, np.array(out), joints, np.fmax.accumulate(line_time) + INTERPOLATOR_DELAY_PERIODS * T,
                       (len(joints) - 1) * T)
