"""What the fallback to the planned original costs: the gain (RMS contour error of the original over
that of the written program) with and without it, and what the written program leaves after its
first travel. Programs: Fay's butterfly, dense (1 ms blocks) and as 0.05 mm chords, scaled 1, 2 and 3,
on the patent stage; the sliced prints in tests/data on the two-mode printer profile.

The written program is run block by block at its feeds through the profile's model (``fbspost
simulate --compensated``): these figures are predictions of fbspost's ideal-controller model, not
of a firmware's planner.

    python bench/fallback_gain.py [--lines N] [--only NAME,...]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np

from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import load_profile
from fbspost.tools.examples import butterfly_dense_program, butterfly_polyline_program
from fbspost.tools.simulate import simulate_program

ROOT = Path(__file__).resolve().parent.parent
PRINTS = sorted((ROOT / "tests" / "data").glob("*.gcode"))


def programs(folder: Path, lines: int | None):
    """(name, path, profile name) of every program measured."""
    for scale in (1, 2, 3):
        for kind, make in (("dense", butterfly_dense_program), ("polyline", butterfly_polyline_program)):
            path = folder / f"butterfly-{kind}-x{scale}.ngc"
            path.write_text(make(0.8 * scale))
            yield path.stem, path, "patent-xy-stage"
    for source in PRINTS:
        path = folder / source.name
        with open(source, "rb") as f:
            path.write_bytes(b"".join(itertools.islice(f, lines or None)))
        yield source.stem, path, "printer-two-mode"


def unbudgeted(profile):
    """Without the firmware's line budget and steps: blocks within the tolerance, timed by their
    XYZ length as ``simulate --compensated`` times them (Marlin times creeping blocks by E)."""
    return dataclasses.replace(profile, firmware=dataclasses.replace(profile.firmware, max_line_rate_hz=None,
                                                                     steps_per_mm={}))


def measure(path: Path, profile, fallback: bool, folder: Path) -> dict:
    out = folder / f"{path.stem}-{'fb' if fallback else 'nofb'}.gcode"
    report = compensate_file(path, out, profile, CompensateOptions(fallback=fallback))
    sim = simulate_program(path, profile, (), compensated=out, flavor=report.flavor)
    original, fbs = sim.methods
    return {"gain": original.path.rms_contour_error_um / fbs.path.rms_contour_error_um,
            "rms": fbs.path.rms_contour_error_um, "max": fbs.path.max_contour_error_um,
            "orig_rms": original.path.rms_contour_error_um, "orig_max": original.path.max_contour_error_um,
            "added_s": report.added_time_s, "print_s": report.print_time_s,
            "stretches": sum("falls back" in w for w in report.warnings)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lines", type=int, help="only the first N lines of each sliced print")
    parser.add_argument("--only", help="comma-separated program names")
    args = parser.parse_args()
    only = set(args.only.split(",")) if args.only else None
    print(f"{'program':34} {'orig um':>9} {'with':>9} {'without':>9} {'kept':>6} {'max um':>8} {'orig max':>8} "
          f"{'stretches':>9} {'added s':>8} {'wall s':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, profile_name in programs(Path(tmp), args.lines):
            if only and name not in only:
                continue
            clock = time.perf_counter()
            profile = unbudgeted(load_profile(profile_name))
            on, off = measure(path, profile, True, Path(tmp)), measure(path, profile, False, Path(tmp))
            print(f"{name:34} {on['orig_rms']:9.3f} {on['gain']:8.2f}x "
                  f"{off['gain']:8.2f}x {on['gain'] / off['gain']:6.3f} "
                  f"{on['max']:8.2f} {on['orig_max']:8.2f} {on['stretches']:9d} {on['added_s']:8.3f} "
                  f"{time.perf_counter() - clock:7.1f}", flush=True)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
