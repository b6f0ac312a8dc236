"""Tests of fbspost.read.gcode (the G-code reader) against truths written here.

Truths used: positions, feeds and dwell times computed by hand from each small program; circle
centres and sweeps from the geometry of G2/G3 (right-hand rule in the plane's axis order);
the cubic Bezier formula with its arc length integrated numerically here; PlannerLimits written
out from the program text; the file's own bytes for ``raw``; pygcode's parse of a CNC program,
accumulated here; and the extrusion total of the real slicer files from a regex scan here.
"""
from __future__ import annotations

import itertools
import math
import re
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.integrate import cumulative_trapezoid
from scipy.spatial import cKDTree

from fbspost.errors import InputError
from fbspost.read.blocks import Kind, PlannerLimits
from fbspost.read.flavors import detect_flavor
from fbspost.read.gcode import read_gcode

DATA = Path(__file__).resolve().parent / "data"
GEAR = DATA / "gear-marlin2.gcode"  # PrusaSlicer 2.5, marlin2, absolute E with G92 E0 resets
BLOB = DATA / "blob-reprap-relative-e.gcode"  # PrusaSlicer 2.5, reprap, relative E (M83)
NAN = math.nan
TOL = 0.5e-3  # chord error promised by the reader, mm
HOME = "G28\nG1 X0 Y0 Z0 F600\n"  # two lines: at the origin, known, feed 10 mm/s


def read(tmp_path, text, flavor="marlin", name="t.gcode"):
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return list(read_gcode(path, flavor))


def close(actual, expected, atol=1e-12):
    """Positions given as X Y Z E: LinuxCNC's other axes (the columns after) where they were (0 or unknown)."""
    actual, expected = np.asarray(actual, float), np.asarray(expected, float)
    if expected.shape[-1:] == (4,) and actual.shape[-1] > 4:
        actual, rest = actual[..., :4], actual[..., 4:]
        assert np.all((rest == 0) | np.isnan(rest)), rest
    np.testing.assert_allclose(actual, expected, rtol=0, atol=atol)


def before(blocks, line_no):
    """The machine position before line ``line_no`` (1-based)."""
    return blocks[line_no - 2].position_mm


def arc_check(start, points, center, radius, plane=(0, 1)):
    """Every piece end on the circle (1e-9), chord error <= TOL; returns the unwrapped angles
    from the start (strictly monotonic) so callers can check the sweep and the direction."""
    a, b = plane
    pts = np.vstack([start, points[:, :len(start)]])
    du, dv = pts[:, a] - center[0], pts[:, b] - center[1]
    close(np.hypot(du, dv), np.full(len(pts), radius), atol=1e-9)
    theta = np.unwrap(np.arctan2(dv, du))
    step = np.diff(theta)
    assert np.all(step > 0) or np.all(step < 0), "the arc turns back"
    assert np.abs(step).max() < math.pi / 2 + 1e-12
    sagitta = radius * (1.0 - np.cos(step / 2.0))
    assert sagitta.max() <= TOL + 1e-12
    return theta - theta[0]


# ------------------------------------------------------------------------------------------------
# linear moves, feeds, units, modes


def test_linear_absolute_and_relative(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X10 Y5 Z0.2 E1\nG0 X20 F3000\nG91\nG1 X-5 Y2 Z0.5 E0.5\nG1 Z-0.5\n")
    expected = [
        (Kind.MOVE, (10, 5, 0.2, 1), 10.0),
        (Kind.MOVE, (20, 5, 0.2, 1), 50.0),  # Marlin G0: the modal feed, here set by its own F
        (Kind.PASS, (20, 5, 0.2, 1), None),
        (Kind.MOVE, (15, 7, 0.7, 1.5), 50.0),  # G91: E relative too (Marlin)
        (Kind.MOVE, (15, 7, 0.2, 1.5), 50.0),
    ]
    for block, (kind, pos, feed) in zip(blocks[2:], expected, strict=True):
        assert block.kind is kind
        close(block.position_mm, pos)
        if kind is Kind.MOVE:
            assert block.feed_mm_s == pytest.approx(feed, rel=1e-15)
            close(block.points_mm, [pos])  # a line is one piece ending at the target
    assert blocks[5].modal.absolute_xyz is False and blocks[5].modal.absolute_e is False


def test_rapid_is_infinite_feed_in_linuxcnc_only(tmp_path):
    program = HOME + "G0 X10\nG1 X11 F300\nG0 X12\n"
    cnc = read(tmp_path, program, "linuxcnc")
    assert [b.feed_mm_s for b in cnc[2:]] == [math.inf, 5.0, math.inf]
    marlin = read(tmp_path, program, "marlin")
    assert [b.feed_mm_s for b in marlin[2:]] == [10.0, 5.0, 5.0]


def test_modal_feed_and_feed_only_lines(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X1 F1200\nG1 X2\nG1 F3000\nG1 X3\nF600\nG1 X4\nG0 X5\n")
    kinds = [b.kind for b in blocks[2:]]
    assert kinds == [Kind.MOVE, Kind.MOVE, Kind.PASS, Kind.MOVE, Kind.PASS, Kind.MOVE, Kind.MOVE]
    feeds = [b.feed_mm_s for b in blocks[2:]]
    assert feeds == [20.0, 20.0, None, 50.0, None, 10.0, 10.0]
    close(blocks[4].position_mm, (2, 0, 0, 0))  # the F-only line moves nothing


COORD = st.one_of(st.none(), st.integers(-200000, 200000).map(lambda i: i / 1000))
MOVES = st.lists(
    st.tuples(st.booleans(), COORD, COORD, COORD, COORD, st.sampled_from(range(5)), st.booleans()),
    min_size=1, max_size=25,
)


def word_text(letter, value, lower, space):
    text = f"{letter.lower() if lower else letter}{value:.3f}".rstrip("0").rstrip(".")
    return (" " if space else "") + text


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(MOVES)
def test_random_linear_programs(tmp_path, moves):
    """Absolute and relative G1 moves written in five styles against positions summed here."""
    lines, expected = [], []
    pos, relative = [0.0, 0.0, 0.0, 0.0], False
    for rel, x, y, z, e, style, with_feed in moves:
        if rel != relative:
            lines.append("G91" if rel else "G90")
            expected.append((Kind.PASS, list(pos)))
            relative = rel
        words = [(a, v) for a, v in zip("XYZE", (x, y, z, e), strict=True) if v is not None]
        lower, space = style == 1, style != 1
        body = "".join(word_text(a, v, lower, space) for a, v in words)
        feed = word_text("F", 1200.0, lower, space) if with_feed else ""
        line = ("g1" if lower else "G1") + feed + body
        line = ["{}", "{}", "N{} {}*77".format(len(lines) + 3, "{}"), "{} ; note", "/{}"][style].format(line)
        lines.append(line)
        start = list(pos)
        for i, v in enumerate((x, y, z, e)):
            if v is not None:
                pos[i] = pos[i] + v if relative else v  # Marlin: G91 makes E relative too
        expected.append((Kind.PASS if pos == start else Kind.MOVE, list(pos)))
    blocks = read(tmp_path, HOME + "\n".join(lines) + "\n")
    assert len(blocks) == 2 + len(expected)
    for block, (kind, position) in zip(blocks[2:], expected, strict=True):
        assert block.kind is kind, block.raw
        close(block.position_mm, position, atol=1e-9)
        if kind is Kind.MOVE:
            close(block.points_mm, [position], atol=1e-9)
            assert block.feed_mm_s == 10.0 or block.feed_mm_s == 20.0


def test_move_to_where_it_is_passes(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X0 Y0\nG1 X0 E0\nG1 X1\n")
    assert [b.kind for b in blocks[2:]] == [Kind.PASS, Kind.PASS, Kind.MOVE]


def test_inches(tmp_path):
    blocks = read(tmp_path, HOME + "G20\nG1 X1 Y2 F10\nG2 X3 Y2 I1 J0\nG21\nG1 X0 Y0\n")
    assert blocks[2].modal.inches and not blocks[6].modal.inches
    close(blocks[3].position_mm, (25.4, 50.8, 0, 0))
    assert blocks[3].feed_mm_s == pytest.approx(10 * 25.4 / 60, rel=1e-15)
    theta = arc_check(blocks[3].position_mm, blocks[4].points_mm, (50.8, 50.8), 25.4)
    assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)  # G2: clockwise half circle
    close(blocks[4].position_mm, (76.2, 50.8, 0, 0))
    close(blocks[6].position_mm, (0, 0, 0, 0))
    assert blocks[6].feed_mm_s == pytest.approx(10 * 25.4 / 60, rel=1e-15)  # the feed is a speed


@pytest.mark.parametrize(
    "flavor, e_after",
    [
        # G1 X1 E2 | G91 | G1 X1 E1 | G90 | G1 X3 E5 | M83 | G1 X4 E1 | G90 | G1 X5 E1
        ("marlin", [2, 3, 5, 6, 1]),  # G90/G91 set E's mode too; G90 undoes M83
        ("klipper", [2, 3, 5, 6, 7]),  # E relative under G91 or M83
        ("reprap", [2, 1, 5, 6, 7]),  # only M82/M83 decide
    ],
)
def test_e_modes(tmp_path, flavor, e_after):
    program = HOME + "G1 X1 E2\nG91\nG1 X1 E1\nG90\nG1 X3 E5\nM83\nG1 X4 E1\nG90\nG1 X5 E1\n"
    blocks = read(tmp_path, program, flavor)
    moves = [b for b in blocks if b.kind is Kind.MOVE]
    assert [b.line_no for b in moves] == [3, 5, 7, 9, 11]
    close([b.position_mm[0] for b in moves], [1, 2, 3, 4, 5])
    close([b.position_mm[3] for b in moves], e_after)
    assert blocks[7].modal.absolute_e is False  # after M83


def test_g92_offsets(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X3 E5\nG92 E0\nG1 X4 E1\nG92 X10\nG1 X20\nG91\nG1 X1\nG90\nG92 Y-2\nG1 Y0\n")
    b = {blk.line_no: blk for blk in blocks}
    close(b[3].position_mm, (3, 0, 0, 5))
    assert b[4].kind is Kind.PASS
    close(b[4].position_mm, (3, 0, 0, 5))  # the machine does not move
    assert b[4].modal.offsets_mm[:4] == (0, 0, 0, 5)
    close(b[5].position_mm, (4, 0, 0, 6))
    close(b[6].position_mm, (4, 0, 0, 6))
    assert b[6].modal.offsets_mm[:4] == (-6, 0, 0, 5)
    close(b[7].position_mm, (14, 0, 0, 6))  # program X20 = machine 14
    close(b[9].position_mm, (15, 0, 0, 6))
    close(b[12].position_mm, (15, 2, 0, 6))
    assert b[12].modal.offsets_mm[:4] == (-6, 2, 0, 5)


def test_g92_on_unknown_axes_makes_them_known(tmp_path):
    blocks = read(tmp_path, "G92 X0 Y0 Z0\nG1 X5 F600\n")
    close(blocks[0].position_mm, (0, 0, 0, 0))
    assert blocks[1].kind is Kind.MOVE
    close(blocks[1].points_mm, [(5, 0, 0, 0)])


def test_g92_without_words(tmp_path):
    program = HOME + "G1 X3 Y4 E2\nG92\nG1 X1\n"
    marlin = read(tmp_path, program, "marlin")  # Marlin: nothing is set
    assert marlin[3].modal.offsets_mm[:4] == (0, 0, 0, 0)
    close(marlin[4].position_mm, (1, 4, 0, 2))
    klipper = read(tmp_path, program, "klipper")  # Klipper: every axis is now 0
    assert klipper[3].modal.offsets_mm[:4] == (3, 4, 0, 2)
    close(klipper[4].position_mm, (4, 4, 0, 2))
    with pytest.raises(InputError):
        read(tmp_path, program.replace(" E2", ""), "linuxcnc")


def test_dwell_units(tmp_path):
    program = HOME + "G4 P500\nG4 S2\nG4 P1.5\n"
    blocks = read(tmp_path, program, "marlin")
    assert [b.kind for b in blocks[2:]] == [Kind.STOP] * 3
    assert [b.dwell_s for b in blocks[2:]] == [0.5, 2.0, 0.0015]
    cnc = read(tmp_path, HOME + "G4 P1.5\n", "linuxcnc")  # LinuxCNC: P is seconds
    assert cnc[2].kind is Kind.STOP and cnc[2].dwell_s == 1.5
    close(cnc[2].position_mm, (0, 0, 0, 0))


# ------------------------------------------------------------------------------------------------
# syntax


def test_line_numbers_checksums_comments_case_and_spaces(tmp_path):
    program = HOME + (
        "N10 G1 X5 Y1*71\n"
        "N11 M117 hi*3\n"
        "; a comment\n"
        "(a paren comment)\n"
        "G1 X1 (move) Y2 ; c\n"
        "G1 X3;no space\n"
        "g1x10y5e.5\n"
        "g1 x 11 y 6\n"
        "G01X12Y7E1.5F1200\n"
        "/G1 X13\n"
        "   \n"
    )
    blocks = read(tmp_path, program)
    expected = [
        (Kind.MOVE, (5, 1, 0, 0)),
        (Kind.PASS, (5, 1, 0, 0)),
        (Kind.PASS, (5, 1, 0, 0)),
        (Kind.PASS, (5, 1, 0, 0)),
        (Kind.MOVE, (1, 2, 0, 0)),
        (Kind.MOVE, (3, 2, 0, 0)),
        (Kind.MOVE, (10, 5, 0, 0.5)),
        (Kind.MOVE, (11, 6, 0, 0.5)),
        (Kind.MOVE, (12, 7, 0, 1.5)),
        (Kind.MOVE, (13, 7, 0, 1.5)),
        (Kind.PASS, (13, 7, 0, 1.5)),
    ]
    assert len(blocks) == 2 + len(expected)
    for block, (kind, pos) in zip(blocks[2:], expected, strict=True):
        assert block.kind is kind, block.raw
        close(block.position_mm, pos)
    assert blocks[10].feed_mm_s == 20.0


def test_modal_continuation(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X1\nX2 Y3\nG2 X4 Y3 I1 J0\nX6 Y3 I1 J0\nG0 X0 Y0\nY5\n")
    close(blocks[3].position_mm, (2, 3, 0, 0))
    assert blocks[3].kind is Kind.MOVE
    for line, center in ((5, (3, 3)), (6, (5, 3))):  # both clockwise half circles of radius 1
        theta = arc_check(before(blocks, line), blocks[line - 1].points_mm, center, 1.0)
        assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)
    close(blocks[7].position_mm, (0, 5, 0, 0))
    with pytest.raises(InputError, match="motion"):
        read(tmp_path, "X5\n")


def test_raw_bytes_are_exact(tmp_path):
    lines = [
        b"G28\r\n",
        b"G1 X0 Y0 Z0 F600\r\n",
        b"; caf\xe9 \xff not utf-8\r\n",
        b"G1 X1 ; \xfe\xfd\r\n",
        b"M117 \xe9t\xe9\n",
        b"\r\n",
        b"G1 X2",  # the last line has no line ending
    ]
    data = b"".join(lines)
    blocks = read(tmp_path, data)
    assert [b.raw for b in blocks] == lines
    assert b"".join(b.raw for b in blocks) == data
    assert [b.line_no for b in blocks] == list(range(1, 8))
    # (G28 homes to 0: the move to the origin moves nothing)
    assert [b.kind for b in blocks] == [Kind.STOP, Kind.PASS, Kind.PASS, Kind.MOVE, Kind.PASS, Kind.PASS, Kind.MOVE]
    close(blocks[3].position_mm, (1, 0, 0, 0))
    close(blocks[6].position_mm, (2, 0, 0, 0))


def test_reprap_strings(tmp_path):
    program = HOME + 'M83\nM291 P"Print done; ok (really)" S1\nG1 X1\nM98 P"homeall.g"\nG1 X2 Y2 Z1\nG1 X3\n'
    blocks = read(tmp_path, program, "reprap")
    assert blocks[3].kind is Kind.STOP  # an unknown M code: the machine may do anything
    assert blocks[5].kind is Kind.STOP  # a macro call
    close(blocks[5].position_mm, (NAN, NAN, NAN, 0))
    assert blocks[6].kind is Kind.STOP  # the move after a macro passes through
    close(blocks[6].position_mm, (2, 2, 1, 0))
    assert blocks[7].kind is Kind.MOVE


def test_block_arrays_are_copies(tmp_path):
    blocks = read(tmp_path, HOME + "G1 X1\nG1 X2\nM400\n")
    before = [b.position_mm.copy() for b in blocks]
    blocks[2].position_mm[:] = 99.0
    blocks[2].points_mm[:] = 77.0
    for b, p in zip(blocks[3:], before[3:], strict=True):
        close(b.position_mm, p)
    close(blocks[2].position_mm, np.full(len(blocks[2].position_mm), 99.0))


def test_streams_lazily(tmp_path):
    path = tmp_path / "t.gcode"
    path.write_text(HOME + "G1 X1\nG41 D1\n")
    with pytest.raises(ValueError):
        read_gcode(path, "grbl")  # the flavor is checked at the call
    blocks = read_gcode(path, "marlin")
    assert isinstance(blocks, types.GeneratorType)
    got = [next(blocks) for _ in range(3)]  # the bad line 4 is not read yet
    assert got[2].kind is Kind.MOVE
    with pytest.raises(InputError):
        next(blocks)


# ------------------------------------------------------------------------------------------------
# arcs and Beziers


def test_arcs_ij_xy_plane(tmp_path):
    blocks = read(tmp_path, HOME + "G2 X10 Y0 I5 J0\nG3 X20 Y0 I5 J0\nG3 X25 Y5 I0 J5\n")
    cases = [(3, (5, 0), 5, -math.pi), (4, (15, 0), 5, math.pi), (5, (20, 5), 5, math.pi / 2)]
    for line, center, radius, sweep in cases:
        block = blocks[line - 1]
        assert block.kind is Kind.MOVE and block.feed_mm_s == 10.0
        theta = arc_check(before(blocks, line), block.points_mm, center, radius)
        assert theta[-1] == pytest.approx(sweep, abs=1e-12)
        sagitta = radius * (1 - np.cos(np.diff(theta) / 2))
        assert sagitta.max() > 0.4 * TOL  # not needlessly fine
        close(block.points_mm[:, 2:], np.zeros((len(block.points_mm), block.points_mm.shape[1] - 2)))
    assert (blocks[2].points_mm[:, 1] >= 0).all()  # G2 from the left goes over the top
    assert (blocks[3].points_mm[:, 1] <= 1e-12).all()  # G3 from the left goes under
    close(blocks[4].position_mm, (25, 5, 0, 0))


@pytest.mark.parametrize(
    "code, center, sweep, above",
    [
        # from (0,0) to (10,0), |R| = 10: h = sqrt(100 - 25), centre (5, +-h)
        ("G2 X10 Y0 R10", (5, -math.sqrt(75)), -math.pi / 3, True),
        ("G2 X10 Y0 R-10", (5, math.sqrt(75)), -5 * math.pi / 3, True),
        ("G3 X10 Y0 R10", (5, math.sqrt(75)), math.pi / 3, False),
        ("G3 X10 Y0 R-10", (5, -math.sqrt(75)), 5 * math.pi / 3, False),
        ("G2 X10 Y0 R5", (5, 0), -math.pi, True),
        ("G2 X10 Y0 R4.9999999", (5, 0), -math.pi, True),  # within 1e-6 of half the chord
    ],
)
def test_arcs_radius(tmp_path, code, center, sweep, above):
    blocks = read(tmp_path, HOME + code + "\n")
    radius = math.hypot(*center)
    theta = arc_check((0, 0, 0, 0), blocks[2].points_mm, center, radius)
    assert theta[-1] == pytest.approx(sweep, abs=1e-6)
    y = blocks[2].points_mm[:, 1]
    assert (y >= -1e-9).all() if above else (y <= 1e-9).all()


def test_arcs_other_planes(tmp_path):
    blocks = read(tmp_path, HOME + "G18\nG2 X10 Z0 I5 K0\nG19\nG0 X0 Y0 Z0\nG3 Y10 Z0 J5 K0\n")
    # G18: plane Z-X (normal +Y); seen from +Y, G2 from X0 to X10 about X5 dips to Z = -5
    zx = blocks[3].points_mm
    theta = arc_check((0, 0, 0, 0), zx, (0, 5), 5, plane=(2, 0))
    assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)
    assert (zx[:, 2] <= 1e-12).all() and zx[:, 2].min() == pytest.approx(-5, abs=1e-6)
    close(zx[:, 1], np.zeros(len(zx)))
    # G19: plane Y-Z (normal +X); G3 from Y0 to Y10 about Y5 dips to Z = -5
    yz = blocks[6].points_mm
    theta = arc_check((0, 0, 0, 0), yz, (5, 0), 5, plane=(1, 2))
    assert theta[-1] == pytest.approx(math.pi, abs=1e-12)
    assert (yz[:, 2] <= 1e-12).all() and yz[:, 2].min() == pytest.approx(-5, abs=1e-6)
    close(yz[:, 0], np.zeros(len(yz)))


def test_helical_full_circles_and_turns(tmp_path):
    blocks = read(tmp_path, HOME + "G3 X0 Y0 I5 J0 Z2 E1.5\nG2 I-5\nG3 X0 Y0 I5 J0 P2\n")
    helix = blocks[2]
    theta = arc_check((0, 0, 0, 0), helix.points_mm, (5, 0), 5)
    assert theta[-1] == pytest.approx(2 * math.pi, abs=1e-12)  # end = start: a full circle
    close(helix.points_mm[:, 2], 2.0 * theta[1:] / (2 * math.pi), atol=1e-12)  # Z with the angle
    close(helix.points_mm[:, 3], 1.5 * theta[1:] / (2 * math.pi), atol=1e-12)  # E with the length
    close(helix.position_mm, (0, 0, 2, 1.5))
    theta = arc_check(helix.position_mm, blocks[3].points_mm, (-5, 0), 5)
    assert theta[-1] == pytest.approx(-2 * math.pi, abs=1e-12)  # no end words: a full circle
    theta = arc_check(blocks[3].position_mm, blocks[4].points_mm, (5, 0), 5)
    assert theta[-1] == pytest.approx(6 * math.pi, abs=1e-12)  # Marlin P2: two circles, then the arc
    cnc = read(tmp_path, HOME + "G3 X0 Y0 I5 J0 P2\nG2 X10 Y0 I5 J0 P3\n", "linuxcnc")
    theta = arc_check((0, 0, 0, 0), cnc[2].points_mm, (5, 0), 5)
    assert theta[-1] == pytest.approx(4 * math.pi, abs=1e-12)  # LinuxCNC P2: two turns in all
    theta = arc_check((0, 0, 0, 0), cnc[3].points_mm, (5, 0), 5)
    assert theta[-1] == pytest.approx(-5 * math.pi, abs=1e-12)  # half a turn and two more


def test_arc_center_absolute_and_relative(tmp_path):
    program = HOME + "G0 X4 Y0\nG90.1\nG2 X6 Y0 I5 J0\nG91.1\nG2 X8 Y0 I1 J0\nG92 X0\nG90.1\nG3 X2 Y0 I1 J0\n"
    blocks = read(tmp_path, program)
    theta = arc_check((4, 0, 0, 0), blocks[4].points_mm, (5, 0), 1)  # I5 is the centre itself
    assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)
    theta = arc_check((6, 0, 0, 0), blocks[6].points_mm, (7, 0), 1)  # I1 from the start
    assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)
    # after G92 X0 at machine X8, the program's centre X1 is machine X9, its end X2 machine X10
    theta = arc_check((8, 0, 0, 0), blocks[9].points_mm, (9, 0), 1)
    assert theta[-1] == pytest.approx(math.pi, abs=1e-12)
    close(blocks[9].position_mm, (10, 0, 0, 0))


def bezier(t, p0, p1, p2, p3):
    t = np.asarray(t, float)[..., None]
    s = 1 - t
    return s**3 * p0 + 3 * s * s * t * p1 + 3 * s * t * t * p2 + t**3 * p3


@pytest.mark.parametrize("flavor", ["marlin", "linuxcnc"])
def test_bezier(tmp_path, flavor):
    e_words = " E2" if flavor == "marlin" else ""
    blocks = read(tmp_path, HOME + f"G5 I10 J0 P0 Q10 X20 Y20{e_words}\n", flavor)
    block = blocks[2]
    assert block.kind is Kind.MOVE
    # I J from the start, P Q from the end
    p0, p1, p2, p3 = (np.array(p, float) for p in ((0, 0), (10, 0), (20, 30), (20, 20)))
    points = block.points_mm
    close(points[-1], (20, 20, 0, 2 if e_words else 0))
    # each piece end's parameter on the cubic: nearest of a dense grid, then Newton
    grid = np.linspace(0, 1, 200001)
    curve = bezier(grid, p0, p1, p2, p3)
    t = grid[cKDTree(curve).query(points[:, :2])[1]]
    for _ in range(8):
        d1 = (
            3 * (1 - t[:, None]) ** 2 * (p1 - p0)
            + 6 * (1 - t[:, None]) * t[:, None] * (p2 - p1)
            + 3 * t[:, None] ** 2 * (p3 - p2)
        )
        d2 = 6 * (1 - t[:, None]) * (p2 - 2 * p1 + p0) + 6 * t[:, None] * (p3 - 2 * p2 + p1)
        r = bezier(t, p0, p1, p2, p3) - points[:, :2]
        t = np.clip(t - (r * d1).sum(1) / ((d1 * d1).sum(1) + (r * d2).sum(1)), 0, 1)
    distance = np.hypot(*(bezier(t, p0, p1, p2, p3) - points[:, :2]).T)
    assert distance.max() <= 1e-9
    assert np.all(np.diff(np.concatenate([[0.0], t])) > 0)
    # chord error: the curve between consecutive ends against the chord
    ts = np.concatenate([[0.0], t])
    ends = np.vstack([p0, points[:, :2]])
    worst = 0.0
    for k in range(len(points)):
        s = np.linspace(ts[k], ts[k + 1], 41)
        c = bezier(s, p0, p1, p2, p3)
        a, b = ends[k], ends[k + 1]
        ab = b - a
        cross = np.abs(ab[0] * (c[:, 1] - a[1]) - ab[1] * (c[:, 0] - a[0])) / np.hypot(*ab)
        worst = max(worst, cross.max())
    assert worst <= TOL + 1e-12
    assert worst > 0.2 * TOL  # not needlessly fine
    if e_words:  # E in proportion to the arc length
        speed = np.hypot(
            *(
                3 * (1 - grid[:, None]) ** 2 * (p1 - p0)
                + 6 * (1 - grid[:, None]) * grid[:, None] * (p2 - p1)
                + 3 * grid[:, None] ** 2 * (p3 - p2)
            ).T
        )
        length = cumulative_trapezoid(speed, grid, initial=0.0)
        expected_e = 2.0 * np.interp(t, grid, length) / length[-1]
        close(points[:, 3], expected_e, atol=1e-8)
    with pytest.raises(InputError, match="XY"):
        read(tmp_path, HOME + "G18\nG5 I10 J0 P0 Q10 X20 Y20\n", flavor)


# ------------------------------------------------------------------------------------------------
# limits, classification, unknown positions


def test_planner_limits(tmp_path):
    program = (
        "M204 S1000\n"
        "M204 P500 T800 R1500\n"
        "M204 R3000\n"
        "M201 X2000 Y1500 Z100 E5000\n"
        "M203 X300 Y250 Z10 E60\n"
        "M205 J0.02\n"
        "M205 X8 Y10 Z0.4 E5\n"
        "SET_VELOCITY_LIMIT VELOCITY=200 ACCEL=3000 SQUARE_CORNER_VELOCITY=5 "
        "ACCEL_TO_DECEL=1500 MINIMUM_CRUISE_RATIO=0.5\n"
        "SET_VELOCITY_LIMIT ACCEL_TO_DECEL=100\n"
    )
    blocks = read(tmp_path, program, "marlin")
    assert all(b.kind is Kind.PASS for b in blocks)
    assert [b.limits for b in blocks] == [
        PlannerLimits(acceleration_mm_s2=1000.0, travel_acceleration_mm_s2=1000.0),
        PlannerLimits(acceleration_mm_s2=500.0, travel_acceleration_mm_s2=800.0),
        None,
        PlannerLimits(axis_max_acceleration_mm_s2={"X": 2000.0, "Y": 1500.0, "Z": 100.0, "E": 5000.0}),
        PlannerLimits(axis_max_velocity_mm_s={"X": 300.0, "Y": 250.0, "Z": 10.0, "E": 60.0}),
        PlannerLimits(junction_deviation_mm=0.02),
        PlannerLimits(square_corner_velocity_mm_s=8.0),  # classic jerk: min of X and Y
        PlannerLimits(acceleration_mm_s2=3000.0, travel_acceleration_mm_s2=3000.0, max_velocity_mm_s=200.0,
                      square_corner_velocity_mm_s=5.0, minimum_cruise_ratio=0.5, accel_to_decel_mm_s2=1500.0),
        PlannerLimits(accel_to_decel_mm_s2=100.0),
    ]
    rrf = read(tmp_path, "M203 X18000 Y12000 Z600\nM566 X600 Y900\nM204 P1200 T3000\n", "reprap")
    assert rrf[0].limits == PlannerLimits(axis_max_velocity_mm_s={"X": 300.0, "Y": 200.0, "Z": 10.0})  # mm/min
    assert rrf[1].limits == PlannerLimits(square_corner_velocity_mm_s=10.0)
    assert rrf[2].limits == PlannerLimits(acceleration_mm_s2=1200.0, travel_acceleration_mm_s2=3000.0)
    klipper = read(tmp_path, "M204 P1200 T3000\nM204 S2500\n", "klipper")
    assert klipper[0].limits == PlannerLimits(acceleration_mm_s2=1200.0, travel_acceleration_mm_s2=1200.0)
    assert klipper[1].limits == PlannerLimits(acceleration_mm_s2=2500.0, travel_acceleration_mm_s2=2500.0)


PASS_LINES = [
    "",
    "; comment",
    "M104 S200",
    "M106 S255",
    "M107",
    "M140 S60",
    "M141 S40",
    "M73 P10 R5",
    "M117 Printing X...",
    "M118 E1 hello",
    "M82",
    "G90",
    "G21",
    "G17",
    "G90.1",
    "G91.1",
    "M221 S100",
    "M900 K0.04",
    "M486 S1",
    "M104 S200 T1",
    'M862.3 P "MK3S"',
    "M862.1 P0.4",
    "M115 U3.9.0",
    "M84",
    "M18",
    "SET_FAN_SPEED FAN=part SPEED=0.5",
    "SET_PRESSURE_ADVANCE ADVANCE=0.04",
    "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60",
    "EXCLUDE_OBJECT_DEFINE NAME=a CENTER=1,2 POLYGON=[[0,0],[1,1]]",
    "EXCLUDE_OBJECT_START NAME=a",
    "EXCLUDE_OBJECT_END NAME=a",
    "F1200",
    "S100",
    "M204 S500",
    "M201 X100",
    "M203 X100",
    "M205 X10",
    "G92 E0",
    "SET_VELOCITY_LIMIT ACCEL=500",
]
STOP_KEEP_LINES = [
    "G4 P10",
    "M400",
    "M0",
    "M1",
    "M109 S200",
    "M190 S60",
    "M191 S40",
    "M116",
    "T1",
    "M600",
    "G10",
    "G11",
]
STOP_HOME_LINES = [("G28 X", "X"), ("G28 Y0 Z0", "YZ"), ("G28", "XYZ"), ("G28 W", "XYZ")]  # (line, axes homed)
STOP_UNKNOWN_LINES = [  # (line, axes unknown afterwards)
    ("G29", "XYZ"), ("G30", "XYZ"),
    ("G38.2 Z-10", "XYZ"), ('M98 P"x.g"', "XYZ"), ("BED_MESH_CALIBRATE", "XYZ"), ("PRINT_START BED=60", "XYZ"),
    ("G12345", "XYZ"), ("M9999", "XYZ"), ("G80", "XYZ"), ("M32 file.gco", "XYZ"),
]


@pytest.mark.parametrize("line", PASS_LINES)
def test_pass_lines(tmp_path, line):
    blocks = read(tmp_path, HOME + "M83\nG1 X1 Y2 Z3\n" + line + "\n")
    assert blocks[-1].kind is Kind.PASS
    close(blocks[-1].position_mm, (1, 2, 3, 0))


@pytest.mark.parametrize("line, flavor, kind", [
    ("G10 S210 P0", "reprap", Kind.PASS),  # a tool's temperatures: RRF goes on moving
    ("G10 P1 R140 S205", "reprap", Kind.PASS),
    ("G10", "reprap", Kind.STOP),  # firmware retraction, an E move: X and Y at rest
    ("G10 P0 X1", "reprap", Kind.STOP),  # a tool offset (RRF locks the movement)
    ("G10 L2 P1 X0", "reprap", Kind.STOP),  # a coordinate system
    ("G10 S210 P0", "marlin", Kind.STOP),  # Marlin's G10 is a retraction whatever its words
])
def test_reprap_tool_temperatures_pass_while_the_machine_moves(tmp_path, line, flavor, kind):
    """RepRapFirmware's G10 P S R sets a tool's temperatures without waiting for the motion
    (GCodes::SetOrReportOffsets locks the movement only for an offset): a PrusaSlicer RRF
    print's second-layer temperature is no stop there, as the bracket's line 215 is not."""
    blocks = read(tmp_path, HOME + "M83\nG1 X1 Y2 Z3\n" + line + "\nG1 X4\n", flavor)
    assert blocks[-2].kind is kind
    if kind is Kind.PASS:
        close(blocks[-2].position_mm, (1, 2, 3, 0))
        assert blocks[-1].kind is Kind.MOVE


@pytest.mark.parametrize("line", STOP_KEEP_LINES)
def test_stop_lines_keep_the_position(tmp_path, line):
    blocks = read(tmp_path, HOME + "M83\nG1 X1 Y2 Z3\n" + line + "\nG1 X4\n")
    assert blocks[-2].kind is Kind.STOP
    close(blocks[-2].position_mm, (1, 2, 3, 0))
    assert blocks[-1].kind is Kind.MOVE
    assert blocks[-2].dwell_s == (0.01 if line == "G4 P10" else 0.0)


@pytest.mark.parametrize("line, unknown", STOP_UNKNOWN_LINES)
def test_stop_lines_lose_the_position(tmp_path, line, unknown):
    blocks = read(tmp_path, HOME + "M83\nG1 X1 Y2 Z3 E1\n" + line + "\nG1 X4 Y5 Z6 E1\nG1 X7\n")
    stop, after, last = blocks[-3:]
    assert stop.kind is Kind.STOP
    expected = [NAN if a in unknown else v for a, v in zip("XYZ", (1, 2, 3), strict=True)] + [1]  # E (relative) kept
    close(stop.position_mm, expected)
    assert after.kind is Kind.STOP and after.points_mm is None  # passes through: the controller plans it
    close(after.position_mm, (4, 5, 6, 2))  # absolute words: known again
    assert last.kind is Kind.MOVE


@pytest.mark.parametrize("line, homed", STOP_HOME_LINES)
def test_homing_puts_the_axes_at_home(tmp_path, line, homed):
    """G28 leaves the axes it homes at the home position (0 here), the others where they were; the
    next move is planned from there."""
    blocks = read(tmp_path, HOME + "M83\nG1 X1 Y2 Z3 E1\n" + line + "\nG1 X4 Y5 Z6 E1\n")
    stop, after = blocks[-2:]
    assert stop.kind is Kind.STOP
    close(stop.position_mm, [0.0 if a in homed else v for a, v in zip("XYZ", (1, 2, 3), strict=True)] + [1])
    assert after.kind is Kind.MOVE
    close(after.points_mm, [(4, 5, 6, 2)])


def test_unknown_start(tmp_path):
    blocks = read(tmp_path, "G1 X5 F600\nG91\nG1 Y1\nG90\nG2 X10 Y0 I5 J0\nG1 Z0\nG1 X7\nM82\nPRINT_START\nG92 E0\n")
    assert blocks[0].kind is Kind.STOP
    close(blocks[0].position_mm, (5, NAN, NAN, 0))  # XYZ unknown at the start, E known at 0
    close(blocks[2].position_mm, (5, NAN, NAN, 0))  # relative on an unknown axis: still unknown
    assert blocks[4].kind is Kind.STOP and blocks[4].points_mm is None
    close(blocks[4].position_mm, (10, 0, NAN, 0))
    assert blocks[5].kind is Kind.STOP
    assert blocks[6].kind is Kind.MOVE
    close(blocks[8].position_mm, (NAN, NAN, NAN, NAN))  # a macro while E is absolute: E lost too
    close(blocks[9].position_mm, (NAN, NAN, NAN, 0))


def test_moves_need_only_the_axes_they_move(tmp_path):
    """An XY program that never sets Z moves; the unknown Z column is NaN. After G28 X, Y moves."""
    blocks = read(tmp_path, "G0 X0 Y0\nG1 X1 Y1 F60\nG2 X3 Y1 I1 J0\nG1 Z2\nG28 X\nG1 Y5\nG1 X1 Y6\n", "linuxcnc")
    assert "".join(b.kind.name[0] for b in blocks) == "SMMSSMS"
    close(blocks[1].points_mm, [(1, 1, NAN, 0)])
    assert blocks[1].feed_mm_s == 1.0
    arc = blocks[2].points_mm
    assert np.isnan(arc[:, 2]).all() and (arc[:, 3] == 0).all()
    theta = arc_check((1, 1, NAN, 0), arc, (2, 1), 1)
    assert theta[-1] == pytest.approx(-math.pi, abs=1e-12)
    close(blocks[3].position_mm, (3, 1, 2, 0))  # Z named on an unknown start: passes through
    close(blocks[5].points_mm, [(NAN, 5, 2, 0)])  # only X lost by G28 X


def test_linuxcnc_program(tmp_path):
    program = (
        "%\n"
        "O1000 (pocket)\n"
        "G17 G21 G90 G64 P0.01 G40 G49 G80 G54 G94\n"
        "T1 M6\n"
        "M3 S1000\n"
        "M8\n"
        "G0 X0 Y0 Z5\n"
        "G1 Z0 F100\n"
        "G0 X10\n"
        "G4 P1.5\n"
        "G55\n"
        "G0 X0 Y0 Z5\n"
        "G53 G0 Z0\n"
        "X1 Y1 Z1\n"
        "G1 X2\n"
        "M5 M9\n"
        "M30\n"
        "%\n"
    )
    blocks = read(tmp_path, program, "linuxcnc")
    kinds = "PPPSPPSMMSSSSSMPSP"
    assert "".join(b.kind.name[0] for b in blocks) == kinds
    assert blocks[7].feed_mm_s == pytest.approx(100 / 60, rel=1e-15)
    assert blocks[8].feed_mm_s == math.inf
    close(blocks[8].position_mm, (10, 0, 0, 0))
    assert blocks[9].dwell_s == 1.5
    assert np.isnan(blocks[10].position_mm[:3]).all()  # G55: another work offset, unknown here
    close(blocks[11].position_mm, (0, 0, 5, 0))  # known again in the new frame (E stays 0)
    close(blocks[12].position_mm, (NAN, NAN, NAN, 0))  # G53: machine coordinates, unknown here
    close(blocks[13].position_mm, (1, 1, 1, 0))  # modal G0 from an unknown start passes through
    assert blocks[14].feed_mm_s == pytest.approx(100 / 60, rel=1e-15)


# ------------------------------------------------------------------------------------------------
# errors

LONG = "9" * 400
BAD = [
    ("G41 D1", "linuxcnc"), ("G42 D1", "linuxcnc"), ("G41 D1", "marlin"), ("G68 X0 Y0 R45", "linuxcnc"),
    ("G51 X0 Y0 P2", "linuxcnc"), ("G73 X1 Y1 Z-1 R1 Q0.5", "linuxcnc"), ("G76 P0.05 Z-1 I-0.1 J0.1 K0.2", "linuxcnc"),
    *[(f"G{g} X1 Y1 Z-1 R1", "linuxcnc") for g in range(81, 90)],
    ("G93", "linuxcnc"), ("G1 X1 E1", "linuxcnc"), ("o100 sub", "linuxcnc"), ("G1 X#1", "linuxcnc"),
    *[(f"G1 X1 {axis}5", "marlin") for axis in "ABCUVW"],
    ("G1 X", "marlin"), ("G1 Xabc", "marlin"), ("G1 X1.2.3", "marlin"), ("G1 Xnan", "marlin"), ("G1 Xinf", "marlin"),
    (f"G1 X{LONG}", "marlin"), ("G1 X1 X2", "marlin"),
    ("G2 X10 Y0 I0 J0", "marlin"), ("G2 X10 Y0", "marlin"), ("G2 X10 Y0 R4.99", "marlin"), ("G3 X10 Y0 R-4", "marlin"),
    ("G2 X10.1 Y0 I5 J0", "marlin"),  # the end 0.1 mm off the circle
    ("G1 X1 F0", "marlin"), ("G1 X1 F-10", "marlin"), ("G0 X1 F0", "linuxcnc"), ("G1 X1 Y1 F0", "klipper"),
    ("G1 F0", "marlin"), ("M204 S0", "marlin"), ("G4 P-5", "marlin"),
    ("G5 P0 Q1 X2 Y2", "linuxcnc"), ("G5 I1 J0 X2 Y2", "linuxcnc"),  # LinuxCNC: I J first, P Q always
]


@pytest.mark.parametrize("line, flavor", BAD)
def test_bad_input_names_file_and_line(tmp_path, line, flavor):
    path = tmp_path / "bad.gcode"
    path.write_text(HOME + line + "\nG1 X1\n")
    with pytest.raises(InputError) as info:
        list(read_gcode(path, flavor))
    assert str(info.value).startswith(f"{path}:3: ")


# ------------------------------------------------------------------------------------------------
# flavor detection


@pytest.mark.parametrize(
    "text, flavor",
    [
        ("PRINT_START BED=60\nG1 X1 Y1 E1\n", "klipper"),
        ("G1 X1 E1\n; gcode_flavor = klipper\n", "klipper"),
        (";FLAVOR:Marlin\nSET_PRESSURE_ADVANCE ADVANCE=0.04\nG1 X1 E1\n", "klipper"),
        ("G1 X1 E1\nEXCLUDE_OBJECT_START NAME=a\n", "klipper"),
        (";FLAVOR:RepRap\nG1 X1 E1\n", "reprap"),
        ('M98 P"config.g"\nG1 X1 E1\n', "reprap"),
        ('M291 P"hello" S1\nG1 X1 E1\n', "reprap"),
        ("G1 X1 E1\n; gcode_flavor = reprapfirmware\n", "reprap"),
        ("%\nO1000 (pocket)\nG17 G21 G90 G64 P0.01\nG0 X0 Y0\nG1 X10 F300\nM30\n%\n", "linuxcnc"),
        ("(outline)\nG0 X0 Y0\nG1 X10 F300\nM2\n", "linuxcnc"),
        (";FLAVOR:Marlin\nG1 X1 E1\n", "marlin"),
        ("G1 X1 E1\n; gcode_flavor = marlin2\n", "marlin"),
        ('M862.3 P "MK3S"\nG1 X1 E1\n', "marlin"),
        ("G1 X1 Y1 E1\n", "marlin"),
        ("G17\nG1 X1 E1\nM2\n", "marlin"),  # CNC-like words, but it extrudes
    ],
)
def test_detect_flavor(tmp_path, text, flavor):
    path = tmp_path / "f.gcode"
    path.write_text(text)
    assert detect_flavor(path) == flavor


def test_detect_flavor_reads_only_head_and_tail(tmp_path):
    body = ["G1 X1 Y1 E1\n"] * 5000
    for where, flavor in ((3000, "marlin"), (4800, "klipper"), (1500, "klipper")):
        lines = body.copy()
        lines[where] = "SET_PRESSURE_ADVANCE ADVANCE=0.04\n"
        path = tmp_path / f"f{where}.gcode"
        path.write_text("".join(lines))
        assert detect_flavor(path) == flavor


def test_detect_flavor_of_real_files():
    assert detect_flavor(GEAR) == "marlin"
    assert detect_flavor(BLOB) == "reprap"


# ------------------------------------------------------------------------------------------------
# real files and an independent parser


def scan_extrusion(path):
    """E change of each G0/G1 line with an E word, from the text alone (M82/M83, G92 E)."""
    deltas, absolute, e = {}, True, 0.0
    with open(path, encoding="utf-8", errors="replace") as f:
        for n, line in enumerate(f, 1):
            code = line.split(";")[0].strip().upper()
            word = re.search(r"\bE([-+]?[\d.]+)", code)
            if re.match(r"M82\b", code):
                absolute = True
            elif re.match(r"M83\b", code):
                absolute = False
            elif re.match(r"G92\b", code) and word:
                e = float(word.group(1))
            elif re.match(r"G0?[01]\b", code) and word:
                v = float(word.group(1))
                deltas[n] = v - e if absolute else v
                e = v if absolute else e + v
    return deltas


@pytest.mark.parametrize("path", [GEAR, BLOB], ids=["absolute-e", "relative-e"])
@pytest.mark.slow
def test_total_extrusion_of_real_files(path):
    deltas = scan_extrusion(path)
    blocks = list(read_gcode(path, detect_flavor(path)))
    assert len(blocks) == sum(1 for _ in open(path, "rb"))
    moved, passed_through = 0.0, []
    for prev, block in itertools.pairwise(blocks):
        if block.line_no in deltas:
            assert block.position_mm[3] - prev.position_mm[3] == pytest.approx(deltas[block.line_no], abs=1e-9)
        if block.kind is Kind.MOVE:
            d = block.points_mm[-1, 3] - prev.position_mm[3]
            assert d == pytest.approx(deltas.get(block.line_no, 0.0), abs=1e-9)
            moved += d
        elif block.line_no in deltas:
            passed_through.append(block.line_no)
    # only the start, before X, Y and Z are all known after G28, passes through
    assert len(passed_through) <= 2 and all(n < 40 for n in passed_through)
    total = sum(deltas.values())
    assert total > 100.0
    assert moved == pytest.approx(total - sum(deltas[n] for n in passed_through), abs=1e-6)


def pocket_program():
    """A CNC program: rounded-rectangle pocket outlines, alternately G3 and G2, some modal lines."""
    out = ["G17 G21 G90", "G0 Z5.000"]
    for k in range(24):
        inset, r = 0.75 * k, 6.0
        x0, y0, x1, y1 = 10 + inset, 10 + inset, 110 - inset, 80 - inset
        out += [f"G0 X{x0 + r:.3f} Y{y0:.3f}", f"G1 Z{-0.25 * (k % 4 + 1):.3f} F120"]
        if k % 2 == 0:  # counter-clockwise
            out += [
                f"G1 X{x1 - r:.3f} Y{y0:.3f} F{600 + 10 * k}",
                f"G3 X{x1:.3f} Y{y0 + r:.3f} I0 J{r:.3f}",
                f"G1 Y{y1 - r:.3f}",
                f"G3 X{x1 - r:.3f} Y{y1:.3f} I{-r:.3f} J0",
                f"G1 X{x0 + r:.3f}",
                f"X{x0 + r - 0.5:.3f}",  # modal G1
                f"X{x0 + r:.3f}",
                f"G3 X{x0:.3f} Y{y1 - r:.3f} I0 J{-r:.3f}",
                f"G1 Y{y0 + r:.3f}",
                f"G3 X{x0 + r:.3f} Y{y0:.3f} I{r:.3f} J0",
            ]
        else:  # clockwise, one corner as a modal G2
            out += [
                f"G1 X{x0:.3f} Y{y0:.3f} F{600 + 10 * k}",
                f"G1 X{x0:.3f} Y{y0 + r:.3f}",
                f"G1 Y{y1 - r:.3f}",
                f"G2 X{x0 + r:.3f} Y{y1:.3f} I{r:.3f} J0",
                f"G1 X{x1 - r:.3f}",
                f"G2 X{x1:.3f} Y{y1 - r:.3f} I0 J{-r:.3f}",
                f"G1 Y{y0 + r:.3f}",
                f"G2 X{x1 - r:.3f} Y{y0:.3f} I{-r:.3f} J0",
                f"X{x1 - 2 * r:.3f} Y{y0 + r:.3f} I0 J{r:.3f}",  # modal G2 back up
                f"G1 X{x0 + r:.3f} Y{y0:.3f}",
            ]
        out.append("G0 Z5.000")
    out.append("M30")
    return out


def test_cnc_program_against_pygcode(tmp_path):
    pygcode = pytest.importorskip("pygcode")
    from pygcode.gcodes import GCodeFeedRate

    lines = pocket_program()
    assert len(lines) > 250
    blocks = read(tmp_path, "\n".join(lines) + "\n", "linuxcnc")
    assert len(blocks) == len(lines)
    pos, motion, feed = [NAN, NAN, NAN], None, None
    moves = arcs = 0
    for text, block in zip(lines, blocks, strict=True):
        parsed = pygcode.Line(text).block
        words = None
        for g in parsed.gcodes:
            if isinstance(g, GCodeFeedRate):
                feed = g.word.value / 60.0
            elif g.word is not None and g.word.letter == "G" and g.word.value in (0, 1, 2, 3):
                motion, words = int(g.word.value), g.get_param_dict()
        if words is None and parsed.modal_params:
            words = {w.letter: w.value for w in parsed.modal_params}
        if not words:
            continue
        start = list(pos)
        pos = [words.get(a, p) for a, p in zip("XYZ", pos, strict=True)]
        close(block.position_mm[:3], pos, atol=1e-3)
        if block.kind is not Kind.MOVE:
            assert np.isnan(start).any()  # only moves from an unknown start pass through
            continue
        moves += 1
        assert block.feed_mm_s == (math.inf if motion == 0 else pytest.approx(feed, abs=1e-3))
        close(block.points_mm[-1, :3], pos, atol=1e-3)
        if motion in (2, 3):
            arcs += 1
            center = (start[0] + words.get("I", 0.0), start[1] + words.get("J", 0.0))
            radius = math.hypot(start[0] - center[0], start[1] - center[1])
            theta = arc_check(np.array(start + [0.0]), block.points_mm, center, radius)
            assert theta[-1] * (1 if motion == 3 else -1) > 0
    assert moves > 250 and arcs == 4 * 24


def test_linuxcnc_work_offsets_from_the_parameter_file_make_a_switch_a_move(tmp_path):
    """With LinuxCNC's work offsets known (the profile's parameter file), a switch between systems
    the program selected moves the frame by the difference of their offsets: the rapid after it
    is a MOVE from where the tool is, to the target in the new frame (machine = program + offset
    difference, by hand); G92.1 keeps the work offset but loses XYZ (it takes off the machine's own
    G92 offsets too, which LinuxCNC keeps from program to program); the program's first selection
    loses XYZ (the machine's system before it is unknown); a G10 drops the file's offsets."""
    offsets = [(0.0, 0.0, 0.0), (10.0, -5.0, 1.0), (2.0, 2.0, 0.0)] + [(0.0, 0.0, 0.0)] * 6
    program = ("G21 G90\nG0 X1 Y1 Z0\nG54\nG0 X1 Y1 Z0\nG1 X2 F600\nG55\nG0 X0 Y0\nG92 X5\nG92.1\nG56\n"
               "G0 X3 Y1 Z0\nG10 L2 P2 X0\nG55\nG0 X0 Y0\n")
    (tmp_path / "p.ngc").write_text(program)
    blocks = list(read_gcode(tmp_path / "p.ngc", "linuxcnc", work_offsets_mm=offsets))
    assert np.isnan(blocks[2].position_mm[:3]).all()  # the first G54: from the machine's unknown system
    assert blocks[5].kind is Kind.PASS
    assert blocks[6].kind is Kind.MOVE and blocks[6].feed_mm_s == math.inf
    close(blocks[6].points_mm[-1, :3], (10.0, -5.0, 0.0))  # G55's X0 Y0 where G54's is (10, -5); Z stays
    assert blocks[6].modal.offsets_mm[:3] == (10.0, -5.0, 1.0)
    assert blocks[8].modal.offsets_mm[:3] == (10.0, -5.0, 1.0)  # G92.1: G55's own offsets stay
    assert np.isnan(blocks[8].position_mm[:3]).all()
    close(blocks[10].position_mm[:3], (5.0, 3.0, 0.0))  # G56's (3, 1) + its offset (2, 2)
    assert np.isnan(blocks[12].position_mm[:3]).all()  # after G10 the offsets are the program's own
    assert blocks[13].kind is Kind.STOP
    unknown = list(read_gcode(tmp_path / "p.ngc", "linuxcnc"))  # without the file: lost at every switch
    assert np.isnan(unknown[5].position_mm[:3]).all() and unknown[6].kind is Kind.STOP
