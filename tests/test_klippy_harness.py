"""The harness of Klipper's own planner (tests/klippy_planner.py) against closed forms: a program
of one move, planned by klippy's toolhead.py, must take the textbook trapezoid's time.

Truths: t = 2 v / a + (d - v^2 / a) / v for a move from rest to rest whose peak v is reached,
v^2 = d * accel_to_decel when klippy's smoothing (max_accel_to_decel = accel / 2) lowers it;
a triangle 2 sqrt(d / a) for a retraction at Klipper's derived max_extrude_only_accel
(max_accel * 4 nozzle^2 / filament area = 798.24 mm/s^2 on the printer profile)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from klippy_planner import KlippyPlanner, klippy_or_skip


@pytest.fixture(scope="module")
def klippy():
    return klippy_or_skip()


def klippy_moves(tmp_path, text: str, klippy, profile="printer-two-mode"):
    path = tmp_path / "p.gcode"
    path.write_text(text)
    return KlippyPlanner(load_profile(profile), klippy).run(list(read_gcode(path, "klipper")))


def test_long_move_cruises_at_its_feed(tmp_path, klippy):
    """100 mm at 100 mm/s, accel 3000: d / v + v / a."""
    (move,) = klippy_moves(tmp_path, "G1 X0 Y0 F6000\nG1 X100 F6000\n", klippy)
    assert move.cruise_v == pytest.approx(100.0, rel=1e-15)
    assert move.duration_s == pytest.approx(1.0 + 100.0 / 3000.0, rel=1e-14)


def test_short_move_peak_lowered_by_accel_to_decel(tmp_path, klippy):
    """2 mm at up to 100 mm/s: the smoothed pass caps the peak at sqrt(d * accel / 2)."""
    (move,) = klippy_moves(tmp_path, "G1 X0 Y0 F6000\nG1 X2 F6000\n", klippy)
    v = math.sqrt(2.0 * 1500.0)
    assert move.cruise_v == pytest.approx(v, rel=1e-14)
    assert move.duration_s == pytest.approx(2 * v / 3000.0 + (2.0 - v * v / 3000.0) / v, rel=1e-14)


def test_retraction_at_derived_extrude_only_accel(tmp_path, klippy):
    """A 1 mm retraction at F2400: a triangle at 798.24 mm/s^2 (its peak 28 mm/s stays under F)."""
    (move,) = klippy_moves(tmp_path, "G1 X0 Y0 F6000\nG1 E-1 F2400\n", klippy)
    accel = 3000.0 * 0.64 / (math.pi * 0.875**2)
    assert not move.is_kinematic
    assert move.accel_mm_s2 == pytest.approx(accel, rel=1e-15)
    assert move.duration_s == pytest.approx(2.0 * math.sqrt(1.0 / accel), rel=1e-14)


def test_set_velocity_limit_reaches_klippy(tmp_path, klippy):
    """SET_VELOCITY_LIMIT ACCEL=1000 ACCEL_TO_DECEL=1000: 100 mm at 100 mm/s takes d / v + v / a."""
    (move,) = klippy_moves(tmp_path, "G1 X0 Y0 F6000\nSET_VELOCITY_LIMIT ACCEL=1000 ACCEL_TO_DECEL=1000\n"
                                     "G1 X100 F6000\n", klippy)
    assert move.duration_s == pytest.approx(1.0 + 100.0 / 1000.0, rel=1e-14)


def test_samples_of_klippys_moves(tmp_path, klippy):
    """sample_moves: 0.5 a t^2 while accelerating, d / v + v / a to the end, the end held."""
    from klippy_planner import sample_moves
    moves = klippy_moves(tmp_path, "G1 X0 Y0 F6000\nG1 X100 F6000\n", klippy)
    samples = sample_moves(moves, 1000.0, 1.2)
    assert samples.shape == (1201, 4)
    np.testing.assert_allclose(samples[:34, 0], 0.5 * 3000.0 * (np.arange(34) / 1000.0) ** 2, rtol=1e-12, atol=1e-12)
    t = np.arange(34, 1000) / 1000.0  # cruising until 1 s: 100 / 3000 s behind the ideal
    np.testing.assert_allclose(samples[34:1000, 0], 100.0 * (t - 0.5 * 100.0 / 3000.0), rtol=1e-12)
    assert samples[1034:, 0] == pytest.approx(100.0, abs=1e-12) and samples[1034:, 1:].max() == 0.0
