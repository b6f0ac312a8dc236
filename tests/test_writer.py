"""The writer through the whole pipeline on small programs, judged by the executor in
reference.py: lines kept byte-exact, extrusion and end positions exact in every mode; its bulk
number formatting against Decimal's text."""
import itertools
import math
import re
from decimal import Decimal

import numpy as np
import pytest

from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.plan.margins import RunMargins
from fbspost.profile import load_profile
from fbspost.read.blocks import AXES
from fbspost.write.blockends import breakpoints
from fbspost.write.emitter import Emitter
from fbspost.write.linetext import line_text
from reference import execute, fine_servo, positions_at, rest_limits, unbudgeted

PRINTER = unbudgeted(load_profile("bedslinger-example"))


def square(e_relative: bool, xyz_relative: bool = False, inches: bool = False) -> list[str]:
    """Two layers of a 20 mm square with a retract and a G92 E0 between them."""
    unit = 25.4 if inches else 1.0
    lines = ["; test square", "G21" if not inches else "G20", "M83" if e_relative else "M82", "G92 E0",
             "G1 X10 Y10 Z0.2 F6000" if not xyz_relative else "G1 X0 Y0 Z0.2 F6000"]
    if xyz_relative:
        lines = [
            "; test square",
            "G21",
            "G90",
            "G1 X10 Y10 Z0.2 F6000",
            "G91",
            "M83" if e_relative else "M82",
            "G92 E0",
        ]
    corners = [(30, 10), (30, 30), (10, 30), (10, 10)]
    e = 0.0
    for layer in range(2):
        lines.append(f";LAYER:{layer}")
        previous = (10, 10)
        for x, y in corners:
            de = 0.8
            e += de
            value = de if e_relative else e
            if xyz_relative:
                lines.append(f"G1 X{(x - previous[0]):.3f} Y{(y - previous[1]):.3f} E{value:.5f} F3000")
            else:
                lines.append(f"G1 X{x / unit:.5f} Y{y / unit:.5f} E{value:.5f} F{3000 / unit:.3f}")
            previous = (x, y)
        lines.append("M106 S128")
        lines.append("G1 E-0.8 F2400" if e_relative else f"G1 E{e - 0.8:.5f} F2400")
        lines.append("G92 E0")
        e = 0.0
    lines.append("M107")
    return lines


@pytest.mark.parametrize("e_relative, xyz_relative, inches, newline, final_newline", [
    (False, False, False, "\n", True),
    (True, False, False, "\r\n", True),
    (True, True, False, "\n", False),
    (False, False, True, "\n", True),
])
def test_lines_and_extrusion_exact(tmp_path, e_relative, xyz_relative, inches, newline, final_newline):
    source = tmp_path / "in.gcode"
    text = newline.join(square(e_relative, xyz_relative, inches)) + (newline if final_newline else "")
    source.write_bytes(text.encode())
    target = tmp_path / "out.gcode"
    compensate_file(source, target, PRINTER)
    original, compensated = execute(source), execute(target)
    kept = [line for line in compensated.nonmotion if line in set(original.nonmotion)]
    assert kept == original.nonmotion
    e_out = [
        e
        for line, e in zip(compensated.nonmotion, compensated.e_at_lines, strict=True)
        if line in set(original.nonmotion)
    ]
    assert np.abs(np.array(e_out) - np.array(original.e_at_lines)).max() <= 1e-9
    assert abs(compensated.extruded - original.extruded) <= 1e-9
    # The last motion ends exactly where the original's does.
    assert np.allclose(compensated.ends[-1][1:4], original.ends[-1][1:4], atol=1e-9)
    out = target.read_bytes()
    lines = out.split(newline.encode())
    # The program's lines after its last XY move (the retract, G92 E0, M107) end the output as
    # written, after the firmware's settings as the program has them (restored before a move of E
    # alone; Marlin's: the profile's planner acceleration and corner speed as jerk, its default
    # 20 ms) and, before those, the motion of the settle margin (a dwell where it no longer moves).
    restore = [b"M204 P3000 T3000", b"M205 B20000 X5 Y5"]
    program_end = [line.encode() for line in square(e_relative, xyz_relative, inches)[-3:]] + [b""] * final_newline
    at = len(lines) - len(restore) - len(program_end)
    assert lines[at:] == restore + program_end
    settling = list(itertools.takewhile(lambda line: line.startswith((b"G1 ", b"G4 P")) and b"E" not in line,
                                        lines[at - 1::-1]))
    moves = sum(line.startswith(b"G1 ") for line in settling)
    assert moves >= 5
    # That motion (the executor's ends: one per G1 line, the retract last; G91 words are relative)
    # ends where the program does, to the written decimals, and stays within 10.5 um of it: the
    # command's last approach after E stops and the settling of the ringing it cancels (10.2 um at
    # most on this square with the margins by each run's end, 9.5 um with 14.7 ms before and
    # after every run; not within 2 um, as this test once said without checking it).
    settle_xy = np.array(compensated.ends)[-1 - moves:-1, 1:3] - original.ends[-1][1:3]
    assert np.abs(settle_xy[-1]).max() <= 1e-9 and np.abs(settle_xy).max() <= 10.5e-3
    if newline == "\r\n":
        assert out.count(b"\n") == out.count(b"\r\n")


def outputs(tmp_path, text: str, profile, flavor: str):
    """The program compensated to dense and to G5 output, each run through the executor. Blocks
    may be one sample short: no minimum length wins over the tolerance (at sharp corners; nor
    LinuxCNC's shortest block: ``fine_servo``)."""
    source = tmp_path / "in.gcode"
    source.write_text(text)
    runs = []
    for output_format in ("dense", "g5"):
        target = tmp_path / f"{output_format}.gcode"
        options = CompensateOptions(flavor=flavor, output_format=output_format,
                                    min_segment_time_s=1 / profile.sample_rate_hz)
        compensate_file(source, target, fine_servo(profile), options)
        runs.append(execute(target, profile.sample_rate_hz, dwell_p_seconds=flavor == "linuxcnc",
                            rests=rest_limits(profile)))
    return execute(source), *runs, (tmp_path / "g5.gcode").read_text().splitlines()


def assert_g5_where_dense_is(dense, g5, period_s, tolerance_mm=1e-3, rounding_mm=0.5e-4, drift_s=0.0):
    """At the dense output's block ends (on the command), the G5 output's XY, Z and E are within the
    tolerance and the rounding of both (``rounding_mm``: the largest per output); both end at the
    same time, but for the last samples at rest (a block that rounds to no motion is not written:
    the end of a settle margin, where the command moves less than the written decimals).
    ``drift_s`` (Marlin, RRF): how far the two outputs' clocks may drift apart on this executor,
    which runs a block in its length over its F, where the writer raises F to make up the
    firmware's ramps between the blocks' speeds (``emitter._feeds``) and the G5 output has fewer
    such ramps. The G5 output is then compared on the dense output's clock: each G5 block end is a
    dense one (the same sample of the command), and between them time is mapped linearly."""
    ends = np.array(dense.ends)
    at_s = ends[:, 0]
    if drift_s:
        g5_s = np.array(g5.ends)[:, 0]
        nearest = np.clip(np.searchsorted(at_s, g5_s), 1, len(at_s) - 1)
        nearest -= np.abs(at_s[nearest - 1] - g5_s) < np.abs(at_s[nearest] - g5_s)
        apart_s = g5_s - at_s[nearest]
        assert np.abs(apart_s).max() <= drift_s
        at_s = at_s + np.interp(at_s, at_s[nearest], apart_s)
    at_ends = positions_at(g5.path, at_s)
    assert np.hypot(*(at_ends[:, :2] - ends[:, 1:3]).T).max() <= tolerance_mm + 2 * rounding_mm * math.sqrt(2)
    assert np.abs(at_ends[:, 2:] - ends[:, 3:]).max() <= tolerance_mm + 2 * rounding_mm
    settle_s = RunMargins.for_profile(PRINTER).settle_s
    assert abs(g5.ends[-1][0] - dense.ends[-1][0]) <= settle_s + 2 * period_s


@pytest.mark.slow
def test_g5_in_inches_relative_xyz_and_e(tmp_path):
    """G20, G91, M83 and a G92 mid-program: G5 words in inches (one more decimal), relative X Y E
    whose rounding residues do not accumulate (the end is exact), E exact at every copied line,
    every copied line in order, and the motion where the dense output's is."""
    lines = ["; relative inches", "G20", "G90", "G1 X0.4 Y0.4 Z0.01 F200", "G91", "M83"]
    for turn in range(3):  # a rounded square, a corner cut by a short move, a copied line mid-motion
        lines += [f"G1 X0.75 Y0 E0.031 F{80 + 20 * turn}", "G1 X0.05 Y0.05 E0.0021", "M106 S128",
                  "G1 X0 Y0.75 E0.031", "G1 X-0.8 Y0 E0.033", "G1 X0 Y-0.8 E0.033", "G1 E-0.03 F1500", "G92 E0"]
    original, dense, g5, text = outputs(tmp_path, "\n".join(lines + ["M107", ""]), PRINTER, "marlin")
    curves = [line for line in text if line.startswith("G5")]
    assert len(curves) >= 10
    xy, e, f = (rf"-?\d+(\.\d{{1,{decimals}}})?" for decimals in (5, 6, 3))  # 0.1 um, 10 nm, 0.001 in/min
    form = rf"G5 I{xy} J{xy} P{xy} Q{xy} X{xy} Y{xy}( E{e})?( F{f})?"
    assert all(re.fullmatch(form, line) for line in curves), curves[:5]
    assert [line for line in g5.nonmotion if line in set(original.nonmotion)] == original.nonmotion
    e_out = [e for line, e in zip(g5.nonmotion, g5.e_at_lines, strict=True) if line in set(original.nonmotion)]
    assert np.abs(np.array(e_out) - np.array(original.e_at_lines)).max() <= 1e-9
    assert abs(g5.extruded - original.extruded) <= 1e-9
    assert np.allclose(g5.ends[-1][1:], original.ends[-1][1:], atol=1e-9)
    # 5 decimals of an inch; the clocks drift apart by the ramps made up (7.3 us at most here: on their
    # own clocks the outputs are 1.370 um apart at 42 mm/s, on one clock 1.213 um)
    assert_g5_where_dense_is(dense, g5, 1 / PRINTER.sample_rate_hz, rounding_mm=0.5e-5 * 25.4, drift_s=10e-6)
    assert len(g5.ends) < len(dense.ends)


@pytest.mark.slow
def test_g5_on_linuxcnc_only_in_the_xy_plane_and_without_z(tmp_path):
    """LinuxCNC runs G5 in G17 only and without Z (the executor refuses G5 outside G17): the
    output is G1 where Z moves, after a copied G18, and after a move line that went back to G17
    until the output does too (before the next copied line)."""
    program = "\n".join([
        "G21 G90 G17", "G0 X0 Y0 Z1", "G1 X20 Y0 F3000", "G1 X20 Y20", "G1 X25 Y25 Z0", "G1 X0 Y20 Z1",
        "G18", "G1 X0 Y0 Z0", "G1 X10 Z2", "G1 X20 Z0", "M8", "G17 G1 X30 Y10", "G1 X0 Y0", "M9",
        "G1 X10 Y20", "G1 X0 Y0", "M2", ""])
    stage = unbudgeted(load_profile("patent-xy-stage"))
    original, dense, g5, text = outputs(tmp_path, program, stage, "linuxcnc")
    assert not any(line.startswith("G5") and ("Z" in line or "E" in line) for line in text)
    assert text.index("G18") < text.index("M8") < text.index("G17") < text.index("M9")
    assert not any(line.startswith("G5") for line in text[text.index("G18"):text.index("G17")])
    assert any(line.startswith("G5") for line in text[:text.index("G18")])
    assert any(line.startswith("G5") for line in text[text.index("M9"):])
    assert [line for line in g5.nonmotion if line in set(original.nonmotion)] == original.nonmotion
    assert np.allclose(g5.ends[-1][1:4], original.ends[-1][1:4], atol=1e-9)
    assert_g5_where_dense_is(dense, g5, 1 / stage.sample_rate_hz)


def test_mode_words_on_move_lines_reach_the_controller(tmp_path):
    """LinuxCNC runs every command on a line: `G91 G1 ...` is rewritten, but the program is in G91
    afterwards, so the output is too before the next copied line."""
    source = tmp_path / "in.gcode"
    source.write_text("G21\nG90\nG1 X10 Y10 F6000\nG91 G1 X5 Y0 F3000\nG1 X0 Y5\nM400\nG1 Z2\n")
    target = tmp_path / "out.gcode"
    compensate_file(source, target, PRINTER, CompensateOptions(flavor="linuxcnc"))
    lines = target.read_text().splitlines()
    assert lines.index("G91") < lines.index("M400") < lines.index("G1 Z2")


def test_breakpoints_keep_chords_within_tolerance():
    """Every chord that spans more than the minimum stays within the tolerance of the samples it
    spans (measured here by brute force); no block is shorter than the minimum but the last."""
    rng = np.random.default_rng(3)
    t = np.arange(20000) * 1e-3
    command = np.column_stack([np.sin(3 * t) * 20, np.cumsum(np.cumsum(rng.normal(size=t.size))) * 1e-5])
    points = breakpoints(command, 1e-3, 2)
    assert points[0] == 0 and points[-1] == len(command) - 1
    assert np.all(np.diff(points)[:-1] >= 2)
    for a, b in zip(points[:-1], points[1:], strict=True):
        frac = np.linspace(0.0, 1.0, b - a + 1)[:, None]
        chord = command[a] + frac * (command[b] - command[a])
        if b - a > 2:
            assert np.linalg.norm(command[a:b + 1] - chord, axis=1).max() <= 1e-3


@pytest.mark.parametrize("digits", [(4, 4, 4, 5, 3), (5, 5, 5, 6, 3), (3,) * 5, (6,) * 5, (7,) * 5])
@pytest.mark.parametrize("newline", [b"\n", b"\r\n"])
@pytest.mark.parametrize("letters", ["XYZEF", "IJPQXYZEF"])
def test_bulk_formatting_matches_decimal_text(digits, newline, letters):
    """Every number is its shortest decimal (as Decimal normalizes it), the words in order, only
    the shown ones: zero, values below 1, negatives, trailing zeros, up to 1e14 units; G5 or G1
    as asked, row by row."""
    digits = (digits[0],) * (len(letters) - len(digits)) + digits
    k = len(letters)
    rng = np.random.default_rng(sum(digits) + len(newline))
    n = 5000
    size = 10 ** rng.integers(0, 15, (n, k))
    cut = 10 ** rng.integers(0, 8, (n, k))
    values = rng.integers(-size, size + 1) // cut * cut  # some with trailing zeros, some all zero
    special = [0, 1, -1, 5, -5, 9, 10, -10, 999, 1000, 1001, -10**6, 10**14 - 1, -10**14 + 1, 10**14]
    values[:len(special)] = np.array(special)[:, None]
    shown = rng.random((n, k)) < 0.7
    shown[:len(special)] = True
    g5 = rng.random(n) < (0.5 if "I" in letters else 0.0)
    expected = b"".join(
        (("G5" if curve else "G1") + "".join(
            f" {letter}{format(Decimal(int(v)).scaleb(-d).normalize(), 'f')}"
            for letter, v, d, s in zip(letters, row, digits, show, strict=True) if s)).encode() + newline
        for row, show, curve in zip(values, shown, g5, strict=True))
    assert line_text(values, shown, np.array(digits), letters, newline, g5) == expected


def test_feed_is_written_only_when_it_changes_also_across_calls():
    emitter = Emitter(np.zeros(len(AXES)), b"\n")
    targets = np.zeros((5, len(AXES)))
    targets[:, 0] = np.arange(1, 6)  # 1 mm in 0.1 s: F600
    first, count = emitter.blocks(targets, np.full(5, 0.1))
    assert count == 5 and first.split(b"\n")[:2] == [b"G1 X1 F600", b"G1 X2"]
    targets[:, 0] = [6, 7, 9, 11, 13]  # 2 mm in 0.1 s from the third block on: F1200
    second, count = emitter.blocks(targets, np.full(5, 0.1))
    assert second == b"G1 X6\nG1 X7\nG1 X9 F1200\nG1 X11\nG1 X13\n"


def test_retraction_and_z_hop_are_copied_lines_with_xy_still(tmp_path):
    """A move of E alone and a Z hop (axes without modes) are copied as they are, one line each,
    between runs that end and start at rest: no written block mixes a creep of X Y with them
    (Klipper would run such a block at its extrude-only limits)."""
    lines = square(e_relative=False)
    hop = lines.index("M106 S128") + 2  # after the first retraction
    lines[hop:hop] = ["G1 Z1.2 F600", "G1 X12 Y12 F6000", "G1 Z0.2 F600"]
    source = tmp_path / "in.gcode"
    source.write_text("\n".join(lines) + "\n")
    target = tmp_path / "out.gcode"
    compensate_file(source, target, PRINTER)
    out = target.read_text().splitlines()
    for copied in ("G1 E2.40000 F2400", "G1 Z1.2 F600", "G1 Z0.2 F600"):
        assert out.count(copied) == lines.count(copied) > 0, copied
    x, y, e = None, None, None
    for line in out:  # absolute X Y E: each written block's extrusion per mm of X Y
        if line.startswith("G92"):
            e = 0.0
        words = dict(re.findall(r"([XYE])(-?[\d.]+)", line)) if line.startswith("G1") else {}
        x1, y1, e1 = (float(words[k]) if k in words else v for k, v in (("X", x), ("Y", y), ("E", e)))
        if e is not None and e1 != e and (x1, y1) != (x, y):
            # the square's 0.04 per mm, a few times over where the command runs ahead of or behind the plan
            assert abs(e1 - e) <= 5 * 0.04 * math.hypot(x1 - x, y1 - y) + 1e-5, line
        x, y, e = x1, y1, e1
