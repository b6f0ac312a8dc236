"""fbspost.firmware.linuxcnc_time: the feeds at which LinuxCNC runs the original, and fbspost's plan of them.

Truths: LinuxCNC's TP caps a segment's speed at its length / (1.02 servo periods)
(tcClampVelocityByLength, TP_MIN_SEGMENT_CYCLES); a move from rest to rest at speed v over d in
fbspost's trapezoidal plan (acceleration a, the profile's planner) takes d / v + v / a. The patent
stage: planner 5000 mm/s^2, servo period 1 ms.
"""
from __future__ import annotations

import math

import pytest

from fbspost.firmware.linuxcnc_time import MAX_PAID, UNPAID_SHARE, linuxcnc_feeds, retimed
from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode

STAGE = load_profile("patent-xy-stage")
T = STAGE.firmware.linuxcnc.servo_period_s
CAPPED_MM_S = 0.05 / (1.02 * T)  # 49.02 mm/s: 0.05 mm segments at F6000 (100 mm/s)


def chain(tmp_path, n: int = 400):
    """``n`` collinear 0.05 mm segments at F6000 after a rapid to the start, then a dwell and
    one more such chain back."""
    lines = ["G21 G90 G17", "G0 X0 Y0", "G1 X0.05 F6000", *(f"X{0.05 * (k + 2):.2f}" for k in range(n - 1)),
             "G4 P0.5", *(f"G1 X{0.05 * (n - k - 1):.2f}" for k in range(n)), "M2"]
    path = tmp_path / "chain.ngc"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_short_segments_get_linuxcnc_s_capped_speed_and_the_plan_its_time(tmp_path):
    path = chain(tmp_path)
    feeds = list(linuxcnc_feeds(path, STAGE))
    blocks = list(read_gcode(path, "linuxcnc", STAGE.home_mm))
    assert len(feeds) == len(blocks)
    moving = [k for k, b in enumerate(blocks) if b.kind.name == "MOVE" and math.isfinite(b.feed_mm_s)]
    assert [k for k, f in enumerate(feeds) if f is not None] == moving  # not the rapid, nor the dwell
    middle = [feeds[k] for k in moving[100:300] + moving[500:700]]  # cruising, away from the stops
    assert min(middle) == pytest.approx(CAPPED_MM_S, rel=1e-3)
    assert max(middle) == pytest.approx(CAPPED_MM_S, rel=1e-3)
    # fbspost's plan of the retimed program: each chain from rest to rest at the capped speed
    # (F6000 would have taken 20 mm / 100 mm/s + 100 / 5000 = 0.22 s each); measured 0.04% short
    plan = plan_blocks(retimed(iter(blocks), path, STAGE), STAGE)
    v, a = CAPPED_MM_S, STAGE.planner_acceleration_mm_s2
    one_chain_s = 20.0 / v + v / a
    moving_s = plan.n_samples / STAGE.sample_rate_hz - 0.5
    assert moving_s == pytest.approx(2 * one_chain_s, rel=0.002)


@pytest.mark.parametrize("rest", ["G4 P3", "A30"])
def test_a_run_s_last_line_keeps_its_feed_before_a_rest(tmp_path, rest):
    """Two 10 mm lines at F600 (10 mm/s), between them a 3 s dwell or a move of A alone (30
    degrees at F600: 3 s): each line runs at its F on LinuxCNC (1.0 s and its ramps), so each
    keeps its feed, within 0.5% (the ramps, and LinuxCNC's parabolic blend out of the A move:
    0.2%). Before, a run's last line was read against
    the plan's time across the rest that follows it: the first line's feed 39.9 mm/s (its F
    times the rest's 4 s over its own 1 s), and the output cut it at four times its feed."""
    path = tmp_path / "rest.ngc"
    path.write_text(f"G21 G90 G64\nG0 X0 Y0 Z0 A0\nG1 X10 F600\n{rest}\nX0\nM2\n")
    feeds = [f for f in linuxcnc_feeds(path, STAGE) if f is not None]
    assert feeds == pytest.approx([10.0, 10.0], rel=0.005)


def test_a_run_pays_its_margins_where_linuxcnc_caps_it_below_its_feed(tmp_path):
    """Each chain is a run LinuxCNC caps at 49 mm/s (F6000 written): given margins M, its feeds
    are raised by its time T on LinuxCNC over T less what it owes, M - UNPAID_SHARE T, the same on
    every line of it, never above F; fbspost's plan of each chain is then shorter by its cruise at
    v k for v, less its ramps' v / a made longer: the closed form of the trapezoid."""
    path = chain(tmp_path)
    blocks = list(read_gcode(path, "linuxcnc", STAGE.home_mm))
    plain, margins_s = list(linuxcnc_feeds(path, STAGE)), 0.015
    paid = list(linuxcnc_feeds(path, STAGE, margins_s=margins_s))
    moving = [k for k, f in enumerate(plain) if f is not None]
    line_time_s = run_linuxcnc(blocks, STAGE).line_time_s
    v, a = CAPPED_MM_S, STAGE.planner_acceleration_mm_s2
    saved_s = 0.0
    for run in (moving[:400], moving[400:]):
        taken_s = line_time_s[run[-1]] - line_time_s[run[0] - 1]
        factor = taken_s / (taken_s - (margins_s - UNPAID_SHARE * taken_s))
        assert 1.0 < factor < 1.0 + MAX_PAID
        assert all(paid[k] == pytest.approx(plain[k] * factor, rel=1e-12) for k in run[100:300])
        assert all(paid[k] <= max(plain[k], 100.0) for k in run)  # never above F, unless the plain feed was
        saved_s += 20.0 / v * (1.0 - 1.0 / factor) - (factor - 1.0) * v / a
    plans = [plan_blocks(retimed(iter(blocks), path, STAGE, margins_s=m), STAGE) for m in (0.0, margins_s)]
    assert (plans[0].n_samples - plans[1].n_samples) / STAGE.sample_rate_hz == pytest.approx(saved_s, rel=0.05)
