"""fbspost's LinuxCNC output run by LinuxCNC 2.9 itself (issue 31; skipped where Debian's
linuxcnc-uspace is not installed, ``.ci/run`` installs it): its own task, interpreter and
trajectory planner, headless (tests/linuxcnc_itself.py), run what fbspost computed, on time.

Truth: the joint commands LinuxCNC itself outputs every servo period, against the written
blocks run exactly as written (each at its F)."""
import re
from pathlib import Path

import numpy as np
import pytest

from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.firmware.verify import printed_path
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from linuxcnc_itself import as_written, follows, from_first_motion, installed, joint_commands, on_grid

STAGE = load_profile("patent-xy-stage")
DENSE = Path(__file__).resolve().parents[1] / "samples" / "butterfly-dense.gcode"
TOLERANCE_MM = 1e-3  # fbspost's default: the G64 P of the output
needs_linuxcnc = pytest.mark.skipif(not installed(),
                                    reason="LinuxCNC is not installed (apt-get install linuxcnc-uspace)")


@pytest.fixture(scope="module")
def butterfly_part(tmp_path_factory):
    """The dense butterfly (1 ms blocks, 3.1 s) compensated for the patent's stage (--no-verify:
    the output itself), its blocks as written (from their first motion, the profile's grid) and
    their path. (Its first 1.2 s alone: LinuxCNC's start, a few ms that vary from run to run
    under load, is 0.4 to 0.6% of it.)"""
    output = tmp_path_factory.mktemp("butterfly") / "out.ngc"
    compensate_file(DENSE, output, STAGE, CompensateOptions(flavor="linuxcnc", verify=False))
    blocks = list(read_gcode(output, "linuxcnc"))
    grid, starts, ends = as_written(blocks, STAGE.sample_rate_hz)
    return output, blocks, from_first_motion(grid), printed_path(starts, ends)[0]


@pytest.mark.slow
@needs_linuxcnc
def test_linuxcnc_itself_runs_the_compensated_butterfly_on_its_path_and_time(butterfly_part):
    """LinuxCNC itself at SERVO_PERIOD 1 ms keeps within the tolerance + 2 um of the written
    path and takes the written time within 0.5%, the largest lag along the path under 1% of it
    (measured, load average 10, the plan at LinuxCNC's time: 2.38 um, 3.1610 s for the written
    3.1606 s, 11.1 ms at most; before, load 12: 2.29 um, 3.0570 s for 3.0557 s; blocks of 1 servo
    period: 35 um, 3.4160 s, 394 ms late)."""
    output, _, written, path = butterfly_part
    fs = STAGE.sample_rate_hz
    real = on_grid(joint_commands(output, STAGE), STAGE.firmware.linuxcnc.servo_period_s, fs)
    far_mm, lag_s = follows(real, written, path, fs)
    real_s, written_s = (len(real) - 1) / fs, (len(written) - 1) / fs
    print(f"LinuxCNC: {real_s:.4f} s (written {written_s:.4f} s), {far_mm * 1e3:.2f} um from the path, "
          f"lag {lag_s * 1e3:.1f} ms")
    assert far_mm < TOLERANCE_MM + 0.002
    assert abs(real_s / written_s - 1.0) < 0.005
    assert lag_s < 0.01 * written_s


@pytest.mark.slow
@needs_linuxcnc
def test_the_model_of_linuxcnc_s_planner_agrees_with_linuxcnc_itself(butterfly_part):
    """Issue 31 item 3: on the same written program, fbspost's model of LinuxCNC's planner keeps
    to the written path as LinuxCNC does (the tolerance + 2 um) and takes LinuxCNC's time
    within 0.5%, so that --verify judges the motion LinuxCNC makes (measured: 1.70 um, 3.0580 s
    against LinuxCNC's 3.0570 s; before the model's blend arcs ramped at half the
    acceleration, as LinuxCNC's do: 3.0390 s, -0.59%)."""
    output, blocks, written, path = butterfly_part
    fs = STAGE.sample_rate_hz
    real = on_grid(joint_commands(output, STAGE), STAGE.firmware.linuxcnc.servo_period_s, fs)
    model = from_first_motion(run_linuxcnc(blocks, STAGE).positions_mm(fs))
    far_mm, _ = follows(model, written, path, fs)
    assert far_mm < TOLERANCE_MM + 0.002
    assert abs(len(model) / len(real) - 1.0) < 0.005


@pytest.mark.slow
@needs_linuxcnc
def test_linuxcnc_itself_runs_excite_s_sweep_as_written(tmp_path):
    """Issue 30: `fbspost excite --flavor linuxcnc` (printer-two-mode's X, 2 s, 5-120 Hz: 3.9 s
    with the move back and the clock mark, one block per half period from rest to rest) run by
    LinuxCNC itself at SERVO_PERIOD 1 ms: the axis turns back on the servo period each block's
    closed-form end (L / F + F / a at the INI's acceleration) falls in, up to the move back
    (which ends inside a period and leaves the rest of it), up to a period later from there; the
    duration within 0.05%. Measured (load average 13): every turn within 4 us of its period,
    +0.04 ms from the clock mark on, 3.9120 s for 3.9120 s. Before (1 ms blocks in G64): 5.4 to
    6.4 s of motion for a 2.93 s sweep.

    And the model of LinuxCNC's planner gives LinuxCNC's joint commands (its planner's points
    through the cubic interpolator: LinuxCNC turns back 1.67 um short of every written end)
    within 10 nm (measured: 0.5 nm, halsampler's six decimals)."""
    from click.testing import CliRunner

    from fbspost.cli import main
    from linuxcnc_itself import rest_to_rest_ends, turns

    printer = load_profile("printer-two-mode")
    path = tmp_path / "sweep.ngc"
    result = CliRunner().invoke(main, ["excite", "--machine", "printer-two-mode", "--axis", "X", "--center", "100",
                                       "--duration", "2", "--flavor", "linuxcnc", "-o", str(path)])
    assert result.exit_code == 0, result.output
    text = path.read_text()
    begin, end = "; fbspost excite: sweep begins", "; fbspost excite: sweep ends"
    index, ends_s = rest_to_rest_ends(text, begin, end, printer.axes["X"].max_acceleration_mm_s2)
    lines = text.splitlines()
    targets = np.array([float(lines[i].split()[1][1:]) for i in index])
    start_mm = float(next(line for line in lines if line.startswith("G1 X")).split()[1][1:])
    direction = np.sign(np.diff(np.append(start_mm, targets)))
    written = np.flatnonzero(direction[1:] != direction[:-1])  # the blocks whose end turns back
    run = tmp_path / "run.ngc"
    run.write_text(f"G0 X{start_mm} Y0\n" + text)  # (the harness moves to the first X Y before it records)
    period_s = printer.firmware.linuxcnc.servo_period_s
    joints = joint_commands(run, printer)
    real_s = turns(joints[:, 0]) * period_s
    mark = int(np.argmin(np.abs(ends_s - float(re.search(r"clock mark at ([\d.]+) s", text)[1]))))
    late_s = real_s - ends_s[written]
    late_s -= late_s[0]
    print(f"LinuxCNC: {len(real_s)} turns for {len(written)} written; before the clock mark "
          f"{late_s[written < mark].min() * 1e3:+.3f} to {late_s[written < mark].max() * 1e3:+.3f} ms, from it "
          f"{late_s[written >= mark].min() * 1e3:+.3f} to {late_s[written >= mark].max() * 1e3:+.3f} ms; "
          f"{real_s[-1] - real_s[0]:.4f} s for {ends_s[written[-1]] - ends_s[written[0]]:.4f} s")
    assert len(real_s) == len(written)
    assert np.abs(late_s[written < mark]).max() <= 0.5 * period_s
    assert late_s[written >= mark].min() >= -0.5 * period_s and late_s[written >= mark].max() <= 1.5 * period_s
    assert abs((real_s[-1] - real_s[0]) / (ends_s[written[-1]] - ends_s[written[0]]) - 1) <= 5e-4

    blocks = list(read_gcode(run, "linuxcnc"))
    motion = run_linuxcnc(blocks, printer)
    at_rest = int(motion.line_time_s[[b.raw.strip() for b in blocks].index(begin.encode())] / period_s) - 10
    model = from_first_motion(motion.joint_positions_mm[at_rest:, :1])[:, 0]
    n = min(len(model), len(joints))
    assert abs(len(model) - len(joints)) <= 1
    print(f"the model's joint commands: {len(model)} periods for {len(joints)}, "
          f"{np.abs(model[:n] - joints[:n, 0]).max() * 1e6:.1f} nm from LinuxCNC's")
    assert np.abs(model[:n] - joints[:n, 0]).max() < 1e-5  # (halsampler prints 6 decimals)
    assert np.abs(motion.cycle_positions_mm[:, 0].max() - joints[:, 0].max()) > 1e-3  # the TP's points are not


@pytest.mark.slow
@pytest.mark.parametrize("runner", ["model", pytest.param("linuxcnc", marks=needs_linuxcnc)])
def test_identify_recovers_the_patent_stage_from_excite_s_linuxcnc_sweep(tmp_path, runner):
    """Issue 30 item 4 for LinuxCNC: excite's LinuxCNC sweep of the patent stage's X (10 s,
    5-100 Hz), run by LinuxCNC itself (or the model of its planner), the joint commands through
    the profile's own modes (the truth) recorded by a simulated ADXL345 (tests/accel_recording:
    3200 Hz on its own clock, offset and drift, noise), identified with --machine (the plan: the
    model of LinuxCNC's planner): the fitted FRF within 5% of the truth's peak over 5-100 Hz, the
    first mode within 1% and its damping within 5%. Measured (load average 3.5): from LinuxCNC
    itself and from the model alike 1.54% (20.521 Hz, 0.0921); truth 20.52 Hz, 0.092. Before the
    model had LinuxCNC's cubic interpolator (so the plan missed it): from LinuxCNC itself 4.32%
    (20.540 Hz, 0.0909), from the model 1.56%."""
    from click.testing import CliRunner

    from accel_recording import Accelerometer, record, write_csv
    from fbspost.cli import main

    program, log, out = tmp_path / "sweep.ngc", tmp_path / "log.csv", tmp_path / "id.toml"
    result = CliRunner().invoke(main, ["excite", "--machine", "patent-xy-stage", "--axis", "X", "--center", "0",
                                       "--end-hz", "100", "--duration", "10", "--flavor", "linuxcnc",
                                       "-o", str(program)])
    assert result.exit_code == 0, result.output
    text = program.read_text()
    start_mm = next(line for line in text.splitlines() if line.startswith("G1 X")).split()[1][1:]
    run = tmp_path / "run.ngc"
    run.write_text(f"G0 X{start_mm} Y0\n" + text)  # (the harness moves to the first X Y before it records)
    if runner == "linuxcnc":
        x = joint_commands(run, STAGE)[:, 0]
    else:
        x = from_first_motion(run_linuxcnc(list(read_gcode(run, "linuxcnc")), STAGE).joint_positions_mm)[:, 0]
    period_s, fs = STAGE.firmware.linuxcnc.servo_period_s, STAGE.sample_rate_hz
    t = np.arange(int((len(x) * period_s + 2.0) * fs)) / fs  # 1 s at rest before and after
    command = np.interp(t - 1.0, np.arange(len(x)) * period_s, x)
    write_csv(log, record(t, np.column_stack([command, np.zeros_like(command)]), {"X": STAGE.axes["X"].modes},
                          Accelerometer()))
    result = CliRunner().invoke(main, ["identify", "--accel-log", str(log), "--program", str(program), "--axis", "X",
                                       "--machine", "patent-xy-stage", "-o", str(out), "--merge", STAGE.source])
    assert result.exit_code == 0, result.output
    found = load_profile(out).axes["X"].modes
    f = np.linspace(5.0, 100.0, 4000)
    s = 2j * np.pi * f

    def frf(modes):  # sum (alpha + beta s) / (s^2 + 2 zeta w s + w^2)
        return sum((m.alpha + m.beta * s) / (s * s + 4 * np.pi * m.damping * m.frequency_hz * s
                                             + (2 * np.pi * m.frequency_hz) ** 2) for m in modes)

    truth = frf(STAGE.axes["X"].modes)
    error = np.abs(frf(found) - truth).max() / np.abs(truth).max()
    first = min(found, key=lambda m: abs(m.frequency_hz - 20.52))
    print(f"{runner}: FRF within {error:.2%} of the peak; first mode {first.frequency_hz:.3f} Hz, "
          f"damping {first.damping:.4f}")
    assert error <= 0.05
    assert first.frequency_hz == pytest.approx(20.52, rel=0.01) and first.damping == pytest.approx(0.092, rel=0.05)


@pytest.mark.slow
@needs_linuxcnc
def test_linuxcnc_itself_is_recorded_from_where_the_program_s_path_starts(tmp_path):
    """A program whose first move (from a place the file does not give) rises in Z, as
    arcspiral.ngc's `G0 X0 Y0 Z1` in inches: that move is no part of the path fbspost reads, so
    LinuxCNC must start there. Before, the sim started at Z 0 and its record rose 25.4 mm off the
    path. Truth: the path's own segments, at a feed slow enough that LinuxCNC stays on them
    within its G64 P (1 um here)."""
    program = tmp_path / "rise.ngc"
    program.write_text("G21 G90 G64 P0.001 Q0\nG0 X0 Y0 Z25.4\nG1 X5 F600\nG1 Y5\nG1 Z20\nM2\n")
    blocks = list(read_gcode(program, "linuxcnc"))
    _, starts, ends = as_written(blocks, STAGE.sample_rate_hz)
    joints = joint_commands(program, STAGE)
    assert np.abs(joints[0] - [0.0, 0.0, 25.4]).max() < 1e-5
    assert printed_path(starts, ends)[0](joints)[0].max() < 0.001 + 0.002


@pytest.mark.slow
@needs_linuxcnc
def test_max_linear_velocity_caps_the_path_speed_in_linuxcnc_and_in_fbspost_s_plan(tmp_path):
    """[TRAJ] MAX_LINEAR_VELOCITY 60 mm/s (the profile's ``max_linear_velocity``) on the patent
    stage, a diagonal at F6000 from rest to rest in G61.1: LinuxCNC itself cruises along the path
    at 60 mm/s, not the 100 mm/s the feed and each axis allow, and so do the model of its planner
    and fbspost's plan of the program for LinuxCNC (whose output would otherwise ask the machine
    for speeds it clamps); the closed form d / v + v / a with v = 60 and a the INI's acceleration
    along the diagonal for LinuxCNC."""
    from dataclasses import replace

    from fbspost.plan.planner import plan_blocks

    capped = replace(STAGE, firmware=replace(STAGE.firmware, linuxcnc=replace(
        STAGE.firmware.linuxcnc, max_linear_velocity_mm_s=60.0)))
    program = tmp_path / "diagonal.ngc"
    program.write_text("G21 G90 G61.1\nG0 X0 Y0\nG1 X30 Y30 F6000\nM2\n")
    length_mm, period_s = 30.0 * np.sqrt(2.0), capped.firmware.linuxcnc.servo_period_s
    accel = 8000.0 * np.sqrt(2.0)  # each axis at its 8000 mm/s^2 along the diagonal
    joints = joint_commands(program, capped)
    speed = np.linalg.norm(np.diff(joints[:, :2], axis=0), axis=1) / period_s
    print(f"LinuxCNC itself: {speed.max():.4f} mm/s at most, {(len(joints) - 1) * period_s:.4f} s")
    assert speed.max() == pytest.approx(60.0, rel=1e-4)
    assert (len(joints) - 1) * period_s == pytest.approx(length_mm / 60.0 + 60.0 / accel, abs=4 * period_s)
    blocks = list(read_gcode(program, "linuxcnc", capped.home_mm))
    model = run_linuxcnc(blocks, capped)
    assert np.linalg.norm(np.diff(model.cycle_positions_mm[:, :2], axis=0), axis=1).max() / period_s == \
        pytest.approx(60.0, rel=1e-9)
    plan = plan_blocks(blocks, capped, firmware="linuxcnc")
    planned = np.linalg.norm(np.diff(plan.positions_mm[:, :2], axis=0), axis=1) * capped.sample_rate_hz
    assert planned.max() == pytest.approx(60.0, rel=1e-6)


@pytest.mark.slow
@needs_linuxcnc
@pytest.mark.parametrize("moves, original_s", [
    ("G1 X10 F600\nA30\nX0", 2 * (10.0 / 10.0 + 10.0 / 8000.0) + 30.0 / 10.0 + 10.0 / 8000.0),
    ("G1 X10 F600\nX20 A30\nY10\nX0", 50.0 / 10.0 + 4 * 10.0 / 8000.0)])
def test_linuxcnc_itself_and_its_model_run_a_compensated_rotary_move_alike(tmp_path, moves, original_s):
    """A move of A alone (30 degrees at F600) between two X moves takes its own length at F on
    LinuxCNC, 3 s, and X Y with A together are timed by X Y's length (the closed forms of the
    moves from rest to rest at the stage's 8000 mm/s^2, A at the slowest axis' limits in the sim;
    measured for A alone 5.0050 s, the model 5.0060 s, before 2.0 s: A in one servo period).
    LinuxCNC blends no segment that moves A (tpRotaryMotionCheck): written in a run's dense
    blocks, X10 A90 ran twice as long as the original (2.147 s for 1.025 s, load 10). fbspost
    copies both as written between runs (a rest of X Y): LinuxCNC itself runs the output as the
    model says (A alone 5.154 s and 5.160 s; X with A 5.153 s and 5.159 s, the original 5.004 s
    itself; load 3), and --verify keeps it."""
    program, output = tmp_path / "a.ngc", tmp_path / "out.ngc"
    program.write_text(f"G21 G90\nG0 X0 Y0 Z1 A0\n{moves}\nM2\n")
    compensate_file(program, output, STAGE, CompensateOptions(flavor="linuxcnc", verify=False))
    period_s = STAGE.firmware.linuxcnc.servo_period_s
    for written in (program, output):
        real_s = (len(joint_commands(written, STAGE)) - 1) * period_s
        model_s = run_linuxcnc(list(read_gcode(written, "linuxcnc")), STAGE).duration_s
        print(f"{written.name}: LinuxCNC itself {real_s:.4f} s, the model {model_s:.4f} s")
        assert model_s == pytest.approx(real_s, rel=0.005)
        if written is program:
            assert real_s == pytest.approx(original_s, rel=0.005)
    checked = compensate_file(program, tmp_path / "checked.ngc", STAGE,
                              CompensateOptions(flavor="linuxcnc", verify=True))
    assert not checked.original_kept
