"""The fbspost command: version, profile listing, the trajectory job, and one-line errors."""
import subprocess
import sys
from importlib.metadata import version

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost.cli import main
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
    rows = [(f"{ti:.4f}", f"{xi:.9f}", f"{-xi / 2:.9f}", "0.200") for ti, xi in zip(t, x)]
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
