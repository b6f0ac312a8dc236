"""The writer through the whole pipeline on small programs, judged by the executor in
reference.py: lines kept byte-exact, extrusion and end positions exact in every mode; its bulk
number formatting against Decimal's text."""
from decimal import Decimal

import numpy as np
import pytest

from fbspost.pipeline import CompensateOptions, compensate_file
from fbspost.profile import load_profile
from fbspost.writer import _Emitter, _g1_lines, breakpoints
from reference import execute

PRINTER = load_profile("bedslinger-example")


def square(e_relative: bool, xyz_relative: bool = False, inches: bool = False) -> list[str]:
    """Two layers of a 20 mm square with a retract and a G92 E0 between them."""
    unit = 25.4 if inches else 1.0
    lines = ["; test square", "G21" if not inches else "G20", "M83" if e_relative else "M82", "G92 E0",
             "G1 X10 Y10 Z0.2 F6000" if not xyz_relative else "G1 X0 Y0 Z0.2 F6000"]
    if xyz_relative:
        lines = ["; test square", "G21", "G90", "G1 X10 Y10 Z0.2 F6000", "G91", "M83" if e_relative else "M82", "G92 E0"]
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
    e_out = [e for line, e in zip(compensated.nonmotion, compensated.e_at_lines) if line in set(original.nonmotion)]
    assert np.abs(np.array(e_out) - np.array(original.e_at_lines)).max() <= 1e-9
    assert abs(compensated.extruded - original.extruded) <= 1e-9
    # The last motion ends exactly where the original's does.
    assert np.allclose(compensated.ends[-1][1:4], original.ends[-1][1:4], atol=1e-9)
    out = target.read_bytes()
    # The program's last line, then only the controller's acceleration as the program left it.
    tail = out[out.rindex(b"M107"):]
    assert tail in (b"M107" + (newline.encode() if final_newline else b""),
                    b"M107" + newline.encode() + b"M204 P3000 T3000" + newline.encode())
    if newline == "\r\n":
        assert out.count(b"\n") == out.count(b"\r\n")


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
    for a, b in zip(points[:-1], points[1:]):
        frac = np.linspace(0.0, 1.0, b - a + 1)[:, None]
        chord = command[a] + frac * (command[b] - command[a])
        if b - a > 2:
            assert np.linalg.norm(command[a:b + 1] - chord, axis=1).max() <= 1e-3


def test_acceleration_lines_keep_whole_numbers():
    from fbspost.writer import acceleration_line

    assert acceleration_line("marlin", 3000.0, 1500.0) == "M204 P3000 T1500"
    assert acceleration_line("klipper", 10000.0) == "SET_VELOCITY_LIMIT ACCEL=10000"
    assert acceleration_line("linuxcnc", 3000.0) is None


@pytest.mark.parametrize("digits", [(4, 4, 4, 5, 3), (5, 5, 5, 6, 3), (3,) * 5, (6,) * 5, (7,) * 5])
@pytest.mark.parametrize("newline", [b"\n", b"\r\n"])
def test_bulk_formatting_matches_decimal_text(digits, newline):
    """Every number is its shortest decimal (as Decimal normalizes it), the words in order, only
    the shown ones: zero, values below 1, negatives, trailing zeros, up to 1e14 units."""
    rng = np.random.default_rng(sum(digits) + len(newline))
    n = 5000
    size = 10 ** rng.integers(0, 15, (n, 5))
    cut = 10 ** rng.integers(0, 8, (n, 5))
    values = rng.integers(-size, size + 1) // cut * cut  # some with trailing zeros, some all zero
    special = [0, 1, -1, 5, -5, 9, 10, -10, 999, 1000, 1001, -10**6, 10**14 - 1, -10**14 + 1, 10**14]
    values[:len(special)] = np.array(special)[:, None]
    shown = rng.random((n, 5)) < 0.7
    shown[:len(special)] = True
    expected = b"".join(
        ("G1" + "".join(f" {letter}{format(Decimal(int(v)).scaleb(-d).normalize(), 'f')}"
                        for letter, v, d, s in zip("XYZEF", row, digits, show) if s)).encode() + newline
        for row, show in zip(values, shown))
    assert _g1_lines(values, shown, np.array(digits), newline) == expected


def test_feed_is_written_only_when_it_changes_also_across_calls():
    emitter = _Emitter(np.zeros(4), b"\n")
    targets = np.zeros((5, 4))
    targets[:, 0] = np.arange(1, 6)  # 1 mm in 0.1 s: F600
    first, count = emitter.blocks(targets, np.full(5, 0.1))
    assert count == 5 and first.split(b"\n")[:2] == [b"G1 X1 F600", b"G1 X2"]
    targets[:, 0] = [6, 7, 9, 11, 13]  # 2 mm in 0.1 s from the third block on: F1200
    second, count = emitter.blocks(targets, np.full(5, 0.1))
    assert second == b"G1 X6\nG1 X7\nG1 X9 F1200\nG1 X11\nG1 X13\n"
