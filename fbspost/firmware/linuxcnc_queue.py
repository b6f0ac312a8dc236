"""The queue of LinuxCNC 2.9's trajectory planner (``linuxcnc_tp``) as segments are added.

Takes the segments (``linuxcnc_segments.Tc``) in order and the INI's limits; gives them with
their terminal conditions (stop, exact, parabolic, tangent), blend arcs between lines queued in
their place, and their final velocities from the look-ahead: ``Queue`` (``tpAddLine`` ..
``tpFinalizeAndEnqueue``, ``tpSetupTangent``, ``blendmath``'s line-line blend,
``tpRunOptimization``). Units: mm, s.
"""
from __future__ import annotations

import math

import numpy as np

from .linuxcnc_segments import (
    ACC_TAN,
    EXACT,
    PARABOLIC,
    STOP,
    TANGENT,
    LinuxCNCConfig,
    Tc,
    find_v_peak,
    max_target,
    parabolic_velocities,
    unit,
)

MIN_SEGMENT_CYCLES = 1.02  # tp_types.h TPMIN_SEGMENT_CYCLES
_ACC_NORMAL = math.sqrt(0.75)  # BLEND_ACC_RATIO_NORMAL
_SHARP_CORNER = (math.pi * 2.0 / 180.0) ** 2  # tpSetupTangent: SHARP_CORNER_DEG 2


def _in_plane(bounds: np.ndarray, binormal: np.ndarray) -> float:
    """calculateInscribedDiameter: the bound on any direction in the plane normal to ``binormal``."""
    scales = np.linalg.norm(np.eye(3) - np.outer(binormal, binormal), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.where(scales > 1e-12, bounds / scales, np.inf).min())


class Queue:
    """The TP's queue as segments are added (``tpAddLine`` .. ``tpFinalizeAndEnqueue``)."""

    def __init__(self, config: LinuxCNCConfig):
        self.config, self.items = config, []
        self.acc_bound = np.array(config.axis_acceleration_mm_s2, dtype=float)
        self.vel_bound = np.array(config.axis_velocity_mm_s, dtype=float)

    def add(self, tc: Tc) -> None:
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
    def _set_term(prev: Tc, tc: Tc | None, term: str) -> None:
        """tcSetTermCond: the previous segment's end, and whether the next blends with it."""
        prev.term = term
        if tc is not None:
            tc.blend_prev = term == PARABOLIC

    def _finalize(self, tc: Tc) -> None:
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

    def _tangent(self, prev: Tc, tc: Tc) -> str:
        """tpSetupTangent: 'ok' (tangent), 'fail' (no blend arc) or 'try' (kink too large).
        With A B C U V W motion on either side, LinuxCNC tries neither a tangent nor a blend arc
        (tpRotaryMotionCheck): the segments keep their own term (a parabolic blend in G64)."""
        if prev.term == STOP or self.config.optimization_depth < 2 or prev.rotary or tc.rotary:
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
            scale_max /= ACC_TAN
        ratio = self.config.kink_ratio
        if scale_max < ratio:
            self._set_term(prev, tc, TANGENT)
            self._kink(prev, tc, v_max, scale_max)
            return "ok"
        self._kink(prev, tc, v_max * ratio / scale_max, ratio)
        return "try"

    @staticmethod
    def _kink(prev: Tc, tc: Tc, kink_vel: float, reduce: float) -> None:
        """tcSetKinkProperties (reduce < 0: tcRemoveKinkProperties)."""
        prev.kink_vel = kink_vel
        prev.kink_reduce = max(reduce, prev.kink_reduce) if reduce >= 0 else 0.0
        tc.kink_reduce_prev = max(reduce, tc.kink_reduce_prev) if reduce >= 0 else 0.0

    def _blend(self, prev: Tc, tc: Tc) -> None:
        """tpHandleBlendArc: tangent, a blend arc, or the best of parabolic and tangent."""
        if self._tangent(prev, tc) != "try":
            return
        if prev.term == PARABOLIC and not (prev.arc or tc.arc or prev.finalized):
            arc = self._line_blend(prev, tc)
            if arc is not None:
                return
        self._choose(prev, tc, None)

    def _choose(self, prev: Tc, tc: Tc, arc: Tc | None) -> str:
        """tpChooseBestBlend by performance: parabolic / 2, the tangent kink_vel, the arc's maxvel."""
        if prev.term in (STOP, EXACT):
            return "none"
        parabolic = parabolic_velocities(prev, tc, max_target(prev, self.config), max_target(tc, self.config))[2]
        perf = [parabolic / 2.0, prev.kink_vel, arc.maxvel if arc is not None else 0.0]
        best = ("parabolic", "tangent", "arc")[int(np.argmax(perf))]
        if best != "tangent":
            self._kink(prev, tc, -1.0, -1.0)
        if best == "parabolic":
            self._set_term(prev, tc, PARABOLIC)
        elif best == "tangent":
            self._set_term(prev, tc, TANGENT)
        return best

    def _line_blend(self, prev: Tc, tc: Tc) -> Tc | None:
        """tpCreateLineLineBlend: the blend arc between two lines, queued if it is the best blend."""
        u1, u2 = prev.end_unit(), tc.start_unit()
        theta = math.acos(max(-1.0, min(1.0, -float(u1 @ u2)))) / 2.0
        phi = math.pi - 2.0 * theta
        binormal, normal = unit(np.cross(u1, u2)), unit(u2 - u1)
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
        u = unit(arc_start - center)
        w = unit(arc_end - center - u * float(u @ (arc_end - center)))
        points = np.vstack([prev.path[:1], arc_start, arc_end]) if consume else np.vstack([arc_start, arc_end])
        arc = Tc(prev.at(prev.target - (prev.target if consume else d_plan)), tc.at(d_plan), points, prev.line,
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
                prev.finalvel = min(prev.maxvel, find_v_peak(tc.tangential_accel(), tc.target),
                                    max_target(tc, config))
                if prev.kink_vel >= 0:
                    prev.finalvel = min(prev.finalvel, prev.kink_vel)
                tc.finalvel = 0.0
            else:
                self._optimal_velocity(tc, prev)
            if tc.at_max:
                hit_peaks += 1
            if hit_peaks > 4:  # TP_OPTIMIZATION_CUTOFF
                return

    def _optimal_velocity(self, tc: Tc, prev: Tc) -> None:
        """tpComputeOptimalVelocity: the previous segment's final velocity, and the sample-rate cap."""
        vs_back = math.sqrt(tc.finalvel ** 2 + 2.0 * tc.tangential_accel() * tc.target)
        limit = min(tc.maxvel, prev.maxvel if prev.kink_vel < 0 else min(prev.maxvel, prev.kink_vel))
        if vs_back >= limit:
            vs_back = limit
            prev.at_max = True
        prev.finalvel = vs_back
        tc.maxvel = min(tc.maxvel, tc.target / (self.config.servo_period_s * MIN_SEGMENT_CYCLES))


def _blend_tolerance(prev: Tc, tc: Tc) -> float:
    """tcFindBlendTolerance: P, or a quarter of a segment (P 0 and the limit either way)."""
    t1 = prev.tolerance or 0.25 * prev.nominal
    t2 = tc.tolerance or 0.25 * tc.nominal
    return min(t1, t2, 0.25 * prev.nominal, 0.25 * tc.nominal)


def _trim(tc: Tc, point: np.ndarray, at_end: bool) -> None:
    """tcConnectBlendArc: a line shortened to end (or start) at ``point``."""
    path = np.array([tc.path[0], point]) if at_end else np.array([point, tc.path[-1]])
    lo, hi = (0.0, tc.target - float(np.linalg.norm(tc.path[-1] - point))) if at_end else \
        (float(np.linalg.norm(point - tc.path[0])), tc.target)
    tc.start, tc.end = tc.at(lo), tc.at(hi)
    tc.set_path(path)
