"""fbspost's planner with Klipper's rules (``plan_blocks(..., firmware="klipper")``) against
Klipper's own planner: klippy's toolhead.py of the registry's sdist, driven by
tests/klippy_planner.py over the same program.

Truth: the speeds and times klippy's MoveQueue gives every move (start, cruise, end speed; accel,
cruise, decel time), on the sliced prints of tests/data, both butterflies and fbspost's own dense
compensated output of a sliced print; with Klipper's defaults (this klippy's max_accel_to_decel =
accel / 2, and the newer minimum_cruise_ratio 0.5 as the harness applies it on this klippy) and
with the transparency settings the writer emits (taken from the writer: ACCEL 1e8, no smoothing,
SQUARE_CORNER_VELOCITY 1e4). Equal to floating-point precision: fbspost's passes are vectorized,
klippy's sequential.
"""
from __future__ import annotations

import dataclasses
import itertools
import re
from pathlib import Path

import numpy as np
import pytest

from fbspost.firmware.transparency import transparent_limits
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.plan.planner import PlanStream, plan_blocks
from fbspost.profile import load_profile
from fbspost.read.blocks import Kind
from fbspost.read.flavors import detect_flavor
from fbspost.read.gcode import read_gcode
from klippy_planner import KlippyPlanner, klippy_or_skip
from reference import unbudgeted

ROOT = Path(__file__).resolve().parents[1]
PROGRAMS = [("tests/data/gear-marlin2.gcode", "printer-two-mode", 3000),
            ("tests/data/tube-marlin2.gcode", "printer-two-mode", 3000),
            ("tests/data/pocket-klipper.gcode", "printer-two-mode", 3000),
            ("tests/data/blob-reprap-relative-e.gcode", "printer-two-mode", 3000),
            ("tests/data/bracket-reprapfirmware-relative-e.gcode", "printer-two-mode", 3000),
            ("samples/butterfly-polyline.gcode", "patent-xy-stage", 3400),
            ("samples/butterfly-dense.gcode", "patent-xy-stage", 3000)]
# the writer's line, as it writes it (the tolerance is LinuxCNC's only)
TRANSPARENT = "".join(line + "\n" for line in transparent_limits("klipper", 0.01))


@pytest.fixture(scope="module")
def klippy():
    return klippy_or_skip()


def with_smoothing(profile, smoothing: str):
    """``fixed``: this klippy's default max_accel_to_decel = max_accel / 2; ``ratio``: the
    profile's minimum_cruise_ratio (0.5, Klipper's default now)."""
    if smoothing == "ratio":
        return profile
    firmware = dataclasses.replace(profile.firmware, max_accel_to_decel_mm_s2=profile.planner_acceleration_mm_s2 / 2)
    return dataclasses.replace(profile, firmware=firmware)


def assert_same_motion(blocks, profile, klippy) -> None:
    """Every piece fbspost plans is the move klippy plans, to floating-point precision; every line
    that moves no compensated axis (E or Z alone), a rest that fbspost copies, lasts as long as
    klippy's move of it. fbspost plans those from rest to rest, as its output runs them (its own
    blocks around them at rest): klippy is given a stop before and after each (where its
    neighbours would let it keep some speed, a Z move after a travel, at most a few ms apart)."""
    planned = [b for b, _, _ in PlanStream(blocks, profile, firmware="klipper").blocks()]
    rests = {i for i, (b, given) in enumerate(zip(planned, blocks, strict=True)) if b.kind is not given.kind}
    rests_s = [planned[i].dwell_s for i in sorted(rests)]
    stopped = []
    for i, block in enumerate(blocks):
        if i in rests:
            halt = dict(kind=Kind.STOP, dwell_s=0.0, points_mm=None, limits=None)
            stopped += [dataclasses.replace(blocks[i - 1], **halt), block, dataclasses.replace(block, **halt)]
        else:
            stopped.append(block)
    moves = KlippyPlanner(profile, klippy).run(stopped)
    pieces = plan_blocks(blocks, profile, firmware="klipper").pieces
    paired, alone = [], []  # klippy's moves that are fbspost's pieces, in order; the rest are rests
    for m in moves:
        j = len(paired)
        same = j < pieces.end_mm.shape[0] and np.allclose(m.end_pos[:4], pieces.end_mm[j, :4], rtol=0, atol=1e-9)
        (paired if same else alone).append(m)
    assert all(m.start_pos[:2] == m.end_pos[:2] for m in alone)  # (the profiles compensate X and Y)
    np.testing.assert_allclose(rests_s, [m.accel_t + m.cruise_t + m.decel_t for m in alone], rtol=1e-12)
    moves = paired
    assert len(moves) == pieces.length_mm.size
    assert np.array_equal([not m.is_kinematic for m in moves], pieces.extrude_only)
    column = {name: np.array([getattr(m, name) for m in moves]) for name in
              ("start_v", "cruise_v", "end_v", "accel_t", "cruise_t", "decel_t", "accel_mm_s2")}
    np.testing.assert_allclose(pieces.accel_mm_s2, column["accel_mm_s2"], rtol=1e-15)
    speeds = ((pieces.start_v_mm_s, "start_v"), (pieces.peak_v_mm_s, "cruise_v"), (pieces.end_v_mm_s, "end_v"))
    for mine, name in speeds:
        # (squared speeds: where klippy decides on exact equality fbspost allows CLOSE_V2, 1e-6 (mm/s)^2)
        np.testing.assert_allclose(mine**2, column[name] ** 2, rtol=1e-9, atol=2e-6, err_msg=name)
    accel_t = (pieces.peak_v_mm_s - pieces.start_v_mm_s) / pieces.accel_mm_s2  # a trapezoid's phases
    decel_t = (pieces.peak_v_mm_s - pieces.end_v_mm_s) / pieces.accel_mm_s2
    np.testing.assert_allclose(accel_t, column["accel_t"], rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(decel_t, column["decel_t"], rtol=1e-6, atol=1e-10)
    klippy_s = column["accel_t"] + column["cruise_t"] + column["decel_t"]
    np.testing.assert_allclose(pieces.duration_s, klippy_s, rtol=1e-9, atol=1e-10)
    assert pieces.duration_s.sum() == pytest.approx(klippy_s.sum(), rel=1e-12, abs=1e-9)


def program(tmp_path, name: str, lines: int, prefix: str = "") -> Path:
    path = tmp_path / Path(name).name
    with open(ROOT / name, encoding="utf-8", errors="surrogateescape") as f:
        path.write_text(prefix + "".join(itertools.islice(f, lines)), encoding="utf-8", errors="surrogateescape")
    return path


@pytest.mark.parametrize("smoothing", ["fixed", "ratio"])
@pytest.mark.parametrize("name,profile,lines", PROGRAMS, ids=[Path(p[0]).stem for p in PROGRAMS])
def test_plan_is_klippys(tmp_path, klippy, name, profile, lines, smoothing):
    """Sliced prints and the butterflies, Klipper's defaults: fbspost's plan is klippy's."""
    path = program(tmp_path, name, lines)
    blocks = list(read_gcode(path, detect_flavor(ROOT / name)))
    assert_same_motion(blocks, with_smoothing(load_profile(profile), smoothing), klippy)


@pytest.mark.parametrize("smoothing", ["fixed", "ratio"])
@pytest.mark.parametrize("name,profile,lines", PROGRAMS[::3], ids=[Path(p[0]).stem for p in PROGRAMS[::3]])
def test_plan_is_klippys_with_transparency_settings(tmp_path, klippy, name, profile, lines, smoothing):
    """The same with the writer's transparency settings in force from the first line. They serve
    both Klipper generations: after them klippy's planner (``fixed``: its own ACCEL_TO_DECEL;
    ``ratio``: the newer MINIMUM_CRUISE_RATIO) decelerates as hard as it accelerates, at ACCEL."""
    path = program(tmp_path, name, lines, TRANSPARENT)
    blocks = list(read_gcode(path, "klipper"))
    profile = with_smoothing(load_profile(profile), smoothing)
    head = KlippyPlanner(profile, klippy)
    for block in blocks[:len(TRANSPARENT.splitlines())]:
        head.command(block)
    words = dict(re.findall(r"(\w+)=(\S+)", TRANSPARENT))
    assert head.toolhead.max_accel == head.toolhead.max_accel_to_decel == float(words["ACCEL"])
    assert head.toolhead.square_corner_velocity == float(words["SQUARE_CORNER_VELOCITY"])
    assert_same_motion(blocks, profile, klippy)


@pytest.fixture(scope="module")
def compensated(tmp_path_factory) -> Path:
    """fbspost's dense output of a sliced print's first 120 lines (about 25000 short blocks)."""
    directory = tmp_path_factory.mktemp("compensated")
    source = program(directory, "tests/data/pocket-klipper.gcode", 120)
    target = directory / "out.gcode"
    compensate_file(source, target, unbudgeted(load_profile("printer-two-mode")), CompensateOptions())  # (1 ms blocks)
    return target


@pytest.mark.parametrize("smoothing", ["fixed", "ratio"])
@pytest.mark.slow
def test_plan_of_dense_output_is_klippys(klippy, compensated, smoothing):
    """fbspost's own dense output (its SET_VELOCITY_LIMIT lines included): klippy's plan."""
    blocks = list(read_gcode(compensated, "klipper"))
    assert len(blocks) > 10000
    assert_same_motion(blocks, with_smoothing(load_profile("printer-two-mode"), smoothing), klippy)


@pytest.mark.parametrize("batch", [13, 211])
def test_klipper_plan_streams_exactly(tmp_path, batch):
    """The plan with Klipper's rules is bit for bit the same however the program is cut."""
    path = program(tmp_path, "tests/data/gear-marlin2.gcode", 2500, re.sub(r"\bACCEL=\d+", "ACCEL=2500", TRANSPARENT))
    blocks = list(read_gcode(path, "klipper"))
    whole = plan_blocks(blocks, load_profile("printer-two-mode"), firmware="klipper")
    cut = plan_blocks(blocks, load_profile("printer-two-mode"), batch_blocks=batch, firmware="klipper")
    for name in ("start_v_mm_s", "peak_v_mm_s", "end_v_mm_s", "duration_s", "start_s"):
        assert np.array_equal(getattr(whole.pieces, name), getattr(cut.pieces, name)), name
    assert np.array_equal(whole.line_time_s, cut.line_time_s)
    assert np.array_equal(whole.positions_mm, cut.positions_mm)
