"""What Klipper really does with a program and with fbspost's output of it: firmware results.

Run from the repository root:  python bench/firmware.py PROGRAM.gcode PROFILE [LINES [FLAVOR]]
Without arguments: the first 8000 lines of tests/data/gear-marlin2.gcode on printer-two-mode,
then samples/butterfly-polyline.gcode on patent-xy-stage.

For the program's first LINES lines (all by default) it runs (a) the original and (b) fbspost's
output (``python -m fbspost.cli compensate``) through Klipper's own planner (klippy's
toolhead.py, tests/klippy_planner.py; the program compensated as a Klipper program, or as
FLAVOR), samples the motion klippy plans on the profile's grid,
runs it through the profile's modelled dynamics (fbspost/dynamics.py) and measures the contour
error as ``fbspost simulate`` does (simulate.PathDistance: the distance from the modelled
position to the original's path, its extruding moves for a printer, at the samples where the
executed E rises on both sides; every move for a machine without E, while it moves). For
comparison, each of ``fbspost simulate``'s input shapers, tuned to the profile's dominant modes
and applied to klippy's plan of the original. Print time is klippy's: moves and dwells.
"""
from __future__ import annotations

import itertools
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from fbspost.gcode import detect_flavor  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from firmware_results import contour_um, klippy_run, modelled, printed_path, shaped_plans  # noqa: E402

DEFAULT = [("tests/data/gear-marlin2.gcode", "printer-two-mode", 8000),
           ("samples/butterfly-polyline.gcode", "patent-xy-stage", None)]


def bench(program: str, machine: str, lines: int | None, output_flavor: str = "klipper") -> None:
    profile = load_profile(machine)
    flavor = detect_flavor(ROOT / program)
    with tempfile.TemporaryDirectory() as tmp:
        original = Path(tmp) / Path(program).name
        with open(ROOT / program, "rb") as f:
            original.write_bytes(b"".join(itertools.islice(f, lines)))
        output = Path(tmp) / "compensated.gcode"
        done = subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(original), "-m", machine,
                               "-o", str(output), "--flavor", output_flavor], cwd=ROOT, capture_output=True, text=True)
        if done.returncode:
            raise SystemExit(done.stderr)
        time_a, moves_a, plan_a = klippy_run(original, profile, output_flavor)
        time_b, _, plan_b = klippy_run(output, profile, output_flavor)
    path, printer = printed_path(moves_a)
    rows = [("original", time_a, contour_um(modelled(plan_a, profile), plan_a, path, printer)),
            ("fbspost", time_b, contour_um(modelled(plan_b, profile), plan_b, path, printer))]
    shaped = {name: (contour_um(modelled(command, profile), padded, path, printer), lag_s)
              for name, (command, padded, lag_s) in shaped_plans(plan_a, profile).items()}
    best = min(shaped, key=lambda name: shaped[name][0][0])
    rows.append((f"{best} shaper (best)", time_a + shaped[best][1], shaped[best][0]))
    print(f"{program} ({lines or 'all'} lines, {flavor}; compensated as {output_flavor}) on {machine}, "
          f"through klippy's own planner (firmware results):")
    print(f"  {'run':24} {'print s':>9} {'vs original':>12} {'RMS contour um':>15} {'max um':>9} {'RMS gain':>9}")
    for name, seconds, (rms, peak) in rows:
        print(f"  {name:24} {seconds:9.3f} {100 * (seconds / time_a - 1):+11.2f}% {rms:15.3f} {peak:9.1f} "
              f"{rows[0][2][0] / rms:8.2f}x")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        bench(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else None, *sys.argv[4:5])
    else:
        for job in DEFAULT:
            bench(*job)
