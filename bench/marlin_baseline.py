"""Marlin's own input shaping against fbspost's Marlin output, all through whole steps (issue 32).

Run from the repository root:  python bench/marlin_baseline.py [PROFILE ...] [--lines N] [--prints P ...]
    [--budgets 300 0] [--flavor marlin|reprap]
Default: printer-two-mode and bedslinger-example, the first 8000 lines of every sliced print in
tests/data, once at a serial host's 300 lines/s and once without a line budget (an SD card).
A print named with a path is read from there (a print sliced anew: bench/sliced_anew.py).
With ``--flavor reprap`` the same for RepRapFirmware: *the model of its planner*
(fbspost/firmware/reprap.py: whole-step targets, its ring, junctions and look-ahead), its
stepper's whole steps, and in place of Marlin's shapers RRF's own M593 types (ZVD, ZVDD, ZVDDD,
MZV, EI2, EI3, ``shaping.reprap_shaper``: one for X and Y together, at each of the profile's
dominant modes, through whole steps), the best by RMS; fbspost's default RRF output.

Every run is *the model of Marlin's planner* (fbspost/firmware/marlin.py: whole-step block ends, the
6-step merge, its buffer and look-ahead), then *the model of its stepper* (each axis on the whole
step its Bresenham gives, fbspost/firmware/shaping.py), then the profile's modes:
- original: the program as Marlin runs it, unshaped;
- Marlin ZV: INPUT_SHAPING_X/Y at the profile's dominant modes (``M593 X F.. D..``, ``M593 Y
  F.. D..``) on the original's plan, as its stepper shapes steps (each axis late by its own
  shaper's mean delay: not centred);
- FT_MOTION: each of its shapers at the same modes on the original's plan (echoes on its 1 kHz
  grid, axes kept in step), the best by RMS;
- fbspost: its default Marlin output (``compensate --flavor marlin``, written for the budget);
- the floor: fbspost's output for the same machine with 100 times the steps per mm (motors with
  no whole steps to speak of: 0.125 um), written and run so; fbspost over it is the steps' cost.
RMS and max contour error over the extruding samples to the original's commanded path
(fbspost.firmware.verify), print time as the model runs it (a shaper adds its lead and lag).
Each 1 kHz sample is held on its whole step (``shaping.stepper_positions``), which aliases a fast
axis' step rate into the modes' band; ``rows(..., staircase=True)`` adds the original, FT_MOTION's
best and fbspost on the stepper's staircase (``shaping.staircase_positions``), which does not.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench"), str(ROOT / "tests")]

from firmware import compensated, excerpt, model_run, reprap_shapers  # noqa: E402

from fbspost.firmware.shaping import (  # noqa: E402
    FT_MOTION_SHAPERS,
    ft_motion_shaper,
    marlin_zv,
    marlin_zv_shaper,
    shaped_steps,
    staircase_positions,
    stepper_positions,
)
from fbspost.firmware.verify import contour_um, modelled  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.tools.simulate import shaper_settings  # noqa: E402
from firmware_results import shaped_plans  # noqa: E402

PRINTS = ("gear-marlin2.gcode", "tube-marlin2.gcode", "pocket-klipper.gcode",
          "bracket-reprapfirmware-relative-e.gcode", "blob-reprap-relative-e.gcode")
BUDGETS = (300.0, None)


def shaped(plan: np.ndarray, profile, shapers: dict, shape_axis) -> tuple[np.ndarray, np.ndarray, float]:
    """(the plan through ``shape_axis`` per shaped axis and whole steps, the plan padded alike,
    the time the shaping adds: its largest lead (FT_MOTION delays every axis by it) and lag)."""
    (command, padded, _), = shaped_plans(plan, profile, {"": shapers}, shape_axis).values()
    added_s = max(s.lead_s for s in shapers.values()) + max(s.lag_s for s in shapers.values())
    return stepper_positions(command, profile.firmware.steps_per_mm), padded, added_s


def fine_steps(machine: str, folder: Path, times: float = 100.0) -> Path:
    """A copy of ``machine``'s profile in ``folder`` with ``times`` its steps per mm."""
    text = Path(load_profile(machine).source).read_text()
    line = re.search(r"(?m)^steps_per_mm\s*=.*$", text).group(0)
    scaled = re.sub(r"=\s*([0-9.]+)", lambda m: f"= {float(m.group(1)) * times!r}", line[line.index("{"):])
    copy = folder / f"{machine}-fine.toml"
    copy.write_text(text.replace(line, "steps_per_mm = " + scaled))
    return copy


def rows(original: Path, output: Path, profile, budget: float | None,
         floor: tuple[Path, object] | None = None, flavor: str = "marlin", staircase: bool = False,
         **config_changes) -> list[tuple[str, float, tuple]]:
    """(name, seconds, (RMS um, max um)) of every run (see the module docstring); ``floor``: the
    output for fine steps and that profile (None: no floor row); ``flavor``: marlin (Marlin ZV,
    FT_MOTION's best) or reprap (RRF's best M593 shaper); ``staircase``: then the original, the
    best shaper but Marlin's ZV and fbspost again, each on the stepper's staircase
    (``shaping.staircase_positions``); ``config_changes``: MarlinConfig (ReprapConfig) fields the
    profile does not set (``classic_jerk=True``), for every run."""
    plain = model_run(original, profile, flavor, budget, **config_changes)
    fbs = model_run(output, profile, flavor, budget, **config_changes)
    spm = profile.firmware.steps_per_mm

    def error(command, mask_source):
        return contour_um(modelled(command, profile), mask_source, plain.path, plain.printer)

    out = [("original", plain.seconds, error(stepper_positions(plain.samples, spm), plain.samples))]
    if flavor == "reprap":
        out.append(_best_reprap_shaper(plain, profile, error))
    else:
        out += _marlin_shapers(plain, profile, error)
    out.append(("fbspost", fbs.seconds, error(stepper_positions(fbs.samples, spm), fbs.samples)))
    out.append(("fbspost, no stepper", fbs.seconds, error(fbs.samples, fbs.samples)))
    if floor is not None:
        fine = model_run(floor[0], floor[1], flavor, budget, **config_changes)
        out.append(("floor", fine.seconds, error(fine.samples, fine.samples)))
    if staircase:
        out += _on_staircase(plain, fbs, out, profile, error)
    return out


def _on_staircase(plain, fbs, out: list, profile, error) -> list[tuple[str, float, tuple]]:
    """The original, FT_MOTION's best shaper of ``out`` (Marlin only: Marlin's ZV shapes step
    counts, RRF's is not done) and fbspost, each on the stepper's staircase
    (``shaping.staircase_positions``): the shaper's plan on steps too fine to matter, then that."""
    spm = profile.firmware.steps_per_mm
    rows = [("original, staircase", plain.seconds, error(staircase_positions(plain.samples, spm), plain.samples))]
    for name, seconds, _ in out:
        if name.startswith("FT_MOTION"):
            settings = shaper_settings(profile)
            per_axis = {a: ft_motion_shaper(name.split()[1].lower(), *settings[a]) for a in settings}
            fine = lambda x, period_s, s, axis: shaped_steps(x, period_s, 1e9, s)  # noqa: E731
            (command, padded, _), = shaped_plans(plain.samples, profile, {"": per_axis}, fine).values()
            rows.append((f"{name}, staircase", seconds, error(staircase_positions(command, spm), padded)))
    rows.append(("fbspost, staircase", fbs.seconds, error(staircase_positions(fbs.samples, spm), fbs.samples)))
    return rows


def _best_reprap_shaper(plain, profile, error) -> tuple[str, float, tuple]:
    """RRF's best M593 shaper on ``plain`` through whole steps (``firmware.reprap_shapers``)."""
    spm = profile.firmware.steps_per_mm
    best = None
    for name, per_axis in reprap_shapers(profile)["shapers"].items():
        command, padded, added_s = shaped(plain.samples, profile, per_axis,
                                          lambda x, period_s, s, axis: shaped_steps(x, period_s, spm[axis], s))
        row = (f"RRF {name.upper().replace(' HZ', 'Hz').replace(' ', '@')}", plain.seconds + added_s,
               error(command, padded))
        best = row if best is None or row[2][0] < best[2][0] else best
    return best


def _marlin_shapers(plain, profile, error) -> list[tuple[str, float, tuple]]:
    """Marlin's ZV and FT_MOTION's best shaper on ``plain``, through whole steps."""
    settings, spm = shaper_settings(profile), profile.firmware.steps_per_mm
    out = []
    command, padded, added_s = shaped(
        plain.samples, profile, {a: marlin_zv_shaper(*settings[a]) for a in settings},
        lambda x, period_s, s, axis: marlin_zv(x, period_s, spm[axis], s.frequency_hz, s.damping))
    out.append(("Marlin ZV", plain.seconds + added_s, error(command, padded)))
    best = None
    for name in FT_MOTION_SHAPERS:
        command, padded, added_s = shaped(plain.samples, profile,
                                          {a: ft_motion_shaper(name, *settings[a]) for a in settings},
                                          lambda x, period_s, s, axis: shaped_steps(x, period_s, spm[axis], s))
        row = (f"FT_MOTION {name.upper()}", plain.seconds + added_s, error(command, padded))
        best = row if best is None or row[2][0] < best[2][0] else best
    out.append(best)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("profiles", nargs="*", default=["printer-two-mode", "bedslinger-example"])
    parser.add_argument("--lines", type=int, default=8000)
    parser.add_argument("--prints", nargs="*", default=list(PRINTS))
    parser.add_argument("--budgets", nargs="*", type=float, default=[b or 0.0 for b in BUDGETS])
    parser.add_argument("--flavor", choices=("marlin", "reprap"), default="marlin")
    args = parser.parse_args()
    shapers = ["RRF best"] if args.flavor == "reprap" else ["Marlin ZV", "FT_MOTION best"]
    print(f"| profile | program | line budget | original um (max) | {' um (max) | '.join(shapers)} um (max) "
          "| fbspost um (max) | fbspost, no stepper um (max) | floor um (max) | fbspost time vs original "
          f"| fbspost / {' | fbspost / '.join(shapers)} | fbspost / floor |")
    print("|---" * (11 + 2 * len(shapers) - 2) + "|")
    for machine in args.profiles:
        profile = load_profile(machine)
        for program in args.prints:
            for budget in (b or None for b in args.budgets):
                with tempfile.TemporaryDirectory() as tmp:
                    original = excerpt(program if "/" in program else f"tests/data/{program}", args.lines, Path(tmp))
                    output = compensated(original, machine, args.flavor, budget).rename(Path(tmp) / "fbspost.gcode")
                    fine = fine_steps(machine, Path(tmp))
                    floor = (compensated(original, str(fine), args.flavor, budget), load_profile(fine))
                    result = rows(original, output, profile, budget, floor, args.flavor)
                print(_row(machine, program, budget, result, len(shapers)), flush=True)


def _row(machine: str, program: str, budget: float | None, result: list, n_shapers: int) -> str:
    """A table row of ``rows``' ``result`` (the shapers' after the original, then fbspost's)."""
    cells = [f"{rms:.2f} ({peak:.0f})" for _, _, (rms, peak) in result]
    for k in range(1, 1 + n_shapers):
        if result[k][0] != "Marlin ZV":  # (the best of several: which)
            cells[k] = f"{result[k][0].split(maxsplit=1)[-1]} {cells[k]}"
    fbs = 1 + n_shapers
    time = 100 * (result[fbs][1] / result[0][1] - 1)
    ratios = " | ".join(f"{result[fbs][2][0] / result[k][2][0]:.2f}" for k in [*range(1, fbs), len(result) - 1])
    return (f"| {machine} | {Path(program).name.split('-')[0]} | {f'{budget:g} lines/s' if budget else 'none'} | "
            f"{' | '.join(cells)} | {time:+.2f}% of {result[0][1]:.1f} s | {ratios} |")


if __name__ == "__main__":
    main()
