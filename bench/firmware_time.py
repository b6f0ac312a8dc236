"""How long fbspost's output lasts against the original, through a model of the firmware's planner.

Run from the repository root:  python bench/firmware_time.py [--flavor marlin|reprap] [PROFILE ...]
    [--lines N] [--prints P ...] [--budgets 300 0]
Default: Marlin, printer-two-mode and bedslinger-example, the first 8000 lines of every sliced
print in tests/data, at a serial host's 300 lines/s and without a budget (0: an SD card).

Each row: the original and fbspost's default output (``compensate --flavor``), each run through
*the model of the firmware's planner* (fbspost/firmware/marlin.py or fbspost/firmware/reprap.py, as
bench/marlin_baseline.py runs them, without its shapers and floor), the output's time against
the original's, and its RMS (max) contour error through whole steps and the profile's modes (um,
over the extruding samples, to the original's commanded path).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench"), str(ROOT / "tests")]

from firmware import compensated, excerpt, model_run  # noqa: E402
from marlin_baseline import PRINTS  # noqa: E402

from fbspost.firmware.shaping import stepper_positions  # noqa: E402
from fbspost.firmware.verify import contour_um, modelled  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("profiles", nargs="*", default=["printer-two-mode", "bedslinger-example"])
    parser.add_argument("--flavor", choices=("marlin", "reprap"), default="marlin")
    parser.add_argument("--lines", type=int, default=8000)
    parser.add_argument("--prints", nargs="*", default=list(PRINTS))
    parser.add_argument("--budgets", nargs="*", type=float, default=[300.0, 0.0])
    args = parser.parse_args()
    print("| firmware | profile | program | line budget | original s | fbspost s | time | fbspost um (max) |")
    print("|---|---|---|---|---|---|---|---|")
    for machine in args.profiles:
        profile = load_profile(machine)
        for program in args.prints:
            for budget in (b or None for b in args.budgets):
                with tempfile.TemporaryDirectory() as tmp:
                    original = excerpt(f"tests/data/{program}", args.lines, Path(tmp))
                    output = compensated(original, machine, args.flavor, budget)
                    plain = model_run(original, profile, args.flavor, budget)
                    fbs = model_run(output, profile, args.flavor, budget)
                stepped = stepper_positions(fbs.samples, profile.firmware.steps_per_mm)
                rms, peak = contour_um(modelled(stepped, profile), fbs.samples, plain.path, plain.printer)
                print(f"| {args.flavor} | {machine} | {program.split('-')[0]} | "
                      f"{f'{budget:g} lines/s' if budget else 'none'} | {plain.seconds:.2f} | {fbs.seconds:.2f} | "
                      f"{100 * (fbs.seconds / plain.seconds - 1):+.2f}% | {rms:.2f} ({peak:.0f}) |", flush=True)


if __name__ == "__main__":
    main()
