"""LinuxCNC programs (issue 18): NURBS evaluated exactly, clear refusals, I/O words, extra axes,
and --expand through LinuxCNC's own interpreter with no silently wrong output.

Truths: scipy's BSpline on homogeneous coordinates (an independent NURBS evaluation) and the
closed form of a circle (a rational quadratic with weights 1, sqrt(2)/2, 1); LinuxCNC's rs274
for the expanded programs (its canonical path and its non-motion calls, see canon_check)."""
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from canon_check import canonical_moves, command_problems, path_problems
from fbspost.cli import main
from fbspost.errors import InputError
from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.plan.margins import RunMargins
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.blocks import AXES, CHORD_TOLERANCE_MM, Kind
from fbspost.read.expand import canonical_calls, expand
from fbspost.read.gcode import read_gcode
from fbspost.read.rs274_probes import check_static
from fbspost.read.splines import nurbs_points

needs_rs274 = pytest.mark.skipif(shutil.which("rs274") is None,
                                 reason="LinuxCNC's rs274 is not installed (apt-get install linuxcnc-uspace)")
NCFILES = Path("/usr/share/linuxcnc/ncfiles")


def scipy_nurbs(ctrl, order):
    """LinuxCNC's NURBS (knots k zeros, 1 .. m - k, k times m - k + 1) by scipy, homogeneous."""
    m = len(ctrl)
    knots = np.concatenate([np.zeros(order), np.arange(1.0, m - order + 1), np.full(order, m - order + 1.0)])
    spline = BSpline(knots, np.column_stack([ctrl[:, :2] * ctrl[:, 2:], ctrl[:, 2]]), order - 1)
    return lambda u: (lambda h: h[:, :2] / h[:, 2:])(spline(u))


def moves(path, text):
    path.write_text(text)
    return list(read_gcode(path, "linuxcnc"))


def polyline(blocks):
    return np.concatenate([b.points_mm[:, :2] for b in blocks if b.kind is Kind.MOVE])


def off_polyline(points, line):
    """Each point's distance from the polyline ``line``."""
    a, b = line[:-1], line[1:]
    d = b - a
    t = np.clip(((points[:, None] - a) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-300), 0, 1)
    return np.hypot(*(points[:, None] - a - t[..., None] * d).transpose(2, 0, 1)).min(axis=1)


CTRL = np.array(
    [[1.0, 2.0, 1.0], [4.0, 6.0, 2.5], [7.0, 1.0, 0.5], [9.0, 5.0, 1.0], [12.0, 3.0, 3.0], [14.0, 8.0, 1.0]]
)


@pytest.mark.parametrize("order", [3, 4, 5, 6])
def test_nurbs_evaluation_matches_scipy(order):
    u = np.linspace(0.0, len(CTRL) - order + 1.0, 1001)
    assert np.abs(nurbs_points(CTRL, order, u) - scipy_nurbs(CTRL, order)(u)).max() < 1e-10


@pytest.mark.slow
@pytest.mark.parametrize("order", [3, 4])
def test_g52_is_planned_on_the_curve(tmp_path, order):
    """Every piece end within 0.1 um of scipy's curve, the curve within the chord tolerance of
    the pieces, the end exact, every line of the NURBS a MOVE (none copied without its curve)."""
    points = "\n".join(f"X{x:g} Y{y:g} P{w:g}" for x, y, w in CTRL[2:])
    blocks = moves(tmp_path / "n.ngc", f"G21 G90 G17 F600\nG0 X{CTRL[0, 0]:g} Y{CTRL[0, 1]:g} Z1\n"
                                       f"G5.2 X{CTRL[1, 0]:g} Y{CTRL[1, 1]:g} P{CTRL[1, 2]:g} L{order}\n"
                                       f"{points}\n(a comment)\nG5.3\nG1 X0 Y0\nM2\n")
    assert [b.kind for b in blocks[2:10]] == [Kind.MOVE] * 5 + [Kind.PASS, Kind.MOVE, Kind.MOVE]
    curve = scipy_nurbs(CTRL, order)(np.linspace(0.0, len(CTRL) - order + 1.0, 2_000_001))  # 1e-5 mm apart
    pieces = np.concatenate([CTRL[:1, :2], polyline(blocks[2:9])])
    assert cKDTree(curve).query(pieces)[0].max() < 1e-4
    assert off_polyline(curve[::500], pieces).max() < CHORD_TOLERANCE_MM * 1.01
    assert np.array_equal(blocks[8].position_mm[:3], [*CTRL[-1, :2], 1.0])


def test_weighted_nurbs_is_a_circle(tmp_path):
    """Closed form: the rational quadratic (r,0), (r,r) weight sqrt(2)/2, (0,r) is a quarter circle."""
    blocks = moves(tmp_path / "c.ngc", "G21 G90 F600\nG0 X10 Y0\nG5.2 X10 Y10 P0.70710678118654752 L3\n"
                                       "X0 Y10 P1\nG5.3\nM2\n")
    pieces = polyline(blocks)
    assert np.abs(np.hypot(*pieces.T) - 10.0).max() < 1e-9 and np.allclose(pieces[-1], [0, 10])
    angles = np.arctan2(pieces[:, 1], pieces[:, 0])
    assert np.all(np.diff(angles) > 0) and 10 * (1 - math.cos(np.diff(angles).max() / 2)) <= CHORD_TOLERANCE_MM


# G6.2 (LinuxCNC 2.10): order P, each line a knot K, control points with weights R; the knots
# are the K words in order, unevenly spaced, one of them doubled (a corner of a quadratic)
G62 = ("F600\nG6.2 P3 K0 X10 Y0 R1\nX14 Y6 R2.5 K0\nX20 Y1 R0.4 K0\nX26 Y7 R1 K0.7\nX30 Y-2 R3 K2.5\n"
       "X35 Y4 R1 K2.5\nX40 Y0 R1 K4\nG6.2 K6\nK6\nG6.2 K6\nG1 X0\nM2\n")
G62_CTRL = np.array([[10.0, 0, 1], [14, 6, 2.5], [20, 1, 0.4], [26, 7, 1], [30, -2, 3], [35, 4, 1], [40, 0, 1]])
G62_KNOTS = [0, 0, 0, 0.7, 2.5, 2.5, 4, 6, 6, 6]


def test_g62_is_planned_on_its_curve(tmp_path):
    """Every piece end within 0.1 um of scipy's curve (its knots the K words as written), the
    curve within the chord tolerance of the pieces, every line of the NURBS a MOVE, the end exact."""
    blocks = moves(tmp_path / "g62.ngc", "G21 G90 G17\nG0 X10 Y0 Z1\n" + G62)
    assert [b.kind for b in blocks[3:13]] == [Kind.MOVE] * 10
    homogeneous = np.column_stack([G62_CTRL[:, :2] * G62_CTRL[:, 2:], G62_CTRL[:, 2]])
    h = BSpline(np.array(G62_KNOTS, float), homogeneous, 2)(np.linspace(0.0, 6.0, 2_000_001))
    curve = h[:, :2] / h[:, 2:]
    pieces = np.concatenate([G62_CTRL[:1, :2], polyline(blocks[3:13])])
    assert cKDTree(curve).query(pieces)[0].max() < 1e-4
    assert off_polyline(curve[::4000], pieces).max() < CHORD_TOLERANCE_MM * 1.01
    assert np.array_equal(blocks[12].position_mm[:3], [40.0, 0.0, 1.0])


@pytest.mark.parametrize("old, new, words", [
    ("X40 Y0 R1 K4\n", "X40 Y0 R1 K1\n", "G6.2 knots K must not decrease"),
    ("X40 Y0 R1 K4\nG6.2 K6", "X40 Y0 R1 K4\nG6.2 K5", "G6.2 knots must begin with 3 equal knots and end with 3"),
    ("X20 Y1 R0.4", "X20 Y1", "a G6.2 control point needs a positive weight R"),
    ("\nK6\n", "\nX1 Y1 R1 K6\n", "a G6.2 control point after the knots that end the NURBS"),
    ("G1 X0\n", "X1 Y1 R1 K6\n", "the first G6.2 line needs its order P"),  # modal G6.2: a new NURBS
])
def test_g62_errors(tmp_path, old, new, words):
    program = tmp_path / "bad.ngc"
    program.write_text("G21 G90 G17\nG0 X10 Y0 Z1\n" + G62.replace(old, new))
    with pytest.raises(InputError, match=words):
        list(read_gcode(program, "linuxcnc"))


def test_g51_is_the_quadratic_spline(tmp_path):
    blocks = moves(tmp_path / "q.ngc", "G21 G90 F600\nG0 X0 Y0\nG5.1 X4 Y0 I2 J3\nM2\n")
    ctrl = np.array([[0.0, 0, 1], [2, 3, 1], [4, 0, 1]])
    curve = scipy_nurbs(ctrl, 3)(np.linspace(0, 1, 1_000_001))
    assert cKDTree(curve).query(polyline(blocks))[0].max() < 1e-4


def test_a_g51_inside_an_open_nurbs_is_refused_as_rs274_refuses_it(tmp_path):
    """Bad input, once a traceback: the G5.1 ended the open G5.2 NURBS and its next line had
    none to join. LinuxCNC's own interpreter refuses the program too (where it is installed)."""
    program = tmp_path / "p.ngc"
    program.write_text("G21 G90 G17\nG1 X0 Y0 F600\nG5.2 X1 Y0 P1 L3\nX2 Y1 P1\nG5.1 X3 Y1 I1 J0\nX4 Y2 P1\nG5.3\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--no-expand", "-o", str(tmp_path / "out.ngc")])
    assert result.exit_code == 1 and not (tmp_path / "out.ngc").exists()
    assert result.stderr == f"error: {program}:5: G5.1 inside a G5.2 NURBS: end the NURBS with G5.3 first\n"
    if shutil.which("rs274"):
        canon = subprocess.run(["rs274", "-g", str(program)], capture_output=True, text=True, timeout=60)
        assert canon.returncode == 1 and "PROGRAM_END" not in canon.stdout, canon.stdout + canon.stderr


@pytest.mark.parametrize("line, words", [
    ("#<xmax> = 9", "parameters (#<xmax>) need --expand (LinuxCNC's interpreter)"),
    ("G1 X[1 + 2]", "expressions ([1 + 2]) need --expand"),
    ("o100 while [#1 lt 3]", "O-word 'while': subroutines and control flow are not supported: --expand"),
    ("G81 X1 Y1 Z-1 R1", "canned cycles (G81) is not supported: --expand runs it"),
    ("G7", "lathe diameter mode (G7) is not supported: --expand runs it"),
    ("G6.2 P3 Q2 X10 Y0 R1", "every G6.2 line needs its knot K"),
    ("G6.2 P3 K0 X9 Y0 R1", "a G6.2 NURBS starts at its first control point"),
    ("G5.3", "G5.3 without G5.2 first"),
])
def test_without_expand_the_feature_is_named(tmp_path, line, words):
    program = tmp_path / "p.ngc"
    program.write_text(f"G21 G90\nG0 X0 Y0 Z1\nG1 X10 F600\n{line}\nG1 X20\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--no-expand", "-o", str(tmp_path / "out.ngc")])
    assert result.exit_code == 1 and result.stderr.startswith(f"error: {program}:4: ") and words in result.stderr, \
        result.stderr
    assert not (tmp_path / "out.ngc").exists()


def test_io_words_and_extra_axes(tmp_path):
    """E in M66/M67/M68 is the I/O word before and after the first motion; an extra axis' first
    move (from where the machine happens to be) passes as written at rest, then it is planned
    with the others: A moves with X; B, set once, stays; U V W never set, unknown (NaN); A B C
    in degrees under G20."""
    blocks = moves(tmp_path / "io.ngc", "G21 G90\nM66 E0 L0\nM67 E1 Q2.5\nG0 X0 Y0 Z1 A0\nG0 B0\nG1 X5 A30 F600\n"
                                        "M68 E2 Q1\nG20 G1 Y0.5 B10\nM2\n")
    assert [b.kind for b in blocks] == [Kind.PASS, Kind.STOP, Kind.PASS, Kind.STOP, Kind.STOP, Kind.MOVE,
                                        Kind.PASS, Kind.MOVE, Kind.STOP]
    nan = np.nan
    assert np.array_equal(blocks[5].points_mm, [[5.0, 0.0, 1.0, 0.0, 30.0, 0.0, nan, nan, nan, nan]], equal_nan=True)
    assert np.array_equal(blocks[7].points_mm, [[5.0, 12.7, 1.0, 0.0, 30.0, 10.0, nan, nan, nan, nan]], equal_nan=True)


PROGRAM = """(a program that needs LinuxCNC's interpreter: everything --expand must get right)
G20 G90 G17 G94 G64 P0.001
#<r> = 0.25
T1 M6
G43 H1
G0 X0 Y0 Z0.5
M3 S1200
M8
G92 X1 Y-1
o100 repeat [2]
  G1 Z-0.05 F20
  G2 X[1 + #<r> * 2] Y-1 I#<r> J0
  G3 X1 Y-1 R#<r>
o100 endrepeat
G92.1
G0 X0 Y0 Z0
G18 G2 X0.5 Z0 I0.25 K0
G19 G3 Y0.5 Z0 J0.25 K0 P2
G17 G55 G0 X0 Y0
G10 L2 P2 X0.5
G93 G1 X1 Y1 F60
G94 G81 X0.2 Y0.2 Z-0.1 R0.1 F10
G80 G54 G0 Z1
(MSG, half way)
M62 P1
M67 E0 Q2.5
G4 P0.5
M9
M5
M30
"""


@needs_rs274
def test_expanded_program_follows_linuxcncs_canonical_path(tmp_path):
    program, expanded = tmp_path / "part.ngc", tmp_path / "part.expanded.ngc"
    program.write_text(PROGRAM)
    table = tmp_path / "tool.tbl"
    table.write_text("T1 P1 Z0.5 D0.125\n")
    expand(program, expanded, "test", table)
    assert path_problems(program, expanded, True, table) == []
    assert command_problems(program, expanded, table) == []


def machine_positions(program: Path, parameter_file: Path) -> list[tuple[float, ...]]:
    """X Y Z where rs274 (LinuxCNC's interpreter, on its own) moves the machine in ``program``, started
    from the machine's ``parameter_file``: each move's end with the G92 offsets in force added."""
    moves = canonical_moves(canonical_calls(program, parameter_file=parameter_file), False)[0]
    return [tuple(np.round(end[:3], 4)) for _, end, _ in moves]


@needs_rs274
def test_expansion_runs_where_the_original_does_with_the_machines_g92_offsets(tmp_path):
    """LinuxCNC keeps G92 offsets from program to program (parameters 5210-5213): a program runs
    shifted by them, its own G92 carries them on (it is relative to where the tool is) and its
    G92.1 takes them off; so must its expansion, which rs274 makes from none (rs274, given the
    machine's parameter file, is the judge). The expansion writes G92.2 for the program's G92.1
    (the positions are the same; the machine's offsets stay stored) and never G92.1."""
    var = tmp_path / "machine.var"
    var.write_text("5210 1\n5211 10\n5212 -5\n5213 0\n5220 1\n")
    program, expanded = tmp_path / "part.ngc", tmp_path / "part.expanded.ngc"
    for text, shifted in (("G0 X1 Y2 Z3\nG1 X[1 + #<r>] F600\nG2 X5 Y2 I1 J0\nG1 X6\n", 4),
                          ("G0 X1 Y2 Z3\nG92 X0\nG1 X[#<r>] F600\nG92.1\nG0 X4 Y4\nG1 X5\n", 2)):
        program.write_text(f"G21 G90\n#<r> = 2\n{text}M2\n")
        expand(program, expanded, "test")
        assert "G92.1" not in expanded.read_text()
        original = machine_positions(program, var)
        assert original[0] == (1 + 254.0, 2 - 127.0, 3.0)  # (rs274 reads the file's lengths as inches)
        assert sum(p[0] > 200 for p in original) == shifted  # (the arc too; the second: shifted until its G92.1)
        assert machine_positions(expanded, var) == original


@needs_rs274
@pytest.mark.parametrize("name", ["arcspiral.ngc", "cds.ngc", "comp.ngc", "daisy.ngc", "spiral.ngc"])
def test_installed_examples_expand_exactly(tmp_path, name):
    program = NCFILES / name
    if not program.exists():
        pytest.skip(f"{program} is not installed")
    expanded, table = tmp_path / "x.ngc", tmp_path / "tool.tbl"
    table.write_text("".join(f"T{t} P{t} Z{0.1 * t:g} D{0.0625 * t:g}\n" for t in range(1, 6)))
    expand(program, expanded, "test", table)
    assert path_problems(program, expanded, True, table) == []
    assert command_problems(program, expanded, table) == []


@pytest.mark.slow
@needs_rs274
def test_compensate_expands_and_says_so(tmp_path):
    program, out = tmp_path / "part.ngc", tmp_path / "out.ngc"
    program.write_text("G21 G90\nG0 X0 Y0 Z1\n#<d> = 4\nG1 X#<d> F1200\nG2 X0 Y0 I[-#<d> / 2] J0\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "-o", str(out), "-q"])
    assert result.exit_code == 0, result.stderr
    text = out.read_text()
    assert text.startswith("; fbspost: expanded by LinuxCNC's interpreter rs274 from part.ngc: line 3 uses "
                           "parameters (#<d>)")
    assert command_problems(program, out) == []


@needs_rs274
def test_inverse_time_becomes_the_feed_that_takes_as_long(tmp_path):
    """G93 F30 is 1/30 min per move whatever its length: 1 inch in 2 s is 762 mm/min; an arc
    of radius 10 mm over a half turn (31.416 mm) at F60 in 1 s is 1884.96 mm/min."""
    program, expanded = tmp_path / "t.ngc", tmp_path / "x.ngc"
    program.write_text("G20 G90 G0 X0 Y0 Z0\nG93 G1 X1 F30\nG21 G3 X5.4 Y0 I-10 J0 F60\nG94 G1 X0 F100\nM2\n")
    expand(program, expanded, "test")
    moves = [line for line in expanded.read_text().splitlines() if line.startswith(("G1", "G3"))]
    assert moves[0] == "G1 X25.4 F762"
    assert moves[1].startswith("G3 X5.4 Y0 Z0 I-10 J0 F1884.955")
    assert moves[2] == "G1 X0 F100"


def test_without_rs274_one_line_says_how_to_install_it(tmp_path, monkeypatch):
    program = tmp_path / "p.ngc"
    program.write_text("G21 G90\nG0 X0 Y0\n#<d> = 4\nG1 X#<d> F600\nM2\n")
    monkeypatch.setenv("PATH", str(tmp_path))  # no rs274 there
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "-o", str(tmp_path / "out.ngc")])
    assert result.exit_code == 1 and result.stderr == (
        f"error: {program}: LinuxCNC's interpreter rs274 is not installed: apt-get install linuxcnc-uspace\n")
    assert not (tmp_path / "out.ngc").exists()


@needs_rs274
def test_ini_subroutine_path_is_from_the_ini_directory(tmp_path):
    """LinuxCNC runs in its INI's directory: a relative SUBROUTINE_PATH is found from there,
    wherever fbspost runs; the expansion follows rs274's path (a 5 mm square from the subroutine)."""
    config = tmp_path / "config"
    (config / "subs").mkdir(parents=True)
    (config / "machine.ini").write_text("[RS274NGC]\nSUBROUTINE_PATH = ./subs\n")
    (config / "subs" / "square.ngc").write_text("o<square> sub\nG1 X#1\nG1 Y#1\nG1 X0\nG1 Y0\no<square> endsub\nM2\n")
    program, expanded = tmp_path / "part.ngc", tmp_path / "x.ngc"
    program.write_text("G21 G90 F600\nG0 X0 Y0 Z1\no<square> call [5]\nM2\n")
    with pytest.raises(InputError, match="seeking o-word: o<square>"):
        expand(program, expanded, "test")
    expand(program, expanded, "test", ini=config / "machine.ini")
    moves = [line for line in expanded.read_text().splitlines() if line.startswith("G1")]
    assert moves == ["G1 X5 F600", "G1 Y5", "G1 X0", "G1 Y0"]
    assert path_problems(program, expanded, True, ini=config / "machine.ini") == []


def trapezoid_mm(t_s, length, v, a):
    """Closed form: distance covered at ``t_s`` by a move of ``length`` from rest to rest at
    cruise ``v`` and acceleration ``a`` (the cruise reached)."""
    ramp, total = v / a, length / v + v / a
    t = np.clip(t_s, 0.0, total)
    return np.where(t < ramp, 0.5 * a * t * t, np.where(t < total - ramp, v * (t - 0.5 * ramp),
                                                       length - 0.5 * a * (total - t) ** 2))


def test_rotary_axis_is_planned_with_x(tmp_path):
    """LinuxCNC's feed rule: G1 X10 A90 F600 is timed by its 10 mm of X (1 s at 10 mm/s, plus
    v/a = 2 ms at the stage's 5000 mm/s^2), A moving with X (A = 9 X); G1 A180 alone by its 90
    degrees at 10 deg/s (9.002 s), a rest of the compensated axes (copied as written). Closed
    forms of the trapezoids."""
    blocks = moves(tmp_path / "a.ngc", "G21 G90\nG0 X0 Y0 Z1 A0\nG1 X10 A90 F600\nG1 A180\nM2\n")
    plan = plan_blocks(blocks, load_profile("patent-xy-stage"), margins=RunMargins(0.0, 0.0))
    assert np.allclose(plan.pieces.duration_s, [1.002], rtol=0, atol=1e-9)
    last = plan.runs[0][1]  # the rest is timed from the run's last sample
    assert plan.duration_s == pytest.approx(last / plan.sample_rate_hz + 9.002, abs=1e-9)
    samples = plan.samples(0, last + 1)
    t = np.arange(last + 1) / plan.sample_rate_hz - plan.pieces.start_s[0]
    x, a = samples[:, AXES.index("X")], samples[:, AXES.index("A")]
    assert np.abs(x - trapezoid_mm(t, 10.0, 10.0, 5000.0)).max() < 1e-9
    assert np.abs(a - 9.0 * trapezoid_mm(t, 10.0, 10.0, 5000.0)).max() < 1e-9


def test_an_axis_the_profile_leaves_out_is_planned_at_the_slowest_given_axis_limits(tmp_path):
    """LinuxCNC's INI has finite limits for every axis; fbspost's plan and its model of
    LinuxCNC's planner give Z, which the stage's profile leaves out, the slowest given axis'
    (100 mm/s, 8000 mm/s^2): G1 Z10 F12000 takes what G1 X10 F12000 takes in each, the plan's the
    closed form of the trapezoid from rest to rest at 100 mm/s and the profile's planner
    acceleration (5000 mm/s^2: linuxcnc_time retimes it to LinuxCNC's). The plan had Z unlimited
    (200 mm/s, the program's F: 0.09 s)."""
    stage = load_profile("patent-xy-stage")
    times = {}
    for axis in "XZ":
        blocks = moves(tmp_path / "z.ngc", f"G21 G90\nG0 X0 Y0 Z0\nG1 {axis}10 F12000\nM2\n")
        plan = plan_blocks(blocks, stage, margins=RunMargins(0.0, 0.0), firmware="linuxcnc")
        times[axis] = plan.pieces.duration_s.sum(), run_linuxcnc(blocks, stage).duration_s
    assert times["Z"][0] == pytest.approx(10.0 / 100.0 + 100.0 / 5000.0, abs=1e-9)
    assert times["Z"] == pytest.approx(times["X"], abs=1e-9)


def test_moves_of_a_rotary_axis_are_copied_as_written_between_runs(tmp_path):
    """LinuxCNC blends no segment that moves A B C (tpRotaryMotionCheck), so written in a run's
    dense blocks they ran twice as long: a move of X Y with A (or A alone) is copied as written,
    the compensated X Y at rest on either side of it. The output says A only on the original's
    lines, the runs around each copy end and start exactly where the original's line does, and
    its feed, replayed as LinuxCNC times a block (each block's F along its XYZ length, along A
    where X Y Z stay), is the original's: 10 mm of X at F600 in 1 s."""
    program, out = tmp_path / "a.ngc", tmp_path / "out.ngc"
    program.write_text("G21 G90\nG0 X0 Y0 Z1 A0\nG1 X10 F600\nG1 X20 A30\nG1 Y10\nA45\nX0\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--no-expand", "--no-verify", "-o", str(out), "-q"])
    assert result.exit_code == 0, result.stderr
    position, feed, copied = {"X": 0.0, "Y": 0.0, "Z": 1.0, "A": 0.0}, None, {}
    for line in out.read_text().splitlines():
        words = dict((w[0], float(w[1:])) for w in line.split() if w[0] in "XYZAF" and not line.startswith("("))
        feed = words.get("F", feed)
        if "A" in words:
            copied[line] = (dict(position), feed)
        position.update((k, v) for k, v in words.items() if k != "F")
    assert list(copied) == ["G0 X0 Y0 Z1 A0", "G1 X20 A30", "A45"]
    assert copied["G1 X20 A30"] == ({"X": 10.0, "Y": 0.0, "Z": 1.0, "A": 0.0}, 600.0)
    assert copied["A45"] == ({"X": 20.0, "Y": 10.0, "Z": 1.0, "A": 30.0}, 600.0)
    assert position == {"X": 0.0, "Y": 10.0, "Z": 1.0, "A": 45.0}


@needs_rs274
def test_copied_moves_get_the_programs_feed_and_rapid_mode_back(tmp_path):
    """LinuxCNC's puma_seam_weld.ngc: B moved from an unknown place (a0 b-30, copied as written)
    and the axis words of a rapid (x0 y0 a0 b0 after g0 z30) after the output's G1 blocks. The
    output, read by LinuxCNC's rs274, runs every line that moves A or B as the original does: the
    same canonical call (STRAIGHT_FEED or STRAIGHT_TRAVERSE) to the same end, at the same feed.
    Before, B's 30 degrees ran at the last written block's F28 (64 s for 3.6) and the rapid as a
    feed move at F87."""
    program = Path("/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/vismach/puma/puma_seam_weld.ngc")
    if not program.is_file():
        pytest.skip("linuxcnc-uspace's examples are not installed")
    out = tmp_path / "out.ngc"
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--no-verify", "-o", str(out), "-q"])
    assert result.exit_code == 0, result.stderr

    def rotary_moves(path):
        """Each canonical move that changes A B C: (call, its end, the feed in force for a feed move)."""
        feed, rotary, found = None, (0.0, 0.0, 0.0), []
        for name, args in canonical_calls(path):
            if name == "SET_FEED_RATE":
                feed = float(args[0])
            elif name in ("STRAIGHT_FEED", "STRAIGHT_TRAVERSE"):
                end = tuple(float(a) for a in args)
                if end[3:] != rotary:
                    found.append((name, end, feed if name == "STRAIGHT_FEED" else None))
                rotary = end[3:]
        return found

    original = rotary_moves(program)
    assert len(original) == 6 and original[1] == ("STRAIGHT_FEED", (-50.0, 50.0, -10.0, 0.0, -30.0, 0.0), 500.0)
    assert original[-1][0] == "STRAIGHT_TRAVERSE"
    assert rotary_moves(out) == original


@needs_rs274
def test_g62_under_expand_says_this_rs274_cannot_run_it(tmp_path):
    program = tmp_path / "p.ngc"
    program.write_text("G21 G90\nG0 X0 Y0 Z1\n#1 = 2\nG6.2 P1 K0 X1 Y1 L3\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "-o", str(tmp_path / "out.ngc")])
    assert result.exit_code == 1 and result.stderr == (
        f"error: {program}:4: LinuxCNC's interpreter: G6.2 (LinuxCNC 2.10's NURBS) is not run by this install's "
        "rs274: Unknown g code used\n")
    assert not (tmp_path / "out.ngc").exists()


def test_helix_narrower_than_rs274s_digits_is_its_axis_line():
    """rs274 prints a helix of radius below its 4 decimals (cutter compensation on a hole of the
    tool's size, useful-subroutines.ngc) with its centre on its start and end: LinuxCNC runs a
    circle within 0.5e-4 of an inch of the axis, written as the plunge along it."""
    from fbspost.read.expand import _Expander
    calls = [("USE_LENGTH_UNITS", ["CANON_UNITS_INCHES"]), ("SET_FEED_RATE", ["60.0000"]),
             ("STRAIGHT_TRAVERSE", ["1.0000", "2.0000", "0.1000", "0", "0", "0"]),
             ("ARC_FEED", ["1.0000", "2.0000", "1.0000", "2.0000", "1", "-0.0212", "0", "0", "0"])]
    assert list(_Expander("p.ngc", [0]).lines(calls))[1:] == ["G1 Z-0.53848 F1524"]


@pytest.mark.parametrize("remap", ["F", "g01", "G64"])
def test_remapped_code_fbspost_writes_is_refused(tmp_path, remap):
    """A machine whose INI remaps F (LinuxCNC's extend-builtins example) would run the remap's
    code at each of fbspost's F words: refused in one line, before any output."""
    program, ini = tmp_path / "p.ngc", tmp_path / "machine.ini"
    program.write_text("G21 G90\nG0 X0 Y0 Z1\nG1 X10 F600\nM2\n")
    ini.write_text(f"[RS274NGC]\nREMAP=M6 modalgroup=6 ngc=change\nREMAP = {remap} prolog=setfeed_prolog ngc=setfeed\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--ini", str(ini), "-o", str(tmp_path / "out.ngc")])
    assert result.exit_code == 1 and result.stderr == (
        f"error: {program}: the machine's INI remaps {remap} (machine.ini), a code fbspost writes in every "
        "compensated move: not supported\n")
    assert not (tmp_path / "out.ngc").exists()


@needs_rs274
@pytest.mark.slow
def test_g5_splines_expand_as_rs274_evaluates_them(tmp_path):
    """rs274 prints G5/G5.1 without their control points: the program reports the values it
    evaluates (rs274_splines), and the expansion writes the same splines in mm: here the words
    by hand (inches: #3 = 0.5 in; the second G5 starts with the first's -P -Q); rs274's path
    check accepts it and rejects a control point moved by 50 um."""
    program, expanded = tmp_path / "s.ngc", tmp_path / "x.ngc"
    program.write_text("G20 G90 G17 F10\n#3 = 0.5\nG0 X0 Y0 Z0.1\nG5 X[4*#3] Y0 I[#3] J[2*#3] P[-#3] Q#3 (a comment)\n"
                       "G5 X[8*#3] Y[2*#3] P-0.25 Q0.5\nG5.1 X[12*#3] Y0 I[#3*2] J[-3*#3]\nG1 X0 Y0\nM2\n")
    expand(program, expanded, "test")
    lines = [line for line in expanded.read_text().splitlines() if line.startswith("G5")]
    assert lines == ["G5 X50.8 Y0 I12.7 J25.4 P-12.7 Q12.7 F254", "G5 X101.6 Y25.4 I12.7 J-12.7 P-6.35 Q12.7",
                     "G5.1 X152.4 Y0 I25.4 J-38.1"]
    assert path_problems(program, expanded, True) == []
    assert command_problems(program, expanded) == []
    expanded.write_text(expanded.read_text().replace("I25.4 J-38.1", "I25.45 J-38.1"))
    assert path_problems(program, expanded, True) != []


def test_g33_is_a_copied_rest_at_the_spindles_speed(tmp_path):
    """G33 K is the distance along the move per spindle revolution: 10 mm at K2 and S600 (10
    rev/s) take 0.5 s; the 45 degree exit, sqrt(2) inches at K0.1 in and S300, 1/0.1/5 * sqrt(2)
    = 2.828 s; copied as written (STOP, nothing compensated), the plan's time is their sum.
    Without the spindle turning, or under G96, one line as LinuxCNC refuses it."""
    blocks = moves(tmp_path / "t.ngc", "G21 G90 G18\nG0 X0 Y0 Z0\nS600 M3\nG33 Z-10 K2\nG20 S300\n"
                                       "G33 X1 Z-1.3937 K0.1\nM5\nM2\n")
    assert [b.kind for b in blocks[3:6]] == [Kind.STOP, Kind.PASS, Kind.STOP]
    assert blocks[3].dwell_s == pytest.approx(0.5, abs=1e-12)
    assert blocks[5].dwell_s == pytest.approx(math.sqrt(2.0) / 0.5, rel=1e-4)  # from Z -10 mm = -0.3937 in
    assert np.allclose(blocks[5].position_mm[[0, 2]], [25.4, -1.3937 * 25.4])
    plan = plan_blocks(blocks, load_profile("patent-xy-stage"), margins=RunMargins(0.0, 0.0))
    assert plan.duration_s == pytest.approx(0.5 + blocks[5].dwell_s, abs=1e-9)
    for text in ("G21\nG0 X0 Z0\nG33 Z-10 K2\n", "G21 G0 X0 Z0\nS600 M3 G96\nG33 Z-10 K2\n",
                 "G21 G0 X0 Z0\nS600 M3\nG33 Z-10\n"):
        with pytest.raises(InputError, match="t.ngc:3: (G33 needs|K needs)"):
            moves(tmp_path / "t.ngc", text)


PROBING = """G21 G90 F3000
#<safe> = 5
(PROBEOPEN results.txt)
G0 X0 Y0 Z#<safe>
G38.2 Z-3 F50
G0 Z#<safe>
G1 X10 Y5 F3000
G38.3 X20 F40
G0 X10 Y5 Z#<safe>
G1 X0 Y0 F3000
(PROBECLOSE)
M2
"""


@pytest.mark.slow
@needs_rs274
def test_probing_program_compensates_and_follows_rs274(tmp_path):
    """The probes written back as the program's (code, target, feed: by hand), the moves after
    them copied from where they stop, the rest compensated; rs274's path (but the probes' ends)
    and its non-motion calls (probe on/off, PROBEOPEN) and probe targets on the output."""
    program, out, expanded = tmp_path / "p.ngc", tmp_path / "out.ngc", tmp_path / "x.ngc"
    program.write_text(PROBING)
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "-o", str(out), "-q"])
    assert result.exit_code == 0, result.stderr
    lines = out.read_text().splitlines()
    probes = [i for i, line in enumerate(lines) if line.startswith("G38")]
    assert [lines[i] for i in probes] == ["G38.2 X0 Y0 Z-3 F50", "G38.3 X20 Y5 Z5 F40"]
    assert [lines[i + 1] for i in probes] == ["G0 X0 Y0 Z5", "G0 X10 Y5 Z5"]  # copied from the unknown end
    assert "(PROBEOPEN results.txt)" in lines and "(PROBECLOSE)" in lines
    assert command_problems(program, out) == []
    expand(program, expanded, "test")
    assert path_problems(program, expanded, True) == []
    out.write_text(out.read_text().replace("G38.3 X20 Y5", "G38.3 X20.01 Y5"))
    assert command_problems(program, out)[0].startswith("probe 2: expected the target")


@needs_rs274
@pytest.mark.parametrize("lines, message", [
    ("G38.2 Z-3\nG91 G0 Z1\nG90", "depends on where a probe (G38) stops (STRAIGHT_TRAVERSE"),  # relative
    ("G38.2 Z-3\nG92 Z0", "stops (SET_G92_OFFSET"),
    ("G38.2 Z-3\nG10 L20 P1 Z0", "stops (SET_G5X_OFFSET"),
    ("G38.2 Z-3\nG0 X5", "stops (STRAIGHT_TRAVERSE"),  # leaves Z where the probe stopped
    ("G38.2 Z-3\nG91 G38.4 Z1\nG90", "stops (the target of a probe (G38.4)"),
    ("G38.2 Z-3\nG0 Z[#5063 + 1]", "uses the probe's result (#5063)"),
    ("G38.3 Z-3\nO1 if [#5070 EQ 0]\nG0 Z6\nO1 endif", "uses the probe's result (#5070)"),
    ("G38.2 Z-3\n(LOG,#5061)", "uses the probe's result (#5061)"),
])
def test_motion_from_the_probes_result_is_refused(tmp_path, lines, message):
    """Each way a later move (or message) depends on where the probe stops: one line, nothing written."""
    program, out = tmp_path / "p.ngc", tmp_path / "out.ngc"
    program.write_text(f"G21 G90 F100\nG0 X0 Y0 Z5\n{lines}\nG0 X0 Y0 Z5\nM2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", "patent-xy-stage", "--flavor", "linuxcnc",
                                       "--expand", "-o", str(out), "-q"])
    assert result.exit_code == 1
    assert result.stderr.startswith(f"error: {program}") and message in result.stderr
    assert result.stderr.count("\n") == 1 and not out.exists()


def test_probing_program_calling_subroutine_files_is_refused(tmp_path):
    """Their use of #5061..#5070 is not read: refused (the INI's remaps likewise); a subroutine
    of the program's own file is read with it."""
    program, ini = tmp_path / "p.ngc", tmp_path / "m.ini"
    program.write_text("o<here> sub\nG0 X1\no<here> endsub\nG38.2 Z-3\no<here> call\nO<elsewhere> call\nM2\n")
    with pytest.raises(InputError, match=r"p.ngc: a probing program that calls subroutine files \(<elsewhere>\)"):
        check_static(program, None)
    program.write_text("o<here> sub\nG0 X1\no<here> endsub\nG38.2 Z-3\no<here> call\nM2\n")
    check_static(program, None)
    ini.write_text("[RS274NGC]\nREMAP=M6 modalgroup=6 ngc=change\n")
    with pytest.raises(InputError, match="calls the INI's remapped codes"):
        check_static(program, ini)


@needs_rs274
def test_g76_is_written_back_as_g33_with_rs274s_pitch(tmp_path):
    """LinuxCNC's G76 (pitch P0.05 in, 29.5 degree compound, no taper: rs274 expands it) comes
    back as G33 moves, one per synchronized feed of rs274, each with K 0.05 in = 1.27 mm; rs274
    on the output gives the same synchronized calls and path, and catches a pitch 0.1 um off."""
    program, expanded = tmp_path / "g76.ngc", tmp_path / "x.ngc"
    program.write_text("G20 G18 G90\nS500 M3\nG0 X0.6 Z0.5\nG76 P0.05 Z-0.5 I-0.075 J0.008 R1.0 K0.045 Q29.5 L0 "
                       "H3\nG0 X1\nM5\nM2\n")
    expand(program, expanded, "test")
    g33 = [line for line in expanded.read_text().splitlines() if line.startswith("G33")]
    synced = sum(name == "START_SPEED_FEED_SYNC" for name, _ in canonical_calls(program))
    assert len(g33) == synced > 5 and all(line.endswith(" K1.27") for line in g33)
    assert path_problems(program, expanded, True) == []
    assert command_problems(program, expanded) == []
    expanded.write_text(expanded.read_text().replace(" K1.27", " K1.2701", 1))
    assert command_problems(program, expanded)[0].startswith("non-motion command")


def test_blocks_last_two_servo_periods_and_the_startup_blending_is_restored(tmp_path):
    """Issue 31: LinuxCNC caps a block's speed at its length / 1.02 servo periods, and 1 ms blocks
    ran 4.3% late on LinuxCNC itself (tests/test_linuxcnc_itself.py): every compensated block
    lasts 2 servo periods or more (2.5 ms at the profile's SERVO_PERIOD 1.25 ms; length over its
    F, within F's 3 printed decimals), and the blending mode the machine starts in (the
    profile's g64_p / g64_q, its RS274NGC_STARTUP_CODE) is what the output restores after the
    compensated motion, not G64 alone (which sets P 0)."""
    text = (Path(load_profile("patent-xy-stage").source).read_text()
            .replace("[firmware]", "[firmware]\nservo_period = 0.00125\ng64_p = 0.02\ng64_q = 0.005"))
    machine = tmp_path / "stage.toml"
    machine.write_text(text)
    program, output = tmp_path / "part.ngc", tmp_path / "out.ngc"
    with open(Path(__file__).resolve().parents[1] / "samples" / "butterfly-dense.gcode", "rb") as f:
        program.write_bytes(b"".join(f.readlines()[:400]) + b"M2\n")
    result = CliRunner().invoke(main, ["compensate", str(program), "-m", str(machine), "--flavor", "linuxcnc",
                                       "--no-verify", "-o", str(output)])
    assert result.exit_code == 0, result.output
    blocks = list(read_gcode(output, "linuxcnc"))
    lines = output.read_text().splitlines()
    first = next(i for i, b in enumerate(blocks) if b.raw.startswith(b"G1"))
    durations = []
    for before, block in zip(blocks[first - 1:], blocks[first:], strict=False):
        if block.raw.startswith(b"G1"):
            length = np.linalg.norm(np.nan_to_num(block.position_mm[:3] - before.position_mm[:3]))
            durations.append(length / block.feed_mm_s)
    assert len(durations) > 100
    # (the run's last block, where the command comes to rest, can be shorter: 2.3 ms here since
    # the plan takes LinuxCNC's time, linuxcnc_time; still over LinuxCNC's cap, 1.02 periods)
    assert min(durations[:-1]) >= 0.0025 * (1 - 1e-3)
    assert durations[-1] >= 1.02 * 0.00125
    restore = max(i for i, line in enumerate(lines) if line.startswith("G64"))
    assert lines[restore] == "G64 P0.02 Q0.005"
    assert restore > max(i for i, line in enumerate(lines) if line.startswith("G1"))
