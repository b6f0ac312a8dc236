"""The motion planner against independent truths: trapezoids and junction speeds worked out by
hand here, the closed-form position of a trapezoid, and a plain scalar re-statement of Klipper's
look-ahead (Move.calc_junction, the flush loop, Move.set_junction) written as a loop over moves.
Nothing here reads the planner's output back as its own truth."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbspost.plan import lookahead, pieces, planner
from fbspost.plan.lookahead import backward_pass, forward_pass
from fbspost.plan.margins import TRAVEL_SHARE, RunMargins
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.blocks import AXES, Block, Kind, Modal, PlannerLimits

BED = load_profile("bedslinger-example")  # X 300/10000, Y 300/8000, Z 12/500, E 120/5000; 3000, scv 5; 1 kHz
PATENT = load_profile("patent-xy-stage")  # X, Y 100/8000; 5000, scv 5; 10 kHz
SQRT2M1 = math.sqrt(2.0) - 1.0
ORIGIN = (0.0, 0.0, 0.0, 0.0)


# ---- program builders --------------------------------------------------------------------------

def xyze(points) -> np.ndarray:
    """X Y Z E positions (rows or one) with the other axes (LinuxCNC's) at 0, where printers keep them."""
    points = np.asarray(points, dtype=float)
    return np.concatenate([points, np.zeros(points.shape[:-1] + (len(AXES) - 4,))], axis=-1)


class Program:
    """Blocks built by hand, numbered from line 1, starting at rest at a known position."""

    def __init__(self, start=ORIGIN):
        self.blocks: list[Block] = []
        self.pos = np.asarray(start, dtype=float)
        self.stop(position=start)

    def _add(self, kind, **kw) -> int:
        position = kw.pop("position", self.pos)
        self.blocks.append(Block(len(self.blocks) + 1, b"", kind, Modal(), xyze(position), **kw))
        return len(self.blocks) - 1

    def move(self, *points, feed=100.0) -> int:
        pts = np.asarray(points, dtype=float).reshape(-1, 4)
        self.pos = pts[-1].copy()
        return self._add(Kind.MOVE, points_mm=xyze(pts), feed_mm_s=feed)

    def stop(self, dwell=0.0, position=None) -> int:
        if position is not None:
            self.pos = np.asarray(position, dtype=float)
        return self._add(Kind.STOP, dwell_s=dwell)

    def passthrough(self, limits=None) -> int:
        return self._add(Kind.PASS, limits=limits)


# ---- closed forms --------------------------------------------------------------------------------

def rest_to_rest(d, v, a):
    """Duration of a move of d mm from rest to rest, cruise v, acceleration a (hand formulas)."""
    if v * v / a < d:
        return d / v + v / a  # trapezoid: d/v of cruise plus the v/a lost accelerating and braking
    return 2.0 * math.sqrt(d / a)  # triangle


def trapezoid_time(d, v0, vc, v1, a):
    """Duration of d mm from v0 to v1 with cruise at most vc and acceleration a."""
    peak = min(vc, math.sqrt((v0 * v0 + v1 * v1 + 2 * a * d) / 2))
    t_up, t_down = (peak - v0) / a, (peak - v1) / a
    d_up, d_down = (peak * peak - v0 * v0) / (2 * a), (peak * peak - v1 * v1) / (2 * a)
    return t_up + t_down + (d - d_up - d_down) / peak


def rest_to_rest_distance(t, d, v, a):
    """Distance after t seconds of a rest-to-rest move (hand-written piecewise parabola)."""
    v = min(v, math.sqrt(a * d))  # the peak of a triangle
    t_ramp = v / a
    total = d / v + t_ramp
    t = min(max(t, 0.0), total)
    if t <= t_ramp:
        return 0.5 * a * t * t
    if t >= total - t_ramp:
        return d - 0.5 * a * (total - t) ** 2
    return 0.5 * v * t_ramp + v * (t - t_ramp)


def sample_times(plan):
    return np.arange(plan.positions_mm.shape[0]) / plan.sample_rate_hz


# ---- scalar reference: Klipper's look-ahead, one move at a time ---------------------------------

class RefMove:
    """klippy/toolhead.py's Move, re-stated: limits, junction, trapezoid."""

    def __init__(self, start, end, speed, accel, jd, axis_v, axis_a, max_velocity=math.inf, rest_before=False):
        self.d_axes = [e - s for s, e in zip(start, end, strict=True)]
        self.move_d = math.sqrt(sum(x * x for x in self.d_axes[:3]))
        self.kinematic = self.move_d >= 1e-9
        if not self.kinematic:
            self.move_d = abs(self.d_axes[3])
            self.axes_r = [0.0, 0.0, 0.0, math.copysign(1.0, self.d_axes[3])]
        else:
            self.axes_r = [x / self.move_d for x in self.d_axes]
        velocity = min(speed, max_velocity)
        for i, name in enumerate("XYZE"):
            if self.axes_r[i] != 0.0 and name in axis_v:
                velocity = min(velocity, axis_v[name] / abs(self.axes_r[i]))
                accel = min(accel, axis_a[name] / abs(self.axes_r[i]))
        self.accel, self.jd, self.rest_before = accel, jd, rest_before
        self.max_cruise_v2 = velocity * velocity
        self.delta_v2 = 2.0 * self.move_d * accel
        self.max_start_v2 = 0.0

    def calc_junction(self, prev):
        if not self.kinematic or not prev.kinematic or self.rest_before:
            return
        max_start_v2 = min(self.max_cruise_v2, prev.max_cruise_v2, prev.max_start_v2 + prev.delta_v2)
        cos_theta = -sum(self.axes_r[i] * prev.axes_r[i] for i in range(3))
        sin_d2 = math.sqrt(max(0.5 * (1.0 - cos_theta), 0.0))
        cos_d2 = math.sqrt(max(0.5 * (1.0 + cos_theta), 0.0))
        if 1.0 - sin_d2 > 0.0 and cos_d2 > 0.0:
            r_jd = sin_d2 / (1.0 - sin_d2)
            tan_d2 = sin_d2 / cos_d2
            max_start_v2 = min(max_start_v2, r_jd * self.jd * self.accel, r_jd * prev.jd * prev.accel,
                               0.5 * self.move_d * tan_d2 * self.accel, 0.5 * prev.move_d * tan_d2 * prev.accel)
        self.max_start_v2 = max_start_v2

    def set_junction(self, start_v2, cruise_v2, end_v2):
        accel_d = (cruise_v2 - start_v2) * 0.5 / self.accel
        decel_d = (cruise_v2 - end_v2) * 0.5 / self.accel
        cruise_d = self.move_d - accel_d - decel_d
        self.start_v, self.cruise_v, self.end_v = math.sqrt(start_v2), math.sqrt(cruise_v2), math.sqrt(end_v2)
        self.time = (accel_d / ((self.start_v + self.cruise_v) * 0.5) + cruise_d / self.cruise_v
                     + decel_d / ((self.end_v + self.cruise_v) * 0.5))


def reference_plan(moves):
    """Junctions in order, then Klipper's backward flush (no accel_to_decel smoothing)."""
    for prev, move in zip([None, *moves[:-1]], moves, strict=True):
        if prev is not None:
            move.calc_junction(prev)
    next_end_v2 = 0.0
    for move in reversed(moves):
        start_v2 = min(move.max_start_v2, next_end_v2 + move.delta_v2)
        cruise_v2 = min(move.max_cruise_v2, (start_v2 + next_end_v2 + move.delta_v2) * 0.5)
        move.set_junction(start_v2, cruise_v2, next_end_v2)
        next_end_v2 = start_v2
    return moves


def profile_limits(profile):
    return ({n: a.max_velocity_mm_s for n, a in profile.axes.items()},
            {n: a.max_acceleration_mm_s2 for n, a in profile.axes.items()})


def random_program(rng, n_moves, profile=BED):
    """A random polyline with corners, straight continuations, extrude-only pieces, rapids,
    multi-piece blocks and planner-limit changes; returns the program and the reference moves."""
    prog = Program()
    axis_v, axis_a = profile_limits(profile)
    accel, travel, scv = profile.planner_acceleration_mm_s2, None, profile.planner_square_corner_velocity_mm_s
    refs, direction = [], np.array([1.0, 0.0, 0.0])
    for _ in range(n_moves):
        u = rng.random()
        if u < 0.04:
            accel = float(rng.uniform(500, 5000))
            travel = float(rng.uniform(1000, 6000)) if rng.random() < 0.5 else travel
            scv = float(rng.uniform(1, 10))
            prog.passthrough(PlannerLimits(acceleration_mm_s2=accel, travel_acceleration_mm_s2=travel,
                                           square_corner_velocity_mm_s=scv))
            continue
        feed = math.inf if rng.random() < 0.05 else float(rng.uniform(5, 250))
        n_pieces = 3 if rng.random() < 0.1 else 1
        points = []
        pos = prog.pos.copy()
        for _ in range(n_pieces):
            v = rng.random()
            if v < 0.08 and n_pieces > 1:  # extrude-only within a block (a block of E alone is a rest)
                step = np.array([0, 0, 0, rng.uniform(-3, 3)])
            else:
                if v > 0.3:  # a new direction; otherwise straight on
                    direction = rng.normal(size=3) * [1, 1, 0.05]
                    direction /= np.linalg.norm(direction)
                length = math.exp(rng.uniform(math.log(0.005), math.log(30)))  # centripetal limits too
                e = length * 0.033 if rng.random() < 0.6 else (rng.uniform(-1, 0) if rng.random() < 0.1 else 0.0)
                step = np.append(direction * length, e)
            pos = pos + step
            points.append(pos)
        start = prog.pos.copy()
        prog.move(*points, feed=feed)
        for end in points:
            a = accel if end[3] - start[3] > 0 or travel is None else travel
            refs.append(RefMove(start, end, feed, a, scv * scv * SQRT2M1 / accel, axis_v, axis_a))
            start = end
    prog.stop()
    return prog, refs


# ---- a single move -------------------------------------------------------------------------------

@pytest.mark.parametrize("profile, d, feed", [
    (BED, 100.0, 100.0),  # trapezoid: v^2/a = 3.3 mm < 100 mm
    (BED, 10.0, 300.0),  # triangle: v^2/a = 30 mm > 10 mm
    (PATENT, 20.0, 60.0),  # trapezoid at 10 kHz, accel 5000
    (PATENT, 0.5, 100.0),  # triangle at 10 kHz
])
def test_single_move_matches_closed_form(profile, d, feed):
    a = profile.planner_acceleration_mm_s2
    prog = Program()
    i = prog.move((d, 0, 0, 0), feed=feed)
    plan = plan_blocks(prog.blocks, profile)
    expected = d / feed + feed / a if feed * feed / a < d else 2 * math.sqrt(d / a)
    assert plan.duration_s == pytest.approx(expected, rel=1e-12)
    assert plan.line_time_s[i] == pytest.approx(expected, rel=1e-12)
    assert plan.move_start_s[i] == 0.0
    fs = profile.sample_rate_hz
    n = math.floor(expected * fs) + 1 + (0 if (expected * fs).is_integer() else 1)
    assert plan.positions_mm.shape == (n, len(AXES))
    assert plan.runs == [(0, n - 1)]
    x = [rest_to_rest_distance(t, d, feed, a) for t in sample_times(plan)]
    np.testing.assert_allclose(plan.positions_mm[:, 0], x, rtol=0, atol=1e-9)
    assert np.all(plan.positions_mm[:, 1:] == 0.0)
    assert plan.positions_mm[-1, 0] == d and plan.positions_mm[0, 0] == 0.0


def test_two_collinear_moves_do_not_slow_down():
    a = 3000.0
    prog = Program()
    first = prog.move((40, 0, 0, 0), feed=100.0)
    second = prog.move((100, 0, 0, 0), feed=100.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.pieces.end_v_mm_s[0] == pytest.approx(100.0, rel=1e-12)
    assert plan.duration_s == pytest.approx(100 / 100 + 100 / a, rel=1e-12)
    # the first block ends 40 mm into one 100 mm trapezoid: a v/a = 1/30 s ramp over
    # v^2/2a = 1.667 mm, then cruise
    assert plan.line_time_s[first] == pytest.approx(100 / a + (40 - 100**2 / (2 * a)) / 100, rel=1e-12)
    assert plan.move_start_s[second] == plan.line_time_s[first]
    x = [rest_to_rest_distance(t, 100.0, 100.0, a) for t in sample_times(plan)]
    np.testing.assert_allclose(plan.positions_mm[:, 0], x, rtol=0, atol=1e-9)


# ---- junctions ----------------------------------------------------------------------------------

@pytest.mark.parametrize("limits, v_corner", [
    (None, 5.0),  # the profile's scv: at 90 degrees R_jd = 1/(sqrt2 - 1), so v^2 = scv^2
    (PlannerLimits(square_corner_velocity_mm_s=8.0), 8.0),
    (PlannerLimits(acceleration_mm_s2=1200.0), 5.0),  # jd follows the new accel: still scv at 90 deg
    (PlannerLimits(junction_deviation_mm=0.02), math.sqrt(0.02 * 3000 / SQRT2M1)),  # Marlin M205 J
])
def test_90_degree_corner_speed(limits, v_corner):
    a = 1200.0 if limits is not None and limits.acceleration_mm_s2 else 3000.0
    prog = Program()
    prog.passthrough(limits)
    first = prog.move((100, 0, 0, 0), feed=100.0)
    second = prog.move((100, 100, 0, 0), feed=100.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.pieces.end_v_mm_s[0] == pytest.approx(v_corner, rel=1e-12)
    assert plan.pieces.start_v_mm_s[1] == pytest.approx(v_corner, rel=1e-12)
    t1 = trapezoid_time(100, 0, 100, v_corner, a)
    t2 = trapezoid_time(100, v_corner, 100, 0, a)
    assert plan.line_time_s[first] == pytest.approx(t1, rel=1e-12)
    assert plan.line_time_s[second] == pytest.approx(t1 + t2, rel=1e-12)
    # the sampled corner: over the period holding it, X arrives and Y leaves at v_corner, each
    # faster by at most a t away from it, so the mean speed lies in [v, v + a T / 2]
    fs = BED.sample_rate_hz
    k = int(plan.line_time_s[first] * fs)
    step = np.sum(np.abs(plan.positions_mm[k + 1, :2] - plan.positions_mm[k, :2])) * fs
    assert v_corner - 1e-9 <= step <= v_corner + a / fs / 2 + 1e-9


def test_short_corner_limited_by_centripetal_term():
    # 90 degrees between 0.01 mm pieces: .5 d tan(45 deg) a = 15 mm^2/s^2, below scv^2 = 25 and
    # below 2 a d = 60 (what either piece can reach from rest)
    prog = Program()
    prog.move((0.01, 0, 0, 0), feed=50.0)
    prog.move((0.01, 0.01, 0, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.pieces.start_v_mm_s[1] ** 2 == pytest.approx(0.5 * 0.01 * 3000, rel=1e-12)
    v = math.sqrt(15.0)
    assert plan.duration_s == pytest.approx(2 * trapezoid_time(0.01, 0, 50, v, 3000), rel=1e-12)


def test_reversal_stops():
    prog = Program()
    prog.move((10, 0, 0, 0), feed=50.0)
    prog.move((0, 0, 0, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.pieces.end_v_mm_s[0] == 0.0
    assert plan.duration_s == pytest.approx(2 * rest_to_rest(10, 50, 3000), rel=1e-12)


# ---- limits -------------------------------------------------------------------------------------

def test_axis_velocity_limits_diagonal_rapid():
    # patent stage, 45-degree G0: each axis at its 100 mm/s, so the path at 100 sqrt 2
    prog = Program()
    prog.move((30, 30, 0, 0), feed=math.inf)
    plan = plan_blocks(prog.blocks, PATENT)
    v = 100 * math.sqrt(2)
    assert plan.pieces.peak_v_mm_s[0] == pytest.approx(v, rel=1e-12)
    assert plan.duration_s == pytest.approx(rest_to_rest(30 * math.sqrt(2), v, 5000), rel=1e-12)
    step = np.abs(np.diff(plan.positions_mm[:, :2], axis=0)) * PATENT.sample_rate_hz
    assert step.max() <= 100 * (1 + 1e-9) and step.max() > 99.9


def test_rapid_runs_at_axis_max_velocity():
    prog = Program()
    prog.move((200, 0, 0, 0), feed=math.inf)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.duration_s == pytest.approx(200 / 300 + 300 / 3000, rel=1e-12)


def test_axis_limits_on_z_diagonal():
    # X 3, Z 4: u_Z = 0.8, so v <= 12 / 0.8 = 15 mm/s and a <= 500 / 0.8 = 625 mm/s^2
    prog = Program()
    prog.move((3, 0, 4, 0), feed=100.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.pieces.accel_mm_s2[0] == pytest.approx(625.0, rel=1e-12)
    assert plan.duration_s == pytest.approx(5 / 15 + 15 / 625, rel=1e-12)
    dz = np.diff(plan.positions_mm[:, 2]) * BED.sample_rate_hz
    assert np.abs(dz).max() <= 12 * (1 + 1e-9)


def test_m203_m201_change_axis_limits_from_their_block_on():
    prog = Program()
    before = prog.move((100, 0, 0, 0), feed=100.0)
    prog.passthrough(PlannerLimits(axis_max_velocity_mm_s={"X": 50.0}, axis_max_acceleration_mm_s2={"X": 1000.0}))
    after = prog.move((0, 0, 0, 0), feed=100.0)  # a reversal: both moves from rest to rest
    plan = plan_blocks(prog.blocks, BED)
    t1 = 100 / 100 + 100 / 3000
    assert plan.line_time_s[before] == pytest.approx(t1, rel=1e-12)
    assert plan.line_time_s[after] - plan.move_start_s[after] == pytest.approx(100 / 50 + 50 / 1000, rel=1e-12)


def test_planner_velocity_limit():
    prog = Program()
    prog.passthrough(PlannerLimits(max_velocity_mm_s=80.0))
    prog.move((100, 0, 0, 0), feed=math.inf)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.duration_s == pytest.approx(100 / 80 + 80 / 3000, rel=1e-12)


def test_travel_and_print_acceleration():
    # M204 P1000 T5000: the extruding move at 1000, the travel back at 5000 (a reversal: stops)
    prog = Program()
    prog.passthrough(PlannerLimits(acceleration_mm_s2=1000.0, travel_acceleration_mm_s2=5000.0))
    printing = prog.move((100, 0, 0, 3.0), feed=100.0)
    travel = prog.move((0, 0, 0, 3.0), feed=100.0)
    retract = prog.move((0, 0, 0, 1.0), feed=40.0)  # not extruding: travel accel, E limit 5000
    plan = plan_blocks(prog.blocks, BED)
    assert plan.line_time_s[printing] == pytest.approx(100 / 100 + 100 / 1000, rel=1e-12)
    assert plan.line_time_s[travel] - plan.move_start_s[travel] == pytest.approx(1 + 100 / 5000, rel=1e-12)
    # the retraction is a rest of X Y Z for its trapezoid's time, as a dwell after its line
    assert plan.is_stop[retract] and plan.line_time_s[retract] == plan.line_time_s[travel]
    assert plan.duration_s - plan.line_time_s[retract] == pytest.approx(2 / 40 + 40 / 5000, rel=1e-12)


@pytest.mark.parametrize("firmware", [None, "klipper"])
def test_travels_at_a_share_of_the_hard_accelerations(firmware):
    """RunMargins.travel_share 0.5 on BED (hard limits X 10000, Y 8000, Z 500), once the program
    has printed (a run before): a travel (X or Y moved, E not advanced) accelerates at half the
    hard limits along its direction, its corner with a printing move at the firmware's junction
    speed (the profile's scv at 90 degrees); printing, a retraction and a Z move (a rest of X and
    Y, copied) keep the firmware's 3000 and 500: closed-form trapezoids. A share under the
    firmware's acceleration changes nothing, nor does it before the program prints."""
    prog = Program()
    first_travel = prog.move((0, 100, 0, 0.0), feed=100.0)
    prog.move((0, 0, 0, 1.0), feed=100.0)
    prog.stop(dwell=0.1)
    printing = prog.move((100, 0, 0, 3.0), feed=100.0)
    travel = prog.move((100, 100, 0, 3.0), feed=100.0)  # Y alone: 0.5 * 8000
    prog.stop(dwell=0.1)
    diagonal = prog.move((0, 0, 0, 3.0), feed=100.0)  # |u| 1/sqrt2: Y's 4000 sqrt2 rules (X 5000 sqrt2)
    retract = prog.move((0, 0, 0, 1.0), feed=40.0)
    lift = prog.move((0, 0, 1, 1.0), feed=10.0)
    margins = RunMargins(travel_share=0.5)
    plan = plan_blocks(prog.blocks, BED, margins=margins, firmware=firmware)
    assert plan.line_time_s[first_travel] == pytest.approx(rest_to_rest(100, 100, 3000), rel=1e-12)
    t1 = trapezoid_time(100, 0, 100, 5.0, 3000)
    assert plan.pieces.start_v_mm_s[3] == pytest.approx(5.0, rel=1e-12)
    assert plan.line_time_s[printing] - plan.move_start_s[printing] == pytest.approx(t1, rel=1e-12)
    assert plan.line_time_s[travel] - plan.move_start_s[printing] == pytest.approx(
        t1 + trapezoid_time(100, 5.0, 100, 0, 4000), rel=1e-12)
    retract_s = rest_to_rest(2, 40, 3000 if firmware is None else BED.extrude_only_accel_mm_s2)
    diagonal_s = rest_to_rest(100 * math.sqrt(2), 100, 4000 * math.sqrt(2))
    assert plan.line_time_s[diagonal] - plan.move_start_s[diagonal] == pytest.approx(diagonal_s, rel=1e-12)
    assert plan.line_time_s[lift] - plan.line_time_s[retract] == pytest.approx(retract_s, rel=1e-12)
    assert plan.duration_s - plan.line_time_s[lift] == pytest.approx(rest_to_rest(1, 10, 500), rel=1e-12)
    slow = plan_blocks(prog.blocks, BED, margins=RunMargins(travel_share=0.2), firmware=firmware)
    plain = plan_blocks(prog.blocks, BED, firmware=firmware)
    assert slow.duration_s == plain.duration_s
    assert plain.line_time_s[travel] - plain.move_start_s[printing] == pytest.approx(
        t1 + trapezoid_time(100, 5.0, 100, 0, 3000), rel=1e-12)


def test_limit_change_mid_program_applies_to_later_moves():
    prog = Program()
    first = prog.move((50, 0, 0, 0), feed=100.0)
    prog.passthrough(PlannerLimits(acceleration_mm_s2=1000.0))
    second = prog.move((50, 50, 0, 0), feed=100.0)
    plan = plan_blocks(prog.blocks, BED)
    jd1, jd2 = 25 * SQRT2M1 / 3000, 25 * SQRT2M1 / 1000
    v2 = min(jd1 * 3000, jd2 * 1000) / SQRT2M1  # R_jd = 1/(sqrt2-1) at 90 degrees; both give 25
    v = math.sqrt(v2)
    assert plan.pieces.accel_mm_s2.tolist() == [3000.0, 1000.0]
    assert plan.line_time_s[first] == pytest.approx(trapezoid_time(50, 0, 100, v, 3000), rel=1e-12)
    assert plan.line_time_s[second] - plan.line_time_s[first] == pytest.approx(
        trapezoid_time(50, v, 100, 0, 1000), rel=1e-12)


# ---- extrude-only moves -----------------------------------------------------------------------

def test_extrude_only_retract():
    """A move of E alone is a rest of X Y Z for its trapezoid's time (copied as it is): a STOP
    with that dwell, the position jumping there."""
    prog = Program((10, 10, 0.2, 5.0))
    i = prog.move((10, 10, 0.2, 0.0), feed=40.0)
    plan = plan_blocks(prog.blocks, BED)
    assert plan.duration_s == pytest.approx(5 / 40 + 40 / 3000, rel=1e-12)
    assert plan.is_stop[i] and plan.line_time_s[i] == 0.0 and plan.runs == []
    assert np.all(plan.positions_mm[:, :4] == [10, 10, 0.2, 0.0])


def test_extrude_only_limited_by_e_axis_and_splits_runs():
    prog = Program()
    prog.move((20, 0, 0, 0), feed=100.0)
    retract = prog.move((20, 0, 0, 10), feed=200.0)  # E limit 120 mm/s
    prog.move((40, 0, 0, 10), feed=100.0)  # collinear with the first move, but after an E-only move
    plan = plan_blocks(prog.blocks, BED)
    np.testing.assert_array_equal(plan.pieces.start_v_mm_s, 0.0)
    np.testing.assert_array_equal(plan.pieces.end_v_mm_s, 0.0)
    t1, fs = rest_to_rest(20, 100, 3000), BED.sample_rate_hz
    last = math.ceil(t1 * fs)  # the rest is timed from the first run's last sample ...
    first = math.ceil((last / fs + rest_to_rest(10, 120, 3000)) * fs)  # ... the next run starts on a sample
    assert plan.is_stop[retract] and plan.runs[1][0] == first
    assert plan.duration_s == pytest.approx(first / fs + t1, rel=1e-12)


# ---- stops, dwells, passthrough lines -------------------------------------------------------------

def test_dwell_rests_exactly_and_splits_runs():
    prog = Program()
    prog.move((10, 0, 0, 0), feed=50.0)
    pause = prog.stop(dwell=0.5)
    after = prog.passthrough()
    second = prog.move((0, 0, 0, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    t1, fs = rest_to_rest(10, 50, 3000), BED.sample_rate_hz
    assert plan.line_time_s[pause] == pytest.approx(t1, rel=1e-12)
    # the dwell counts from the sample the first run ends on (where the output runs the G4)
    last = math.ceil(t1 * fs)
    assert plan.move_start_s[second] == pytest.approx(last / fs + 0.5, rel=1e-12)
    assert plan.line_time_s[after] == pytest.approx(t1 + 0.5, rel=1e-12)  # when the original's dwell ends
    assert plan.duration_s == pytest.approx(last / fs + 0.5 + t1, rel=1e-12)
    assert plan.runs == [(0, last), (last + 500, plan.positions_mm.shape[0] - 1)]
    rest = plan.positions_mm[last:last + 501]
    assert np.all(rest == xyze([10, 0, 0, 0]))


def test_margins_lead_and_settle_every_run():
    """Lead and settle margins (whole samples): each run starts lead_s before its motion and ends
    settle_s after it; the line at rest after a run (its dwell, the next run) waits for the settle
    margin; the program lasts both margins longer per run; ``added_s`` counts them. The same
    program as test_dwell_rests_exactly_and_splits_runs, with its closed-form times."""
    prog = Program()
    first = prog.move((10, 0, 0, 0), feed=50.0)
    pause = prog.stop(dwell=0.5)
    second = prog.move((0, 0, 0, 0), feed=50.0)
    fs, lead, settle = BED.sample_rate_hz, 7, 12
    plan = plan_blocks(prog.blocks, BED, margins=RunMargins(lead / fs, settle / fs))
    t1 = rest_to_rest(10, 50, 3000)
    assert plan.move_start_s[first] == pytest.approx(lead / fs, rel=1e-12)
    end1 = lead / fs + t1
    last = math.ceil(end1 * fs) + settle
    assert plan.line_time_s[pause] == pytest.approx(end1 + settle / fs, rel=1e-12)
    assert plan.runs[0] == (0, last)
    second_first = last + 500
    assert plan.move_start_s[second] == pytest.approx((second_first + lead) / fs, rel=1e-12)
    assert plan.runs[1] == (second_first, math.ceil((second_first + lead) / fs * fs + t1 * fs) + settle)
    assert plan.duration_s == pytest.approx((second_first + lead) / fs + t1 + settle / fs, rel=1e-12)
    positions = plan.positions_mm
    assert np.all(positions[:lead + 1] == 0.0) and positions[lead + 2, 0] > 0.0  # at rest through the lead
    assert np.all(positions[math.ceil(end1 * fs):last + 500] == xyze([10, 0, 0, 0]))  # the settle margin and the dwell
    stream = planner.PlanStream(prog.blocks, BED, margins=RunMargins(lead / fs, settle / fs))
    while stream.advance():
        pass
    assert stream.added_s == pytest.approx(2 * (lead + settle) / fs, rel=1e-12)


def test_margins_by_what_the_runs_end_does():
    """Up to the first run that prints (its pieces extrude), every run gets ``lead_s`` and
    ``settle_s``; after it, a run's end that prints its ``printing`` margins, a travel's (E still)
    its ``travel`` ones: the closed-form times of test_margins_lead_and_settle_every_run, each run
    with its own margins."""
    prog = Program()
    prog.move((10, 0, 0, 1), feed=50.0)
    prog.stop(dwell=0.5)
    travel = prog.move((0, 0, 0, 1), feed=50.0)
    prog.stop(dwell=0.5)
    printing = prog.move((10, 0, 0, 2), feed=50.0)
    fs, t1 = BED.sample_rate_hz, rest_to_rest(10, 50, 3000)
    margins = RunMargins(7 / fs, 12 / fs, printing=(5 / fs, 9 / fs), travel=(3 / fs, 0.0))
    plan = plan_blocks(prog.blocks, BED, margins=margins)
    first, last = 0, math.ceil((7 / fs + t1) * fs) + 12
    for (lead, settle), block, run in zip([(3, 0), (5, 9)], [travel, printing], plan.runs[1:], strict=True):
        first = last + 500
        assert plan.move_start_s[block] == pytest.approx((first + lead) / fs, rel=1e-12)
        last = math.ceil((first + lead) / fs * fs + t1 * fs) + settle
        assert run == (first, last)
    assert plan.runs[0] == (0, math.ceil((7 / fs + t1) * fs) + 12)
    assert plan.duration_s == pytest.approx((first + 5) / fs + t1 + 9 / fs, rel=1e-12)
    stream = planner.PlanStream(prog.blocks, BED, margins=margins)
    while stream.advance():
        pass
    assert stream.added_s == pytest.approx((7 + 12 + 3 + 5 + 9) / fs, rel=1e-12)


def test_klippers_margins_by_end():
    """For Klipper, once the program prints: at a run's end that prints half the other flavors'
    lead and a third of their settle margin; a quarter of the lead before a travel and a fifth of
    the settle margin after it (BY_END). Either time given: that everywhere."""
    half_s = RunMargins.for_profile(BED).lead_s
    assert RunMargins.for_profile(BED, flavor="klipper") == RunMargins(
        half_s, half_s, (half_s / 2, half_s / 3), (half_s / 4, half_s / 5), TRAVEL_SHARE)
    assert RunMargins.for_profile(BED, 0.0, None, "klipper") == RunMargins(0.0, half_s)


def test_default_margins_are_half_the_lowest_damped_period():
    lowest = BED.axes["Y"].modes[0]  # 36 Hz: the lowest
    margins = RunMargins.for_profile(BED)
    assert margins.lead_s == margins.settle_s == 0.5 / (36.0 * math.sqrt(1 - lowest.damping**2))
    assert RunMargins.for_profile(BED, 0.0, 0.02) == RunMargins(0.0, 0.02)


def test_linuxcnc_z_moves_are_in_the_run():
    """On LinuxCNC (planner.RESTS_WITHIN_RUNS) a move of Z alone (no modes: a plunge, a
    retraction) is a piece of its run, not a rest between runs: one run, one lead and one settle
    margin; the compensated axes stop before it and start after it from rest, so it takes its
    rest-to-rest time and the program the sum of the moves' (closed form). Elsewhere it is a rest
    that splits the runs."""
    def program():
        prog = Program()
        prog.move((10, 0, 0, 0), feed=50.0)
        prog.move((10, 0, 2, 0), feed=20.0)
        prog.move((20, 0, 2, 0), feed=50.0)
        prog.move((20, 0, 0, 0), feed=20.0)
        prog.move((30, 0, 0, 0), feed=50.0)
        return prog.blocks

    fs, a = PATENT.sample_rate_hz, PATENT.planner_acceleration_mm_s2
    margins = RunMargins(7 / fs, 12 / fs)
    plan = plan_blocks(program(), PATENT, margins=margins, firmware="linuxcnc")
    assert len(plan.runs) == 1
    moves = 3 * rest_to_rest(10, 50, a) + 2 * rest_to_rest(2, 20, a)
    assert plan.duration_s == pytest.approx(7 / fs + moves + 12 / fs, rel=1e-9)
    pieces = plan.pieces
    assert np.all(pieces.start_v_mm_s == 0.0) and np.all(pieces.end_v_mm_s == 0.0)
    assert len(plan_blocks(program(), PATENT, margins=margins).runs) == 3


def test_stop_without_dwell_still_separates_runs():
    prog = Program()
    prog.move((10, 0, 0, 0), feed=50.0)
    pause = prog.stop()
    second = prog.move((20, 0, 0, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    (a0, b0), (a1, b1) = plan.runs
    assert a0 == 0 and b0 < a1 and b1 == plan.positions_mm.shape[0] - 1
    # both ends of every run at rest: the samples next to them hold the same position
    assert np.all(plan.positions_mm[b0] == xyze([10, 0, 0, 0])) and np.all(plan.positions_mm[a1] == xyze([10, 0, 0, 0]))
    # the later run starts on its sample, less than two periods after the rest began
    assert 0 <= plan.move_start_s[second] - plan.line_time_s[pause] < 2 / BED.sample_rate_hz
    assert plan.line_time_s[second] - plan.move_start_s[second] == pytest.approx(rest_to_rest(10, 50, 3000), rel=1e-12)


def test_passthrough_stop_jumps_in_no_time():
    prog = Program()
    prog.move((10, 0, 0, 0), feed=50.0)
    home = prog.stop(position=(0, 0, 5, 0))  # G28-like: no pieces, the position changed
    second = prog.move((0, 10, 5, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    t1 = rest_to_rest(10, 50, 3000)
    assert plan.line_time_s[home] == pytest.approx(t1, rel=1e-12)
    (_, b0), (a1, _) = plan.runs
    assert np.all(plan.positions_mm[b0] == xyze([10, 0, 0, 0]))
    assert np.all(plan.positions_mm[b0 + 1:a1 + 1] == xyze([0, 0, 5, 0]))
    assert plan.duration_s - plan.move_start_s[second] == pytest.approx(rest_to_rest(10, 50, 3000), rel=1e-12)


def test_stop_that_loses_an_axis_holds_its_last_known_value():
    prog = Program()
    first = prog.move((10, 0, 0, 0), feed=50.0)
    lost = prog.stop(position=(np.nan, 0, 0, 0))  # e.g. a move the reader could not follow in X
    second = prog.move((np.nan, 10, 0, 0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    after = sample_times(plan) >= plan.line_time_s[first]
    assert np.all(plan.positions_mm[after, 0] == 10.0)  # X held at 10: the second move is pure Y
    assert np.all(plan.positions_mm[-1] == xyze([10, 10, 0, 0]))
    for i in (first, second):
        assert plan.line_time_s[i] - plan.move_start_s[i] == pytest.approx(rest_to_rest(10, 50, 3000), rel=1e-12)
    assert any(note.startswith(f"line {lost + 1}: X") for note in plan.notes)


def test_pass_lines_happen_when_the_previous_move_ends():
    prog = Program()
    early = prog.passthrough()
    first = prog.move((30, 0, 0, 0), feed=100.0)
    middle = prog.passthrough()
    second = prog.move((60, 0, 0, 0), feed=100.0)
    last = prog.passthrough()
    plan = plan_blocks(prog.blocks, BED)
    assert plan.line_time_s[early] == 0.0 == plan.move_start_s[early]
    assert plan.line_time_s[middle] == plan.line_time_s[first] == plan.move_start_s[second]
    assert plan.move_start_s[middle] == plan.line_time_s[middle]
    assert plan.line_time_s[last] == plan.line_time_s[second] == plan.duration_s
    assert plan.pieces.end_v_mm_s[0] == pytest.approx(100.0, rel=1e-12)  # the PASS does not stop it


def test_unknown_axes_are_never_nan():
    prog = Program((np.nan, np.nan, np.nan, np.nan))
    prog.move((10, 0, np.nan, np.nan), (10, 10, np.nan, 2.0), feed=50.0)
    plan = plan_blocks(prog.blocks, BED)
    assert np.isfinite(plan.positions_mm).all()
    assert np.all(plan.positions_mm[:, 2] == 0.0)  # Z never known: 0
    assert np.all(plan.positions_mm[:, 3] == 2.0)  # E: its first known value, so no E motion
    assert np.all(plan.positions_mm[0] == xyze([10, 0, 0, 2]))  # X, Y: start at their first known values
    assert any(note.startswith("Z") for note in plan.notes)
    assert plan.duration_s == pytest.approx(rest_to_rest(10, 50, 3000), rel=1e-12)


def test_unknown_axis_found_after_the_prologue_is_planned_at_0_until_then(monkeypatch):
    """Streaming cannot wait for ever for an axis' first position: past PROLOGUE_ROWS waypoints
    an unknown axis is at 0 until known, and moves from there."""
    monkeypatch.setattr(pieces, "PROLOGUE_ROWS", 3)
    prog = Program((0.0, 0.0, np.nan, 0.0))
    for x in (10, 20, 30):
        prog.move((x, 0, np.nan, 0), feed=50.0)
    known = prog.move((30, 0, 0.4, 0), feed=5.0)
    plan = plan_blocks(prog.blocks, BED, batch_blocks=2)
    assert np.all(plan.positions_mm[:, 2][sample_times(plan) <= plan.move_start_s[known]] == 0.0)
    assert plan.positions_mm[-1, 2] == 0.4
    assert plan.line_time_s[known] - plan.move_start_s[known] > 0.4 / 5.0  # a real Z move, at most 5 mm/s
    monkeypatch.setattr(pieces, "PROLOGUE_ROWS", 5)  # known within (the start is a waypoint): there from the start
    assert np.all(plan_blocks(prog.blocks, BED, batch_blocks=2).positions_mm[:, 2] == 0.4)
    assert any(
        note.startswith(f"Z: position not known in the first 3 waypoints, planned at 0 mm until line {known + 1}")
        for note in plan.notes
    )


def mixed_program(rng, n_blocks):
    """Moves, corners, extrude-only pieces, dwells, rests without dwell, jumps and lost axes at
    STOPs, planner-limit changes and passthrough lines, at random."""
    prog = Program()
    for _ in range(n_blocks):
        u = rng.random()
        if u < 0.06:
            prog.stop(dwell=float(rng.choice([0.0, 0.0137, 0.5])))
        elif u < 0.08:
            prog.stop(position=(rng.uniform(0, 50), np.nan if rng.random() < 0.5 else 5.0, 0.2, prog.pos[3]))
        elif u < 0.12:
            prog.passthrough(PlannerLimits(acceleration_mm_s2=float(rng.uniform(500, 5000))))
        elif u < 0.16:
            prog.passthrough()
        else:
            step = np.append(rng.normal(size=2) * rng.choice([0.05, 1.0, 10.0]), [0.0, rng.uniform(-0.5, 1.0)])
            if rng.random() < 0.1:
                step[:2] = 0.0  # extrude-only
            points = [prog.pos + step * k for k in range(1, int(rng.integers(1, 4)) + 1)]
            prog.move(*points, feed=float(rng.uniform(5, 300)) if rng.random() < 0.95 else math.inf)
    return prog


@pytest.mark.parametrize("seed", range(6))
def test_the_plan_is_the_same_however_the_blocks_are_batched(monkeypatch, seed):
    """Streamed a few blocks at a time (scans in chunks of 16 pieces, so that they carry over
    chunks and batches both), the plan is bit for bit the plan of every block at once."""
    monkeypatch.setattr(lookahead, "SCAN_CHUNK", 16)
    prog = mixed_program(np.random.default_rng(seed), 400)
    whole = plan_blocks(prog.blocks, BED, batch_blocks=10**9)
    assert len(whole.runs) > 5 and whole.pieces.length_mm.size > 300
    for batch in (1, 7, 64):
        plan = plan_blocks(prog.blocks, BED, batch_blocks=batch)
        assert plan.runs == whole.runs and plan.n_samples == whole.n_samples and plan.duration_s == whole.duration_s
        for name in ("line_time_s", "move_start_s", "is_move", "is_stop"):
            np.testing.assert_array_equal(getattr(plan, name), getattr(whole, name))
        for name in ("start_v_mm_s", "end_v_mm_s", "start_s", "duration_s"):
            np.testing.assert_array_equal(getattr(plan.pieces, name), getattr(whole.pieces, name))
        np.testing.assert_array_equal(plan.positions_mm, whole.positions_mm)
        assert plan.notes == whole.notes and plan.warnings == whole.warnings


def test_empty_program():
    plan = plan_blocks([], BED)
    assert plan.duration_s == 0.0 and plan.runs == [] and plan.positions_mm.shape == (1, len(AXES))


# ---- whole programs against the scalar reference ------------------------------------------------

def test_min_plus_scans_equal_their_loops():
    rng = np.random.default_rng(7)
    n = 1000
    limit = rng.uniform(0, 1e4, n + 1)
    limit[rng.random(n + 1) < 0.3] = np.inf
    limit[[0, n]] = 0.0
    delta = rng.uniform(0, 500, n)
    fwd, bwd = limit.copy(), limit.copy()
    for i in range(1, n + 1):
        fwd[i] = min(limit[i], fwd[i - 1] + delta[i - 1])
    for i in range(n - 1, -1, -1):
        bwd[i] = min(limit[i], bwd[i + 1] + delta[i])
    for chunk in (7, 64, 4096):  # small chunks exercise the carry between chunks
        np.testing.assert_allclose(forward_pass(limit, delta, chunk), fwd, rtol=1e-10)
        np.testing.assert_allclose(backward_pass(limit, delta, chunk), bwd, rtol=1e-10)


def check_against_reference(prog, refs, profile):
    plan = plan_blocks(prog.blocks, profile)
    reference_plan(refs)
    pieces = plan.pieces
    assert len(pieces.length_mm) == len(refs)
    np.testing.assert_allclose(pieces.start_v_mm_s, [m.start_v for m in refs], rtol=1e-9, atol=0)
    np.testing.assert_allclose(pieces.end_v_mm_s, [m.end_v for m in refs], rtol=1e-9, atol=0)
    np.testing.assert_allclose(pieces.peak_v_mm_s, [m.cruise_v for m in refs], rtol=1e-9, atol=0)
    np.testing.assert_allclose(pieces.duration_s, [m.time for m in refs], rtol=1e-9, atol=1e-12)
    ends = np.cumsum([m.time for m in refs])
    assert plan.duration_s == pytest.approx(ends[-1], rel=1e-9)
    np.testing.assert_allclose(pieces.start_s + pieces.duration_s, ends, rtol=1e-9, atol=1e-9)
    return plan


def test_random_polyline_matches_scalar_klipper():
    rng = np.random.default_rng(2024)
    prog, refs = random_program(rng, 400)
    plan = check_against_reference(prog, refs, BED)
    assert len(plan.runs) == 1
    # some corners really were at speed and some at rest, so the comparison means something
    assert (plan.pieces.start_v_mm_s > 1).sum() > 50 and (plan.pieces.start_v_mm_s == 0).sum() > 10


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=0, max_value=2**32 - 1), st.integers(min_value=1, max_value=30))
def test_small_random_polylines_match_scalar_klipper(seed, n_moves):
    prog, refs = random_program(np.random.default_rng(seed), n_moves, PATENT if seed % 2 else BED)
    if refs:
        check_against_reference(prog, refs, PATENT if seed % 2 else BED)


def test_samples_continuous_and_within_limits():
    rng = np.random.default_rng(5)
    prog = Program((50, 50, 0.2, 0))
    for _ in range(120):
        target = prog.pos + np.append(rng.normal(size=2) * rng.uniform(0.2, 15), [0, rng.uniform(0, 0.5)])
        prog.move(target, feed=math.inf if rng.random() < 0.1 else float(rng.uniform(20, 250)))
    plan = plan_blocks(prog.blocks, BED)
    fs, p = BED.sample_rate_hz, plan.positions_mm
    velocity = np.diff(p, axis=0) * fs
    for i, axis in enumerate("XYZE"):
        assert np.abs(velocity[:, i]).max() <= BED.axes[axis].max_velocity_mm_s * (1 + 1e-9)
    # acceleration: only where three samples lie inside one piece (junctions may jump speed)
    t = sample_times(plan)
    piece = np.searchsorted(plan.pieces.start_s, t, side="right") - 1
    inside = (piece[:-2] == piece[2:]) & (t[2:] <= (plan.pieces.start_s + plan.pieces.duration_s)[piece[2:]])
    accel = np.diff(p, 2, axis=0)[inside] * fs * fs
    assert np.linalg.norm(accel[:, :3], axis=1).max() <= 3000 * (1 + 1e-6)
    for i, axis in enumerate("XYZE"):
        assert np.abs(accel[:, i]).max() <= BED.axes[axis].max_acceleration_mm_s2 * (1 + 1e-6)
    # continuity: no sample moves further than the fastest axis can in one period
    assert np.abs(np.diff(p, axis=0)).max() <= 300 / fs * (1 + 1e-9)
    assert np.all(p[0] == xyze([50, 50, 0.2, 0])) and np.allclose(p[-1], xyze(prog.pos), rtol=0, atol=1e-12)


@pytest.mark.slow
def test_100k_piece_polyline_smoke(capsys):
    rng = np.random.default_rng(11)
    n = 100_000
    steps = rng.normal(size=(n, 4)) * [2, 2, 0.01, 0.05]
    points = xyze(np.cumsum(steps, axis=0))
    blocks = [Block(1, b"", Kind.STOP, Modal(), np.zeros(len(AXES)))]
    blocks += [Block(i + 2, b"", Kind.MOVE, Modal(), points[i], points[i:i + 1], 120.0) for i in range(n)]
    t0 = time.perf_counter()
    plan = plan_blocks(blocks, BED)
    elapsed = time.perf_counter() - t0
    with capsys.disabled():
        print(f"\n100k pieces: {elapsed:.2f} s, {plan.positions_mm.shape[0]} samples")
    assert np.isfinite(plan.positions_mm).all()
    assert plan.runs == [(0, plan.positions_mm.shape[0] - 1)]
    assert np.all(plan.positions_mm[-1] == points[-1])
    assert np.all(np.diff(plan.line_time_s[1:]) > 0)


@pytest.mark.slow
def test_real_print_samples_stay_within_axis_velocity():
    """A whole sliced print (PrusaSlicer, 37k lines): inside every run, no sample steps faster than
    the axes allow. Phase start times that round an ulp past the next piece's start once made
    the sampler jump back along the previous piece."""
    from fbspost.read.gcode import read_gcode

    profile = load_profile("bedslinger-example")
    path = Path(__file__).resolve().parent / "data" / "gear-marlin2.gcode"
    plan = plan_blocks(list(read_gcode(path, "marlin")), profile)
    fs = profile.sample_rate_hz
    for first, last in plan.runs:
        steps = np.abs(np.diff(plan.positions_mm[first:last + 1], axis=0)) * fs
        for i, axis in enumerate("XYZE"):
            assert steps[:, i].max(initial=0.0) <= profile.axes[axis].max_velocity_mm_s * (1 + 1e-6), axis
