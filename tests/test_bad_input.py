"""Bad input through `fbspost compensate`: one line `error: FILE:LINE: message` (a profile: `error:
FILE: KEY: message`), exit status 1, no traceback, no output file, the input byte-for-byte as it
was. And input that is odd but valid: bytes that are not UTF-8 in comments, an empty program, a
feed beyond the machine's velocity."""
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fbspost.cli import main
from fbspost.plan.margins import RunMargins
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import execute, is_motion_line, kept_lines
from test_profile import BASE, BROKEN, edited

ROOT = Path(__file__).resolve().parent.parent
# Three good lines, so that the bad one is line 4 (and a line after it).
PRINT = "M83\nG1 X0 Y0 Z0.2 F3000\nG1 X10 Y0 E0.5\n{}\nG1 X20 Y5 E0.5\n"
CNC = "G21 G90 G17\nG0 X0 Y0 Z1\nG1 X10 Y0 F600\n{}\nG1 X20 Y5\n"


def compensate(program, *args, machine="bedslinger-example"):
    return CliRunner().invoke(main, ["compensate", str(program), "-m", str(machine), *map(str, args)])


def assert_refused(result, program, original, prefix, words, others=()):
    """Exit status 1 from the one-line handler (not an uncaught exception), the line as expected,
    nothing written next to the input (and the ``others`` files), the input unchanged."""
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.exception
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.startswith(prefix) and words in result.stderr, result.stderr
    assert program.read_bytes() == original
    assert sorted(p.name for p in program.parent.iterdir()) == sorted([program.name, *others])


def refuse(tmp_path, text, flavor, words, *options):
    program = tmp_path / "part.gcode"
    program.write_bytes(text.encode())
    result = compensate(program, "--flavor", flavor, "-o", tmp_path / "out.gcode", *options)
    assert_refused(result, program, text.encode(), f"error: {program}:4: ", words)
    assert not (tmp_path / "out.gcode").exists()


MISSING = [
    ("G1 X", "X needs a number"), ("G1 X20 Y", "Y needs a number"), ("G1 X20 F", "F needs a number"),
    ("G1 X20 E", "E needs a number"), ("G4 P", "P needs a number"), ("G4 S", "S needs a number"),
    ("G92 E", "E needs a number"), ("M204 S", "S needs a number"), ("G2 X20 Y0 R", "R needs a number"),
    ("G2 X20 Y0 I", "I needs a number"),
]
NOT_FINITE = [
    ("G1 Xnan", "Xnan is not a finite number"), ("G1 X20 Y-NaN", "Y-NaN is not a finite number"),
    ("G1 X20 E+inf", "E+inf is not a finite number"), ("G1 X20 Finf", "Finf is not a finite number"),
    ("G1 X20 Y-Infinity", "Y-Infinity is not a finite number"), ("G1 X" + "9" * 400, "is not a finite number"),
    ("G4 Snan", "Snan is not a finite number"), ("G92 Einf", "Einf is not a finite number"),
    ("M204 Sinf", "Sinf is not a finite number"), ("G2 X20 Y0 Rnan", "Rnan is not a finite number"),
    ("G2 X20 Y0 I5 Jinf", "Jinf is not a finite number"),
]
ARCS = [  # from X10 Y0
    ("G2 X20 Y0 I0 J0", "arc center I=0 J=0: the radius is zero"),
    ("G3 X20 Y0 J0 I0", "arc center I=0 J=0: the radius is zero"),
    ("G2 X30 Y0 R9.99", "arc radius 9.99 mm is shorter than half the chord (10 mm)"),
    ("G3 X10 Y20 R-5", "arc radius 5 mm is shorter than half the chord (10 mm)"),
    ("G2 X10 Y0 R5", "an R arc must end away from its start"),
    ("G2 X20 Y0", "an arc needs I/J (center) or R (radius)"),
    ("G2 X20.1 Y0 I5 J0", "mm off its circle"),
    ("G2 X20 Y0 R5 I5", "an arc with both R and I/J"),
]
FEEDS = [
    ("G1 X20 F0", "feed F0 must be positive"), ("G1 X20 F-600", "feed F-600 must be positive"),
    ("G1 F0", "feed F0 must be positive"), ("G0 X20 F-.5", "feed F-.5 must be positive"),
    ("G2 X20 Y0 I5 J0 F0", "feed F0 must be positive"),
]


@pytest.mark.parametrize("line, words", MISSING + NOT_FINITE + ARCS + FEEDS)
def test_bad_line_is_refused(tmp_path, line, words):
    refuse(tmp_path, PRINT.format(line), "marlin", words)


UNSUPPORTED = [
    ("G41 D1", "cutter radius compensation (G41)"), ("G42 D1", "cutter radius compensation (G42)"),
    ("G41.1 D2 L3", "dynamic cutter radius compensation (G41.1)"), ("G68 X0 Y0 R30", "coordinate rotation (G68)"),
    ("G51 X0 Y0 P2", "scaling (G51)"), ("G73 X1 Y1 Z-1 R1 Q0.5", "canned cycles (G73)"),
    ("G76 P0.05 Z-1 I-0.1 J0.1 K0.2", "canned cycles (G76)"),
    *[(f"G{g} X1 Y1 Z-1 R1 Q0.5", f"canned cycles (G{g})") for g in range(81, 90)],
    ("G93", "inverse time feed (G93)"), ("G95", "feed per revolution (G95)"),
]


@pytest.mark.parametrize("flavor", ["linuxcnc", "marlin"])
@pytest.mark.parametrize("line, words", UNSUPPORTED)
def test_unsupported_path_changing_code_is_refused(tmp_path, flavor, line, words):
    """(LinuxCNC programs with these are expanded by rs274 unless --no-expand: test_linuxcnc.)"""
    refuse(tmp_path, (CNC if flavor == "linuxcnc" else PRINT).format(line), flavor, f"{words} is not supported",
           *(["--no-expand"] if flavor == "linuxcnc" else []))


@pytest.mark.parametrize("old, new, key", [c[1:] for c in BROKEN], ids=[c[0] for c in BROKEN])
def test_profile_with_an_invalid_field_is_refused(tmp_path, old, new, key):
    """Every broken profile of test_profile, through the command: the file and the key named."""
    program = tmp_path / "part.gcode"
    program.write_bytes(PRINT.format("G1 X15").encode())
    profile = tmp_path / "machine.toml"
    profile.write_text(edited(old, new))
    result = compensate(program, machine=profile)
    assert_refused(result, program, PRINT.format("G1 X15").encode(), f"error: {profile}: ", "", [profile.name])
    message = result.stderr.split(f"error: {profile}: ", 1)[1]
    assert message.startswith(f"{key}: ") or message.startswith(f"{key} "), message


def test_profile_that_is_not_toml_names_its_line(tmp_path):
    program = tmp_path / "part.gcode"
    program.write_bytes(PRINT.format("G1 X15").encode())
    profile = tmp_path / "machine.toml"
    profile.write_text(BASE.replace("sample_rate = 1000.0", "sample_rate = 1000.0 Hz"))
    result = compensate(program, machine=profile)
    assert_refused(result, program, PRINT.format("G1 X15").encode(), f"error: {profile}: not valid TOML: ", "line 5",
                   [profile.name])


@pytest.mark.parametrize("machine, prefix", [("bedslinger-example", "error: {program}:4: arc center I=0 J=0"),
                                             ("{profile}", "error: {profile}: axes.Y.modes[0].damping: ")],
                         ids=["program", "profile"])
def test_real_entry_point_prints_no_traceback(tmp_path, machine, prefix):
    program = tmp_path / "part.gcode"
    program.write_bytes(PRINT.format("G2 X20 Y0 I0 J0").encode())
    profile = tmp_path / "machine.toml"
    profile.write_text(edited("damping = 0.06", "damping = 1"))
    proc = subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(program),
                           "-m", machine.format(profile=profile)], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(prefix.format(program=program, profile=profile)), proc.stderr
    assert program.read_bytes() == PRINT.format("G2 X20 Y0 I0 J0").encode()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["machine.toml", "part.gcode"]


# ---- odd but valid -------------------------------------------------------------------------------

def test_comments_that_are_not_utf8_pass_byte_exact(tmp_path):
    lines = [b"; \xff\xfe UTF-16 mark, then Latin-1: \xe9t\xe9\r\n", b"M83\n", b"G1 X0 Y0 Z0.2 F3000 ; \x80\x81\n",
             b"M117 \xc3\x28 broken sequence\n", b"(\xe9paisseur \xb0C)\r\n", b"G1 X10 Y5 E0.4\n",
             b"M104 S200 ; \xf0\x28\x8c\x28\n", b"; \xed\xa0\x80 surrogate\n", b"G1 X20 Y0 E0.4\n", b"; end \xff"]
    program = tmp_path / "part.gcode"
    program.write_bytes(b"".join(lines))
    result = compensate(program, "-q", "-o", tmp_path / "out.gcode", "--flavor", "marlin")
    assert result.exit_code == 0, result.stderr
    kept_lines([line for line in lines if not is_motion_line(line)], execute(tmp_path / "out.gcode").nonmotion)


@pytest.mark.parametrize("in_place", [True, False], ids=["in-place", "output"])
def test_empty_program_comes_out_unchanged(tmp_path, in_place):
    program = tmp_path / "part.gcode"
    program.write_bytes(b"")
    target = program if in_place else tmp_path / "out.gcode"
    result = compensate(program, *([] if in_place else ["-o", target]))
    assert result.exit_code == 0, result.stderr
    assert target.read_bytes() == b"" and program.read_bytes() == b""


FAST = "G28\nG1 X0 Y0 F600\nG1 X100 F30000\n"  # 500 mm/s asked; bedslinger-example: X 300 mm/s, 3000 mm/s^2


def test_feed_beyond_the_machine_is_clamped_as_the_controller_does(tmp_path):
    """The 100 mm move from rest to rest at the axis' 300 mm/s, accelerating at 3000 mm/s^2:
    100/300 + 300/3000 s and the run's lead and settle margins; no block of the output faster
    than 300 mm/s."""
    program = tmp_path / "part.gcode"
    program.write_text(FAST)
    result = compensate(program, "-q", "-o", tmp_path / "out.gcode")
    assert result.exit_code == 0, result.stderr
    ends = np.array(execute(tmp_path / "out.gcode").ends)
    margins = RunMargins.for_profile(load_profile("bedslinger-example"))
    # (the output's F times each block by its whole steps, as Marlin does; the executor by its length)
    assert ends[-1, 0] - ends[0, 0] == pytest.approx(
        100 / 300 + 300 / 3000 + margins.lead_s + margins.settle_s, rel=6e-3
    )
    dt = np.diff(ends[:, 0])
    assert (np.abs(np.diff(ends[:, 1])[dt > 0] / dt[dt > 0]) <= 300 * (1 + 1e-3)).all()


def test_feed_beyond_the_machine_is_a_warning_naming_the_line(tmp_path):
    program = tmp_path / "part.gcode"
    program.write_text(FAST)
    result = compensate(program, "-o", tmp_path / "out.gcode")
    assert result.exit_code == 0
    assert any(line.startswith("warning: ") and "line 3" in line for line in result.stderr.splitlines()), result.stderr


# ---- not G-code at all ---------------------------------------------------------------------------

PNG = (ROOT / "samples" / "butterfly-simulate.png").read_bytes()[:4096]


@pytest.mark.parametrize("flavor", [None, "marlin", "klipper", "reprap", "linuxcnc"])
@pytest.mark.parametrize("content", ["png", "random-0", "random-1", "random-2"])
def test_binary_file_is_not_gcode(tmp_path, flavor, content):
    """A picture or random bytes: one line naming the file and its first line, whatever the flavor
    (without --flavor, before the detection can take the bytes for a LinuxCNC program and run rs274)."""
    data = PNG if content == "png" else np.random.default_rng(int(content[-1])).bytes(4096)
    program = tmp_path / "part.gcode"
    program.write_bytes(data)
    result = compensate(program, *(["--flavor", flavor] if flavor else []), "-o", tmp_path / "out.gcode")
    assert_refused(result, program, data, f"error: {program}:1: ", "not a G-code file: binary content")


@pytest.mark.parametrize("flavor", ["marlin", "klipper", "reprap", "linuxcnc"])
@pytest.mark.parametrize("line", [b"\x00\x00\x00\rIHDR\x00", b"G1 X5\x00 Y2", b"\x89PNG", b"\xff\xd8\xff\xe0 JFIF",
                                  b"G1 X\x1b[31m5"])
def test_binary_line_after_good_ones_names_its_line(tmp_path, flavor, line):
    """Binary content in the code of line 4 (a file cut into by another, a download that went wrong)."""
    text = (CNC if flavor == "linuxcnc" else PRINT).encode().replace(b"{}", line)
    program = tmp_path / "part.gcode"
    program.write_bytes(text)
    result = compensate(program, "--flavor", flavor, "-o", tmp_path / "out.gcode")
    assert_refused(result, program, text, f"error: {program}:4: ", "not a G-code file: binary content")


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(min_size=1, max_size=600), flavor=st.sampled_from([None, "marlin", "klipper", "reprap",
                                                                          "linuxcnc"]))
def test_fuzz_bytes_one_line_or_a_program(tmp_path, data, flavor):
    """Any bytes, in any flavor: either a program (exit 0, an output) or a one-line refusal naming the
    file (exit 1, nothing written); never a traceback, never the input changed."""
    program = tmp_path / "fuzz" / "part.gcode"
    program.parent.mkdir(exist_ok=True)
    for stale in program.parent.iterdir():
        stale.unlink()
    program.write_bytes(data)
    result = compensate(program, *(["--flavor", flavor] if flavor else []), "-q", "-o", program.parent / "out.gcode")
    if result.exit_code == 0:
        assert (program.parent / "out.gcode").exists()
        assert program.read_bytes() == data
    else:
        assert_refused(result, program, data, f"error: {program}", "")


@pytest.mark.parametrize("flavor, line, words", [
    ("klipper", "G1 X-0.01 Y0 E0.5", "moves X to -0.01 mm, beyond the machine's travel 0 to inf mm"),
    ("marlin", "G2 X10 Y0 I0 J-3 E0.5", "moves Y to -0.00"),  # (a full circle from X10 Y0 below Y0: its first chord)
    ("reprap", "G0 Y-2", "moves Y to -2 mm"),
    ("marlin", "G1 X-1 Y3 E0.2", "moves X to -1 mm")])
def test_move_beyond_the_travel_is_refused(tmp_path, flavor, line, words):
    """A move of the program itself beyond the firmware's default travel (the minimum 0 of X and Y:
    Klipper refuses it, "Move out of range") is refused, naming its line; LinuxCNC has no default."""
    refuse(tmp_path, PRINT.format(line), flavor, words)


def test_move_beyond_the_profiles_travel_is_refused(tmp_path):
    """The profile's position_max, on LinuxCNC (as its soft limits abort); a program that ends at
    it is compensated, and its command never goes beyond it."""
    machine = tmp_path / "stage.toml"
    machine.write_text(edited("max_velocity = 200.0", "max_velocity = 200.0\nposition_max = 5.0"))
    program = tmp_path / "part.ngc"
    program.write_text(CNC.format("G1 Y5.5"))
    result = compensate(program, "-o", tmp_path / "out.ngc", machine=machine)
    assert_refused(result, program, CNC.format("G1 Y5.5").encode(), f"error: {program}:4: ",
                   "moves Y to 5.5 mm, beyond the machine's travel -inf to 5 mm (the profile's axes.Y.position_min "
                   "and position_max", [machine.name])
    program.write_text(CNC.format("G1 Y4"))
    assert compensate(program, "-q", "-o", tmp_path / "out.ngc", machine=machine).exit_code == 0
    written = [b.points_mm[:, 1] for b in read_gcode(tmp_path / "out.ngc", "linuxcnc") if b.points_mm is not None]
    assert np.nanmax(np.concatenate(written)) == 5.0


@pytest.mark.parametrize("flavor, text", [("marlin", PRINT.format("G1 X15 Y2 E0.3")),
                                          ("linuxcnc", CNC.format("G1 X15 Y2"))])
@pytest.mark.parametrize("in_place", [True, False], ids=["in-place", "output"])
def test_compensated_file_is_refused(tmp_path, flavor, text, in_place):
    """fbspost's output given to it again (a slicer that runs its scripts twice): one line naming the
    header's line, its version and profile; the file as it was."""
    program = tmp_path / "part.gcode"
    program.write_bytes(("; sliced by hand\n" + text).encode())
    assert compensate(program, "--flavor", flavor, "-q").exit_code == 0
    once = program.read_bytes()
    header = [n for n, line in enumerate(once.decode().splitlines(), 1) if "filtered B-spline compensation" in line]
    assert header == [2], once.decode()[:300]
    result = compensate(program, "--flavor", flavor, *([] if in_place else ["-o", tmp_path / "again.gcode"]))
    assert_refused(result, program, once, f"error: {program}:2: already compensated (fbspost ",
                   "for machine profile bedslinger-example): compensate the original instead")


@pytest.mark.parametrize("name, flavor", [("part.ngc", None), ("part.gcode", "linuxcnc"), ("PART.NGC", None)])
@pytest.mark.parametrize("line", ["G1 X1e999 Y2 F3000", "G0 X5 E2", "G1 X1e5 F100"])
def test_linuxcnc_e_word_is_refused_as_linuxcnc_does(tmp_path, name, flavor, line):
    """LinuxCNC's rs274 refuses these ("E word with no G70, G76, M66, M67 or M68 to use it"): so does
    fbspost, also where it tells the flavor from the name *.ngc (as Marlin, X1e999 would read as X1 E999)."""
    text = CNC.format(line)
    program = tmp_path / name
    program.write_bytes(text.encode())
    result = compensate(program, *(["--flavor", flavor] if flavor else []), "-o", tmp_path / "out.ngc")
    assert_refused(result, program, text.encode(), f"error: {program}:4: E", "LinuxCNC refuses an E word")
    if shutil.which("rs274"):
        canon = subprocess.run(["rs274", "-g", str(program)], capture_output=True, text=True, timeout=60)
        assert "E word with no G70, G76, M66, M67 or M68 to use it" in canon.stdout + canon.stderr
