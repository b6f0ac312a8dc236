"""fbspost.firmware.linuxcnc_tp: the model of LinuxCNC 2.9's trajectory planner, against its rules worked by hand.

Truths (tp.c, tc.c, blendmath.c; the patent stage's INI limits: X and Y 100 mm/s, 8000 mm/s^2;
servo period T = 1 ms): a segment's speed is at most its length / (1.02 T); a move from rest to
rest at F v over d takes d / v + v / a; G61.1 and G61 stop at a corner the kink forbids; a G64 P
corner of angle 2 t between lines is replaced by an arc of radius R = tan(t) d, d = P cos(t) /
(1 - sin(t)), run at sqrt(0.866 a R), passing the corner at R (1 / sin(t) - 1); without blend
arcs (ARC_BLEND_ENABLE 0) a parabolic blend at half the acceleration starts when the first
segment slows under 2 sqrt(a/2 P / cos(t)), and passes the corner at sqrt(2) v0^2 / (8 a/2).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fbspost.firmware.linuxcnc_queue import Queue as _Queue
from fbspost.firmware.linuxcnc_segments import LinuxCNCConfig
from fbspost.firmware.linuxcnc_segments import segment as _segment
from fbspost.firmware.linuxcnc_tp import interpolated, run_linuxcnc
from fbspost.firmware.planners import replan
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode

STAGE = load_profile("patent-xy-stage")
A, T = 8000.0, 0.001


def blocks(tmp_path, lines: list[str]):
    path = tmp_path / "p.ngc"
    path.write_text("\n".join(["G21 G90 G17", "G0 X0 Y0", *lines, "M2"]) + "\n")
    return list(read_gcode(path, "linuxcnc", STAGE.home_mm))


def run(tmp_path, lines: list[str], **config):
    return run_linuxcnc(blocks(tmp_path, lines), STAGE, LinuxCNCConfig.from_profile(STAGE, **config))


def queued(tmp_path, lines: list[str], **config) -> list:
    """The TP's queue once the G64 P0.01 moves of ``lines`` are added (before any runs)."""
    config = LinuxCNCConfig.from_profile(STAGE, **config)
    queue, start = _Queue(config), np.zeros(10)
    for index, block in enumerate(blocks(tmp_path, lines)):
        if block.points_mm is not None and block.kind.name == "MOVE":
            for tc in _segment(block, index, start, ("parabolic", 0.01), config):
                queue.add(tc)
                start = tc.end
    return queue.items


def speeds(run) -> np.ndarray:
    return np.linalg.norm(np.diff(run.cycle_positions_mm[:, :2], axis=0), axis=1) / run.servo_period_s


def tp_duration_s(run) -> float:
    """How long the TP itself runs (the joints follow it through the interpolator, later)."""
    return (len(run.cycle_positions_mm) - 1) * run.servo_period_s


def test_a_long_line_cruises_at_f_and_ramps_at_half_the_acceleration_in_g64(tmp_path):
    # G64: the last segment's terminal condition is parabolic, which halves its acceleration
    # (tcGetOverallMaxAccel) though no segment follows; G61.1 ramps at the INI's
    done = run(tmp_path, ["G64 P0.01", "G1 X20 F6000"])
    assert speeds(done)[100:150] == pytest.approx(100.0, rel=1e-9)
    assert tp_duration_s(done) == pytest.approx(20.0 / 100.0 + 100.0 / (A / 2), abs=2 * T)
    assert tp_duration_s(run(tmp_path, ["G61.1", "G1 X20 F6000"])) == pytest.approx(0.2 + 100.0 / A, abs=2 * T)
    assert done.cycle_positions_mm[-1, 0] == pytest.approx(20.0, abs=1e-12)


def test_blend_arcs_ramp_at_half_the_acceleration_as_linuxcnc_s_do(tmp_path):
    """A circle of 0.2 mm chords at F3000 (G64 P0.001): every junction a blend arc that takes
    the chord before it (its turn is too much for a tangent junction: (v / T + a) 0.04 rad over
    8000 = 0.27 > ARC_BLEND_KINK_RATIO 0.1). A blend arc is TC_SPHERICAL: tcUpdateArcLimits
    (TC_CIRCULAR only) leaves its tangential share at BLEND_ACC_RATIO_TANGENTIAL 0.5, so the
    machine speeds up at 4000 mm/s^2: 4 mm/s more each 1 ms period, as LinuxCNC 2.9 itself
    did on this program (joint commands, 6 to 46 mm/s in steps of 4.0; the model gave 8.0
    before)."""
    chords = [f"G1 X{5 * math.cos(a):.4f} Y{5 * math.sin(a):.4f} F3000"
              for a in np.arange(1, 158) * 2 * math.pi / 157]
    done = run(tmp_path, ["G0 X5 Y0", "G64 P0.001 Q0", "G4 P0.01", *chords])
    v = speeds(done)
    start = int(np.flatnonzero(np.diff((v > 0).astype(int)) == 1)[-1]) + 1  # (after the rapid and the dwell)
    assert np.diff(v[start + 1:start + 11]) == pytest.approx(0.5 * A * T, rel=1e-4)  # (speeds from chords of a curve)


def test_an_axis_the_profile_leaves_out_moves_at_the_slowest_given_limits(tmp_path):
    """The patent stage has no Z: a plunge G1 Z-2 F100 alone (G61.1: ramps at the full
    acceleration) is the trapezoid d / v + v / a with X's and Y's 8000 mm/s^2; it used to
    never end (no limit: an infinite acceleration)."""
    done = run(tmp_path, ["G0 Z0", "G61.1", "G1 Z-2 F100"])
    v = 100.0 / 60.0
    assert tp_duration_s(done) == pytest.approx(2.0 / v + v / A, abs=2 * T)


@pytest.mark.parametrize("depth", [2, 50])
def test_the_look_ahead_depth_bounds_the_speed_of_short_segments(tmp_path, depth):
    """0.05 mm segments at F3000 in G64: each new (not finalized, parabolic: a/2) segment lets the
    one before end at sqrt(a/2 L) (findVPeak); the backward pass adds 2 a L a segment, over
    depth + 1 junctions: depth 2 gives sqrt(a/2 L + 2 (2 a L)) = 42.4 mm/s; depth 50 reaches the
    short-segment cap, L / 1.02 ms = 49.0 mm/s."""
    chain = [f"G1 X{0.05 * k:.2f} F3000" for k in range(1, 201)]
    L = 0.05
    expected = math.sqrt(A / 2 * L + 2 * 2 * A * L) if depth == 2 else L / (1.02 * T)
    segments = queued(tmp_path, ["G64 P0.01", *chain], optimization_depth=depth)
    assert [tc.finalvel for tc in segments[50:150]] == pytest.approx([expected] * 100, rel=1e-12)
    # each segment's first (split) part of a period is trapezoidal, the rest a ramp (tpActivateSegment)
    middle = speeds(run(tmp_path, ["G64 P0.01", *chain], optimization_depth=depth))[80:120]
    assert expected - 0.01 < middle.min() and middle.mean() < expected + A * T / 2


def test_segments_shorter_than_a_servo_period_are_capped_at_length_over_1_02_periods(tmp_path):
    chain = [f"G1 X{0.02 * k:.2f} F6000" for k in range(1, 301)]
    done = run(tmp_path, ["G64 P0.01", *chain])
    middle = speeds(done)[100:200]
    assert middle == pytest.approx(0.02 / (1.02 * T), rel=1e-9)  # 19.6 mm/s, not F's 100 mm/s
    assert done.cycle_positions_mm[-1, 0] == pytest.approx(6.0, abs=1e-12)


@pytest.mark.parametrize("mode, accel", [("G61.1", A), ("G61", 0.9 * A)])
def test_an_exact_stop_corner_stops_and_each_line_is_a_trapezoid(tmp_path, mode, accel):
    # G61 (exact path) keeps the kink's acceleration reduction (ARC_BLEND_KINK_RATIO 0.1) that
    # tpSetupTangent set before tpChooseBestBlend refused to blend; G61.1 never gets one
    done = run(tmp_path, [mode, "G1 X10 F6000", "G1 X10 Y10"])
    corner = np.linalg.norm(done.cycle_positions_mm[:, :2] - [10.0, 0.0], axis=1)
    assert corner.min() < 1e-12  # it reaches the corner itself
    assert tp_duration_s(done) == pytest.approx(2 * (10.0 / 100.0 + 100.0 / accel), abs=1.5 * T)


def test_a_g64_p_corner_gets_the_blend_arc_of_blendmath(tmp_path):
    P, theta = 0.01, math.pi / 4  # a 90 degree corner: half the interior angle
    first, arc, second = queued(tmp_path, ["G64 P0.01", "G1 X10 F6000", "G1 X10 Y10"])
    d = P * math.cos(theta) / (1 - math.sin(theta))
    radius = math.tan(theta) * d  # the parabolic-equivalent radius is no larger here
    v_plan = math.sqrt(math.sqrt(0.75) * A * radius)
    assert arc.arc_radius == pytest.approx(radius, rel=1e-12)
    assert arc.maxvel == pytest.approx(v_plan, rel=1e-12)
    assert arc.target == pytest.approx(radius * math.pi / 2, rel=1e-6)
    assert first.path[-1] == pytest.approx([10 - d / math.tan(theta) * 1.0, 0, 0], abs=1e-12)
    assert second.path[0] == pytest.approx([10, d, 0], abs=1e-12)
    assert first.term == arc.term == "tangent"
    done = run(tmp_path, ["G64 P0.01", "G1 X10 F6000", "G1 X10 Y10"])
    corner = np.linalg.norm(done.cycle_positions_mm[:, :2] - [10.0, 0.0], axis=1)
    assert radius * (1 / math.sin(theta) - 1) - 1e-12 <= corner.min() <= P + 1.5e-3  # sampled every 1 ms
    near = (corner[1:] < 2 * d) & (corner[:-1] < 2 * d)
    step = v_plan * T / radius  # the angle it turns in a period at v_plan
    chord = v_plan * math.sin(step / 2) / (step / 2)  # a period's chord of the arc over the period
    assert speeds(done)[near].min() == pytest.approx(chord, rel=1e-9)


def test_without_blend_arcs_a_corner_is_a_parabolic_blend_within_p(tmp_path):
    P, cos_t, a_half = 0.01, math.cos(math.pi / 4), A / 2
    blend_vel = 2 * math.sqrt(a_half * P / cos_t)  # 15.0 mm/s: the tolerance's limit
    done = run(tmp_path, ["G64 P0.01", "G1 X10 F6000", "G1 X10 Y10"], arc_blends=False)
    apex = np.linalg.norm(done.cycle_positions_mm[:, :2] - [10.0, 0.0], axis=1).min()
    # the first line slows by a/2 T = 4 mm/s a period from 100 mm/s; the blend starts with the
    # period in which it falls under blend_vel: from v0 = 16 mm/s, both segments at a/2 from
    # then on, closest to the corner v0 / a later: sqrt(2) v0^2 / (8 a/2), over P by the step
    v0 = math.ceil(blend_vel / (a_half * T)) * a_half * T
    assert apex == pytest.approx(math.sqrt(2) * v0 ** 2 / (8 * a_half), rel=1e-9)
    assert P < apex < 1.2 * P
    # both segments at half the acceleration: the first line's ramp takes twice as long
    assert speeds(done)[:5] == pytest.approx(a_half * T * (np.arange(1, 6) - 0.5), rel=1e-9)  # mean of each period


def test_a_tangent_junction_keeps_the_speed_and_replan_uses_the_model(tmp_path):
    lines = ["G64 P0.01", "G1 X10 Y0 F6000", "G1 X20 Y0.0001"]  # a 10 urad kink: tangent
    done = run(tmp_path, lines)
    v = speeds(done)
    assert v[20:-40].min() == pytest.approx(100.0, rel=1e-6)
    motion = replan(blocks(tmp_path, lines), STAGE, "linuxcnc")
    assert motion.duration_s == done.duration_s
    assert motion.positions_mm[-1, :2] == pytest.approx([20.0, 0.0001], abs=1e-12)


def test_the_model_against_linuxcnc_s_own_trajectory_planner(tmp_path):
    """LinuxCNC 2.9's own TP ran the G64 P0.01 corner (tests/data/linuxcnc-corner-joints.txt, its
    joint commands every servo period, the record starting 3 periods before the motion). The
    model's joint commands (the TP's points through the interpolator) are LinuxCNC's within 3 um
    all the way (measured 2.57 um), half a period later: LinuxCNC's first period of this motion
    ramps for half of it (its joints' first step is a T^2 / 24, the model's a T^2 / 12), the
    same ramp from there on. Before the model had the interpolator, this test filtered its TP
    points by (1, 5, 5, 1) / 12: the same half-period average, 2 periods later."""
    real = np.loadtxt(Path(__file__).parent / "data" / "linuxcnc-corner-joints.txt")
    done = run(tmp_path, ["G64 P0.01", "G1 X10 F6000", "G1 X10 Y10"])
    model = done.at((np.arange(len(real) + 20) - 1.5) * T)[:, :2]
    assert real[3, 0] == pytest.approx(A * T * T / 24, abs=1e-6)  # (6 decimals)
    assert model[3, 0] == pytest.approx(A * T * T / 24, abs=1e-12)
    assert np.abs(real - model[:len(real)]).max() < 0.003
    assert np.abs(model[len(real):] - [10.0, 10.0]).max() < 1e-12  # and at rest when LinuxCNC is


def cubic_c(points: np.ndarray) -> list[float]:
    """LinuxCNC's cubic.c at interpolation rate 1 as control.c drives it, step by step: each
    servo period the TP's newest point is added (the first fills all four slots; after the end
    the TP stays at its last), then the cubic is evaluated at its start, its way point wp0."""
    x, out = [], []
    for p in list(points) + [points[-1]] * 3:
        x = [p] * 4 if not x else x[1:] + [p]
        out.append((x[0] + 4 * x[1] + x[2]) / 6)
    return out


def test_the_joints_get_the_tp_s_points_through_linuxcnc_s_cubic_interpolator(tmp_path):
    """The joints' commands are the TP's points through cubic.c (each period the way point
    (1, 4, 1) / 6 of the three points before the newest: 2 periods late), checked against a step
    by step rendering of cubic.c on a corner and against the closed form of its pass-band on a
    sine: 2/3 + 1/3 cos(2 pi f T), 2 periods late. The run ends when the joints are at rest."""
    done = run(tmp_path, ["G64 P0.01", "G1 X10 F6000", "G1 X10 Y10"])
    tp = done.cycle_positions_mm
    for axis in (0, 1):
        assert done.joint_positions_mm[:, axis] == pytest.approx(cubic_c(tp[:, axis]), abs=1e-12)
    assert done.duration_s == pytest.approx((len(tp) + 2) * T, abs=1e-12)
    at_rest = np.abs(done.joint_positions_mm[:, :2] - [10.0, 10.0]).max(axis=1) < 1e-12
    assert at_rest[-1] and not at_rest[-2]
    f_hz = 100.0
    k = np.arange(400)
    joints = interpolated(np.sin(2 * np.pi * f_hz * k * T)[:, None])[:, 0]
    gain = 2 / 3 + np.cos(2 * np.pi * f_hz * T) / 3  # 0.9738 at 100 Hz, 1 ms
    assert joints[10:400] == pytest.approx(gain * np.sin(2 * np.pi * f_hz * (k[10:400] - 2) * T), abs=1e-12)
