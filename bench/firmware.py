"""What the firmware really does with a program and with fbspost's output of it: firmware results.

Run from the repository root:  python bench/firmware.py PROGRAM.gcode PROFILE [LINES [FLAVOR]]
Without arguments: the first 8000 lines of tests/data/gear-marlin2.gcode on printer-two-mode,
then samples/butterfly-polyline.gcode on patent-xy-stage.
FLAVOR marlin or reprap: the program compensated as a Marlin (RepRapFirmware) program and both
run through the model of Marlin's planner (fbspost/firmware/marlin.py; RepRapFirmware's: fbspost/firmware/reprap.py),
once at the profile's max_line_rate, else at a serial host's 300 lines/s (the host sending line
by line) and once without a line budget (an SD-card print; the output written from a copy of
the profile with that max_line_rate, or without one); also where the buffer (ring) ran dry.
The original's path is its commanded one (not the firmware's whole steps); on RepRapFirmware
the output is also run with motors that take no whole steps (its ends are written inside their
steps' cells, so this carries their offsets: the floor is bench/marlin_baseline.py --flavor
reprap's, the output written for fine steps), and every
run is put on its whole steps, the shapers too: RRF's own M593 types (ZVD, ZVDD, ZVDDD, MZV,
EI2, EI3, fbspost/firmware/shaping.py: its impulses on the whole plan, not its per-move segments),
one for X and Y together at each of the profile's dominant modes, as M593 has one. Marlin's own
shaping through its steps: bench/marlin_baseline.py.
FLAVOR linuxcnc: the program compensated as a LinuxCNC program (its G64 P<tolerance> Q0) and both
run through the model of LinuxCNC 2.9's trajectory planner (fbspost/firmware/linuxcnc_tp.py); also how far
the model's motion of the output departs from its blocks run exactly as written (each at its F).
Where LinuxCNC is installed (Debian's linuxcnc-uspace), both are also run by LinuxCNC itself:
headless, its own task, interpreter and TP on a sim config with the profile's limits
(bench/linuxcnc_sim: the joints' commands every servo period, from the program's first point).

For the program's first LINES lines (all by default) it runs (a) the original and (b) fbspost's
output (``python -m fbspost.cli compensate``) through Klipper's own planner (klippy's
toolhead.py, tests/klippy_planner.py; the program compensated as a Klipper program, or as
FLAVOR), samples the motion klippy plans on the profile's grid,
runs it through the profile's modelled dynamics (fbspost/fbs/dynamics.py) and measures the contour
error as ``--verify`` does (verify.contour_um: the distance from the modelled position to the
original's path, its extruding moves for a printer, at the samples where the executed E rises on
both sides, neither rise under verify.END_SLIVER of the other; every move for a machine without
E, while it moves). For
comparison, each of ``fbspost simulate``'s input shapers, tuned to the profile's dominant modes
and applied to klippy's plan of the original. Print time is klippy's: moves and dwells.
"""
from __future__ import annotations

import itertools
import math
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from fbspost.firmware.linuxcnc_tp import INTERPOLATOR_DELAY_PERIODS, run_linuxcnc  # noqa: E402
from fbspost.firmware.marlin import MarlinConfig, run_marlin  # noqa: E402
from fbspost.firmware.reprap import ReprapConfig, commanded_pieces, run_reprap  # noqa: E402
from fbspost.firmware.shaping import REPRAP_SHAPERS, reprap_shaper, shaped_steps, stepper_positions  # noqa: E402
from fbspost.firmware.verify import contour_um, modelled, printed_path  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.read.blocks import AXES  # noqa: E402
from fbspost.read.flavors import detect_flavor  # noqa: E402
from fbspost.read.gcode import read_on_machine  # noqa: E402
from fbspost.tools.simulate import PathDistance, shaper_settings  # noqa: E402
from firmware_results import klippy_run, move_ends, shaped_plans  # noqa: E402
from linuxcnc_itself import as_written, joint_commands, on_grid  # noqa: E402

SERIAL_LINES_PER_S = 300.0  # a serial host's budget where the profile gives none
MODELS = {"marlin": (run_marlin, MarlinConfig, "Marlin's planner"),
          "reprap": (run_reprap, ReprapConfig, "RepRapFirmware's planner")}
DEFAULT = [("tests/data/gear-marlin2.gcode", "printer-two-mode", 8000),
           ("samples/butterfly-polyline.gcode", "patent-xy-stage", None)]


@dataclass
class Run:
    """A program as the firmware runs it."""

    seconds: float
    samples: np.ndarray  # (n, 4) X Y Z E on the profile's grid
    path: PathDistance  # its printing moves (every move for a machine without E)
    printer: bool
    notes: str = ""


def klippy_as_run(path: Path, profile, flavor: str) -> Run:
    """``path`` through klippy's own planner."""
    seconds, moves, samples = klippy_run(path, profile, flavor)
    return Run(seconds, samples, *printed_path(*move_ends(moves)))


def model_run(path: Path, profile, flavor: str, line_rate_hz: float | None, **config_changes) -> Run:
    """``path`` through the model of ``flavor``'s planner, the host sending at ``line_rate_hz``."""
    run_model, config, _ = MODELS[flavor]
    blocks = list(read_on_machine(path, flavor, profile))
    run = run_model(blocks, profile, config.from_profile(profile, line_rate_hz=line_rate_hz, **config_changes))
    rests = np.array(run.starved).reshape(-1, 2)
    taken = np.sort(run.taken_s[np.isfinite(run.taken_s)])
    rate = (np.arange(taken.size) + 1 - np.searchsorted(taken, taken - 1.0, "right")).max(initial=0)
    notes = f"buffer dry {len(rests)}x, {rests[:, 1].sum():.3f} s; at most {rate} lines/s"
    pieces = np.array([piece for _, _, block_pieces in commanded_pieces(blocks) for piece in block_pieces])
    ends = pieces.reshape(-1, 2, pieces.shape[-1] if pieces.size else 4)[:, :, :4]
    return Run(run.duration_s, run.positions_mm(profile.sample_rate_hz)[:, :4], *printed_path(ends[:, 0], ends[:, 1]),
               notes)


def linuxcnc_run(path: Path, profile) -> Run:
    """``path`` through the model of LinuxCNC's trajectory planner; notes: how far its motion is from
    the blocks run as written."""
    blocks = list(read_on_machine(path, "linuxcnc", profile))
    run = run_linuxcnc(blocks, profile)
    samples = run.positions_mm(profile.sample_rate_hz)[:, :4]
    written_s, starts, ends = as_written(blocks, profile.sample_rate_hz)
    # the joints trail the planner by the interpolator's delay: taken out, to compare the timing
    delay_s = INTERPOLATOR_DELAY_PERIODS * run.servo_period_s
    late = samples[round(delay_s * profile.sample_rate_hz):]
    n = min(len(late), len(written_s))
    off_um = 1e3 * np.linalg.norm(late[:n, :3] - written_s[:n, :3], axis=1)
    notes = (f"{1e3 * (run.duration_s - delay_s - len(written_s) / profile.sample_rate_hz):+.1f} ms vs its blocks "
             f"as written; from them {off_um.max():.2f} um at most, {np.sqrt(np.mean(off_um ** 2)):.3f} um RMS "
             f"(the joints' {1e3 * delay_s:g} ms delay taken out)")
    return Run(run.duration_s, samples, *printed_path(starts, ends), notes)


def linuxcnc_own_run(path: Path, profile) -> Run | None:
    """``path`` run by LinuxCNC itself (None where it is not installed): the joint commands every
    servo period (the profile's), from the program's first point, to the profile's grid linearly
    (tests/linuxcnc_itself.py)."""
    joints = joint_commands(path, profile)
    if joints is None:
        return None
    period_s = profile.firmware.linuxcnc.servo_period_s
    blocks = list(read_on_machine(path, "linuxcnc", profile))
    _, starts, ends = as_written(blocks, profile.sample_rate_hz)
    return Run((len(joints) - 1) * period_s, on_grid(joints, period_s, profile.sample_rate_hz),
               *printed_path(starts, ends), "LinuxCNC's own planner")


def compensated(original: Path, machine: str, flavor: str, line_rate_hz: float | None = None) -> Path:
    """fbspost's output of ``original``, written for ``line_rate_hz`` lines/s (None: no budget)."""
    text = re.sub(r"(?m)^max_line_rate\s*=.*$", "", Path(load_profile(machine).source).read_text())
    if line_rate_hz:
        text = re.sub(r"(?m)^\[firmware\]$", f"[firmware]\nmax_line_rate = {line_rate_hz!r}", text)
    machine = str(original.with_name(f"budget-{line_rate_hz}.toml"))
    Path(machine).write_text(text)
    output = original.with_name(f"compensated-{flavor}-{line_rate_hz}.gcode")
    done = subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(original), "-m", machine,
                           "-o", str(output), "--flavor", flavor], cwd=ROOT, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(done.stderr)
    return output


def bench(program: str, machine: str, lines: int | None, output_flavor: str = "klipper") -> None:
    profile = load_profile(machine)
    flavor = detect_flavor(ROOT / program)
    if output_flavor in MODELS:
        shapers = reprap_shapers(profile) if output_flavor == "reprap" else {}
        for budget in (profile.firmware.max_line_rate_hz or SERIAL_LINES_PER_S, None):
            name = f"at {budget:g} lines/s" if budget else "without a line budget"
            with tempfile.TemporaryDirectory() as tmp:
                original = excerpt(program, lines, Path(tmp))
                output = compensated(original, machine, output_flavor, budget)
                more = [("fbspost, no whole steps",
                         model_run(output, profile, output_flavor, budget, steps_per_mm=(math.nan,) * len(AXES)))]
                table(program, lines, flavor, machine, f"through the model of {MODELS[output_flavor][2]}, {name}",
                      profile, model_run(original, profile, output_flavor, budget),
                      model_run(output, profile, output_flavor, budget), more if output_flavor == "reprap" else [],
                      **shapers)
        return
    if output_flavor == "linuxcnc":
        with tempfile.TemporaryDirectory() as tmp:
            original = excerpt(program, lines, Path(tmp))
            output = compensated(original, machine, "linuxcnc", profile.firmware.max_line_rate_hz)
            table(program, lines, flavor, machine, "through the model of LinuxCNC's trajectory planner", profile,
                  linuxcnc_run(original, profile), linuxcnc_run(output, profile))
            own = linuxcnc_own_run(original, profile), linuxcnc_own_run(output, profile)
            if own[0] is not None:
                table(program, lines, flavor, machine, "run by LinuxCNC itself (its own task and TP)", profile, *own)
        return
    with tempfile.TemporaryDirectory() as tmp:
        original = excerpt(program, lines, Path(tmp))
        output = compensated(original, machine, output_flavor, profile.firmware.max_line_rate_hz)
        table(program, lines, flavor, machine, f"compensated as {output_flavor}, through klippy's own planner", profile,
              klippy_as_run(original, profile, output_flavor), klippy_as_run(output, profile, output_flavor))


def excerpt(program: str, lines: int | None, folder: Path) -> Path:
    """The first ``lines`` lines of ``program`` in ``folder``."""
    original = folder / Path(program).name
    with open(ROOT / program, "rb") as f:
        original.write_bytes(b"".join(itertools.islice(f, lines)))
    return original


def reprap_shapers(profile) -> dict:
    """``table``'s keywords for RRF's own M593 shapers through whole steps: each type at each of
    the profile's dominant modes, the same on every shaped axis (M593 has one)."""
    settings, spm = shaper_settings(profile), profile.firmware.steps_per_mm
    shapers = {f"{name} {f:g} Hz": {axis: reprap_shaper(name, f, zeta) for axis in settings}
               for name in REPRAP_SHAPERS for f, zeta in sorted(set(settings.values()))}
    return {"shapers": shapers, "shape_axis": lambda x, period_s, s, axis: shaped_steps(x, period_s, spm[axis], s),
            "steps_per_mm": spm}


def table(program: str, lines, flavor: str, machine: str, how: str, profile, run_a: Run, run_b: Run,
          more: list[tuple[str, Run]] = (), shapers: dict | None = None, shape_axis=None,
          steps_per_mm: dict | None = None) -> None:
    """Print time, RMS and max contour error of the original, fbspost's output (and ``more`` runs)
    and the best input shaper (of ``shapers``, by default simulate's; see ``shaped_plans``), every
    run but ``more`` on its whole steps if ``steps_per_mm`` is given."""
    def on_steps(samples):
        return stepper_positions(samples, steps_per_mm) if steps_per_mm else samples

    time_a, plan_a, path, printer = run_a.seconds, run_a.samples, run_a.path, run_a.printer
    rows = [(name, run.seconds, contour_um(modelled(moved(run.samples), profile), run.samples, path, printer))
            for name, run, moved in [("original", run_a, on_steps), ("fbspost", run_b, on_steps),
                                     *((name, run, np.asarray) for name, run in more)]]
    shaped = {name: (contour_um(modelled(on_steps(command), profile), padded, path, printer), lag_s)
              for name, (command, padded, lag_s) in shaped_plans(plan_a, profile, shapers, shape_axis).items()}
    best = min(shaped, key=lambda name: shaped[name][0][0])
    rows.append((f"{best} shaper (best)", time_a + shaped[best][1], shaped[best][0]))
    print(f"{program} ({lines or 'all'} lines, {flavor}) on {machine}, {how} (firmware results):")
    print(f"  {'run':24} {'print s':>9} {'vs original':>12} {'RMS contour um':>15} {'max um':>9} {'RMS gain':>9}")
    for name, seconds, (rms, peak) in rows:
        print(f"  {name:24} {seconds:9.3f} {100 * (seconds / time_a - 1):+11.2f}% {rms:15.3f} {peak:9.1f} "
              f"{rows[0][2][0] / rms:8.2f}x")
    for name, run in (("original", run_a), ("fbspost", run_b)):
        if run.notes:
            print(f"  {name}: {run.notes}")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        bench(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else None, *sys.argv[4:5])
    else:
        for job in DEFAULT:
            bench(*job)
