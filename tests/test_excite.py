"""fbspost excite: the sweep program as each firmware runs it, and identify with the firmware's plan.

Truths used: Klipper's own planner (klippy's toolhead.py, ``klippy_motion``), the models of
Marlin's planner (``marlin.run_marlin``), RepRapFirmware's (``reprap.run_reprap``) and
LinuxCNC's trajectory planner (``linuxcnc_tp.run_linuxcnc``; LinuxCNC itself: test_linuxcnc_itself.py);
the written program read here as written (time = length / F, G4 P; LinuxCNC's blocks from rest to
rest at the INI's acceleration a: L / F + F / a, a trapezoid's closed form); scipy's continuous-time
simulation of a known model (reference.simulate_lsim) for the recording.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import signal

from fbspost.cli import main
from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.firmware.marlin import run_marlin
from fbspost.firmware.reprap import run_reprap
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from linuxcnc_itself import rest_to_rest_ends
from reference import execute, sample_blocks, simulate_lsim

BEGIN, END = "; fbspost excite: sweep begins", "; fbspost excite: sweep ends"
PRINTER = load_profile("printer-two-mode")
CENTRE_MM = 100.0
STEPS_PER_MM = PRINTER.firmware.steps_per_mm["X"]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def write_sweep(path: Path, flavor: str, profile=PRINTER, duration_s=3.0, *options) -> str:
    result = run("excite", "--machine", profile.source, "--axis", "X", "--center", CENTRE_MM, "--duration",
                 duration_s, "--flavor", flavor, "-o", path, *options)
    assert result.exit_code == 0, result.output
    return path.read_text()


def written_blocks(text: str, flavor: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every G1 between the markers as written, read here: its line index, its end time from the
    begin marker on the program's grid of equal blocks and its X (Marlin: at whole steps, where it
    goes and what it times the block by). A block's time on the grid is the whole number of
    blocks nearest its time as written (length / F, a G4's P in ms), which is
    a little short of it where it makes up the firmware's ramps."""
    at = (lambda x: round(float(x) * STEPS_PER_MM) / STEPS_PER_MM) if flavor == "marlin" else float
    block_s = block_s_of(text)
    lines = text.splitlines()
    begin = lines.index(BEGIN)
    x = feed = None
    for line in lines[:begin]:
        if m := re.match(r"G1 X([-\d.]+)", line):
            x = at(m[1])
    index, ends, xs, blocks = [], [], [], 0
    for i in range(begin + 1, lines.index(END)):
        if m := re.match(r"G4 P([\d.]+)$", lines[i]):
            blocks += round(float(m[1]) / 1e3 / block_s)
            continue
        m = re.fullmatch(r"G1 X([-\d.]+)(?: F([\d.]+))?", lines[i])
        feed = float(m[2]) / 60.0 if m[2] else feed
        blocks += max(1, round(abs(at(m[1]) - x) / feed / block_s))
        x = at(m[1])
        index.append(i)
        ends.append(blocks * block_s)
        xs.append(x)
    return np.array(index), np.array(ends), np.array(xs)


def block_s_of(text: str) -> float:
    return float(re.search(r"in ([\d.]+) ms blocks", text)[1]) / 1e3


def run_on_model(path: Path, flavor: str, profile):
    """The firmware model's run of the program: (each line's time: a move's end, position at times)."""
    blocks = list(read_gcode(path, flavor))
    motion = (run_marlin if flavor == "marlin" else run_reprap)(blocks, profile)
    merged = set(motion.merged_lines)
    times = np.where([i in merged for i in range(len(blocks))], np.nan, motion.line_time_s)
    return times, lambda t: motion.at(np.asarray(t))[:, 0]


def timing_and_position(line_time_s, position, text: str, flavor: str):
    """How the firmware's run departs from the sweep the program is written for, blocks of equal
    time (``written_blocks``): the largest |time| by which a block ends early or late (the begin
    aligned on the first block that ends: Marlin starts a buffer late), the largest |position|
    error at the block ends, and the sweep's duration as run (first to last block end) over its
    duration on the grid."""
    index, ends_s, xs = written_blocks(text, flavor)
    run_s = line_time_s[index]
    kept = np.isfinite(run_s)  # (Marlin: a merged line has no block end of its own)
    first = np.flatnonzero(kept)[0]
    t0 = run_s[first] - ends_s[first]
    late_s = np.abs(run_s[kept] - t0 - ends_s[kept]).max()
    off_mm = np.abs(position(t0 + ends_s[kept]) - xs[kept]).max()
    ratio = (run_s[kept][-1] - run_s[first]) / (ends_s[kept][-1] - ends_s[first])
    return late_s, off_mm, ratio


def klippy_run(path: Path, profile=PRINTER):
    """klippy's run of the program: each line's time (a G1's move end) and X at any time."""
    klippy = pytest.importorskip("klippy_motion")
    try:
        executed = klippy.executed(path, profile)
    except Exception as exc:  # noqa: BLE001 (no network: the sdist cannot be fetched)
        if type(exc).__name__ == "KlippyUnavailable":
            pytest.skip(str(exc))
        raise
    text = path.read_text().splitlines()
    g1 = [i for i, line in enumerate(text) if line.startswith("G1 ")]
    line_time = np.full(len(text), np.nan)
    ends = executed.start_s + executed.phases_s.sum(axis=1)
    moved = executed.end_mm[:, 0] != executed.start_mm[:, 0]  # (the move to the start: from there, no move)
    line_time[g1[len(g1) - int(moved.sum()):]] = ends[moved]
    return line_time, lambda t: executed.at(np.asarray(t))[:, 0]


# ---- the program -------------------------------------------------------------------------------------

def dwells_s(text: str) -> float:
    """The G4 P (ms) dwells in a program's text, s: the executor times them."""
    return sum(float(ms) / 1e3 for ms in re.findall(r"^G4 P([\d.]+)", text, re.M))


def test_excite_program_keeps_the_limits_and_rests_at_the_centre(tmp_path):
    program = tmp_path / "sweep.gcode"
    result = run("excite", "--machine", "printer-two-mode", "--axis", "Y", "--center", 110, "-o", program,
                 "--duration", 10, "--amplitude", 2)
    assert result.exit_code == 0, result.output
    axis = PRINTER.axes["Y"]
    text = program.read_text().replace("Y", "X")  # the executor records once X and Y are known
    (tmp_path / "x.gcode").write_text("G1 Y0 F600\n" + text)
    t, pos = sample_blocks(execute(tmp_path / "x.gcode", 1000.0).ends, 1000.0)
    y = pos[:, 0]
    begin_s = dwells_s(text[:text.index(BEGIN)])  # (the move to the start: from where X is first set, none)
    end_s = t[-1] + dwells_s(text[text.rindex("\nG1 "):text.index(END)])  # the time the last blocks hold still
    # 10 s, two 0.5 s ramps, the clock mark: the first 2 s again
    assert end_s - begin_s == pytest.approx(13.0, abs=2e-3)
    assert y[0] == y[-1] == 110.0
    # every block's speed, and the speed steps between blocks over their mean duration (a block of
    # two samples' time, where the middle one rounds to where the last was, at a reversal, included)
    ends = np.array(execute(tmp_path / "x.gcode", 1000.0).ends)
    ends = ends[(ends[:, 0] > begin_s) & (ends[:, 0] <= end_s)]
    dt, v = np.diff(ends[:, 0]), np.diff(ends[:, 1]) / np.diff(ends[:, 0])
    assert np.abs(v).max() <= axis.max_velocity_mm_s * (1 + 1e-6)
    assert (np.abs(np.diff(v)) / (0.5 * (dt[1:] + dt[:-1]))).max() <= axis.max_acceleration_mm_s2 * (1 + 1e-3)
    assert np.abs(y - 110.0).max() == pytest.approx(2.0, rel=1e-3)  # the amplitude where the limits allow it
    # near 120 Hz the acceleration limit sets the amplitude: 90% of a / w^2
    top = int(round((begin_s + 10.5) * 1000))  # the sweep's top, 120 Hz (2.5 s before its end)
    late = np.abs(y[top - 60:top] - 110.0).max()  # the last 60 ms up to it, about 119 Hz
    assert late == pytest.approx(0.9 * axis.max_acceleration_mm_s2 / (2 * math.pi * 119.0) ** 2, rel=0.03)
    # the clock mark: from 11 s, the sweep's first 1.5 s again (then faded out), within 10 um, 0.15 ms
    # at its speed (the blocks that round to no motion at both starts take their time differently)
    start = int(round(begin_s * 1000))
    assert "; clock mark at 11 s: the sweep's first 2 s again" in text
    np.testing.assert_allclose(y[start + 11000:start + 12500], y[start:start + 1500], rtol=0, atol=1e-2)


@pytest.mark.parametrize("flavor, transparent, restored", [
    ("klipper", "SET_VELOCITY_LIMIT ACCEL=100000000 ACCEL_TO_DECEL=100000000 MINIMUM_CRUISE_RATIO=0 "
                "SQUARE_CORNER_VELOCITY=10000", "SET_VELOCITY_LIMIT ACCEL=3000 ACCEL_TO_DECEL=1500 "
                "MINIMUM_CRUISE_RATIO=0.5 SQUARE_CORNER_VELOCITY=5"),
    ("marlin", "M205 B0 J0.3 X1000 Y1000", "M204 P3000 T3000"),
    ("reprap", "M566 X60000 Y60000", "M204 P3000 T3000"),
    ("linuxcnc", "G61.1 ; exact stop: every block from rest to rest", "G64"),
])
def test_excite_sets_the_firmware_around_the_sweep_and_restores_the_profile(tmp_path, flavor, transparent, restored):
    """The transparency settings before the sweep (at rest, before its dwell), the profile's own after it."""
    lines = write_sweep(tmp_path / "s.gcode", flavor, PRINTER, 1.0).splitlines()
    begin, end = lines.index(BEGIN), lines.index(END)
    assert f"; flavor: {flavor}" in lines and "; machine: printer-two-mode" in lines
    assert transparent in lines[:begin] and restored in lines[end:]
    assert lines[begin - 1].startswith("G4 P")
    assert (lines[-1] == "M2") == (flavor == "linuxcnc")  # (LinuxCNC: the program's end)
    assert lines[-2 if flavor == "linuxcnc" else -1].startswith("G4 P")  # the rest after the sweep


def test_excite_line_budget_is_a_one_line_usage_error(tmp_path):
    """bedslinger-example takes 300 lines/s: blocks of at least 1 / (0.9 * 300) s, a band up to a
    quarter of that rate (67.5 Hz)."""
    out = tmp_path / "s.gcode"
    for options, message in [(("--block-time", 0.001), "--block-time 0.001 s is shorter"),
                             ((), "need --start-hz < --end-hz <= 67.5 Hz")]:
        result = run("excite", "--machine", "bedslinger-example", "--axis", "X", "--center", 0, "-o", out, *options)
        assert result.exit_code == 2 and message in result.output, result.output
        assert [line for line in result.output.splitlines() if line.startswith("Error")] == \
            [result.output.splitlines()[-1]]
        assert not out.exists()
    assert run("excite", "--machine", "bedslinger-example", "--axis", "X", "--center", 0, "--end-hz", 60,
               "-o", out).exit_code == 0
    assert "in 3.7037037 ms blocks" in out.read_text()


def test_excite_unknown_axis_is_one_line_error(tmp_path):
    result = run("excite", "--machine", "bedslinger-example", "--axis", "A", "--center", 0, "-o", tmp_path / "s.gcode")
    assert result.exit_code == 1 and result.output.startswith("error: ") and "axes.A" in result.output
    assert result.output.count("\n") == 1
    assert not (tmp_path / "s.gcode").exists()



def test_identify_plans_the_sweep_on_the_profile_it_names_or_a_default(tmp_path):
    """Without --machine: the bundled profile the header names (the same plan as with it), else
    printer-two-mode, said in one line; the sweep as planned starts at rest at the centre and
    takes its written time (Klipper's rules at the program's settings)."""
    from fbspost.tools import excite

    path = tmp_path / "s.gcode"
    text = write_sweep(path, "klipper", PRINTER, 1.0)
    lines = []
    named = excite.commanded_sweep(path, "X", None, lines)
    given = excite.commanded_sweep(path, "X", "printer-two-mode", lines)
    assert lines == [] and np.array_equal(named.positions_mm, given.positions_mm)
    assert named.positions_mm[0] == CENTRE_MM and named.flavor == "klipper" and named.machine == "printer-two-mode"
    _, ends_s, _ = written_blocks(text, "klipper")
    assert named.times_s[-1] == pytest.approx(ends_s[-1] + dwells_s(text[text.rindex("\nG1 "):text.index(END)]),
                                              abs=2e-4)
    path.write_text(text.replace("; machine: printer-two-mode", "; machine: my-printer"))
    default = excite.commanded_sweep(path, "X", None, lines)
    assert len(lines) == 1 and "no bundled profile named in it" in lines[0]
    assert np.abs(default.position(named.times_s) - named.positions_mm).max() < 1e-4


# ---- Klipper ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_klipper_runs_the_sweep_as_written_and_the_old_setting_did_not(tmp_path):
    """klippy at the program's settings: every block ends within 1% of a block time (10 us) of its
    written time, at most 1 um from its written end; the sweep takes its written time within
    0.1%. The same program with the old header's setting instead of the transparency line
    (ACCEL=10000 MINIMUM_CRUISE_RATIO=0): every speed change ramps inside a block, the sweep
    takes several % longer and the blocks end mm from where they should."""
    path = tmp_path / "sweep.gcode"
    text = write_sweep(path, "klipper")
    assert "; flavor: klipper" in text and "SET_INPUT_SHAPER SHAPER_FREQ_X=0 SHAPER_FREQ_Y=0" in text
    block_s = block_s_of(text)
    late_s, off_mm, ratio = timing_and_position(*klippy_run(path), text, "klipper")
    print(f"klippy: blocks end up to {late_s * 1e6:.2f} us off, {off_mm * 1e3:.3f} um; duration ratio {ratio:.6f}")
    # (2%: the make-up counts the speed steps between blocks, not the stop at each reversal of the
    # axis, 0.02 to 0.05 us each: 17.6 us by the end of the clock mark)
    assert late_s <= 0.02 * block_s
    assert off_mm <= 1e-3
    assert abs(ratio - 1.0) <= 1e-3

    old = re.sub(r"^SET_VELOCITY_LIMIT ACCEL=100000000 .*$", "SET_VELOCITY_LIMIT ACCEL=10000 MINIMUM_CRUISE_RATIO=0",
                 text, count=1, flags=re.M)
    assert old != text
    (tmp_path / "old.gcode").write_text(old)
    late_s, off_mm, ratio = timing_and_position(*klippy_run(tmp_path / "old.gcode"), old, "klipper")
    print(f"klippy, old setting: blocks end up to {late_s * 1e3:.2f} ms off, {off_mm:.3f} mm; "
          f"duration ratio {ratio:.4f}")
    assert ratio > 1.03 and off_mm > 0.1


# ---- Marlin, RepRapFirmware, LinuxCNC (models) -------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("flavor, late_blocks, position_mm", [
    # whole steps: within a step; Marlin's F (to 0.001 mm/min) and steps leave 3.4% of a block (37 us,
    # by the end of the clock mark: the stops at the reversals, as on Klipper)
    ("marlin", 0.04, 1.0 / STEPS_PER_MM),
    # RRF runs a move at M203 I's speed at least (0.5 mm/s by default: the 3 s sweep ran 2% short, its slow
    # blocks 78 ms early); the sweep sets it to RRF's lowest, 0.01 mm/s, and restores it after
    pytest.param("reprap", 0.01, 1e-3, marks=pytest.mark.xfail(strict=True, reason=(
        "RRF's RecalculateMove cruises at a move's start speed where its ramp would take under 10 step "
        "clocks: at the raised acceleration the sweep's speed steps under 13 mm/s are not taken, so its "
        "fast end runs off its time (the 3 s sweep with its clock mark, 6.0 s: 0.33% short, block ends up to 21 ms "
        "off; within issue 30's 1%, test below; identify plans it as RRF runs it)"))),
])
def test_firmware_models_run_the_sweep_as_written(tmp_path, flavor, late_blocks, position_mm):
    """The flavor's firmware model: every block end within ``late_blocks`` of a block time of its
    time on the grid and ``position_mm`` of its written end, the sweep's duration within 0.1%.
    Marlin and RRF at a line budget of 1000 lines/s (blocks of 1/900 s: 90% of it)."""
    path = tmp_path / "sweep.gcode"
    (tmp_path / "p.toml").write_text((Path(PRINTER.source).read_text()).replace(
        "# max_line_rate = 300.0", "max_line_rate = 1000.0"))
    profile = load_profile(tmp_path / "p.toml")
    assert profile.firmware.max_line_rate_hz == 1000.0
    text = write_sweep(path, flavor, profile)
    assert f"; flavor: {flavor}" in text
    block_s = block_s_of(text)
    assert block_s == pytest.approx(1 / 900, rel=1e-8)
    late_s, off_mm, ratio = timing_and_position(*run_on_model(path, flavor, profile), text, flavor)
    print(f"{flavor}: blocks end up to {late_s * 1e6:.2f} us off, {off_mm * 1e3:.3f} um; duration ratio {ratio:.6f}")
    assert late_s <= late_blocks * block_s
    assert off_mm <= position_mm
    assert abs(ratio - 1.0) <= 1e-3


@pytest.mark.slow
def test_rrf_runs_the_sweep_within_issue_30s_bound(tmp_path):
    """Issue 30's bound, which the block-level test above (expected to fail on RRF) is stricter
    than: RRF's model runs the sweep with every block end within 1% of the sweep's duration of its
    time and the duration within 1% (its skipped short ramps: 0.35% and 0.33% of the 6.0 s)."""
    (tmp_path / "p.toml").write_text((Path(PRINTER.source).read_text()).replace(
        "# max_line_rate = 300.0", "max_line_rate = 1000.0"))
    profile = load_profile(tmp_path / "p.toml")
    path = tmp_path / "sweep.gcode"
    text = write_sweep(path, "reprap", profile)
    late_s, off_mm, ratio = timing_and_position(*run_on_model(path, "reprap", profile), text, "reprap")
    duration_s = written_blocks(text, "reprap")[1][-1]  # (the last block's end on the program's grid)
    print(f"reprap: blocks end up to {late_s * 1e3:.2f} ms off of {duration_s:.3f} s, duration ratio {ratio:.5f}")
    assert late_s <= 0.01 * duration_s
    assert abs(ratio - 1.0) <= 0.01


@pytest.mark.parametrize("flavor", ["marlin", "reprap"])
def test_the_plans_clock_mark_is_where_the_models_motion_repeats_the_sweep(tmp_path, flavor):
    """identify searches the sweep's plan for its clock mark within 50 ms of where
    ``excite.firmware_sweep`` puts it. The truth: the firmware model's own motion, the lag at
    which it repeats the sweep's first 1.3 s most closely (searched 0.1 ms apart over +-0.5 s).
    Before, the mark was scaled by the program's own block times, which Marlin's whole steps make
    3% short: 0.4 s late on a 12 s sweep, 0.93 s on a 30 s one (the Marlin model, truth A's limits)."""
    from fbspost.tools.excite import firmware_sweep

    path = tmp_path / "sweep.gcode"
    write_sweep(path, flavor, PRINTER, 5.0)
    sweep = firmware_sweep(path, "X", PRINTER)
    _, position = run_on_model(path, flavor, PRINTER)
    t_s = np.arange(0.0, 20.0, 1e-4)
    x = position(t_s)
    assert x[0] == CENTRE_MM  # (at the sweep's start already: its first motion is the sweep's)
    begin = np.flatnonzero(np.diff(x) != 0.0)[0]
    template = x[begin:begin + 13000] - x[begin]
    designed_s = 5.0 + 1.0  # the header's mark: the sweep and its two ramps
    lags = np.arange(int((designed_s - 0.5) * 1e4), int((designed_s + 0.5) * 1e4))
    off_mm = [np.abs(x[begin + lag:begin + lag + 13000] - x[begin + lag] - template).max() for lag in lags]
    true_s = lags[int(np.argmin(off_mm))] * 1e-4
    print(f"{flavor}: mark at {sweep.mark_s:.4f} s, the model repeats the sweep {true_s:.4f} s after it "
          f"(to {1e3 * min(off_mm):.1f} um)")
    assert min(off_mm) < 0.1  # (a repeat found: a sweep moves 1 mm and more there)
    assert abs(sweep.mark_s - true_s) < 0.02  # (measured: Marlin 0.9 ms, RRF 9.8 ms; before: Marlin 198 ms)


@pytest.mark.slow
def test_linuxcnc_model_runs_the_sweep_as_written(tmp_path):
    """The model of LinuxCNC's planner (1 ms servo period, the INI's 10000 mm/s^2) runs the 3 s
    sweep (5.0 s with the move back and the clock mark, 287 blocks of a half period each, from
    rest to rest in G61.1) as written: every block ends within 10 us (1% of a servo period) of
    its closed-form time (measured 6.5 us: each block 1 nm short and its F rounded up, 30 ns each),
    but the move back to the start (its F not a whole number of periods of acceleration: 44 us
    late), which ends inside a servo period whose rest LinuxCNC leaves: from the clock mark on,
    late by the same, within a period (measured: 0.20 ms); the duration within 0.02% (measured
    +0.004%). Before (1 ms blocks at the profile's limits in G64): 39% long."""
    path = tmp_path / "sweep.ngc"
    text = write_sweep(path, "linuxcnc", PRINTER)
    index, ends_s = rest_to_rest_ends(text, BEGIN, END, PRINTER.axes["X"].max_acceleration_mm_s2)
    motion = run_linuxcnc(list(read_gcode(path, "linuxcnc")), PRINTER)
    late_s = motion.line_time_s[index] - motion.line_time_s[text.splitlines().index(BEGIN)] - ends_s
    late_s -= late_s[0]  # (the first block starts on the servo period after the dwell)
    back = int(np.argmin(np.abs(ends_s - float(re.search(r"clock mark at ([\d.]+) s", text)[1]))))
    mark = back + 1
    print(f"model: {len(index)} blocks, up to {np.abs(late_s[:back]).max() * 1e6:.3f} us late before the move back, "
          f"that {late_s[back] * 1e6:.1f} us, "
          f"{late_s[mark:].min() * 1e3:.3f} to {late_s[mark:].max() * 1e3:.3f} ms from it; "
          f"duration {late_s[-1] / ends_s[-1]:+.3%}")
    assert len(index) > 250
    assert np.abs(late_s[:back]).max() < 1e-5 and 0 <= late_s[back] < late_s[mark]
    assert late_s[mark:].max() - late_s[mark:].min() < 1e-5
    assert late_s[-1] <= PRINTER.firmware.linuxcnc.servo_period_s
    assert abs(late_s[-1]) <= 2e-4 * ends_s[-1]


# ---- identify with the firmware's plan ---------------------------------------------------------------

def recording_of(motion_mm, fs: float, modes, log: Path, offset_s=777.25, rate_hz=3200.0, seed=3) -> None:
    """An accelerometer log of the axis driven by ``motion_mm`` (its commanded position every
    1 / fs s) through the true ``modes`` (scipy's simulation), low-passed (an ideal anti-alias
    filter), sampled at ``rate_hz`` in a time base of its own, 200 mm/s^2 RMS of noise."""
    t = np.arange(len(motion_mm)) / fs
    accel = np.gradient(np.gradient(simulate_lsim(modes, 1 / fs, motion_mm), t), t)
    accel = signal.sosfiltfilt(signal.butter(8, 1000.0, fs=fs, output="sos"), accel)
    t_log = np.arange(int(t[-1] * rate_hz)) / rate_hz
    rng = np.random.default_rng(seed)
    measured = np.interp(t_log, t, accel) + 200.0 * rng.standard_normal(t_log.size)
    log.write_text("#time,accel_x,accel_y,accel_z\n" + "".join(
        f"{ti:.6f},{a:.3f},0.000,9810.000\n" for ti, a in zip(t_log + offset_s, measured, strict=True)))


@pytest.mark.slow
def test_identify_with_the_firmware_plan_of_a_retimed_sweep(tmp_path):
    """A sweep whose program sets the old header's limit (ACCEL=10000 MINIMUM_CRUISE_RATIO=0), so
    that klippy re-times it (every speed change ramps inside a block), run by klippy through
    printer-two-mode's X (52 Hz, zeta 0.07; 96 Hz, 0.03) and recorded: identify with --machine
    plans the program as Klipper does and finds the first mode within 2% (frequency) and its
    damping within 20%; correlated with the sweep as written it does not."""
    from fbspost.tools import excite, measurements, modal_fit, sweep_response

    path, log = tmp_path / "sweep.gcode", tmp_path / "log.csv"
    text = write_sweep(path, "klipper", PRINTER, 8.0)
    path.write_text(re.sub(r"^SET_VELOCITY_LIMIT ACCEL=100000000 .*$",
                           "SET_VELOCITY_LIMIT ACCEL=10000 MINIMUM_CRUISE_RATIO=0", text, count=1, flags=re.M))
    _, position = klippy_run(path)
    fs = 10000.0
    motion = position(np.arange(int(18.0 * fs)) / fs - 1.0)  # 1 s at rest before the program, and after it
    truth = PRINTER.axes["X"].modes
    recording_of(motion, fs, truth, log)
    out = tmp_path / "id.toml"
    result = run("identify", "--accel-log", log, "--program", path, "--axis", "X", "--machine", "printer-two-mode",
                 "-o", out, "--merge", PRINTER.source)
    assert result.exit_code == 0, result.output
    found = min(load_profile(out).axes["X"].modes, key=lambda m: abs(m.frequency_hz - 52.0))
    print(f"firmware plan: {found.frequency_hz:.3f} Hz, damping {found.damping:.4f}")
    assert found.frequency_hz == pytest.approx(truth[0].frequency_hz, rel=0.02)
    assert found.damping == pytest.approx(truth[0].damping, rel=0.2)

    times_s, accel = measurements.read_accel_log(log, "accel_x")
    rec = sweep_response.frf_from_recording(times_s, accel, excite.read_sweep(path, "X"))
    fit = modal_fit.fit_frf(rec.frequency_hz, rec.response, None, 8, weights=rec.coherence, fit_delay=True)
    written = min(fit.modes, key=lambda m: abs(m.frequency_hz - 52.0))
    print(f"as written: {written.frequency_hz:.3f} Hz, damping {written.damping:.4f}")
    assert abs(written.frequency_hz / 52.0 - 1.0) > 0.02 or abs(written.damping / 0.07 - 1.0) > 0.2


def true_frf(modes, frequency_hz):
    """sum (alpha + beta s) / (s^2 + 2 zeta w s + w^2), s = j 2 pi f, written out here."""
    s = 2j * np.pi * np.asarray(frequency_hz)
    return sum((m.alpha + m.beta * s) / (s * s + 2 * m.damping * (2 * np.pi * m.frequency_hz) * s
                                         + (2 * np.pi * m.frequency_hz) ** 2) for m in modes)


@pytest.mark.slow
def test_round_trip_excite_record_identify_within_5_percent(tmp_path):
    """The patent stage's X swept (31 s, 5-100 Hz), run by klippy, recorded through the true model
    (offset 777.25 s in the log's time base, 3200 Hz, noise), identified (the program's header names
    the bundled profile): within 5% of the peak over 5-100 Hz, the sweep's start found within 0.2 ms
    (a fraction of a recording sample, 0.31 ms)."""
    patent = load_profile("patent-xy-stage")
    program, log, out = tmp_path / "sweep.gcode", tmp_path / "raw_data.csv", tmp_path / "id.toml"
    result = run("excite", "--machine", "patent-xy-stage", "--axis", "X", "--center", 50, "--end-hz", 100,
                 "-o", program)
    assert result.exit_code == 0, result.output
    _, position = klippy_run(program, patent)
    fs = 10000.0
    motion = position(np.arange(int(40.0 * fs)) / fs - 1.0)  # 1 s at rest before the program, and after it
    true_modes = patent.axes["X"].modes
    recording_of(motion, fs, true_modes, log)
    sweep_start_s = 777.25 + 1.0 + dwells_s(program.read_text().split(BEGIN)[0])
    result = run("identify", "--accel-log", log, "--program", program, "--axis", "X", "-o", out,
                 "--merge", patent.source)
    assert result.exit_code == 0, result.output
    f = np.linspace(5.0, 100.0, 4000)
    g_true = true_frf(true_modes, f)
    error = np.abs(true_frf(load_profile(out).axes["X"].modes, f) - g_true).max() / np.abs(g_true).max()
    start = float(result.output.split("the sweep starts at ")[1].split()[0])
    print(f"round trip: max FRF error {100 * error:.3f}% of the peak; sweep start found "
          f"{1e3 * (start - sweep_start_s):+.3f} ms off")
    assert error <= 0.05
    assert abs(start - sweep_start_s) < 2e-4
