"""--verify: both programs re-planned on the firmware's planner before the output is committed;
the original written unchanged where the output is no better there. (Its figures against
Klipper's own planner: tests/test_output_klipper.py.) The modelled motion against scipy.signal.lsim
of the continuous modes, the contour error and PathDistance against a brute-force distance to every
segment of the program as reference.execute reads it."""
import dataclasses
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost.cli import main
from fbspost.contour import PathDistance
from fbspost.firmware import linuxcnc_time
from fbspost.firmware import verify as verify_module
from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.firmware.planners import replan
from fbspost.firmware.reprap import commanded_pieces
from fbspost.firmware.verify import MAX_TIME_INCREASE, FirmwareResult, contour_um, modelled, printed_path
from fbspost.job import verification
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import execute, serial, simulate_lsim

DATA = Path(__file__).resolve().parent / "data"
SAMPLES = Path(__file__).resolve().parents[1] / "samples"


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
    # (and why: the time, as the verdict measured it)
    assert f"on the firmware's planner it runs {100 * verdict.time_increase:.2f}% longer than the original" in (
        " ".join(report.warnings))


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
    lines = result.stderr.splitlines()
    assert lines[0].endswith("(marlin): the output written"), lines[0]
    assert lines[1].startswith("result, verified on marlin's planner (fbspost's model of it), original -> output: "
                               "RMS contour error "), lines[1]  # the one result to go by, first
    assert lines[2].startswith("size: ") and " kB out; " in lines[2], lines[2]
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


@pytest.mark.parametrize("after, counted", [(0.01, False), (0.2, True)])
def test_a_sample_at_an_extrusions_end_does_not_print(after, counted):
    """Closed form: a line printed a sample at a time ends ``after`` of a sample past sample 5,
    then a travel leaves it; sample 5 alone is 30 um off the line. Extruding a hundredth of a
    sample on (klippy's timing runs microseconds off the written grid, so its E still rose there
    where the model's had stopped on the sample) it is the line's end and not counted; a fifth on,
    it prints."""
    path, printer = printed_path(np.array([[0, 0, 0, 0.0]]), np.array([[10, 0, 0, 1.0]]))
    x = np.append(np.arange(6.0), [5 + after, 5 + after])
    e = np.append(0.1 * np.arange(6.0), [0.5 + 0.1 * after] * 2)
    command = np.column_stack([x, [0] * 7 + [1.0], np.zeros(8), e])
    actual = command.copy()
    actual[5, 1] = 0.03
    rms_um, max_um = contour_um(actual, command, path, printer)
    assert max_um == pytest.approx(30.0 if counted else 0.0, abs=1e-9)
    assert rms_um == pytest.approx(30.0 / np.sqrt(5) if counted else 0.0, abs=1e-9)  # samples 1 to 5 or 1 to 4


def test_outputs_longer_than_a_chunk_are_verified_by_default(tmp_path, monkeypatch):
    """Verify streams, so it is on by default at any length: an output of many chunks (lowered to 500
    lines: the 400 lines give about 3000) is verified without asking, and no warning says otherwise."""
    monkeypatch.setattr(verify_module, "CHUNK_LINES", 500)
    monkeypatch.setattr(verify_module, "OVERLAP_LINES", 200)
    source, target = gear(tmp_path), tmp_path / "out.gcode"
    auto = compensate_file(source, target, load_profile("printer-two-mode"), CompensateOptions(flavor="marlin",
                                                                                                verify=None))
    assert auto.lines_out > 5 * 500
    assert auto.verified is not None and not any("not verified" in w for w in auto.warnings), auto.warnings


def whole_program(source: Path, program: Path, profile, flavor: str) -> FirmwareResult:
    """``program`` as the firmware's model plans it at once (planners.replan: no chunks), modelled
    at once, measured on the path of ``source`` searched at once: the verdict's independent reference."""
    pieces = [piece for _, _, p in commanded_pieces(read_gcode(source, flavor, profile.home_mm)) for piece in p]
    path, printer = printed_path(*(np.array(column)[:, :4] for column in zip(*pieces, strict=True)))
    motion = replan(list(read_gcode(program, flavor, profile.home_mm)), profile, flavor)
    command = motion.positions_mm[:, :4]
    return FirmwareResult(motion.duration_s, *contour_um(modelled(command, profile), command, path, printer))


def chunked(monkeypatch, source, output, profile, flavor, chunk_lines, overlap_lines):
    """verify's figures with chunks of ``chunk_lines``, slices of 997 samples and the path in groups
    of 64 pieces, 3 of them cached: every seam of the streaming crossed many times."""
    monkeypatch.setattr(verify_module, "SLICE_SAMPLES", 997)
    monkeypatch.setattr(verify_module, "GROUP_PIECES", 64)
    monkeypatch.setattr(verify_module, "_CACHED_GROUPS", 3)
    return verify_module.verify(source, output, profile, flavor, chunk_lines=chunk_lines, overlap_lines=overlap_lines)


def test_chunked_verdict_is_the_whole_programs_on_marlin(tmp_path, monkeypatch):
    """The gear's first 400 lines and their output (about 3000 lines) on the model of Marlin, in
    chunks of 150 lines (3 and about 20 chunks): print time, RMS and max contour error as the whole
    program planned, modelled and measured at once, to 1e-9."""
    profile, source, output = load_profile("printer-two-mode"), gear(tmp_path), tmp_path / "out.gcode"
    compensate_file(source, output, profile, CompensateOptions(flavor="marlin", verify=False))
    verdict = chunked(monkeypatch, source, output, profile, "marlin", 150, 100)
    for program, result in ((source, verdict.original), (output, verdict.output)):
        truth = whole_program(source, program, profile, "marlin")
        assert truth.rms_um > 1.0  # (um: there is an error to measure)
        for name in ("duration_s", "rms_um", "max_um"):
            assert getattr(result, name) == pytest.approx(getattr(truth, name), rel=1e-9), (program.name, name)


@pytest.mark.slow
def test_chunked_verdict_is_the_whole_programs_on_linuxcnc(tmp_path, monkeypatch):
    """The butterfly as CAM chords on the model of LinuxCNC's planner, in 4 chunks of 1000 lines:
    within 2 servo periods of the whole program's time and 0.5% (RMS) and 2% (max) of its
    contour error. (Not exact: a chunk from rest runs its servo periods at another phase of the
    program's samples.)"""
    profile, source = load_profile("patent-xy-stage"), SAMPLES / "butterfly-polyline.gcode"
    verdict = chunked(monkeypatch, source, source, profile, "linuxcnc", 1000, 300)
    truth = whole_program(source, source, profile, "linuxcnc")
    assert truth.rms_um > 10.0
    for result in (verdict.original, verdict.output):
        assert result.duration_s == pytest.approx(truth.duration_s, abs=2e-3)
        assert result.rms_um == pytest.approx(truth.rms_um, rel=5e-3)
        assert result.max_um == pytest.approx(truth.max_um, rel=2e-2)


def test_path_file_is_the_brute_force_distance(tmp_path, monkeypatch):
    """The original's path on disk in groups of 16 pieces, 3 cached, searched by their boxes: the
    distance of points around the gear's path and over its box, to every extruding segment, brute force."""
    monkeypatch.setattr(verify_module, "GROUP_PIECES", 16)
    monkeypatch.setattr(verify_module, "_CACHED_GROUPS", 3)
    source = gear(tmp_path, 300)
    starts, stops = extruding_segments(source)
    rng = np.random.default_rng(11)
    pick = rng.integers(len(starts), size=1500)
    near = starts[pick] + rng.random(1500)[:, None] * (stops - starts)[pick] + rng.normal(0.0, 0.3, (1500, 3))
    low, high = starts.min(axis=0) - 2.0, starts.max(axis=0) + 2.0
    points = np.concatenate([near, low + rng.random((1500, 3)) * (high - low)])
    with open(tmp_path / "path", "w+b") as store:
        path = verify_module._PathFile.of(source, load_profile("printer-two-mode"), "marlin", store)
        assert path.printer and len(path.groups) > 10
        distance = np.concatenate([path(part)[0] for part in np.array_split(points, 7)])
    truth, _ = brute_distance(starts, stops, points)
    np.testing.assert_allclose(distance, truth, rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_path_file_search_is_the_brute_force_distance_on_random_paths(monkeypatch, seed):
    """Random walks (some of their pieces not chosen, some of no length) in groups of 7 pieces, 2
    cached, whose boxes overlap, nest and lie apart: the distance of points along the walks,
    over their box and far beyond it, to every chosen piece, brute force (to rounding)."""
    monkeypatch.setattr(verify_module, "GROUP_PIECES", 7)
    monkeypatch.setattr(verify_module, "_CACHED_GROUPS", 2)
    rng = np.random.default_rng(seed)
    walks = [rng.normal(0.0, 5.0, 3) + np.cumsum(rng.normal(0.0, scale, (n, 3)), axis=0)
             for n, scale in ((120, 0.3), (80, 2.0), (60, 0.01), (150, 1.0))]
    ends = np.concatenate(walks)
    starts, stops = ends[:-1], ends[1:].copy()
    stops[::17] = starts[::17]  # (no length)
    chosen = rng.random(len(starts)) < 0.8
    path = verify_module._PathFile(np.column_stack([starts, stops, chosen]).astype(float), True)
    assert len(path.groups) > 40
    pick = rng.integers(len(starts), size=2000)
    along = starts[pick] + rng.random(2000)[:, None] * (stops - starts)[pick] + rng.normal(0.0, 0.05, (2000, 3))
    low, high = ends.min(axis=0), ends.max(axis=0)
    points = np.concatenate([along, low + rng.random((1000, 3)) * (high - low),
                             low + (rng.random((200, 3)) * 5.0 - 2.0) * (high - low)])
    distance = np.concatenate([path(part)[0] for part in np.array_split(points, 9)])
    truth, _ = brute_distance(starts[chosen], stops[chosen], points)
    np.testing.assert_allclose(distance, truth, rtol=0, atol=1e-12)


def test_a_jump_of_the_command_starts_the_modes_anew_at_rest():
    """A move from an unknown position is a jump in the firmware's motion (no model plans it):
    at rest on both sides, the modelled machine is where it is commanded (the modes' DC gain is
    1), not ringing with a 100 mm step."""
    profile = load_profile("printer-two-mode")
    command = np.zeros((400, 4))
    command[200:, :2] = [100.0, 50.0]
    np.testing.assert_allclose(modelled(command, profile), command, atol=1e-9)


_BOUNDED_DISTANCE = """
import sys
import numpy as np
from fbspost.contour import PathDistance
rng = np.random.default_rng(5)
# a scribble of 1000 pieces in a 20 um box and one piece of 0.24 mm: every point's nearest middles
# stay within half a piece of each other, so the search takes every piece (systems.ngc's case)
corners = np.vstack([rng.uniform(0, 0.02, (1001, 3)), [[0.24, 0, 0]]])
path = PathDistance(corners[:-1], corners[1:])
points = rng.uniform(-0.005, 0.025, (20_000, 3))
distance, nearest = path(points)
np.save(sys.argv[1], np.column_stack([distance, nearest]))
print(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")))
"""


@pytest.mark.slow
def test_path_distance_is_exact_and_bounded_on_a_path_smaller_than_its_pieces(tmp_path):
    """20k points against 1001 pieces that all lie within half a piece of each other: under a cap
    of 1 GB of address space (the search once grew to every piece for all points at once: over 2 GB
    here, and LinuxCNC's systems.ngc went past 14 GB), and exact against a brute-force distance to
    every piece."""
    def capped():
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))

    out = tmp_path / "distance.npy"
    done = subprocess.run([sys.executable, "-c", _BOUNDED_DISTANCE, str(out)], capture_output=True, text=True,
                          preexec_fn=capped, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) < 950_000  # kB of resident memory at most (800 MB seen)
    result = np.load(out)
    rng = np.random.default_rng(5)
    corners = np.vstack([rng.uniform(0, 0.02, (1001, 3)), [[0.24, 0, 0]]])
    points = rng.uniform(-0.005, 0.025, (20_000, 3))
    a, d = corners[:-1], np.diff(corners, axis=0)
    check = np.random.default_rng(1).choice(len(points), 2000, replace=False)
    p = points[check][:, None, :]
    u = np.clip(np.einsum("ijk,jk->ij", p - a, d) / np.einsum("jk,jk->j", d, d), 0.0, 1.0)
    brute = np.linalg.norm(p - (a + u[..., None] * d), axis=2).min(axis=1)
    np.testing.assert_allclose(result[check, 0], brute, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(points[check] - result[check, 1:], axis=1), brute, rtol=0, atol=1e-15)


def gear_motion(tmp_path, lines=300):
    """(profile, the gear's first ``lines`` as Klipper's rules plan them: X Y Z E per sample, its file)."""
    profile, source = load_profile("printer-two-mode"), gear(tmp_path, lines)
    command = replan(list(read_gcode(source, "klipper", profile.home_mm)), profile, "klipper").positions_mm[:, :4]
    return profile, command, source


def brute_distance(starts, ends, points):
    """(distance, nearest point) from every point to every segment, the nearest kept."""
    d = ends - starts
    length2 = np.einsum("ij,ij->i", d, d)
    distance, nearest = np.empty(len(points)), np.empty_like(points)
    for k in range(0, len(points), 64):
        p = points[k:k + 64, None, :]
        u = np.clip(np.einsum("kij,ij->ki", p - starts, d) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        on = starts + u[..., None] * d
        gap = np.linalg.norm(p - on, axis=2)
        best = gap.argmin(axis=1)
        distance[k:k + 64], nearest[k:k + 64] = gap.min(axis=1), on[np.arange(len(best)), best]
    return distance, nearest


def extruding_segments(source):
    """XYZ starts and ends of the moves that extrude, as an independent reader runs the program."""
    ends = np.array(execute(source).ends)[:, 1:]
    extruding = (np.diff(ends[:, 3]) > 0) & (np.linalg.norm(np.diff(ends[:, :3], axis=0), axis=1) > 0)
    return ends[:-1][extruding, :3], ends[1:][extruding, :3]


def test_modelled_is_lsim_of_the_modes(tmp_path):
    """A sliced print's planned command, then a jump of 100 mm and the same again from there:
    each part scipy.signal.lsim of the continuous modes from rest at its start (zero-order hold,
    as the firmware's samples are held); Z and E, without modes, as commanded."""
    profile, command, _ = gear_motion(tmp_path)
    period_s = 1.0 / profile.sample_rate_hz
    # (no jump inside the print: the planner keeps to the top speed, half the jump threshold)
    assert np.abs(np.diff(command[:, :2], axis=0)).max() <= 300.0 * period_s * (1 + 1e-9)
    parts = [command, command + [100.0, 50.0, 0.0, 0.0]]
    actual = modelled(np.concatenate(parts), profile)
    for axis, column in (("X", 0), ("Y", 1)):
        modes = profile.axes[axis].modes
        truth = np.concatenate([simulate_lsim(modes, period_s, part[:, column]) for part in parts])
        assert np.abs(truth - np.concatenate(parts)[:, column]).max() > 0.01  # (the modes lag: a real check)
        np.testing.assert_allclose(actual[:, column], truth, rtol=0, atol=1e-10)
    assert np.array_equal(actual[:, 2:], np.concatenate(parts)[:, 2:])


def test_path_distance_is_the_brute_force_distance(tmp_path):
    """PathDistance on a sliced print's extruding moves: distance and nearest point of points
    scattered around the path (0.7 mm sd) and over its box and 2 mm beyond, to every segment.
    (The box's points are those whose 4 nearest piece middles can miss the nearest piece: the
    search must widen for them.)"""
    starts, stops = extruding_segments(gear(tmp_path, 300))
    assert len(starts) > 150
    rng = np.random.default_rng(7)
    pick = rng.integers(len(starts), size=1500)
    near = starts[pick] + rng.random(1500)[:, None] * (stops - starts)[pick] + rng.normal(0.0, 0.7, (1500, 3))
    low, high = starts.min(axis=0) - 2.0, starts.max(axis=0) + 2.0
    points = np.concatenate([near, low + rng.random((3000, 3)) * (high - low)])
    distance, nearest = PathDistance(starts, stops)(points)
    truth, truth_nearest = brute_distance(starts, stops, points)
    np.testing.assert_allclose(distance, truth, rtol=0, atol=1e-12)
    np.testing.assert_allclose(nearest, truth_nearest, rtol=0, atol=1e-12)


def test_contour_error_is_the_brute_force_distance_of_the_modelled_motion(tmp_path):
    """verify's figures on a sliced print: the modelled motion (lsim of the modes) at the samples
    whose E rises on both sides (``verify.END_SLIVER``), its distance to every extruding segment of the program as an
    independent reader runs it, brute force: RMS and max."""
    profile, command, source = gear_motion(tmp_path)
    blocks = list(read_gcode(source, "klipper", profile.home_mm))
    pieces = [piece for _, _, p in commanded_pieces(blocks) for piece in p]
    path, printer = printed_path(*(np.array(column)[:, :4] for column in zip(*pieces, strict=True)))
    rms_um, max_um = contour_um(modelled(command, profile), command, path, printer)
    period_s = 1.0 / profile.sample_rate_hz
    actual = np.column_stack([simulate_lsim(profile.axes[a].modes, period_s, command[:, i])
                              for i, a in enumerate("XY")])
    e = command[:, 3]
    # E rises on both sides, neither rise under a tenth of the other (a sliver: an extrusion's end)
    printing = [k for k in range(1, len(e) - 1)
                if min(e[k] - e[k - 1], e[k + 1] - e[k]) > 0.1 * max(e[k] - e[k - 1], e[k + 1] - e[k])]
    assert printer and len(printing) > 1000
    points = np.column_stack([actual[printing], command[printing, 2]])
    truth, _ = brute_distance(*extruding_segments(source), points)
    # (1e-11 mm: the two simulations' rounding over 14000 samples)
    assert max_um == pytest.approx(truth.max() * 1e3, rel=0, abs=1e-8)
    assert rms_um == pytest.approx(np.sqrt(np.mean(truth**2)) * 1e3, rel=0, abs=1e-8)
    assert 1.0 < rms_um < max_um  # (um: the modes' error is there to measure)


@pytest.mark.parametrize("flavor, make", [("marlin", "gear"), ("marlin", "coarse"), ("reprap", "gear"),
                                          ("klipper", "gear"), ("linuxcnc", "butterfly")])
def test_the_check_beside_the_compensation_gives_the_verdict_of_the_written_file(tmp_path, monkeypatch, flavor, make):
    """The check in its own process, reading the output as it is written (announced every 4 kB,
    read 997 bytes at a time: lines split across reads), gives the verdict of ``verify`` on the
    file once written, to the last bit, and keeps or replaces the output as that verdict says
    (the coarse Marlin: the original kept)."""
    monkeypatch.setattr(verification, "_ANNOUNCE_BYTES", 4096)
    monkeypatch.setattr(verify_module, "FOLLOW_BYTES", 997)
    if make == "butterfly":
        profile, source = load_profile("patent-xy-stage"), tmp_path / "butterfly.ngc"
        source.write_bytes(b"".join((SAMPLES / "butterfly-polyline.gcode").read_bytes().splitlines(True)[:800]))
    else:
        profile, source = coarse_marlin() if make == "coarse" else load_profile("printer-two-mode"), gear(tmp_path)
    unchecked, checked = tmp_path / "unchecked.gcode", tmp_path / "checked.gcode"
    compensate_file(source, unchecked, profile, CompensateOptions(flavor=flavor, verify=False))
    report = compensate_file(source, checked, profile, CompensateOptions(flavor=flavor, verify=True))
    truth = verify_module.verify(source, unchecked, profile, flavor, report.added_time_s)
    assert report.verified == truth and truth.original.rms_um > 0.1
    assert report.original_kept == (not truth.better) == (make == "coarse")
    assert checked.read_bytes() == (source if report.original_kept else unchecked).read_bytes()
    assert {p.name for p in tmp_path.iterdir()} == {source.name, checked.name, unchecked.name}  # (no temporary file)


class _Told:
    """A channel's messages, given in order (``verify.following``'s)."""

    def __init__(self, messages):
        self.messages = iter(messages)

    def get(self):
        return next(self.messages)


def test_following_gives_the_lines_of_a_file_as_it_is_written(tmp_path, monkeypatch):
    """A file told in three lengths (one within a line), read 7 bytes at a time: its lines as
    iterating over the file gives them, a lone CR within a line and an unterminated last line
    included."""
    monkeypatch.setattr(verify_module, "FOLLOW_BYTES", 7)
    text = b"G1 X1\r\n; a comment\rwith a CR\nG1 Y2 F600\n\nM84"
    written = tmp_path / "out.gcode"
    written.write_bytes(text)
    name, lines = verify_module.following(_Told([(str(written), 10, False), (str(written), 30, False),
                                                 (str(written), len(text), True)]))
    with open(written, "rb") as f:
        assert name == written and list(lines) == list(f) and len(list(f.seek(0) or f)) == 5


def test_linuxcnc_original_is_planned_once_by_the_check_and_the_output_is_the_same(tmp_path, monkeypatch):
    """LinuxCNC, in chunks of 300 lines: with the check, this process plans none of the original's
    chunks on the model of LinuxCNC's planner (the check's plan gives the feeds, linuxcnc_time);
    without it, it plans each one; the written output is the same byte for byte."""
    monkeypatch.setattr(verify_module, "CHUNK_LINES", 300)
    monkeypatch.setattr(verify_module, "OVERLAP_LINES", 100)
    planned = []
    monkeypatch.setattr(linuxcnc_time, "run_linuxcnc", lambda blocks, profile: planned.append(len(blocks))
                        or run_linuxcnc(blocks, profile))
    profile, source = load_profile("patent-xy-stage"), tmp_path / "butterfly.ngc"
    source.write_bytes(b"".join((SAMPLES / "butterfly-polyline.gcode").read_bytes().splitlines(True)[:1000]))
    unchecked, checked = tmp_path / "unchecked.ngc", tmp_path / "checked.ngc"
    compensate_file(source, unchecked, profile, CompensateOptions(flavor="linuxcnc", verify=False))
    assert len(planned) == 4  # lines 1-300, 301-600, 601-900, 901-1000 (each with its overlap)
    report = compensate_file(source, checked, profile, CompensateOptions(flavor="linuxcnc", verify=True))
    assert len(planned) == 4 and report.verified is not None and not report.original_kept
    assert checked.read_bytes() == unchecked.read_bytes()
