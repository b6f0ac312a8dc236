"""fbspost.firmware.marlin: the model of Marlin 2.1's planner, against Marlin's formulas worked by hand.

Truths (planner.cpp, commit 000420e3; the printer profile: 80 steps/mm on X Y, 3000 mm/s^2, X
10000 and Y 8000 mm/s^2 at most): the minimum planner speed v_m^2 = 0.5 a / (steps per mm) =
18.75 mm^2/s^2 for blocks along X; a block from v0 to v1 with peak v takes (v - v0) / a + (v - v1)
/ a + (d - ramps) / v; the first block into an empty buffer waits until 3 are queued or 100 ms;
a block's exit speed is planned over the blocks queued when it starts (at most 13 more: the ring
of 16 holds 15, and the slot the block before frees is taken after it starts), the newest ending
at v_m; SLOWDOWN: seg + 2 (B - seg) / q us (integer division) with q queued blocks in [2, 7];
junction deviation a J sin(t/2) / (1 - sin(t/2)), under 1 mm and 45 degrees at most d a / t;
classic jerk: the junction speed at which no axis' speed steps by more than its jerk.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from fbspost.firmware.marlin import MarlinConfig, run_marlin
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode

PRINTER = load_profile("printer-two-mode")
A = 3000.0
V_MIN2 = 0.5 * A / 80.0


def run(tmp_path, lines: list[str], **config):
    path = tmp_path / "p.gcode"
    path.write_text("\n".join(lines) + "\n")
    blocks = list(read_gcode(path, "marlin", PRINTER.home_mm))
    return run_marlin(blocks, PRINTER, MarlinConfig.from_profile(PRINTER, **{"line_rate_hz": None, **config}))


def trapezoid_s(d, v0, v1, v, a=A):
    peak = min(v, math.sqrt(0.5 * (v0 * v0 + v1 * v1) + a * d))
    ramps = (2 * peak * peak - v0 * v0 - v1 * v1) / (2 * a)
    return (peak - v0) / a + (peak - v1) / a + (d - ramps) / peak


def test_single_trapezoid_waits_for_the_first_move_delay(tmp_path):
    """100 mm at 100 mm/s alone in the buffer: 100 ms, then from v_m to v_m."""
    motion = run(tmp_path, ["G1 X0 Y0 F6000", "G1 X100 F6000"])
    v_min = math.sqrt(V_MIN2)
    assert motion.duration_s == pytest.approx(0.1 + trapezoid_s(100.0, v_min, v_min, 100.0), rel=1e-12)
    assert motion.starved == []


def test_look_ahead_cut_by_the_buffer(tmp_path):
    """80 blocks of 0.5 mm at F 15000 (250 mm/s) in a line: once the buffer is full, every block
    enters and leaves at v^2 = v_m^2 + 2 a (13 x 0.5 mm), 197.5 mm/s, the speed from which the 13
    blocks queued behind it stop, and peaks between at v^2 + a d; the program's length at full
    look-ahead would allow 250."""
    motion = run(tmp_path, ["G1 X0 Y0 F15000"] + [f"G1 X{0.5 * i:g}" for i in range(1, 81)])
    v = math.sqrt(V_MIN2 + 2.0 * A * 13 * 0.5)
    middle = slice(30, 50)
    np.testing.assert_allclose(motion.entry_mm_s[middle], v, rtol=1e-12)
    np.testing.assert_allclose(motion.exit_mm_s[middle], v, rtol=1e-12)
    np.testing.assert_allclose((motion.end_s - motion.start_s)[middle], trapezoid_s(0.5, v, v, 250.0), rtol=1e-12)
    assert trapezoid_s(0.5, v, v, 250.0) < 0.5 / v


def test_line_rate_below_the_block_rate_starves_the_buffer(tmp_path):
    """30 blocks of 1 mm at 12.5 lines/s (80 ms a line): a block that comes into an empty buffer
    waits the 100 ms delay, the next comes meanwhile, and the two run as one 2 mm move from v_m to
    v_m at 3000 mm/s^2 (49 ms); the buffer is dry again before the third comes. Block j is line
    j + 3: the print lasts (lines - 1) / rate + 100 ms + the last pair; 14 rests of 2 lines less a pair."""
    rate = 12.5
    lines = ["M205 B0", "G1 X0 Y0 F6000"] + [f"G1 X{i}" for i in range(1, 31)]
    motion = run(tmp_path, lines, line_rate_hz=rate)
    v_min = math.sqrt(V_MIN2)
    pair_s = trapezoid_s(2.0, v_min, v_min, 100.0)
    assert motion.duration_s == pytest.approx((len(lines) - 1) / rate + 0.1 + pair_s, rel=1e-12)
    np.testing.assert_allclose(motion.start_s[::2], (np.arange(0, 30, 2) + 3) / rate + 0.1, rtol=1e-12)
    rests = np.array(motion.starved)
    assert len(rests) == 14
    np.testing.assert_allclose(rests[:, 1], 2 / rate - pair_s, rtol=1e-9)
    np.testing.assert_allclose(rests[:, 0], (np.arange(0, 28, 2) + 3) / rate + 0.1 + pair_s, rtol=1e-12)


def test_slowdown_while_the_buffer_drains(tmp_path):
    """A 10 s block runs while 1 mm blocks at 100 mm/s (10 000 us) come at 1000 lines/s: the one
    taken with q blocks queued behind the running one, q in [2, 7], lasts 10000 + 20000 // q us
    (M205 B 20000); none with fewer or more. (Block 2 comes as block 0 starts: it still counts.)"""
    lines = ["G1 X0 Y0 F600", "G1 X100"] + [f"G1 X{100 + i} F6000" for i in range(1, 13)]
    motion = run(tmp_path, lines, line_rate_hz=1000.0)
    queued = np.array([0, 1, 2, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11])  # of blocks 0..12
    segment_us = np.where((queued >= 2) & (queued <= 7), 10000 + 20000 // np.maximum(queued, 1), 10000)
    np.testing.assert_allclose(motion.nominal_mm_s[1:], 1e6 / segment_us[1:], rtol=1e-12)
    assert motion.nominal_mm_s[0] == 10.0


@pytest.mark.parametrize("j_mm", [0.05, 0.3])
def test_junction_deviation_corner(tmp_path, j_mm):
    """50 mm along X then 50 along Y at 100 mm/s: the corner's speed is a J sin45 / (1 - sin45),
    a = 3000 (the axes' limits along the junction, 10000 / sin45 and 8000 / sin45, do not bind)."""
    motion = run(tmp_path, [f"M205 J{j_mm}", "G1 X0 Y0 F6000", "G1 X50", "G1 Y50", "G1 Y100"])
    s = math.sin(math.pi / 4)
    assert motion.exit_mm_s[0] == pytest.approx(math.sqrt(A * j_mm * s / (1 - s)), rel=1e-12)


def test_junction_deviation_small_segments(tmp_path):
    """0.9 mm along X, then 0.75 mm turning 30 degrees (steps 52, 30): a short block turning under
    45 degrees passes at most d a / t, t the turn (Marlin's acos, within 0.033 rad), below J 0.3's
    limit."""
    motion = run(tmp_path, ["M205 J0.3", "G1 X0 Y0 F6000", "G1 X0.9", "G1 X1.55 Y0.375", "G1 X10.2 Y5.37"])
    turn = math.atan2(30, 52)
    d = math.hypot(52, 30) / 80.0
    lowest, highest = d * A / (turn + 0.033), d * A / (turn - 0.033)
    assert lowest <= motion.exit_mm_s[0] ** 2 <= highest
    s = math.sin((math.pi - turn) / 2)
    assert highest < A * 0.3 * s / (1 - s)


@pytest.mark.parametrize(("x", "y", "expected"), [(0.0, 50.0, 10.0), (50.0, 50.0, 10.0 / (1.0 - math.sqrt(0.5)))])
def test_classic_jerk_corner(tmp_path, x, y, expected):
    """Classic jerk 10 mm/s (M205 X10 Y10), 100 mm/s both sides: the junction speed v at which
    the larger axis step |v u1 - v u0| is 10: 90 degrees, both axes step by v; 45 degrees, X steps
    by v (1 - sqrt 0.5) and Y by v sqrt 0.5."""
    motion = run(tmp_path, ["M205 X10 Y10", "G1 X0 Y0 F6000", "G1 X50", f"G1 X{50 + x:g} Y{y:g}", "G1 X200 Y200"],
                 classic_jerk=True)
    step = max(abs(x / math.hypot(x, y) - 1.0), y / math.hypot(x, y))
    assert motion.exit_mm_s[0] == pytest.approx(10.0 / step, rel=1e-12)
    assert 10.0 / step == pytest.approx(expected if x == 0 else 10.0 / math.sqrt(0.5), rel=1e-12)


def test_a_dwell_leaves_the_position_in_whole_steps(tmp_path):
    """A G4 moves nothing: the block after it starts where the one before ended, at whole steps
    (X 10.0063 is step 800.504 -> 801 at 80 steps/mm, E 1.00001 is 415.004 -> 415 at 415), not at
    the program's position; so E does not creep while X Y travel (a creep counts as printing)."""
    motion = run(tmp_path, ["M83", "G1 X0 Y0 F6000", "G1 X10.0063 E1.00001 F3000", "G4 P10", "G1 X20 F6000"])
    after = np.flatnonzero(motion.line == 4)[0]
    np.testing.assert_array_equal(motion.start_mm[after, :4], [801 / 80, 0.0, 0.0, 415 / 415])
    np.testing.assert_array_equal(motion.end_mm[after, 3], motion.start_mm[after, 3])
