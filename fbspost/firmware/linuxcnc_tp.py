"""LinuxCNC 2.9's trajectory planner (TP) over a program's moves: the motion the machine makes.

Takes the blocks of a program (``gcode.read_gcode``), a machine profile and a ``LinuxCNCConfig``
(the INI's limits, LinuxCNC's defaults); gives ``LinuxCNCRun``: the TP's position and the
joints' commands every servo period, when each line's motion ends, and the joints' positions on
the profile's sample grid
(``planners.replan(..., "linuxcnc")`` wraps it as ``FirmwareMotion``).

Modelled from LinuxCNC/linuxcnc src/emc/tp (tp.c, tc.c, blendmath.c of the 2.8/2.9 line as the
code index stores them, read November 2026: trapezoidal planner only; the S-curve PLANNER_TYPE
and its jerk limits came with 2.10) and the INI documentation ([TRAJ] ARC_BLEND_*):
- segments (``tpAddLine``): reqvel F; maxvel and maxaccel the axes' MAX_VELOCITY /
  MAX_ACCELERATION along the move (emccanon, A B C U V W too: a move of those alone along their
  own length), vLimit [TRAJ] MAX_LINEAR_VELOCITY; a rapid asks for maxvel. A segment that
  moves A B C U V W is neither tangent to nor blended by an arc with its neighbours
  (``tpRotaryMotionCheck``). A G2/G3 comes from the reader as chords: one segment here, as LinuxCNC keeps it,
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

The segments and the INI's limits: ``linuxcnc_segments``; the queue, its blends and its
look-ahead: ``linuxcnc_queue``; here the servo cycle, the interpolator and the run.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..profile import MachineProfile
from ..read.blocks import AXES, Block, Kind
from .linuxcnc_queue import Queue
from .linuxcnc_segments import (
    PARABOLIC,
    TANGENT,
    LinuxCNCConfig,
    Tc,
    line_mode,
    max_target,
    parabolic_velocities,
    segment,
)

_NA = len(AXES)


def _final_vel(tc: Tc, nexttc: Tc | None, config: LinuxCNCConfig) -> float:
    """tpGetRealFinalVel: the optimizer's final velocity within both targets; 0 unless tangent."""
    if tc.term != TANGENT:
        return 0.0
    return min(tc.finalvel, max_target(tc, config), max_target(nexttc, config) if nexttc else 0.0)


def _trapezoid_accel(tc: Tc, nexttc: Tc | None, config: LinuxCNCConfig) -> tuple[float, float]:
    """tpCalculateTrapezoidalAccel (findTrapezoidalDesiredVel): (acceleration, desired velocity)."""
    a_max, dt = tc.tangential_accel(), max(tc.cycle_s, 1e-12)
    v_final, dx = _final_vel(tc, nexttc, config), tc.target - tc.progress
    half = a_max * dt * 0.5
    discr = v_final ** 2 + a_max * (2.0 * dx - tc.currentvel * dt) + half ** 2
    desired = -half + (math.sqrt(discr) if discr > half ** 2 else 0.0)
    target = max_target(tc, config)
    newvel = max(-target, min(desired, target))
    return max(-a_max, min((newvel - tc.currentvel) / dt, a_max)), desired


def _ramp_accel(tc: Tc, nexttc: Tc | None, config: LinuxCNCConfig) -> tuple[float, float] | None:
    """tpCalculateRampAccel: constant acceleration to the final velocity over the rest."""
    v_final = _final_vel(tc, nexttc, config)
    if v_final < 1e-8:
        return None
    v_avg = 0.5 * (tc.currentvel + v_final)
    dt = max((tc.target - tc.progress) / v_avg, 1e-16) if v_avg > 1e-8 else 1e-16
    a_max = tc.tangential_accel()
    return max(-a_max, min((v_final - tc.currentvel) / dt, a_max)), v_final


def _update(tc: Tc, nexttc: Tc | None, config: LinuxCNCConfig) -> None:
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


def _check_end(tc: Tc, nexttc: Tc | None, config: LinuxCNCConfig) -> None:
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


def _activate(tc: Tc, config: LinuxCNCConfig) -> None:
    """tpActivateSegment: short tangent feed segments ramp (ARC_BLEND_RAMP_FREQ)."""
    ends = tc.currentvel + min(tc.finalvel, max_target(tc, config))
    seconds = 2.0 * (tc.target - tc.progress) / ends if ends > 0 else math.inf
    tc.ramp = seconds < 1.0 / config.ramp_frequency_hz and not tc.rapid and tc.term == TANGENT
    tc.active, tc.blending, tc.on_final_decel = True, False, False


def _cycle(queue: list[Tc], position: np.ndarray, config: LinuxCNCConfig) -> tuple[np.ndarray, float | None]:
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
            tc.blend_vel, nexttc.blend_vel, _ = parabolic_velocities(
                tc, nexttc, max_target(tc, config), max_target(nexttc, config))
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


def _drain(queue: list[Tc], position: np.ndarray, config: LinuxCNCConfig, out: list,
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
    out, queue = [position], Queue(config)
    line_time = np.full(len(blocks), np.nan)
    mode = (PARABOLIC, config.startup_tolerance_mm)  # LinuxCNC starts in G64 (P: its startup code's)
    for index, block in enumerate(blocks):
        mode = line_mode(block.raw, mode)
        if block.kind is Kind.STOP:  # waits for the motion to end, then its dwell
            position = _drain(queue.items, out[-1], config, out, line_time)
            position = np.where(np.isnan(block.position_mm), position, block.position_mm)
            out.extend([position] * int(math.ceil(block.dwell_s / T - 1e-9)))
            out[-1] = position
        elif block.kind is Kind.MOVE and block.points_mm is not None:
            for tc in segment(block, index, position, mode, config):
                queue.add(tc)
                position = tc.end
        line_time[index] = (len(out) - 1) * T
    _drain(queue.items, out[-1], config, out, line_time)
    joints = interpolated(np.array(out))
    # a line blended away (consumed by a blend arc) or without motion: when the motion before it ends
    return LinuxCNCRun(T, np.array(out), joints, np.fmax.accumulate(line_time) + INTERPOLATOR_DELAY_PERIODS * T,
                       (len(joints) - 1) * T)
