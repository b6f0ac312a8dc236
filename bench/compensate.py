"""Benchmark `fbspost compensate` on whole programs: wall time against print time, per stage.

Run from the repository root:  python bench/compensate.py [PROGRAM.gcode:PROFILE ...]
Without arguments: the two sliced prints in tests/data on bedslinger-example and the two
butterfly programs in samples/ on patent-xy-stage.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from fbspost.job.pipeline import compensate_file
from fbspost.profile import load_profile

DEFAULT = [
    "tests/data/gear-marlin2.gcode:bedslinger-example",
    "tests/data/blob-reprap-relative-e.gcode:bedslinger-example",
    "samples/butterfly-dense.gcode:patent-xy-stage",
    "samples/butterfly-polyline.gcode:patent-xy-stage",
]


def main(jobs: list[str]) -> None:
    print(f"{'program':34} {'profile':20} {'lines in':>8} {'lines out':>9} {'print s':>8} {'wall s':>7} "
          f"{'x real':>7} {'read':>6} {'plan':>6} {'optim':>6} {'write':>6}  predicted RMS before -> after (um)")
    for job in jobs:
        path, _, machine = job.rpartition(":")
        profile = load_profile(machine)
        with tempfile.TemporaryDirectory() as tmp:
            started = time.perf_counter()
            report = compensate_file(path, Path(tmp) / "out.gcode", profile)
            wall = time.perf_counter() - started
        stages = " ".join(f"{report.stage_time_s[k]:6.2f}" for k in ("read", "plan", "optimize", "write"))
        errors = ", ".join(
            f"{a} {r.rms_error_before_um:.3g} -> {r.rms_error_after_um:.3g}" for a, r in report.axes.items()
        )
        print(f"{Path(path).name:34} {profile.name:20} {report.lines_in:8d} {report.lines_out:9d} "
              f"{report.print_time_s:8.1f} {wall:7.2f} {report.print_time_s / wall:7.1f} {stages}  {errors}"
              + (f"  ({len(report.warnings)} warnings)" if report.warnings else ""))


if __name__ == "__main__":
    main(sys.argv[1:] or DEFAULT)
