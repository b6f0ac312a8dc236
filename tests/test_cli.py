"""The fbspost command: version, profile listing, the trajectory job, several programs at once
(--jobs), and one-line errors."""
import multiprocessing
import os
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost.cli import main
from fbspost.job import pipeline
from fbspost.profile import bundled_profiles, load_profile
from reference import rms, simulate_lsim


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def write_csv(path, header, rows):
    path.write_text(header + "\n" + "".join(",".join(r) + "\n" for r in rows))
    return path


def move_csv(path, sample_rate_hz=10000.0, seconds=0.25):
    """A minimum-jerk 2 mm move on X and Y, then rest, with a Z column the profile does not model."""
    n = int(seconds * sample_rate_hz) + 1
    t = np.arange(n) / sample_rate_hz
    s = np.clip(t / (0.6 * seconds), 0, 1)
    x = 2.0 * (10 * s**3 - 15 * s**4 + 6 * s**5)
    rows = [(f"{ti:.4f}", f"{xi:.9f}", f"{-xi / 2:.9f}", "0.200") for ti, xi in zip(t, x, strict=True)]
    return write_csv(path, "time_s,X,Y,Z", rows)


def test_version_matches_the_installed_package():
    result = run("--version")
    assert result.exit_code == 0
    assert version("fbspost") in result.output


def test_console_script_runs():
    out = subprocess.run(["fbspost", "--help"], capture_output=True, text=True, check=True)
    for command in ("machines", "trajectory"):
        assert command in out.stdout


def test_machines_lists_every_bundled_profile_on_one_line():
    result = run("machines")
    assert result.exit_code == 0
    lines = result.output.strip().splitlines()
    assert sorted(line.split()[0] for line in lines) == sorted(bundled_profiles())
    assert {"patent-xy-stage", "bedslinger-example"} <= set(bundled_profiles())


def test_trajectory_compensates_modelled_axes_and_copies_the_rest(tmp_path):
    source = move_csv(tmp_path / "move.csv")
    original = source.read_bytes()
    out = tmp_path / "out.csv"
    result = run("trajectory", source, "--machine", "patent-xy-stage", "-o", out)
    assert result.exit_code == 0, result.output
    assert source.read_bytes() == original  # the input is never modified
    header = out.read_text().splitlines()[0]
    assert header == "time_s,X,Y,Z"
    inp = np.loadtxt(source, delimiter=",", skiprows=1)
    got = np.loadtxt(out, delimiter=",", skiprows=1)
    assert got.shape == inp.shape
    assert [r.split(",")[0] for r in out.read_text().splitlines()[1:]] == \
           [r.split(",")[0] for r in source.read_text().splitlines()[1:]]
    assert np.array_equal(got[:, 3], inp[:, 3])  # Z has no modes: copied
    profile = load_profile("patent-xy-stage")
    for column, axis in ((1, "X"), (2, "Y")):
        modes = profile.axes[axis].modes
        # After the first 50 ms: the move starts with a jerk step that no causal command can follow.
        before = rms((inp[:, column] - simulate_lsim(modes, 1e-4, inp[:, column]))[500:])
        after = rms((inp[:, column] - simulate_lsim(modes, 1e-4, got[:, column]))[500:])
        assert after < before / 50
    assert "axis X" in result.stderr and "axis Z: no modes" in result.stderr


def test_quiet_prints_nothing(tmp_path):
    result = run("trajectory", move_csv(tmp_path / "m.csv", seconds=0.05), "-m", "patent-xy-stage", "-q")
    assert result.exit_code == 0 and result.stderr == "" and (tmp_path / "m-compensated.csv").exists()


@pytest.mark.parametrize("header, rows, line, words", [
    ("time_s,X", [("0.0000", "1"), ("0.0001", "abc")], 3, "not a number"),
    ("time_s,X", [("0.0000", "1"), ("0.0001", "nan")], 3, "finite"),
    ("time_s,X", [("0.0000", "1"), ("0.0001", "1", "2")], 3, "expected 2 values"),
    ("time_s,X", [("0.0000", "1"), ("0.0001", "1"), ("0.0003", "1")], 4, "time step"),
    ("time_s,Q", [("0.0000", "1")], 1, "not an axis letter"),
])
def test_bad_csv_is_one_line_error_with_file_and_line(tmp_path, header, rows, line, words):
    source = write_csv(tmp_path / "bad.csv", header, rows)
    out = tmp_path / "out.csv"
    result = run("trajectory", source, "-m", "patent-xy-stage", "-o", out)
    assert result.exit_code == 1
    message = result.stderr.strip()
    assert message.count("\n") == 0 and "Traceback" not in message
    assert message.startswith(f"error: {source}:{line}: ") and words in message
    assert not out.exists() and list(tmp_path.iterdir()) == [source]


def test_bad_profile_is_one_line_error_naming_file_and_key(tmp_path):
    text = bundled_profiles()["patent-xy-stage"].read_text()
    profile = tmp_path / "stage.toml"
    profile.write_text(text.replace("damping = 0.540", "damping = 1.5"))
    source = move_csv(tmp_path / "m.csv", seconds=0.05)
    result = run("trajectory", source, "-m", profile, "-o", tmp_path / "out.csv")
    assert result.exit_code == 1
    assert result.stderr.strip().count("\n") == 0
    assert str(profile) in result.stderr and "axes.X.modes[1].damping" in result.stderr
    assert not (tmp_path / "out.csv").exists()


def test_unknown_machine_name_is_reported():
    result = run("trajectory", "nothing.csv", "-m", "no-such-machine")
    assert result.exit_code == 1 and "no-such-machine" in result.stderr and "patent-xy-stage" in result.stderr


def test_main_module_error_has_no_traceback(tmp_path):
    """Through the real entry point, a missing input file is one line and exit status 1."""
    proc = subprocess.run([sys.executable, "-m", "fbspost.cli", "trajectory", str(tmp_path / "none.csv"),
                           "-m", "patent-xy-stage"], capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


# ---- several programs: compensate INPUT... --jobs N ----------------------------------------------

BUTTERFLY = Path(__file__).resolve().parent.parent / "samples" / "butterfly-dense.gcode"


@pytest.fixture(scope="module")
def programs(tmp_path_factory):
    """Three short programs (the butterfly's first lines, to the planner's stop at their end, so
    that they take a second each), name -> (program, its output from a single-file run)."""
    lines = BUTTERFLY.read_bytes().splitlines(keepends=True)
    folder = tmp_path_factory.mktemp("single")
    out = {}
    for n in (40, 60, 120):
        source, target = folder / f"part{n}.gcode", folder / f"part{n}.out"
        source.write_bytes(b"".join(lines[:n]))
        result = run("compensate", source, "-m", "patent-xy-stage", "-q", "-o", target)
        assert result.exit_code == 0, result.output
        out[source.name] = (source.read_bytes(), target.read_bytes())
    return out


def copy_programs(folder, programs):
    for name, (program, _) in programs.items():
        (folder / name).write_bytes(program)
    return [folder / name for name in programs]


def assert_one_line_errors(stderr):
    assert "Traceback" not in stderr
    starts = ("error: ", "fbspost ", "result, ", "size: ", "predictions, ", "  axis ", "  the written blocks: ",
              "warning: ")
    assert all(line.startswith(starts) for line in stderr.splitlines())


def test_jobs_write_the_single_file_outputs_in_place(tmp_path, programs):
    paths = copy_programs(tmp_path, programs)
    result = run("compensate", *paths, "-m", "patent-xy-stage", "--jobs", "2")
    assert result.exit_code == 0, result.output
    for path in paths:
        assert path.read_bytes() == programs[path.name][1]
        assert f"fbspost {version('fbspost')}: {path} -> {path} on patent-xy-stage" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(programs)  # no temporary file left
    assert_one_line_errors(result.stderr)


def test_output_dir_keeps_the_inputs(tmp_path, programs):
    paths = copy_programs(tmp_path, programs)
    result = run("compensate", *paths, "-m", "patent-xy-stage", "-j", "2", "-q", "--output-dir", tmp_path / "out")
    assert result.exit_code == 0 and result.stderr == "", result.output
    for path in paths:
        assert path.read_bytes() == programs[path.name][0]
        assert (tmp_path / "out" / path.name).read_bytes() == programs[path.name][1]


def test_one_bad_file_fails_alone_and_is_left_unchanged(tmp_path, programs):
    paths = copy_programs(tmp_path, programs)
    bad = tmp_path / "bad.gcode"
    bad.write_bytes(programs["part40.gcode"][0] + b"G1 X1 F-5\n")
    original = bad.read_bytes()
    result = run("compensate", paths[0], bad, *paths[1:], "-m", "patent-xy-stage", "--jobs", "2")
    assert result.exit_code == 1
    assert bad.read_bytes() == original
    for path in paths:
        assert path.read_bytes() == programs[path.name][1]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*programs, "bad.gcode"])
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert errors == [f"error: {bad}:41: feed F-5 must be positive", f"error: 1 of 4 files failed: {bad}"]
    assert result.stderr.splitlines()[-1] == errors[-1]
    assert_one_line_errors(result.stderr)


def test_unexpected_exception_is_one_line_naming_the_file(tmp_path, programs, monkeypatch):
    """Sequential (--jobs 1), so that the patched pipeline is the one that runs on any platform."""
    first, second = copy_programs(tmp_path, programs)[:2]
    compensate_file = pipeline.compensate_file  # (the commands import their stages when run)

    def broken(source, *args, **kwargs):
        if source == second:
            raise RuntimeError("solver exploded\non two lines")
        return compensate_file(source, *args, **kwargs)

    monkeypatch.setattr(pipeline, "compensate_file", broken)
    result = run("compensate", first, second, "-m", "patent-xy-stage", "-q")
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"error: {second}: internal error: RuntimeError: solver exploded on two lines",
        f"error: 1 of 2 files failed: {second}",
    ]
    assert first.read_bytes() == programs[first.name][1] and second.read_bytes() == programs[second.name][0]


@pytest.mark.skipif(multiprocessing.get_start_method() != "fork", reason="the workers must inherit the patch")
def test_a_worker_that_dies_fails_only_its_file(tmp_path, programs, monkeypatch):
    paths = copy_programs(tmp_path, programs)
    compensate_file = pipeline.compensate_file  # (the commands import their stages when run)

    def killed(source, *args, **kwargs):
        if source == paths[1]:
            # Dies the moment the other worker has written its file in place, before the pool
            # can deliver that result: the pool then counts it lost with the dead worker's.
            while paths[0].read_bytes() == programs[paths[0].name][0]:
                time.sleep(0.001)
            os._exit(9)  # as the kernel's out-of-memory killer would end it
        return compensate_file(source, *args, **kwargs)

    monkeypatch.setattr(pipeline, "compensate_file", killed)
    result = run("compensate", *paths, "-m", "patent-xy-stage", "-q", "--jobs", "2")
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [f"error: {paths[1]}: its worker process died (killed, or out of memory?)",
                                          f"error: 1 of 3 files failed: {paths[1]}"]
    for path in paths:
        assert path.read_bytes() == programs[path.name][path != paths[1]]


@pytest.mark.parametrize("args, words", [
    (["b.gcode", "-o", "out.gcode"], "-o/--output takes one INPUT"),
    (["-o", "out.gcode", "--output-dir", "out"], "-o/--output takes one INPUT"),
    (["b.gcode", "--report", "r.json"], "--report takes one INPUT"),
    (["./a.gcode"], "would both be written to"),
    (["sub/a.gcode", "--output-dir", "out"], "would both be written to"),
])
def test_several_inputs_that_would_clash_are_usage_errors(tmp_path, monkeypatch, args, words):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    for name in ("a.gcode", "b.gcode", "sub/a.gcode"):
        (tmp_path / name).write_text("G1 X1 F600\n")
    result = run("compensate", "a.gcode", *args, "-m", "patent-xy-stage")
    assert result.exit_code == 2 and words in result.stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.gcode", "a.gcode", "b.gcode", "sub"]


@pytest.mark.parametrize("flavor", ["klipper", "reprap"])
def test_g5_is_refused_for_a_flavor_without_g5(tmp_path, flavor):
    program = tmp_path / "part.gcode"
    program.write_text("G21\nG90\nG1 X0 Y0 F3000\nG1 X10 Y5\nG1 X20 Y0\n")
    original = program.read_bytes()
    result = run("compensate", "-m", "bedslinger-example", "--format", "g5", "--flavor", flavor, program)
    assert result.exit_code == 1
    assert result.stderr == f"error: {program}: {flavor} has no G5 (cubic Bezier) move: use --format dense " \
                            f"(g5 is for marlin and linuxcnc)\n"
    assert program.read_bytes() == original and [p.name for p in tmp_path.iterdir()] == ["part.gcode"]
