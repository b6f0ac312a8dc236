"""fbspost.firmware.planners: a written program re-planned as each flavor's firmware plans it.

Truths: closed forms. A move from rest to rest takes d / v + v / a when it reaches v; a
retraction on Klipper is a triangle at its max_extrude_only_accel (798.24 mm/s^2 on the printer
profile: 3000 * 4 * 0.4^2 / (pi 0.875^2)); Marlin drops a segment under 6 steps (80 steps/mm:
3 steps is 0.0375 mm) and the next block starts where the last block ended; positions are whole
steps, rounded half away from zero as C's lround.
"""
from __future__ import annotations

import math

import pytest

from fbspost.firmware.marlin import merge_short_segments
from fbspost.firmware.planners import replan
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import serial

PRINTER = serial(load_profile("printer-two-mode"))  # a host sending 300 lines/s


def blocks_of(tmp_path, text: str, flavor: str):
    path = tmp_path / "p.gcode"
    path.write_text(text)
    return list(read_gcode(path, flavor))


@pytest.mark.parametrize("flavor, accel, periods", [("klipper", 3000.0, 0), ("linuxcnc", 5000.0, 3)])
def test_single_trapezoid(tmp_path, flavor, accel, periods):
    """100 mm at 100 mm/s from rest to rest at 3000 mm/s^2: 1 + 100 / 3000 s (Marlin's:
    tests/test_marlin.py; RepRapFirmware's: tests/test_reprap.py). LinuxCNC ramps at the INI's X
    acceleration (the profile's axis limit, 10000 mm/s^2), halved in G64 (tests/test_linuxcnc_tp.py);
    its joints, through its cubic interpolator, are at rest 3 servo periods after its planner."""
    motion = replan(blocks_of(tmp_path, "G1 X0 Y0 F6000\nG1 X100 F6000\n", flavor), PRINTER, flavor)
    period_s = PRINTER.firmware.linuxcnc.servo_period_s
    assert motion.duration_s == pytest.approx(1.0 + 100.0 / accel + periods * period_s, rel=1e-12)
    assert motion.positions_mm[-1, 0] == pytest.approx(100.0, abs=1e-9)


def test_klipper_retraction_is_a_triangle_at_extrude_only_accel(tmp_path):
    """On Klipper a 1 mm retraction at F2400 is limited by max_extrude_only_accel (its peak 28 mm/s
    stays under F); on Marlin it runs at 3000 mm/s^2 and cruises at 40 mm/s, from and to its
    minimum planner speed (0.5 a / 415 steps/mm), after two lines at 300 lines/s and the 100 ms
    first-move delay."""
    text = "G1 X0 Y0 F6000\nG1 E-1 F2400\n"
    accel = 3000.0 * 0.64 / (math.pi * 0.875**2)
    assert replan(blocks_of(tmp_path, text, "klipper"), PRINTER, "klipper").duration_s == pytest.approx(
        2.0 * math.sqrt(1.0 / accel), rel=1e-12)
    v_min = math.sqrt(0.5 * 3000.0 / 415.0)
    assert replan(blocks_of(tmp_path, text, "marlin"), PRINTER, "marlin").duration_s == pytest.approx(
        2.0 / 300.0 + 0.1 + 1.0 / 40.0 + (40.0 - v_min) ** 2 / 3000.0 / 40.0, rel=1e-12)


def test_marlin_merges_a_3_step_segment(tmp_path):
    """X +0.0375 mm (3 steps at 80/mm) is no block: the next block runs 0 -> 1 mm in one piece,
    a triangle from and to the minimum planner speed v (v^2 = 0.5 a / 80), 2 (sqrt(v^2 + a d) - v) / a,
    after three lines at 300 lines/s and the 100 ms first-move delay."""
    blocks = blocks_of(tmp_path, "G1 X0 Y0 F6000\nG1 X0.0375\nG1 X1\n", "marlin")
    merged, lines = merge_short_segments(blocks, PRINTER)
    assert lines == [2]
    assert merged[1].points_mm is None
    motion = replan(blocks, PRINTER, "marlin")
    assert motion.merged_lines == [2]
    v_min2 = 0.5 * 3000.0 / 80.0
    triangle_s = 2.0 * (math.sqrt(v_min2 + 3000.0) - math.sqrt(v_min2)) / 3000.0
    assert motion.duration_s == pytest.approx(3.0 / 300.0 + 0.1 + triangle_s, rel=1e-12)


def test_marlin_keeps_6_steps_and_rounds_to_whole_steps(tmp_path):
    """6 steps (0.075 mm) is a block; X 0.0812 mm is 6.496 steps: 6 steps = 0.075 mm; X 0.08125
    (6.5 steps) rounds away from zero to 7 steps, 0.0875 mm."""
    for x, steps in (("0.075", 6), ("0.0812", 6), ("0.08125", 7), ("-0.08125", -7)):
        blocks = blocks_of(tmp_path, f"G1 X0 Y0 F6000\nG1 X{x}\n", "marlin")
        merged, lines = merge_short_segments(blocks, PRINTER)
        assert lines == [] and merged[1].points_mm[0, 0] == steps / 80.0
