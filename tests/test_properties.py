"""Properties of `compensate` over random valid programs (hypothesis), judged by the executor in
reference.py: the output parses; every non-motion line is there byte-exact and in order; E (and Z,
which has no modes) at every one of them, X and Y where the machine rests (G4) and every axis at
the end are the original's; the output lasts as long as the planned original with its lead and
settle margins; the predicted RMS error is never worse than the original's, and the largest
error is within the fallback's bound: outside the stretches it reports, no sample's error is
above the original's largest around it (check_largest_error).

The programs: Marlin, 10 to 40 lines of G0/G1 (X Y Z E F), G2/G3 (I J and R), G4, M82/M83
with absolute and relative E, G90/G91, G92 E0 and G92 X Y, comments (`;` and `( )`, with bytes
that are not UTF-8), passthrough lines, blank lines, LF and CRLF endings, the last line with or
without one. A few mm at tens of mm/s: a second or two of motion each.

`test_fuzz` runs the same checks for about a minute with a fixed seed. `test_with_stops` adds
lines where the machine rests (G4, M400, T0), with the programs that failed it once (as
@example); `test_with_stops_command_never_worse` checks the largest error too, on the command
itself. The other tests generate programs without them.
"""
import math
import re
import tempfile
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, seed, settings
from hypothesis import strategies as st

from fbspost.fbs import fallback
from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.fallback import FALLBACK, AxisGuard
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits
from fbspost.job.pipeline import SHAPING_LEFT_OFF, compensate_file, compensated_samples
from fbspost.job.report import CompensateOptions
from fbspost.plan.margins import RunMargins
from fbspost.plan.pieces import CLAMPED
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import execute, kept_lines, rest_limits, rms, sample_blocks, simulate_lsim, unbudgeted

# The programs here move around X0 Y0 (arcs, G92 X Y below it): a travel that holds them, not
# Marlin's default minimum 0 (test_bad_input and test_optimizer test the travel).
PRINTER = unbudgeted(load_profile("bedslinger-example"))
PRINTER = replace(PRINTER, axes={**PRINTER.axes, **{a: replace(PRINTER.axes[a], position_min_mm=-1000.0)
                                                    for a in "XY"}})
OPTIONS = CompensateOptions(flavor="marlin")
MARGINS = RunMargins.for_profile(PRINTER, flavor="marlin")
PASSTHROUGH = [b"M106 S128", b"M107", b"M104 S205", b"M140 S60", b"M117 Layer 2", b"; LAYER_CHANGE",
               b"(a CNC comment)", b"", b"M204 S2500", b"M221 S95"]
STOPS = [b"T0", b"M400"]  # the machine rests there, as at G4


def fixed(value: float, decimals: int = 3) -> str:
    return f"{value:.{decimals}f}"


@st.composite
def programs(draw, stops: bool = True) -> bytes:
    """A valid Marlin program; its position is tracked here in program coordinates, so that arcs
    end on their circle and stay a few mm in size. Without ``stops``: no line where the machine
    rests (G4, M400, T0) and so no G92 X Y (see test_with_stops)."""
    x, y = (round(draw(st.floats(0, 20)), 3) for _ in range(2))
    z, e = 0.2, 0.0
    abs_xyz, abs_e = True, draw(st.booleans())
    lines = [b"G21", b"G90", b"M82" if abs_e else b"M83", b"G92 E0",
             f"G1 X{fixed(x)} Y{fixed(y)} Z{fixed(z)} F{draw(st.integers(1200, 6000))}".encode()]
    comment = st.binary(max_size=12).map(lambda b: b.replace(b"\n", b"").replace(b"\r", b""))

    def words(nx, ny):
        """X Y words to (nx, ny), in the distance mode; updates the position."""
        nonlocal x, y
        out = f"X{fixed(nx - x if not abs_xyz else nx)} Y{fixed(ny - y if not abs_xyz else ny)}"
        x, y = nx, ny
        return out

    def extrusion():
        nonlocal e
        de = round(draw(st.floats(-0.8, 1.2)), 4)
        e = round(e + de, 4)
        return f" E{fixed(e if abs_e else de, 4)}"

    for _ in range(draw(st.integers(5, 35))):
        kind = draw(st.sampled_from(["move"] * 6 + ["arc"] * 3 + ["e-mode", "g92", "distance", "pass", "pass",
                                                                   "comment"] + ["dwell", "stop"] * stops))
        if kind == "move":
            nx, ny = (round(draw(st.floats(0, 20)), 3) for _ in range(2))
            line = draw(st.sampled_from(["G1 ", "G1 ", "G0 "])) + words(nx, ny)
            if draw(st.integers(0, 9)) == 0:
                dz = draw(st.sampled_from([0.2, -0.2, 0.4]))
                z = round(z + dz, 3)
                line += f" Z{fixed(dz if not abs_xyz else z)}"
            if draw(st.booleans()):
                line += extrusion()
            if draw(st.booleans()):
                line += f" F{draw(st.integers(600, 9000))}"
            lines.append(line.encode() + (b" ; " + draw(comment) if draw(st.integers(0, 5)) == 0 else b""))
        elif kind == "arc":
            code = draw(st.sampled_from(["G2", "G3"]))
            if draw(st.booleans()):  # I J: the centre at a radius of 1 to 8 mm, the end on the circle
                r, a = draw(st.floats(1, 8)), draw(st.floats(0, 2 * math.pi))
                i, j = round(-r * math.cos(a), 3), round(-r * math.sin(a), 3)
                cx, cy, r = x + i, y + j, math.hypot(i, j)
                b = a + draw(st.floats(0.2, 2 * math.pi - 0.2))
                line = f"{code} {words(round(cx + r * math.cos(b), 3), round(cy + r * math.sin(b), 3))} " \
                       f"I{fixed(i)} J{fixed(j)}"
            else:  # R: at least half the chord; negative takes the long way round
                d, a = draw(st.floats(1, 10)), draw(st.floats(0, 2 * math.pi))
                r = d / 2 * draw(st.floats(1.01, 3)) * draw(st.sampled_from([1, -1]))
                line = f"{code} {words(round(x + d * math.cos(a), 3), round(y + d * math.sin(a), 3))} R{fixed(r)}"
            if draw(st.booleans()):
                line += extrusion()
            lines.append(line.encode())
        elif kind == "dwell":
            lines.append(
                draw(st.sampled_from([f"G4 P{draw(st.integers(0, 300))}", f"G4 S0.{draw(st.integers(0, 3))}"])).encode()
            )
        elif kind == "e-mode":
            abs_e = draw(st.booleans())
            lines.append(b"M82" if abs_e else b"M83")
        elif kind == "g92":
            if not stops or draw(st.booleans()):
                e = 0.0
                lines.append(b"G92 E0")
            else:  # a new origin where the machine rests (see test_g92_in_mid_motion)
                x, y = (round(draw(st.floats(-10, 10)), 3) for _ in range(2))
                lines += [b"M400", f"G92 X{fixed(x)} Y{fixed(y)}".encode()]
        elif kind == "distance":  # in Marlin G90/G91 set E's mode too
            abs_xyz = abs_e = draw(st.booleans())
            lines.append(b"G90" if abs_xyz else b"G91")
        elif kind == "pass":
            lines.append(draw(st.sampled_from(PASSTHROUGH)))
        elif kind == "stop":
            lines.append(draw(st.sampled_from(STOPS)))
        else:
            lines.append(draw(st.sampled_from([b"; ", b"(", b";("])) + draw(comment).replace(b")", b"")
                         + draw(st.sampled_from([b"", b")"])))
    endings = [draw(st.sampled_from([b"\n", b"\r\n"])) for _ in lines]
    if draw(st.booleans()):
        endings[-1] = b""
    return b"".join(line + ending for line, ending in zip(lines, endings, strict=True))


def all_stretches_named():
    """Every stretch the fallback takes named in its warnings (not only the first 5):
    check_largest_error needs them all (what is written is the same)."""
    return mock.patch.object(fallback, "_NAMED", math.inf)


def compensated(program: bytes):
    """(the program's path, the output's path, the report) in a temporary folder kept alive by
    the returned handle."""
    folder = tempfile.TemporaryDirectory()
    source, target = Path(folder.name) / "in.gcode", Path(folder.name) / "out.gcode"
    source.write_bytes(program)
    with all_stretches_named():
        report = compensate_file(source, target, PRINTER, OPTIONS)
    return folder, source, target, report


def check_program_kept(program: bytes, largest_error: bool = False):
    """Every property; the largest predicted error too with ``largest_error`` (see
    test_largest_error_never_worse)."""
    folder, source, target, report = compensated(program)
    with folder:
        list(read_gcode(target, "marlin"))  # fbspost reads what it wrote
        original, output = execute(source), execute(target, rests=rest_limits(PRINTER))
        kept = kept_lines(original.nonmotion, output.nonmotion)
        # E (program coordinates) and Z (no modes) at every non-motion line, exact to the written
        # decimals (X and Y where the machine rests: test_with_stops).
        np.testing.assert_allclose(np.array(output.e_at_lines)[kept], original.e_at_lines, rtol=0, atol=1e-7)
        at_out, at_in = np.reshape(output.at_lines, (-1, 4))[kept], np.reshape(original.at_lines, (-1, 4))
        known = ~np.isnan(at_in[:, 2])
        np.testing.assert_allclose(at_out[known, 2], at_in[known, 2], rtol=0, atol=1e-7)
        dwelling = np.array([line.startswith((b"G4", *STOPS)) for line in original.nonmotion], bool) & known
        np.testing.assert_allclose(at_out[dwelling, :2], at_in[dwelling, :2], rtol=0, atol=1e-7)
        assert output.extruded == pytest.approx(original.extruded, abs=1e-7)
        assert original.ends  # (every program here moves: each starts with a G1 X Y)
        np.testing.assert_allclose(output.ends[-1][1:], original.ends[-1][1:], rtol=0, atol=1e-7)
        # As long as the controller takes for the original (never less than the original at its feeds).
        plan = plan_blocks(list(read_gcode(source, "marlin")), PRINTER, margins=MARGINS)
        assert original.duration_s <= plan.duration_s + 1e-9
        assert output.duration_s == pytest.approx(plan.duration_s, rel=0.01, abs=2e-3)
        # (the profile states no input shaping: the output leaves it off, and says so)
        assert [w for w in report.warnings if not w.startswith((CLAMPED, FALLBACK, SHAPING_LEFT_OFF))] == []
        # The predicted error, the report's and that of the output run block by block through
        # scipy's simulation of the profile, against the planned original (0.2 um: the written
        # decimals and the blocks' 1 um tolerance).
        for axis in report.axes.values():
            assert axis.rms_error_after_um <= axis.rms_error_before_um * (1 + 1e-9)
            assert not largest_error or axis.max_error_after_um <= axis.max_error_before_um * (1 + 1e-9)
        _, command = sample_blocks(output.ends, PRINTER.sample_rate_hz)
        n = min(len(command), len(plan.positions_mm))
        for column, name in ((0, "X"), (1, "Y")):
            before, after = modelled_error(plan.positions_mm[:n, column], command[:n, column],
                                           PRINTER.axes[name].modes, 1.0 / PRINTER.sample_rate_hz)
            assert rms(after) <= rms(before) + 2e-4, f"{name}: {rms(before) * 1e3:.3f} -> {rms(after) * 1e3:.3f} um"
            if largest_error:
                check_largest_error(before, after, report.warnings, name)


def check_largest_error(before, after, warnings, axis):
    """Outside the stretches the fallback reports, no sample's modelled error is above the
    original's largest within the 2 s plus one decision before it and the guard's look-ahead
    after it (1.5 um: the blocks' tolerance and decimals)."""
    stretches = [m.groups() for w in warnings if (m := re.search(rf"axis {axis}, ([\d.]+)-([\d.]+) s", w))]
    assert not any(f"axis {axis}, " in w and "more stretches" in w for w in warnings)  # (compensated(): all named)
    guard = AxisGuard(AxisCompensator(AxisDynamics(PRINTER.axes[axis].modes, 1.0 / PRINTER.sample_rate_hz),
                                      AxisLimits.from_profile(PRINTER.axes[axis]), OPTIONS.settings), None, None)
    back, ahead = guard.recent_samples + guard.lengths[0] * guard.unit, guard.horizon
    fs = PRINTER.sample_rate_hz
    reported = np.zeros(len(after), bool)
    for start, stop in stretches:
        reported[math.floor(float(start) * fs):math.ceil(float(stop) * fs) + 1] = True
    padded = np.pad(np.abs(before), (back, ahead))
    bound = np.lib.stride_tricks.sliding_window_view(padded, back + ahead + 1).max(axis=1)
    over = ~reported & (np.abs(after) > bound + 1.5e-3)
    assert not over.any(), f"{axis}: {np.abs(after)[over].max() * 1e3:.2f} um at {np.flatnonzero(over)[0] / fs:.3f} s"


def modelled_error(desired, command, modes, period_s):
    """Desired minus the scipy simulation of the desired as the command (the planned original),
    and of the command, over the motion and the settling for 0.2 s after it."""
    hold = int(0.2 / period_s)
    desired = np.concatenate([desired, np.full(hold, desired[-1])])
    command = np.concatenate([command, np.full(len(desired) - len(command), command[-1])])
    return (desired - simulate_lsim(modes, period_s, desired)), (desired - simulate_lsim(modes, period_s, command))


COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
# Known failures: the saved examples fail at once; no shrinking of new ones (minutes per example).
KNOWN = settings(max_examples=5, derandomize=True, phases=[Phase.explicit, Phase.generate], **COMMON)


@pytest.mark.slow
@settings(max_examples=15, derandomize=True, **COMMON)
@given(programs(stops=False))
def test_program_kept(program):
    check_program_kept(program)


@pytest.mark.parametrize("program", [
    b"G1 X0 Y12.028 F1151\nG1 X20 Y19.469 E-0.1302 F1475\nG4 P100\n",  # rested 9 um short
    b"G1 X19.651 Y8.295 F1125\nG3 X20.858 Y6.828 R2.479\nG4 P132\n",  # ended 3.7 um short
    b"G1 X2.322 Y10.870 Z0.2 F4073\nG0 X2.902 Y18.239\nG1 X0.707 Y11.768\nG2 X-1.629 Y11.824 R-1.461\n"
    b"G4 P5\nG3 X-4.693 Y-1.533 I-2.337 J-6.494\n",  # lasted 43 ms (6 %) longer
])
def test_lines_at_rest_run_where_the_motion_ended(program):
    """Runs whose end time rounded down once put the line at rest a sample before the motion's
    end (found by test_with_stops)."""
    check_program_kept(program)


# A line at rest is written at its run's last sample (its time rounded up); the output's next run
# starts a dwell later, and the plan's once ran from the run's true end (floor(end + dwell), or a
# sample after the last): a sample off at each such line (M400: a sample early, G4 P5 after a run
# ending at 0.367 s: one late). An output that fell back to the original showed it as an error
# (the last example: Y RMS 35.9 -> 36.3 um, though its command: 35.8 -> 12.5 um). Now the plan
# times the rest from the last sample, and the output's first block of a run takes up the rest of
# a sample (planner, writer).
@pytest.mark.slow
@KNOWN
@example(b"G1 X0 Y12.028 F1151\nG1 X20 Y19.469 E-0.1302 F1475\nG4 P100\n")  # rested 9 um short (fixed)
@example(b"G1 X19.651 Y8.295 F1125\nG3 X20.858 Y6.828 R2.479\nG4 P132\n")  # ends 3.7 um short
@example(b"G1 X2.322 Y10.870 Z0.2 F4073\nG0 X2.902 Y18.239\nG1 X0.707 Y11.768\nG2 X-1.629 Y11.824 R-1.461\n"
         b"G4 P5\nG3 X-4.693 Y-1.533 I-2.337 J-6.494\n")  # lasted 43 ms (6 %) longer (fixed)
@example(b"G21\nG90\nM82\r\nG92 E0\nG1 X0.000 Y11.253 Z0.200 F2119\nM104 S205\r\nM82\r\nG2 X-2.468 Y8.439 I-1.480 "
         b"J-1.191\r\nG1 X0.000 Y19.428 Z0.400 E0.0736\nG2 X3.015 Y18.167 R-3.393 E1.1586\r\nM400\r\nG92 X-0.737 "
         # Y RMS 35.9 -> 40.1 um
         b"Y-3.039\nG2 X-2.527 Y-3.552 R-2.500\nG2 X5.737 Y-9.183 R5.050\nM400\nG1 X14.783 Y20.000")
@example(b'G21\r\nG90\nM83\nG92 E0\nG1 X13.831 Y1.844 Z0.200 F1901\r\nG1 X11.989 Y4.994 Z0.000\r\nG3 X13.73'
         b'6 Y2.274 R4.477\nG4 P168\nG2 X11.043 Y8.735 R8.112 E0.9312\nG1 X19.177 Y0.000 E0.5000 F2679 ; O'
         b'\nG1 X18.044 Y1.523 E0.0000 F1999\nG0 X16.546 Y9.159 E0.9347 F4095\r\nG1 X5.286 Y0.000 F1968\r\n'
         b'G1 X20.000 Y19.662 E0.2950\nG92 E0\nG90\nG4 P60\nG1 X0.000 Y12.895\nG0 X10.400 Y9.406 Z0.400 E0.'
         b'1539\n\r\nT0\nG92 E0\nG1 X10.251 Y18.916 F6465\r\nG4 S0.3\nG4 S0.3\nG2 X9.550 Y16.549 I-4.347 J-'
         b'0.000 E0.4444\r\n;(\x8f\xba*\xd7)\r\n; E3\x1d\x9a\x89\nM82\r\nG0 X0.000 Y0.148 E0.1125 ; HZ\x7f'
         b'\xbb\xda@\xb3o\xa2\x87\x89\xa1\r\nG1 X13.446 Y19.381 F740\nM83\nM400\r\nG92 X4.000 Y-3.000\r\n('
         b'\nG1 X14.318 Y10.351 E-0.8000 F894 ; \xb4')  # X RMS 20.7 -> 31.2 um (a sample off after each of 6 rests)
@given(programs(stops=True))
def test_with_stops(program):
    check_program_kept(program)


@pytest.mark.slow
@settings(max_examples=15, derandomize=True, **COMMON)
@example(b"G1 X2.322 Y10.870 Z0.2 F4073\nG0 X2.902 Y18.239\nG1 X0.707 Y11.768\nG2 X-1.629 Y11.824 R-1.461\n"
         b"G4 P5\nG3 X-4.693 Y-1.533 I-2.337 J-6.494\n")
@example(b"G21\nG90\nM82\r\nG92 E0\nG1 X0.000 Y11.253 Z0.200 F2119\nM104 S205\r\nM82\r\nG2 X-2.468 Y8.439 I-1.480 "
         b"J-1.191\r\nG1 X0.000 Y19.428 Z0.400 E0.0736\nG2 X3.015 Y18.167 R-3.393 E1.1586\r\nM400\r\nG92 X-0.737 "
         b"Y-3.039\nG2 X-2.527 Y-3.552 R-2.500\nG2 X5.737 Y-9.183 R5.050\nM400\nG1 X14.783 Y20.000")
@given(programs(stops=True))
def test_with_stops_command_never_worse(program):
    """With lines at rest, the command as compensate computes it (on the plan's samples, where
    the output's time at those lines does not enter, see test_with_stops) through scipy's
    simulation, and the report: RMS per axis never above the original's, and the largest error
    within the fallback's bound (check_largest_error)."""
    folder, source, _, report = compensated(program)
    with folder:
        plan = plan_blocks(list(read_gcode(source, "marlin")), PRINTER, margins=MARGINS)
    warnings = []
    with all_stretches_named():
        command = compensated_samples(plan, PRINTER, OPTIONS, warnings)
    for column, name in ((0, "X"), (1, "Y")):
        before, after = modelled_error(plan.positions_mm[:, column], command[:, column],
                                       PRINTER.axes[name].modes, 1.0 / PRINTER.sample_rate_hz)
        assert rms(after) <= rms(before) * (1 + 1e-9) + 1e-9, (
            f"{name}: {rms(before) * 1e3:.3f} -> {rms(after) * 1e3:.3f}"
        )
        check_largest_error(before, after, warnings, name)
    for axis in report.axes.values():
        assert axis.rms_error_after_um <= axis.rms_error_before_um * (1 + 1e-9)


@pytest.mark.slow
@settings(max_examples=15, derandomize=True, **COMMON)
@example(b"G1 X2.789 Y0 Z0.2 F1200\nG1 X0 Y0 Z0.4\n")  # X: compensated, largest 68.6 -> 85.2 um (RMS 25.7 -> 14.8)
@given(programs(stops=False))
def test_largest_error_bounded_outside_the_fallback(program):
    check_program_kept(program, largest_error=True)


def test_copied_move_without_its_feed_runs_at_the_programs():
    """Found by test_fuzz: in G91, "G0 X0 Y0 Z0.2" without F after compensated motion ran at the
    last written block's F (0.3 mm/s: 0.67 s for 0.2 mm) instead of the program's F880."""
    check_program_kept(
        b'G21\nG90\nM83\r\nG92 E0\nG1 X15.826 Y0.000 Z0.200 F1696\r\n'
        b'G3 X14.222 Y-2.619 I-1.895 J-0.640\nG3 X15.201 Y-2.417 R-0.534\nG92 E0\n'
        b'G1 X5.289 Y2.572 E0.8185 F1024\r\nG0 X1.282 Y12.868 F5948\nG90\nM83\n'
        b'G3 X4.404 Y17.715 R-5.859\nG2 X0.828 Y12.826 I-0.345 J-3.500\r\nG90\nM83\r\n'
        b'G3 X3.212 Y14.139 I2.584 J-1.872 E-0.7577\r\nG91\nM221 S95\n'
        b'G0 X-1.271 Y-5.134 E0.5000 F880 ; \nG1 X-1.941 Y-6.908 Z0.200 ; \nM83\r\n'
        b'G1 X0.000 Y-2.097\r\nM83\nG0 X0.000 Y0.000 Z0.200 ; \r\nG1 X0.000 Y0.000 Z0.200 F600 ; \n'
        b'M82\r\nG1 X5.462 Y17.321\nM83\nG3 X2.784 Y2.305 R-3.737\nG1 X-4.006 Y-16.962\nG90'
    )


def test_g92_in_mid_motion():
    """G92 Y0 where the original is at Y0 but the compensated command 55 um further: the output
    must end at the original's machine Y, not 55 um off."""
    check_program_kept(b"G1 X10.409 Y2.084 Z0.2 F1422\nG1 X11.911 Y0 Z0.4\nG92 X-10 Y0\nG1 X0.69 Y0 Z0.6\n")


@pytest.mark.slow
@settings(max_examples=60, database=None, phases=[Phase.explicit, Phase.generate], **COMMON)
@seed(20261121)
@given(programs(stops=False))
def test_fuzz(program):
    """About a minute on two cores, a fixed seed, no shrinking (a failure prints its program)."""
    check_program_kept(program)
