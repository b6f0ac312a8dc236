"""Real slicer output on the printer profile (bedslinger-example): every non-motion line and the
extrusion exact, the output within the axes' limits, the contour error per layer through the
modes (scipy's exact discretization, tests/reference.py) and the print's time."""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from fbspost.fbs.fallback import FALLBACK
from fbspost.job.pipeline import SHAPING_LEFT_OFF, compensate_file
from fbspost.job.report import Report
from fbspost.plan.pieces import CLAMPED
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import INSERTED, Executed, contour_error, execute, modelled_xy, rms, sample_blocks, unbudgeted

DATA = Path(__file__).resolve().parent / "data"
PRINTER = unbudgeted(load_profile("bedslinger-example"))  # (the line budget's cost: test_output_marlin)

CORPUS = ["gear-marlin2.gcode", "blob-reprap-relative-e.gcode",
          # Short prints sliced here by tests/data/make_sliced.py (PrusaSlicer 2.5).
          "tube-marlin2.gcode", "pocket-klipper.gcode", "bracket-reprapfirmware-relative-e.gcode"]


@dataclass
class Sliced:
    source: Path
    report: Report
    original: Executed  # the source as the reference executor runs it
    compensated: Executed  # the output likewise (a whole print's output: tens of seconds to run)


@pytest.fixture(scope="module", params=CORPUS)
def sliced(request, tmp_path_factory):
    source = DATA / request.param
    target = tmp_path_factory.mktemp("sliced") / request.param
    report = compensate_file(source, target, PRINTER)
    return Sliced(source, report, execute(source), execute(target))


@pytest.mark.slow
def test_sliced_nonmotion_lines_and_extrusion_exact(sliced):
    original, compensated = sliced.original, sliced.compensated
    known = set(original.nonmotion)
    inserted = [line for line in compensated.nonmotion if line not in known]
    kept = [line for line in compensated.nonmotion if line in known]
    assert kept == original.nonmotion  # every non-motion line, byte-exact, in order
    for line in inserted:  # what fbspost adds: its header, the firmware's settings, mode lines
        assert line.startswith(INSERTED), line
    # E at every non-motion line of the original, matched in order, within 1e-4 mm.
    e_out = [
        e
        for line, e in zip(compensated.nonmotion, compensated.e_at_lines, strict=True)
        if line in known
    ]
    assert np.abs(np.array(e_out) - np.array(original.e_at_lines)).max() <= 1e-4
    assert abs(compensated.extruded - original.extruded) <= 1e-4


@pytest.mark.slow
def test_sliced_output_within_axis_limits(sliced):
    """Run block by block, the output never asks an axis for more than the profile allows:
    velocity per block, and acceleration from block to block (5% for the chords' approximation
    of the sampled command, as for the butterfly). On RRF, beyond that, the speed change at once
    its M566 allows where pieces meld, which fbspost's plan of it makes as RRF does (X and Y: the
    profile's square corner velocity; the original as RRF runs it makes them too)."""
    report = sliced.report
    # (Z moves at travel feeds; stretches where compensating would raise the modelled error)
    # (and the profile states no input shaping: the output leaves it off, and says so)
    assert not [w for w in report.warnings if not w.startswith((CLAMPED, FALLBACK, SHAPING_LEFT_OFF))]
    ends = np.array(sliced.compensated.ends)
    jump_mm_s = PRINTER.planner_square_corner_velocity_mm_s if report.flavor == "reprap" else 0.0
    dt = np.diff(ends[:, 0])
    moving = dt > 0
    for column, name in ((1, "X"), (2, "Y")):
        axis = PRINTER.axes[name]
        velocity = np.diff(ends[:, column])[moving] / dt[moving]
        assert np.abs(velocity).max() <= axis.max_velocity_mm_s * (1 + 1e-3), name
        mid_dt = (dt[moving][1:] + dt[moving][:-1]) / 2
        ramped = np.maximum(np.abs(np.diff(velocity)) - jump_mm_s, 0.0)
        assert (ramped / mid_dt).max() <= axis.max_acceleration_mm_s2 * 1.05, name


@pytest.mark.slow
def test_sliced_contour_error_time_and_speed(sliced):
    original, compensated = sliced.original, sliced.compensated
    period_s = 1.0 / PRINTER.sample_rate_hz
    plan = plan_blocks(list(read_gcode(sliced.source, sliced.report.flavor)), PRINTER)
    _, command = sample_blocks(compensated.ends, PRINTER.sample_rate_hz)
    # Print time within 3% of the planned original (compute speed is bench/'s business).
    assert abs(compensated.ends[-1][0] - plan.duration_s) <= 0.03 * plan.duration_s
    # Per layer, extruding motion: contour error of the modelled machine against the original path.
    ends = np.array(original.ends)
    extruding = np.diff(ends[:, 4]) > 0
    before_xy = modelled_xy(PRINTER, plan.positions_mm[:, :2], period_s)
    after_xy = modelled_xy(PRINTER, command[:, :2], period_s)
    plan_extruding = np.append(np.diff(plan.positions_mm[:, 3]) > 0, False)
    run_extruding = np.append(np.diff(command[:, 3]) > 0, False)
    layers = np.unique(np.round(ends[1:][extruding, 3], 3))
    checked = 0
    for z in layers:
        segments = extruding & (np.round(ends[1:, 3], 3) == z)
        pieces = [np.array([ends[i, 1:3], ends[i + 1, 1:3]]) for i in np.flatnonzero(segments)]
        path = np.concatenate(pieces)
        in_plan = plan_extruding & (np.abs(plan.positions_mm[:, 2] - z) < 1e-6)
        in_run = run_extruding & (np.abs(command[:, 2] - z) < 1e-6)
        if in_plan.sum() < 200 or in_run.sum() < 200:
            continue
        before = rms(contour_error(path, before_xy[in_plan]))
        after = rms(contour_error(path, after_xy[in_run]))
        assert after * 5 <= before, f"layer z={z}: {before * 1e3:.2f} -> {after * 1e3:.2f} um"
        checked += 1
    assert checked >= 3


