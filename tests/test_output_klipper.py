"""The written program run by Klipper's own planner (klippy's toolhead.py, tests/klippy_planner.py),
Klipper's defaults otherwise (minimum_cruise_ratio 0.5 as accel_to_decel, extruder limits): it
lasts as long as fbspost's plan of the original, and its motion on the compensated axes, the
trapezoids klippy plans sampled on the command's grid, stays within the tolerance + 2 um of the
compensated command everywhere (the firmware settings fbspost writes make it run the blocks as
written)."""
from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest

from fbspost.firmware.planners import replan
from fbspost.firmware.verify import contour_um, modelled, printed_path
from fbspost.job.pipeline import compensate_file, compensated_samples
from fbspost.job.report import CompensateOptions
from fbspost.plan.margins import RunMargins
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile, with_travel
from fbspost.read.gcode import read_gcode
from firmware_results import klippy_run, move_ends, shaped_plans
from klippy_motion import executed
from klippy_planner import KlippyPlanner, klippy_or_skip
from reference import rms, serial, simulate_lsim, unbudgeted

pytestmark = pytest.mark.slow  # whole programs through Klipper's own planner

TOLERANCE_MM = 1e-3


@pytest.fixture(scope="module")
def klippy():
    return klippy_or_skip()


def run_by_klipper(tmp_path, source, profile, tolerance_mm=TOLERANCE_MM):
    """(plan of the original, compensated command, the written program as klippy runs it)."""
    target = tmp_path / "out.gcode"
    report = compensate_file(source, target, profile, CompensateOptions(flavor="klipper", tolerance_mm=tolerance_mm))
    plan = plan_blocks(read_gcode(source, "klipper", profile.home_mm), profile, firmware="klipper",
                       margins=RunMargins.for_profile(profile, flavor="klipper"))
    for axis in report.axes.values():  # the gain as the firmware runs the output, and as the command has it
        executed_gain = axis.rms_error_before_um / axis.rms_error_after_um
        assert executed_gain >= 0.9 * axis.rms_error_before_um / axis.rms_error_command_um
    return plan, compensated_samples(plan, with_travel(profile, "klipper")), executed(target, profile)


def beats_the_shapers(source, profile, written):
    """Klipper's plan of the original through the profile's modes, and of it under each of
    simulate's input shapers (tuned to the profile's modes), against ``written`` (samples of the
    written program as klippy runs it) through the same modes: FBS's RMS contour error at most half
    the best shaper's, its largest below the original's largest."""
    _, moves, original = klippy_run(source, profile, "klipper")
    path, printer = printed_path(*move_ends(moves))
    _, original_max = contour_um(modelled(original, profile), original, path, printer)
    fbs_rms, fbs_max = contour_um(modelled(written, profile), written, path, printer)
    best = min(contour_um(modelled(command, profile), padded, path, printer)[0]
               for command, padded, _ in shaped_plans(original, profile).values())
    assert fbs_rms <= 0.5 * best, f"{fbs_rms:.3g} um RMS, best shaper {best:.3g}"
    assert fbs_max < original_max


@pytest.mark.parametrize("name, tolerance_mm", [("butterfly-polyline", TOLERANCE_MM), ("butterfly-dense", 0.5e-3)])
def test_butterfly_runs_as_written(tmp_path, klippy, name, tolerance_mm):
    """The CAM butterflies (0.05 mm chords, and 1 ms blocks, at F6000) on the patent's stage at
    10 kHz; the same through fbspost's own model of Klipper (fbspost.firmware.planners, Klipper's rules).
    The dense one's command tracks to 0.8 um RMS: at 1 um the chords would add more than 10%."""
    profile = load_profile("patent-xy-stage")
    source = f"samples/{name}.gcode"
    plan, command, run = run_by_klipper(tmp_path, source, profile, tolerance_mm)
    assert run.duration_s == pytest.approx(plan.duration_s, rel=2e-3)
    t = np.arange(len(command)) / plan.sample_rate_hz
    off_mm = np.linalg.norm(run.at(t)[:, :2] - command[:, :2], axis=1)
    assert off_mm.max() <= tolerance_mm + 2e-3
    model = replan(list(read_gcode(tmp_path / "out.gcode", "klipper")), profile, "klipper")
    assert model.duration_s == pytest.approx(plan.duration_s, rel=2e-3)
    n = min(len(command), len(model.positions_mm))
    assert np.linalg.norm(model.positions_mm[:n, :2] - command[:n, :2], axis=1).max() <= tolerance_mm + 2e-3
    beats_the_shapers(source, profile, run.at(np.arange(round(run.duration_s * plan.sample_rate_hz) + 1)
                                              / plan.sample_rate_hz))


@pytest.mark.parametrize("name", ["gear-marlin2", "tube-marlin2", "pocket-klipper", "blob-reprap-relative-e",
                                  "bracket-reprapfirmware-relative-e"])
def test_sliced_print_runs_as_written(tmp_path, klippy, name):
    """Every sliced print's first 1000 lines on the two-mode printer, without a line budget
    (Klipper takes its lines from the host's file)."""
    source = tmp_path / f"{name}.gcode"
    with open(f"tests/data/{name}.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readlines()[:1000]))
    profile = unbudgeted(load_profile("printer-two-mode"))
    plan, command, run = run_by_klipper(tmp_path, source, profile)
    assert run.duration_s == pytest.approx(plan.duration_s, rel=2e-3)
    t = np.arange(len(command)) / plan.sample_rate_hz
    assert np.linalg.norm(run.at(t)[:, :2] - command[:, :2], axis=1).max() <= TOLERANCE_MM + 2e-3
    beats_the_shapers(source, profile, run.at(np.arange(round(run.duration_s * plan.sample_rate_hz) + 1)
                                              / plan.sample_rate_hz))


def klippy_gain(source, target, profile) -> tuple[float, float]:
    """(klippy's run of ``target``: its duration, the RMS contour error of klippy's run of ``source``
    over that of ``target``, both through the profile's modes, on the original's path)."""
    _, moves, original = klippy_run(source, profile, "klipper")
    path, printer = printed_path(*move_ends(moves))
    run = executed(target, profile)
    written = run.at(np.arange(round(run.duration_s * profile.sample_rate_hz) + 1) / profile.sample_rate_hz)
    return run.duration_s, (contour_um(modelled(original, profile), original, path, printer)[0]
                            / contour_um(modelled(written, profile), written, path, printer)[0])


@pytest.mark.parametrize("name, tolerance_mm", [("butterfly-polyline", TOLERANCE_MM), ("butterfly-dense", 0.5e-3)])
def test_butterfly_runs_within_klippers_max_velocity(tmp_path, klippy, name, tolerance_mm):
    """The butterflies at twice their size (the chords 0.1 mm at F6000, the dense blocks 2 ms) on
    a Klipper whose max_velocity is the axes' own 100 mm/s (the profile's [firmware] max_velocity):
    the compensated command moves along the path faster than that (up to sqrt(2) 100 mm/s where
    both axes run at their limit), so the output raises it around the compensated motion and gives
    it back (the dense one's command stays under it). Through klippy: the output runs within 0.2% of
    the plan's time and keeps 90% of the gain it has on a Klipper whose max_velocity is raised by
    hand (1000 mm/s). (Without the raise: the polyline's gain fell from 18.6x to 5.6x, 0.93% late.)"""
    source = tmp_path / f"{name}.gcode"
    source.write_text(re.sub(r"([XY])(-?\d+\.\d+)", lambda m: f"{m.group(1)}{2 * float(m.group(2)):.4f}",
                             open(f"samples/{name}.gcode").read()))
    base = load_profile("patent-xy-stage")
    gains = {}
    for velocity in (100.0, 1000.0):
        profile = replace(base, firmware=replace(base.firmware, max_velocity_mm_s=velocity))
        target = tmp_path / f"out-{velocity:g}.gcode"
        compensate_file(source, target, profile, CompensateOptions(flavor="klipper", tolerance_mm=tolerance_mm))
        plan = plan_blocks(read_gcode(source, "klipper", profile.home_mm), profile, firmware="klipper",
                           margins=RunMargins.for_profile(profile, flavor="klipper"))
        duration_s, gains[velocity] = klippy_gain(source, target, profile)
        assert duration_s == pytest.approx(plan.duration_s, rel=2e-3)
    assert "VELOCITY=141.421" in (tmp_path / "out-100.gcode").read_text()
    assert gains[100.0] >= 0.9 * gains[1000.0]


@pytest.mark.parametrize("name", ["gear-marlin2", "tube-marlin2", "pocket-klipper", "blob-reprap-relative-e",
                                  "bracket-reprapfirmware-relative-e"])
def test_sliced_print_stays_within_the_travel(tmp_path, klippy, name):
    """Every sliced print's first 3000 lines on the two-mode printer, through klippy's own range
    check with Klipper's default position_min 0 on X and Y: the output runs without "Move out of
    range" (before the travel's rows, the gear's first moves went to X-0.0006 Y-0.0018)."""
    source, target = tmp_path / f"{name}.gcode", tmp_path / "out.gcode"
    with open(f"tests/data/{name}.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readlines()[:3000]))
    profile = unbudgeted(load_profile("printer-two-mode"))
    compensate_file(source, target, profile, CompensateOptions(flavor="klipper"))
    for program in (source, target):
        KlippyPlanner(profile, travel=True).run(list(read_gcode(program, "klipper")))


def test_report_is_the_written_program_as_klipper_runs_it(tmp_path, klippy):
    """compensate's summary (after) is the tracking error of the written program as klippy runs
    it, through the modes (reference.simulate_lsim), over the runs and two periods of the
    lowest mode after each; before: the plan's. With 300 lines/s, blocks span
    several samples, so the written program is not the command."""
    source, target = tmp_path / "gear.gcode", tmp_path / "out.gcode"
    with open("tests/data/gear-marlin2.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readlines()[:1000]))
    profile = serial(load_profile("printer-two-mode"))
    report = compensate_file(source, target, profile, CompensateOptions(flavor="klipper"))
    plan = plan_blocks(read_gcode(source, "klipper", profile.home_mm), profile, firmware="klipper",
                       margins=RunMargins.for_profile(profile, flavor="klipper"))
    period_s = 1.0 / profile.sample_rate_hz
    for c, axis in enumerate("XY"):
        modes = profile.axes[axis].modes
        settle = math.ceil(2.0 / (min(m.frequency_hz for m in modes) * period_s))
        # the settling after the last run goes on past the program's end, the machine held there
        n = len(plan.positions_mm) + settle
        run = executed(target, profile).at(np.arange(n) * period_s)
        counted = np.zeros(n, dtype=bool)
        for first, last in plan.runs:
            counted[first:last + settle + 1] = True
        desired = np.pad(plan.positions_mm[:, c], (0, settle), mode="edge")
        before = desired - simulate_lsim(modes, period_s, desired)
        after = desired - simulate_lsim(modes, period_s, run[:, c])
        assert report.axes[axis].rms_error_before_um == pytest.approx(rms(before[counted]) * 1e3, rel=1e-3)
        assert report.axes[axis].rms_error_after_um == pytest.approx(rms(after[counted]) * 1e3, rel=0.05)
        # the chords show (with the travels planned faster, X's ran 3.43 um, the command's own 3.66)
        assert abs(report.axes[axis].rms_error_after_um / report.axes[axis].rms_error_command_um - 1) > 0.02


def test_verify_gives_klippys_figures(tmp_path, klippy):
    """--verify's figures (fbspost's model of Klipper's planner) are those of both programs as
    klippy itself plans them, through the modes, on klippy's moves of the original: print times
    to 0.2%, contour errors to 2%. With 300 lines/s, so that the written blocks are not the command."""
    source, target = tmp_path / "gear.gcode", tmp_path / "out.gcode"
    with open("tests/data/gear-marlin2.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readlines()[:1000]))
    profile = serial(load_profile("printer-two-mode"))
    report = compensate_file(source, target, profile, CompensateOptions(flavor="klipper", verify=True))
    seconds, moves, original = klippy_run(source, profile, "klipper")
    path, printer = printed_path(*move_ends(moves))
    run = executed(target, profile)
    written = run.at(np.arange(round(run.duration_s * profile.sample_rate_hz) + 1) / profile.sample_rate_hz)
    for verified, duration_s, samples in ((report.verified.original, seconds, original),
                                          (report.verified.output, run.duration_s, written)):
        rms_um, max_um = contour_um(modelled(samples, profile), samples, path, printer)
        assert verified.duration_s == pytest.approx(duration_s, rel=2e-3)
        assert verified.rms_um == pytest.approx(rms_um, rel=0.02)
        assert verified.max_um == pytest.approx(max_um, rel=0.02)
    assert not report.original_kept and report.verified.output.rms_um < report.verified.original.rms_um / 5
