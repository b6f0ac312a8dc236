"""Issue 30's proof, end to end: from an accelerometer recording to the machine, as a Klipper user
with an accelerometer would go, through Klipper's own planner, against the input shaper Klipper's
own ``shaper_calibrate`` picks from the same recordings. For tests and benches.

Takes a truth (a profile whose modes are the machine's: tests/data/truth-*.toml) and a print.
``measure``: the user's profile is the truth without modes (its limits, planner and firmware);
for X then Y, ``fbspost excite`` at the centre of the travel, the program run by klippy (its own
planner, configured from the user's profile: the program's own lines, or with ``as_written`` a
``SET_VELOCITY_LIMIT`` first that lets klippy run the sweep's blocks as written), the recording of
klippy's motion through the truth (tests/accel_recording.py), ``fbspost identify --accel-log``
(Y with ``--merge``); klippy's ``extras/shaper_calibrate.py`` on the same recordings picks a
shaper per axis as Klipper's SHAPER_CALIBRATE / calibrate_shaper.py do; ``fbspost identify
--klipper-cfg`` of a printer.cfg with that choice; optionally also shaper_calibrate on Klipper's
own excitation (TEST_RESONANCES' moves, ``resonance_test``) recorded alike. ``evaluate``: the print, fbspost's output
(``compensate --flavor klipper``) with the measured, the printer.cfg and the true profile, each
planned by klippy; the chosen shapers on klippy's plan of the original (Klipper shapes the planned
motion); every command through the truth's modes; RMS and max contour error on klippy's path of
the original, print time klippy's; fbspost's prediction of its output (klippy's plan of it
through the identified modes).
"""
from __future__ import annotations

import importlib
import math
import os
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from accel_recording import Accelerometer, record, write_csv
from fbspost.cli import main
from fbspost.profile import format_profile, load_profile
from fbspost.shapers import klipper_shaper
from fbspost.verify import contour_um, modelled, printed_path
from firmware_results import klippy_run, move_ends, shaped_plans
from klippy_motion import executed
from klippy_planner import klippy_dir, load_klippy

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from firmware import excerpt  # noqa: E402, F401  (for the test and the bench)

CENTER_MM = 100.0  # the sweep's centre: mid-travel of a 200 mm axis
KLIPPER_DAMPING = 0.1  # [input_shaper] damping_ratio_x/y default (shaper_defs.DEFAULT_DAMPING_RATIO)
# What lets klippy run a sweep's 1 ms blocks as written (transparency): no acceleration limit
# that matters, no forced cruise, corners at any speed.
AS_WRITTEN = ("SET_VELOCITY_LIMIT ACCEL=100000000 ACCEL_TO_DECEL=100000000 MINIMUM_CRUISE_RATIO=0 "
              "SQUARE_CORNER_VELOCITY=10000\n")
REST_S = 1.0  # the recording runs this long before the program starts and after it ends
# A badly identified profile (a mode of damping 1e-5, one far below the band) can keep compensate
# busy for many minutes: its row then says so instead of holding the whole run.
COMPENSATE_TIMEOUT_S = 600.0


def cli(*args) -> str:
    """``fbspost ARGS`` (the command line, in process); its output, or RuntimeError."""
    result = CliRunner().invoke(main, [str(a) for a in args])
    if result.exit_code:
        raise RuntimeError(f"fbspost {' '.join(map(str, args))}: exit {result.exit_code}\n{result.output}"
                           + (f"\n{result.exception!r}" if result.exception else ""))
    return result.output


@dataclass
class Measured:
    """What the user has once both axes are measured."""

    user: Path  # the truth's limits, planner and firmware; no modes
    identified: Path  # the profile identify wrote from the recordings
    from_cfg: Path  # identify --klipper-cfg of the printer.cfg with shaper_calibrate's choice
    shapers: dict[str, tuple[str, float]]  # per axis, shaper_calibrate's (type, frequency Hz)
    identify_output: str
    # the same from Klipper's own excitation (resonance_test), where measured
    klipper_test_shapers: dict[str, tuple[str, float]] | None = None


def user_profile(truth_path: Path, folder: Path) -> Path:
    """The truth without its modes, written to ``folder``/user.toml."""
    truth = load_profile(truth_path)
    axes = {name: replace(axis, modes=()) for name, axis in truth.axes.items()}
    user = replace(truth, name="user", description="the truth's limits, no modes", axes=axes)
    path = folder / "user.toml"
    path.write_text(format_profile(user))
    return path


def recorded_sweep(truth, user, axis: str, folder: Path, sweep_args=(), as_written: bool = False,
                   chip: Accelerometer | None = None) -> tuple[Path, Path]:
    """(the program klippy ran, the recording): ``fbspost excite`` of ``axis`` run by klippy,
    recorded through the truth."""
    program = folder / f"sweep-{axis}.gcode"
    cli("excite", "-m", user, "--axis", axis, "--center", CENTER_MM, *sweep_args, "-o", program)
    if as_written:
        program.write_text(AS_WRITTEN + program.read_text())
    return program, recorded(program, truth, user, folder / f"raw_data_{axis.lower()}.csv", chip)


def recorded(program: Path, truth, user, log: Path, chip: Accelerometer | None = None) -> Path:
    """The recording ``log`` of ``program`` run by klippy (configured from the profile ``user``)
    through the truth's modes, from ``REST_S`` before to ``REST_S`` after."""
    motion = executed(program, load_profile(user), "klipper")
    t_s = np.arange(-REST_S, motion.duration_s + REST_S, 1e-4)
    modes = {name: truth.axes[name].modes for name in "XY"}
    return write_csv(log, record(t_s, motion.at(t_s)[:, :2], modes, chip or Accelerometer()))


def resonance_test(axis: str, center_mm: float, start_hz: float = 5.0, end_hz: float = 10000.0 / 75.0,
                   accel_per_hz: float = 75.0, hz_per_s: float = 1.0) -> str:
    """Klipper's own excitation for SHAPER_CALIBRATE (this klippy's resonance_tester.py run_test,
    its defaults) along ``axis`` about ``center_mm``, as lines for klippy: at frequency f a move
    out and back of 0.5 a t^2 at speed a t, a = accel_per_hz f, t = 1 / (4 f); f rising by
    hz_per_s every second of these moves."""
    max_accel = end_hz * accel_per_hz
    lines = [f"SET_VELOCITY_LIMIT ACCEL={max_accel:.3f} ACCEL_TO_DECEL={max_accel:.3f}",
             f"G1 X{center_mm:.6f} Y{center_mm:.6f} F3000", "G4 P1000"]
    frequency_hz, sign = start_hz, 1.0
    while frequency_hz <= end_hz + 1e-6:
        t_seg = 0.25 / frequency_hz
        accel = accel_per_hz * frequency_hz
        out = center_mm + sign * 0.5 * accel * t_seg**2
        lines += [f"M204 S{accel:.3f}", f"G1 {axis}{out:.6f} F{60 * accel * t_seg:.4f}",
                  f"G1 {axis}{center_mm:.6f}"]
        sign = -sign
        frequency_hz += 2.0 * t_seg * hz_per_s
    return "\n".join([*lines, "G4 P1000"]) + "\n"


def shaper_calibrate(log: Path) -> tuple[str, float]:
    """(shaper type, frequency Hz) Klipper's calibrate_shaper.py picks from a raw recording: its
    own ShaperCalibrate, with its defaults (no max_smoothing)."""
    load_klippy(klippy_dir())
    module = importlib.import_module("klippy.extras.shaper_calibrate")
    helper = module.ShaperCalibrate(printer=None)
    data = helper.process_accelerometer_data(np.loadtxt(log, comments="#", delimiter=","))
    data.normalize_to_frequencies()
    best, _ = helper.find_best_shaper(data, None)
    return best.name, float(best.freq)


def measure(truth_path: Path, folder: Path, sweep_args=(), as_written: bool = False,
            chip: Accelerometer | None = None, klipper_test: bool = False) -> Measured:
    """X then Y measured as the user would (see the module docstring); with ``klipper_test`` also
    shaper_calibrate on recordings of Klipper's own excitation (``resonance_test``)."""
    truth = load_profile(truth_path)
    user = user_profile(truth_path, folder)
    identified, outputs, shapers = folder / "identified.toml", [], {}
    for axis in "XY":
        program, log = recorded_sweep(truth, user, axis, folder, sweep_args, as_written, chip)
        outputs.append(cli("identify", "--accel-log", log, "--program", program, "--axis", axis, "-o", identified,
                           "--merge", identified if axis == "Y" else user))
        shapers[axis] = shaper_calibrate(log)
    cfg = folder / "printer.cfg"
    cfg.write_text("[input_shaper]\n" + "".join(f"shaper_type_{a.lower()}: {name}\nshaper_freq_{a.lower()}: {f:.1f}\n"
                                                for a, (name, f) in shapers.items()))
    from_cfg = folder / "from-cfg.toml"
    cli("identify", "--klipper-cfg", cfg, "--merge", user, "-o", from_cfg)
    klipper_test_shapers = None
    if klipper_test:
        klipper_test_shapers = {}
        for axis in "XY":
            program = folder / f"resonance-test-{axis}.gcode"
            program.write_text(resonance_test(axis, CENTER_MM))
            log = recorded(program, truth, user, folder / f"resonances_{axis.lower()}.csv", chip)
            klipper_test_shapers[axis] = shaper_calibrate(log)
    return Measured(user, identified, from_cfg, shapers, "".join(outputs), klipper_test_shapers)


@dataclass
class Row:
    """One way of running the print, on the truth."""

    print_s: float  # klippy's (a shaper's: plus its lag)
    rms_um: float
    max_um: float
    predicted_rms_um: float | None = None  # fbspost's figure for its output (the identified modes)
    note: str = ""


def compensate(program: Path, profile: Path, output: Path, timeout_s: float) -> bool:
    """``fbspost compensate --flavor klipper`` in a process of its own; False if it took longer
    than ``timeout_s`` (then stopped)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    try:
        subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(program), "-m", str(profile), "-o",
                        str(output), "--flavor", "klipper", "-q"], cwd=ROOT, env=env, check=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False
    return True


def evaluate(program: Path, truth_path: Path, measured: Measured, folder: Path,
             timeout_s: float = COMPENSATE_TIMEOUT_S) -> dict[str, Row]:
    """The print's rows: original, shaper_calibrate's choice, FBS from printer.cfg, FBS measured,
    FBS with the exact model (see the module docstring); a compensate over ``timeout_s``: NaN."""
    truth, user = load_profile(truth_path), load_profile(measured.user)
    seconds, moves, plan = klippy_run(program, user, "klipper")
    path, printer = printed_path(*move_ends(moves))

    def contour(command, reference, machine=truth):
        return contour_um(modelled(command, machine), reference, path, printer)

    rows = {"original": Row(seconds, *contour(plan, plan))}
    for label, choice in (("shaper_calibrate", measured.shapers), ("TEST_RESONANCES", measured.klipper_test_shapers)):
        if choice:
            chosen = {a: klipper_shaper(name, freq, KLIPPER_DAMPING) for a, (name, freq) in choice.items()}
            name = f"{label}: " + ", ".join(f"{a} {shaper} {freq:.1f} Hz" for a, (shaper, freq) in choice.items())
            ((command, padded, lag_s),) = shaped_plans(plan, user, {name: chosen}).values()
            rows[name] = Row(seconds + lag_s, *contour(command, padded))
    for name, profile in (("FBS, --klipper-cfg", measured.from_cfg), ("FBS, measured", measured.identified),
                          ("FBS, exact model", truth_path)):
        output = folder / f"{program.stem}-{name.split()[-1].strip('-')}.gcode"
        if not compensate(program, profile, output, timeout_s):
            rows[name] = Row(math.nan, math.nan, math.nan, note=f"compensate stopped after {timeout_s:g} s")
            continue
        out_s, _, out_plan = klippy_run(output, user, "klipper")
        predicted = contour(out_plan, out_plan, load_profile(profile))[0] if profile == measured.identified else None
        rows[name] = Row(out_s, *contour(out_plan, out_plan), predicted)
    return rows


def modes_text(profile_path: Path) -> str:
    """The profile's X and Y modes, one line each: frequency, damping, alpha, beta."""
    profile = load_profile(profile_path)
    return "\n".join(f"  {a}: " + "; ".join(f"{m.frequency_hz:.2f} Hz zeta {m.damping:.4f} alpha {m.alpha:.5g} "
                                             f"beta {m.beta:.4g}" for m in profile.axes[a].modes) for a in "XY")


def table(rows: dict[str, Row]) -> str:
    """The rows as a text table (um, s)."""
    lines = [f"  {'run':50} {'RMS um':>9} {'max um':>9} {'predicted':>10} {'print s':>9}"]
    for name, row in rows.items():
        predicted = f"{row.predicted_rms_um:10.3f}" if row.predicted_rms_um is not None else f"{'':10}"
        line = f"  {name:50} {row.rms_um:9.3f} {row.max_um:9.2f} {predicted} {row.print_s:9.3f}  {row.note}"
        lines.append(line.rstrip())
    return "\n".join(lines)
