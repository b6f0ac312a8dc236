"""What each Marlin setting gains, one changed at a time from Marlin's defaults (issue 32, item 3).

Run from the repository root:
    python bench/marlin_settings.py [--machine PROFILE] [--program GCODE] [--lines N]
                                    [--budget LINES_PER_S] [--only LABEL ...]
Default: printer-two-mode, the first 2000 lines of tests/data/gear-marlin2.gcode, no line budget
(an SD card), every setting below (the last row: the two that gain most, together). Each
setting goes into a copy of the profile's ``[firmware]`` table (classic jerk has no key there: it
is a ``MarlinConfig`` field of the model, given to every run), the program is compensated for
that copy (``compensate --flavor marlin``) and ``marlin_baseline.rows`` runs the original,
Marlin's ZV, FT_MOTION's best shaper and fbspost's output through *the model of Marlin's planner
and its whole steps* (fbspost/firmware/marlin.py), then the profile's modes. One markdown row per
setting: RMS (max) contour error in um, fbspost's time against the original's as the model runs
it.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench"), str(ROOT / "tests")]

from firmware import compensated, excerpt  # noqa: E402
from marlin_baseline import rows  # noqa: E402

from fbspost.profile import load_profile  # noqa: E402

FINE_STEPS = "steps_per_mm = { X = 160.0, Y = 160.0, Z = 400.0, E = 415.0 }"
# (label, [firmware] lines replacing the ones with their keys or added, MarlinConfig changes)
SETTINGS = (
    ("Marlin's defaults", (), {}),
    ("MIN_STEPS_PER_SEGMENT 1", ("min_steps_per_segment = 1",), {}),
    ("MIN_STEPS_PER_SEGMENT 3", ("min_steps_per_segment = 3",), {}),
    ("BLOCK_BUFFER_SIZE 32", ("block_buffer = 32",), {}),
    ("BLOCK_BUFFER_SIZE 64", ("block_buffer = 64",), {}),
    ("CLASSIC_JERK", (), {"classic_jerk": True}),
    ("M205 B0", ("min_segment_time = 0.0",), {}),
    ("160 steps/mm on X and Y", (FINE_STEPS,), {}),
    ("both: MIN_STEPS_PER_SEGMENT 1, 160 steps/mm", ("min_steps_per_segment = 1", FINE_STEPS), {}),
)


def with_firmware(machine: str, lines: tuple[str, ...], folder: Path) -> Path:
    """A copy of ``machine``'s profile in ``folder`` with ``lines`` in its ``[firmware]`` table
    (each replacing the line of the same key)."""
    text = Path(load_profile(machine).source).read_text()
    for line in lines:
        key = line.split("=")[0].strip()
        text, found = re.subn(rf"(?m)^{key}\s*=.*$", line, text)
        if not found:
            text = re.sub(r"(?m)^\[firmware\]$", f"[firmware]\n{line}", text)
    copy = folder / "settings.toml"
    copy.write_text(text)
    return copy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machine", default="printer-two-mode")
    parser.add_argument("--program", default="tests/data/gear-marlin2.gcode")
    parser.add_argument("--lines", type=int, default=2000)
    parser.add_argument("--budget", type=float, default=None, help="lines/s a serial host sends (default: none)")
    parser.add_argument("--only", nargs="*", help="the labels of the settings to run (default: all)")
    args = parser.parse_args()
    print("| setting | line budget | original um (max) | Marlin ZV um (max) | FT_MOTION best um (max) "
          "| fbspost um (max) | fbspost time vs original |")
    print("|---|---|---|---|---|---|---|")
    for label, lines, changes in SETTINGS:
        if args.only and label not in args.only:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            machine = with_firmware(args.machine, lines, Path(tmp))
            original = excerpt(args.program, args.lines, Path(tmp))
            output = compensated(original, str(machine), "marlin", args.budget).rename(Path(tmp) / "fbspost.gcode")
            result = rows(original, output, load_profile(machine), args.budget, **changes)
        cells = [f"{rms:.2f} ({peak:.0f})" for _, _, (rms, peak) in result[:4]]
        cells[2] = f"{result[2][0].split()[-1]} {cells[2]}"
        time = 100 * (result[3][1] / result[0][1] - 1)
        print(f"| {label} | {f'{args.budget:g} lines/s' if args.budget else 'none'} | {' | '.join(cells)} "
              f"| {time:+.2f}% of {result[0][1]:.1f} s |", flush=True)


if __name__ == "__main__":
    main()
