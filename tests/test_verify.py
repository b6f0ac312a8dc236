"""--verify: both programs re-planned on the firmware's planner before the output is committed;
the original written unchanged where the output is no better there. (Its figures against
Klipper's own planner: tests/test_output_klipper.py.)"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost import pipeline
from fbspost.cli import main
from fbspost.pipeline import CompensateOptions, compensate_file
from fbspost.profile import load_profile
from fbspost.simulate import PathDistance
from fbspost.verify import MAX_TIME_INCREASE, contour_um, modelled, printed_path
from reference import serial

DATA = Path(__file__).resolve().parent / "data"


def gear(tmp_path, lines=400) -> Path:
    source = tmp_path / "gear.gcode"
    with open(DATA / "gear-marlin2.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readlines()[:lines]))
    return source


def coarse_marlin():
    """The two-mode printer on Marlin at 5 steps/mm (0.2 mm steps) and Marlin's 6-step minimum:
    no block can be shorter than 1.2 mm, so the compensated command cannot be carried; fed at
    300 lines/s."""
    profile = serial(load_profile("printer-two-mode"))
    firmware = dataclasses.replace(profile.firmware, steps_per_mm={"X": 5.0, "Y": 5.0, "Z": 400.0, "E": 415.0},
                                   min_steps_per_segment=6)
    return dataclasses.replace(profile, firmware=firmware)


def test_the_original_is_kept_where_the_firmware_runs_the_output_worse(tmp_path):
    source, target = gear(tmp_path), tmp_path / "out.gcode"
    report = compensate_file(source, target, coarse_marlin(), CompensateOptions(flavor="marlin", verify=True))
    verdict = report.verified
    # Marlin's merge: the output runs long, beyond fbspost's margins
    assert verdict.output.duration_s > (1 + MAX_TIME_INCREASE) * verdict.original.duration_s + report.added_time_s + 1.0
    assert report.original_kept and target.read_bytes() == source.read_bytes()
    assert report.lines_out == report.lines_in == 400
    assert "the original was written unchanged" in " ".join(report.warnings)


def test_in_place_with_verify_leaves_the_input_where_the_original_is_kept(tmp_path):
    source = gear(tmp_path)
    before = source.read_bytes()
    report = compensate_file(source, source, coarse_marlin(), CompensateOptions(flavor="marlin", verify=True))
    assert report.original_kept and source.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gear.gcode"]  # no temporary file left


def test_marlin_is_verified_by_default_and_the_better_output_kept(tmp_path):
    """Marlin at 80 steps/mm, 300 lines/s: verified without asking, the output kept, its figures
    said; Klipper (which runs the blocks as written) is not verified unless asked."""
    source, target = gear(tmp_path), tmp_path / "out.gcode"
    result = CliRunner().invoke(main, ["compensate", str(source), "-m", "printer-two-mode", "--flavor", "marlin",
                                       "-o", str(target)])
    assert result.exit_code == 0, result.output
    assert "verified on marlin's planner (model)" in result.stderr and "the output kept" in result.stderr
    assert target.read_bytes() != source.read_bytes()
    for flags, verified in (([], False), (["--verify"], True)):
        result = CliRunner().invoke(main, ["compensate", str(source), "-m", "printer-two-mode", "--flavor", "klipper",
                                           "-o", str(target), *flags])
        assert result.exit_code == 0, result.output
        assert ("verified on klipper's planner" in result.stderr) == verified


def test_contour_error_is_the_distance_to_the_printed_path():
    """Closed form: a square's extruding sides; points off them by known distances, E rising
    around all but the last (not printing: not counted)."""
    corners = np.array([[0, 0, 0, 0], [10, 0, 0, 1], [10, 10, 0, 2], [0, 10, 0, 3], [0, 0, 0, 4.0]])
    path, printer = printed_path(corners[:-1], corners[1:])
    assert printer and isinstance(path, PathDistance)
    command = np.array([[5, 0, 0, 0], [5, 0, 0, 0.1], [10, 5, 0, 0.2], [5, 10, 0, 0.3], [5, 5, 0, 0.3]])
    actual = command + np.array([[0, 0.003, 0, 0], [0, -0.004, 0, 0], [0.002, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    rms_um, max_um = contour_um(actual, command, path, printer)
    # printing samples: 1 (E rises before and after) and 2; sample 0 and the last two are not
    assert max_um == pytest.approx(4.0)
    assert rms_um == pytest.approx(np.sqrt((4.0**2 + 2.0**2) / 2))


def test_long_prints_are_not_verified_unless_asked(tmp_path, monkeypatch):
    """By default an output over VERIFY_AUTO_LINES is not verified (every block held at once), and
    the summary says so; --verify does it anyway."""
    monkeypatch.setattr(pipeline, "VERIFY_AUTO_LINES", 1000)  # the 400 lines give about 3000
    source, target = gear(tmp_path), tmp_path / "out.gcode"
    auto = compensate_file(source, target, load_profile("printer-two-mode"), CompensateOptions(flavor="marlin",
                                                                                                verify=None))
    assert auto.verified is None and any("not verified" in w for w in auto.warnings)
    asked = compensate_file(source, target, load_profile("printer-two-mode"), CompensateOptions(flavor="marlin",
                                                                                                 verify=True))
    assert asked.verified is not None and not any("not verified" in w for w in asked.warnings)


def test_a_jump_of_the_command_starts_the_modes_anew_at_rest():
    """A move from an unknown position is a jump in the firmware's motion (no model plans it):
    at rest on both sides, the modelled machine is where it is commanded (the modes' DC gain is
    1), not ringing with a 100 mm step."""
    profile = load_profile("printer-two-mode")
    command = np.zeros((400, 4))
    command[200:, :2] = [100.0, 50.0]
    np.testing.assert_allclose(modelled(command, profile), command, atol=1e-9)
