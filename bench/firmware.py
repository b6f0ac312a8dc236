"""What Klipper really does with a program and with fbspost's output of it: firmware results.

Run from the repository root:  python bench/firmware.py PROGRAM.gcode PROFILE [LINES]
Without arguments: the first 8000 lines of tests/data/gear-marlin2.gcode on printer-two-mode,
then samples/butterfly-polyline.gcode on patent-xy-stage.

For the program's first LINES lines (all by default) it runs (a) the original and (b) fbspost's
output (``python -m fbspost.cli compensate``) through Klipper's own planner (klippy's
toolhead.py, tests/klippy_planner.py), samples the motion klippy plans on the profile's grid,
runs it through the profile's modelled dynamics (fbspost/dynamics.py) and measures the contour
error as ``fbspost simulate`` does (simulate.PathDistance: the distance from the modelled
position to the original's path, its extruding moves for a printer, at the samples where the
executed E rises on both sides; every move for a machine without E, while it moves). For
comparison, each of ``fbspost simulate``'s input shapers, tuned to the profile's dominant modes
and applied to klippy's plan of the original. Print time is klippy's: moves and dwells.
"""
from __future__ import annotations

import itertools
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from fbspost.dynamics import AxisDynamics  # noqa: E402
from fbspost.gcode import AXES, detect_flavor, read_gcode  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.shapers import SHAPERS, klipper_shaper, shape  # noqa: E402
from fbspost.simulate import PathDistance, shaper_settings  # noqa: E402
from klippy_planner import KlippyPlanner, sample_moves  # noqa: E402

DEFAULT = [("tests/data/gear-marlin2.gcode", "printer-two-mode", 8000),
           ("samples/butterfly-polyline.gcode", "patent-xy-stage", None)]


def klippy_run(path: Path, profile, flavor: str):
    """(print time s, the moves klippy plans, their samples) of ``path``."""
    planner = KlippyPlanner(profile)
    moves = planner.run(list(read_gcode(path, flavor)))
    return planner.clock_s, moves, sample_moves(moves, profile.sample_rate_hz, planner.clock_s)


def modelled(command: np.ndarray, profile) -> np.ndarray:
    """The actual positions of ``command`` through the profile's modes (axes without modes: as commanded)."""
    actual = command.copy()
    for axis, spec in profile.axes.items():
        if spec.modes and axis in AXES:
            i = AXES.index(axis)
            actual[:, i] = AxisDynamics(spec.modes, 1.0 / profile.sample_rate_hz).simulate(command[:, i])
    return actual


def contour_um(actual: np.ndarray, command: np.ndarray, path: PathDistance, printer: bool) -> tuple[float, float]:
    """(RMS, max) contour error in um at the samples that print (see the module docstring)."""
    if printer:
        rising = np.diff(command[:, 3]) > 0
        mask = np.append(rising, False) & np.insert(rising, 0, False)
    else:
        moving = np.flatnonzero(np.abs(np.diff(command[:, :3], axis=0)).max(axis=1) > 0)
        mask = np.zeros(len(command), bool)
        mask[moving[0]:moving[-1] + 2] = True
    error, _ = path(actual[mask, :3])
    return float(np.sqrt(np.mean(error**2))) * 1e3, float(error.max()) * 1e3


def bench(program: str, machine: str, lines: int | None) -> None:
    profile = load_profile(machine)
    flavor = detect_flavor(ROOT / program)
    with tempfile.TemporaryDirectory() as tmp:
        original = Path(tmp) / Path(program).name
        with open(ROOT / program, "rb") as f:
            original.write_bytes(b"".join(itertools.islice(f, lines)))
        output = Path(tmp) / "compensated.gcode"
        done = subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(original), "-m", machine,
                               "-o", str(output)], cwd=ROOT, capture_output=True, text=True)
        if done.returncode:
            raise SystemExit(done.stderr)
        time_a, moves_a, plan_a = klippy_run(original, profile, flavor)
        time_b, _, plan_b = klippy_run(output, profile, flavor)
    printer = any(m.is_kinematic and m.axes_r[3] > 0 for m in moves_a)
    chosen = [m for m in moves_a if m.is_kinematic and (m.axes_r[3] > 0 or not printer)]
    path = PathDistance(np.array([m.start_pos[:3] for m in chosen]), np.array([m.end_pos[:3] for m in chosen]))
    rows = [("original", time_a, contour_um(modelled(plan_a, profile), plan_a, path, printer)),
            ("fbspost", time_b, contour_um(modelled(plan_b, profile), plan_b, path, printer))]
    settings = shaper_settings(profile)
    period = 1.0 / profile.sample_rate_hz
    shapers = {name: {a: klipper_shaper(name, *settings[a]) for a in settings} for name in SHAPERS}
    pad = math.ceil(max(s.lead_s + s.lag_s for row in shapers.values() for s in row.values()) / period) + 1
    padded = np.pad(plan_a, ((pad, pad), (0, 0)), mode="edge")
    best = None
    for name, row in shapers.items():
        command = padded.copy()
        for axis, shaper in row.items():
            command[:, AXES.index(axis)] = shape(padded[:, AXES.index(axis)], period, shaper)
        result = contour_um(modelled(command, profile), padded, path, printer)
        best = min(best or (name, result), (name, result), key=lambda r: r[1][0])
    lag = max(s.lag_s for s in shapers[best[0]].values())
    rows.append((f"{best[0]} shaper (best)", time_a + lag, best[1]))
    print(f"{program} ({lines or 'all'} lines) on {machine}, through klippy's own planner (firmware results):")
    print(f"  {'run':24} {'print s':>9} {'vs original':>12} {'RMS contour um':>15} {'max um':>9} {'RMS gain':>9}")
    for name, seconds, (rms, peak) in rows:
        print(f"  {name:24} {seconds:9.3f} {100 * (seconds / time_a - 1):+11.2f}% {rms:15.3f} {peak:9.1f} "
              f"{rows[0][2][0] / rms:8.2f}x")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        bench(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else None)
    else:
        for job in DEFAULT:
            bench(*job)
