"""Issue 30's proof, end to end: from an accelerometer recording to the machine, as a user with an
accelerometer would go, through Klipper's own planner (``flavor`` "klipper") or fbspost's models of
Marlin's and RepRapFirmware's planners ("marlin", "reprap": ``planners.PLANNER_MODELS``), against
the input shaping that firmware has, chosen by Klipper's own ``shaper_calibrate`` from the same
recordings. For tests and benches.

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

Marlin and RRF (``flavor``): the sweep written ``--flavor`` FLAVOR, run and recorded from the
model of that firmware's planner (its motion, not its whole steps); shaper_calibrate picks among
the types the firmware has (``BASELINES``: Marlin's INPUT_SHAPING ZV per axis, also at the
identified dominant modes; FT_MOTION's types; RRF's M593 types, one shaper for X and Y: each
axis' choice on both), damping 0.1 (its default), shaped as the firmware shapes, through whole
steps (``fbspost.firmware.shaping``, bench/marlin_baseline.py ``shaped``); the prints compensated
``--flavor`` FLAVOR and run by the same model; every run on its whole steps
(``shaping.stepper_positions``) through the truth, the contour to the original's
commanded path; no ``--klipper-cfg`` row.

LinuxCNC (``flavor`` "linuxcnc"): the sweep written ``--flavor linuxcnc`` at the middle of the
travel and run by LinuxCNC 2.9 itself (tests/linuxcnc_itself.py: its joint commands every servo
period, linear between them as a drive in position mode follows them), recorded through the
truth; identify plans the sweep with the model of LinuxCNC's planner (``--machine``). LinuxCNC
has no input shaper: the baseline is Klipper's shaper at shaper_calibrate's choice (its own
list) applied to LinuxCNC's run of the original, as Klipper shapes its plan. The prints
compensated ``--flavor linuxcnc`` and run by LinuxCNC itself; no whole steps (a servo stage
follows the joint commands); fbspost's prediction is the model of LinuxCNC's planner's run of its
output through the identified modes. Needs linuxcnc-uspace.
"""
from __future__ import annotations

import importlib
import math
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from accel_recording import Accelerometer, record, write_csv
from fbspost.cli import main
from fbspost.firmware.linuxcnc_tp import run_linuxcnc
from fbspost.firmware.planners import PLANNER_MODELS
from fbspost.firmware.shapers import Shaper, klipper_shaper
from fbspost.firmware.shaping import (
    ft_motion_shaper,
    marlin_zv,
    marlin_zv_shaper,
    reprap_shaper,
    shaped_steps,
    stepper_positions,
)
from fbspost.firmware.verify import contour_um, modelled
from fbspost.profile import format_profile, load_profile
from fbspost.read.gcode import read_gcode
from fbspost.tools.simulate import shaper_settings
from firmware_results import shaped_plans
from klippy_motion import executed
from klippy_planner import klippy_dir, load_klippy
from linuxcnc_itself import from_first_motion, joint_commands

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
# (excerpt: for the test and the bench)
from firmware import excerpt, klippy_as_run, linuxcnc_own_run, linuxcnc_run, model_run  # noqa: E402, F401
from marlin_baseline import shaped  # noqa: E402

CENTER_MM = 100.0  # the sweep's centre where the profile gives no travel: mid-travel of a 200 mm axis
KLIPPER_DAMPING = 0.1  # [input_shaper] damping_ratio_x/y default (shaper_defs.DEFAULT_DAMPING_RATIO)
# What lets klippy run a sweep's 1 ms blocks as written (transparency): no acceleration limit
# that matters, no forced cruise, corners at any speed.
AS_WRITTEN = ("SET_VELOCITY_LIMIT ACCEL=100000000 ACCEL_TO_DECEL=100000000 MINIMUM_CRUISE_RATIO=0 "
              "SQUARE_CORNER_VELOCITY=10000\n")
REST_S = 1.0  # the recording runs this long before the program starts and after it ends
# A badly identified profile (a mode of damping 1e-5, one far below the band) can keep compensate
# busy for many minutes: its row then says so instead of holding the whole run.
COMPENSATE_TIMEOUT_S = 600.0


def g_of(modes, frequency_hz):
    """sum (alpha + beta s) / (s^2 + 2 zeta w s + w^2), s = j 2 pi f."""
    s = 2j * math.pi * np.asarray(frequency_hz)
    return sum((m.alpha + m.beta * s) / (s * s + 2 * m.damping * 2 * math.pi * m.frequency_hz * s
                                         + (2 * math.pi * m.frequency_hz) ** 2) for m in modes)


def assert_identified(truth: Path, identified: Path, end_hz: float) -> None:
    """The identified responses within 10% of the truth's peak over the sweep's band, 5 Hz to
    ``end_hz`` (fail here, not after minutes of compensating with a wrong model)."""
    f_hz = np.linspace(5.0, end_hz, 2000)
    for axis in "XY":
        true_g = g_of(load_profile(truth).axes[axis].modes, f_hz)
        error = float(np.abs(g_of(load_profile(identified).axes[axis].modes, f_hz) - true_g).max()
                      / np.abs(true_g).max())
        print(f"{axis}: identified response off the truth's by {100 * error:.1f}% of its peak")
        assert error <= 0.1


def assert_the_bar(rows: dict, baselines: tuple[str, ...]) -> None:
    """Issue 30's bar: FBS from the recordings leaves at most half the RMS contour error of the
    best of the rows named ``baselines...``, a largest error below the original's, and its
    prediction within 2x of what the firmware and the truth give."""
    original, fbs = rows["original"], rows["FBS, measured"]
    baseline = min(row.rms_um for name, row in rows.items() if name.startswith(baselines))
    assert fbs.rms_um <= 0.5 * baseline
    assert fbs.max_um < original.max_um
    assert 0.5 <= fbs.predicted_rms_um / fbs.rms_um <= 2.0


@dataclass(frozen=True)
class Baseline:
    """A firmware's own input shaping: the types it has (Klipper's name -> the firmware's; None:
    shaper_calibrate's own list), its shaper at (type, frequency Hz, damping), and how it shapes an
    axis through whole steps (``shape_axis(steps_per_mm)`` gives ``shaped_plans``' ``shape_axis``;
    None: Klipper's, on the plan, no steps)."""

    label: str
    types: dict[str, str] | None
    make: Callable[[str, float, float], Shaper]
    shape_axis: Callable[[dict], Callable] | None = None
    one_for_all: bool = False  # one shaper for every axis (RRF's M593): each axis' choice on both


def _on_steps(steps_per_mm: dict) -> Callable:
    return lambda x, period_s, shaper, axis: shaped_steps(x, period_s, steps_per_mm[axis], shaper)


def _marlin_steps(steps_per_mm: dict) -> Callable:
    return lambda x, period_s, s, axis: marlin_zv(x, period_s, steps_per_mm[axis], s.frequency_hz, s.damping)


MARLIN_ZV = Baseline("Marlin ZV", {"zv": "zv"}, lambda name, f, zeta: marlin_zv_shaper(f, zeta), _marlin_steps)
BASELINES = {
    "klipper": (Baseline("shaper_calibrate", None, klipper_shaper),),
    "marlin": (MARLIN_ZV, Baseline("FT_MOTION", {"zv": "zv", "mzv": "mzv", "zvd": "zvd", "ei": "ei", "2hump_ei": "2hei",
                                                  "3hump_ei": "3hei"}, ft_motion_shaper, _on_steps)),
    "reprap": (Baseline("RRF M593", {"zvd": "zvd", "mzv": "mzv", "2hump_ei": "ei2", "3hump_ei": "ei3"}, reprap_shaper,
                        _on_steps, one_for_all=True),),
    "linuxcnc": (Baseline("shaper_calibrate (Klipper's, on LinuxCNC's run)", None, klipper_shaper),),
}


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

    flavor: str
    user: Path  # the truth's limits, planner and firmware; no modes
    identified: Path  # the profile identify wrote from the recordings
    from_cfg: Path | None  # identify --klipper-cfg of the printer.cfg with shaper_calibrate's choice (Klipper)
    # the firmware's shapers: by row name, (its baseline, per axis (the firmware's type, frequency Hz,
    # damping)): shaper_calibrate's choices from the same recordings among the firmware's types, and
    # (Klipper) from recordings of Klipper's own excitation (resonance_test), where measured
    shapers: dict[str, tuple[Baseline, dict[str, tuple[str, float, float]]]]
    identify_output: str


def user_profile(truth_path: Path, folder: Path) -> Path:
    """The truth without its modes, written to ``folder``/user.toml."""
    truth = load_profile(truth_path)
    axes = {name: replace(axis, modes=()) for name, axis in truth.axes.items()}
    user = replace(truth, name="user", description="the truth's limits, no modes", axes=axes)
    path = folder / "user.toml"
    path.write_text(format_profile(user))
    return path


def centre_mm(profile, axis: str) -> float:
    """The middle of ``axis``' travel as the profile gives it, else ``CENTER_MM``."""
    lo, hi = profile.axes[axis].position_min_mm, profile.axes[axis].position_max_mm
    return CENTER_MM if lo is None or hi is None else 0.5 * (lo + hi)


def recorded_sweep(truth, user, axis: str, folder: Path, sweep_args=(), as_written: bool = False,
                   chip: Accelerometer | None = None, flavor: str = "klipper") -> tuple[Path, Path]:
    """(the program the firmware ran, the recording): ``fbspost excite --flavor`` of ``axis`` run
    by the firmware (``recorded``), recorded through the truth; ``as_written``: Klipper's only."""
    program = folder / f"sweep-{axis}.gcode"
    cli("excite", "-m", user, "--axis", axis, "--center", centre_mm(truth, axis), "--flavor", flavor, *sweep_args,
        "-o", program)
    if as_written:
        program.write_text(AS_WRITTEN + program.read_text())
    return program, recorded(program, truth, user, folder / f"raw_data_{axis.lower()}.csv", chip, flavor)


def recorded(program: Path, truth, user, log: Path, chip: Accelerometer | None = None, flavor: str = "klipper") -> Path:
    """The recording ``log`` of ``program`` run by klippy (or by the model of ``flavor``'s planner;
    LinuxCNC: by LinuxCNC itself), configured from the profile ``user``, through the truth's modes,
    from ``REST_S`` before to ``REST_S`` after."""
    profile = load_profile(user)
    if flavor == "linuxcnc":
        duration_s, at = run_by_linuxcnc(program, profile, truth)
    else:
        motion = (executed(program, profile, "klipper") if flavor == "klipper"
                  else PLANNER_MODELS[flavor](list(read_gcode(program, flavor, profile.home_mm)), profile))
        duration_s, at = motion.duration_s, motion.at
    t_s = np.arange(-REST_S, duration_s + REST_S, 1e-4)
    modes = {name: truth.axes[name].modes for name in "XY"}
    return write_csv(log, record(t_s, at(t_s)[:, :2], modes, chip or Accelerometer()))


def run_by_linuxcnc(program: Path, profile, truth) -> tuple[float, Callable]:
    """(its duration s, X Y at times s) of ``program`` run by LinuxCNC itself from the middle of
    the travel (the harness moves there first; the record starts at the first motion), the joint
    commands linear between servo periods; RuntimeError where LinuxCNC is not installed."""
    start_xy_mm = (centre_mm(truth, "X"), centre_mm(truth, "Y"))
    run = program.with_name(f"{program.stem}-run.ngc")
    run.write_text(f"G0 X{start_xy_mm[0]!r} Y{start_xy_mm[1]!r}\n" + program.read_text())
    planned = sweep_as_planned(run, profile, start_xy_mm)
    for _ in range(3):
        joints = joint_commands(run, profile)
        if joints is None:
            raise RuntimeError("LinuxCNC is not installed (apt-get install linuxcnc-uspace)")
        # (from the sweep's start: LinuxCNC's task times the dwell before it, to a period or two)
        sweep, plan = after_longest_rest(joints[:, :2]), after_longest_rest(planned)
        n = min(len(sweep), len(plan))
        if abs(len(sweep) - len(plan)) <= 1 and np.abs(sweep[:n] - plan[:n]).max() < 1e-5:
            break
        # LinuxCNC here is not real-time: under the host's load its task can fall behind the
        # sweep's rest-to-rest blocks, and the motion then rests periods its planner never
        # planned (a machine's real-time host does not). Such a run is not the firmware's plan.
        print(f"LinuxCNC's run of {run.name} was off its own plan ({len(sweep)} periods for {len(plan)}): "
              "the host's load (not real-time); run again")
    else:
        raise RuntimeError(f"LinuxCNC ran {run.name} off its own plan three times: the host is too loaded")
    grid_s = np.arange(len(joints)) * profile.firmware.linuxcnc.servo_period_s
    return grid_s[-1], lambda t: np.column_stack([np.interp(t, grid_s, joints[:, i]) for i in range(2)])


def sweep_as_planned(run: Path, profile, start_xy_mm: tuple[float, float]) -> np.ndarray:
    """X Y of the joint commands every servo period of the sweep ``run`` from ``start_xy_mm`` (where
    the harness moves first), from its first motion, as the model of LinuxCNC's planner gives them
    (within halsampler's 1 nm of LinuxCNC's own where it runs in time: test_linuxcnc_itself)."""
    home_mm = np.array(profile.home_mm, dtype=float)
    home_mm[:2] = start_xy_mm
    motion = run_linuxcnc(list(read_gcode(run, "linuxcnc", home_mm)), profile)
    return from_first_motion(motion.joint_positions_mm[:, :3])[:, :2]


def after_longest_rest(samples: np.ndarray) -> np.ndarray:
    """``samples`` from the last row of their longest run of equal rows."""
    moves = np.append(np.flatnonzero(np.any(np.diff(samples, axis=0) != 0.0, axis=1)), len(samples) - 1)
    rests = np.diff(np.append(-1, moves))
    return samples[moves[np.argmax(rests)]:]


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


def shaper_calibrate(log: Path, types=None) -> tuple[str, float]:
    """(shaper type, frequency Hz) Klipper's calibrate_shaper.py picks from a raw recording: its
    own ShaperCalibrate, with its defaults (no max_smoothing); among ``types`` (Klipper's names),
    by default its own list (``AUTOTUNE_SHAPERS``), with its own rule."""
    load_klippy(klippy_dir())
    module = importlib.import_module("klippy.extras.shaper_calibrate")
    helper = module.ShaperCalibrate(printer=None)
    data = helper.process_accelerometer_data(np.loadtxt(log, comments="#", delimiter=","))
    data.normalize_to_frequencies()
    autotune = module.AUTOTUNE_SHAPERS
    module.AUTOTUNE_SHAPERS = list(types or autotune)
    try:
        best, _ = helper.find_best_shaper(data, None)
    finally:
        module.AUTOTUNE_SHAPERS = autotune
    return best.name, float(best.freq)


def firmware_choices(flavor: str, logs: dict[str, Path], identified: Path, label: str = ""
                     ) -> dict[str, tuple[Baseline, dict[str, tuple[str, float, float]]]]:
    """``Measured.shapers`` from the recordings ``logs`` (by axis): each of ``flavor``'s baselines at
    shaper_calibrate's choice among its types (a one-for-all's: each axis' choice on every axis),
    damping Klipper's default; Marlin's ZV also at the ``identified`` profile's dominant modes."""
    out = {}
    for baseline in BASELINES[flavor]:
        chosen = {}
        for axis, log in logs.items():
            name, f_hz = shaper_calibrate(log, baseline.types)
            chosen[axis] = ((baseline.types or {}).get(name, name), f_hz, KLIPPER_DAMPING)
        runs = ({f"{axis}'s on every axis": {a: choice for a in logs} for axis, choice in chosen.items()}
                if baseline.one_for_all else {"": chosen})
        for how, choice in runs.items():
            text = ", ".join(f"{a} {name} {f:.1f} Hz" for a, (name, f, _) in choice.items())
            out[f"{label or baseline.label}{', ' if how else ''}{how}: {text}"] = (baseline, choice)
    if flavor == "marlin":
        dominant = shaper_settings(load_profile(identified))
        text = ", ".join(f"{a} {f:.1f} Hz D {zeta:.3f}" for a, (f, zeta) in dominant.items())
        out[f"Marlin ZV, identified modes: {text}"] = (MARLIN_ZV, {a: ("zv", *fz) for a, fz in dominant.items()})
    return out


def measure(truth_path: Path, folder: Path, sweep_args=(), as_written: bool = False,
            chip: Accelerometer | None = None, klipper_test: bool = False, flavor: str = "klipper") -> Measured:
    """X then Y measured as the user would (see the module docstring), on ``flavor``'s firmware;
    with ``klipper_test`` also shaper_calibrate on recordings of Klipper's own excitation
    (``resonance_test``, run by klippy)."""
    truth = load_profile(truth_path)
    user = user_profile(truth_path, folder)
    identified, outputs, logs = folder / "identified.toml", [], {}
    for axis in "XY":
        program, logs[axis] = recorded_sweep(truth, user, axis, folder, sweep_args, as_written, chip, flavor)
        outputs.append(cli("identify", "--accel-log", logs[axis], "--program", program, "--machine", user,
                           "--axis", axis, "-o", identified, "--merge", identified if axis == "Y" else user))
    shapers = firmware_choices(flavor, logs, identified)
    from_cfg = None
    if flavor == "klipper":
        ((_, choice),) = shapers.values()
        cfg, from_cfg = folder / "printer.cfg", folder / "from-cfg.toml"
        cfg.write_text("[input_shaper]\n" + "".join(f"shaper_type_{a.lower()}: {name}\nshaper_freq_{a.lower()}: "
                                                    f"{f:.1f}\n" for a, (name, f, _) in choice.items()))
        cli("identify", "--klipper-cfg", cfg, "--merge", user, "-o", from_cfg)
    if klipper_test:
        tests = {}
        for axis in "XY":
            program = folder / f"resonance-test-{axis}.gcode"
            program.write_text(resonance_test(axis, CENTER_MM))
            tests[axis] = recorded(program, truth, user, folder / f"resonances_{axis.lower()}.csv", chip)
        shapers.update(firmware_choices("klipper", tests, identified, "TEST_RESONANCES"))
    return Measured(flavor, user, identified, from_cfg, shapers, "".join(outputs))


@dataclass
class Row:
    """One way of running the print, on the truth."""

    print_s: float  # the firmware's (a shaper's: plus the time it adds)
    rms_um: float
    max_um: float
    predicted_rms_um: float | None = None  # fbspost's figure for its output (the identified modes)
    note: str = ""


def compensate(program: Path, profile: Path, output: Path, timeout_s: float, flavor: str = "klipper") -> bool:
    """``fbspost compensate --flavor FLAVOR`` in a process of its own; False if it took longer
    than ``timeout_s`` (then stopped)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    try:
        subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(program), "-m", str(profile), "-o",
                        str(output), "--flavor", flavor, "-q"], cwd=ROOT, env=env, check=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False
    return True


def firmware_run(program: Path, user, flavor: str):
    """``program`` as the firmware runs it (bench/firmware.py's ``Run``): klippy's planner, LinuxCNC
    itself, or the model of ``flavor``'s planner at the profile's line budget."""
    if flavor == "klipper":
        return klippy_as_run(program, user, "klipper")
    if flavor == "linuxcnc":
        run = linuxcnc_own_run(program, user)
        if run is None:
            raise RuntimeError("LinuxCNC is not installed (apt-get install linuxcnc-uspace)")
        return run
    return model_run(program, user, flavor, user.firmware.max_line_rate_hz)


def shaped_run(plan: np.ndarray, user, baseline: Baseline, choice: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(the command, the plan padded alike, the time the shaping adds) of ``baseline``'s shapers at
    ``choice`` (per axis: type, frequency, damping) on ``plan``: Klipper's on the plan; a firmware's
    through its whole steps (bench/marlin_baseline.py)."""
    shapers = {axis: baseline.make(*setting) for axis, setting in choice.items()}
    if baseline.shape_axis is None:
        ((command, padded, lag_s),) = shaped_plans(plan, user, {"": shapers}).values()
        return command, padded, lag_s
    return shaped(plan, user, shapers, baseline.shape_axis(user.firmware.steps_per_mm))


FBS_ROWS = ("FBS, --klipper-cfg", "FBS, measured", "FBS, exact model")


def evaluate(program: Path, truth_path: Path, measured: Measured, folder: Path,
             timeout_s: float = COMPENSATE_TIMEOUT_S, fbs=FBS_ROWS) -> dict[str, Row]:
    """The print's rows: original, the firmware's shapers, the ``fbs`` rows: FBS from printer.cfg
    (Klipper), FBS measured, FBS with the exact model (see the module docstring); a compensate over
    ``timeout_s``: NaN."""
    truth, user, flavor = load_profile(truth_path), load_profile(measured.user), measured.flavor
    original = firmware_run(program, user, flavor)

    def contour(command, reference, machine=truth):
        on_steps = flavor not in ("klipper", "linuxcnc")
        stepped = stepper_positions(command, user.firmware.steps_per_mm) if on_steps else command
        return contour_um(modelled(stepped, machine), reference, original.path, original.printer)

    rows = {"original": Row(original.seconds, *contour(original.samples, original.samples))}
    for name, (baseline, choice) in measured.shapers.items():
        command, padded, added_s = shaped_run(original.samples, user, baseline, choice)
        rows[name] = Row(original.seconds + added_s, *contour(command, padded))
    profiles = dict(zip(FBS_ROWS, (measured.from_cfg, measured.identified, truth_path), strict=True))
    for name in (n for n in fbs if profiles[n]):
        output = folder / f"{program.stem}-{name.split()[-1].strip('-')}.gcode"
        if not compensate(program, profiles[name], output, timeout_s, flavor):
            rows[name] = Row(math.nan, math.nan, math.nan, note=f"compensate stopped after {timeout_s:g} s")
            continue
        out = firmware_run(output, user, flavor)
        predicted = None
        if name == "FBS, measured":  # (LinuxCNC: fbspost's model of its planner, not LinuxCNC's own run)
            planned = linuxcnc_run(output, user) if flavor == "linuxcnc" else out
            predicted = contour(planned.samples, planned.samples, load_profile(profiles[name]))[0]
        rows[name] = Row(out.seconds, *contour(out.samples, out.samples), predicted)
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
