"""A print sliced anew that no change was tuned on (issue 32): tests/data/make_sliced.py's wavy cup,
sliced by PrusaSlicer (Debian's ``prusa-slicer``) as a Marlin 2 program with the test prints'
settings, for bench/marlin_baseline.py and tests/test_output_marlin.py. Written on 29 November
2026 to tests/data/anew/wavy-marlin2.gcode (PrusaSlicer 2.5.0; a folder of its own, so that the
tests that run every print of tests/data leave it out).

Run from the repository root:  python bench/sliced_anew.py [OUT.gcode]
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "data"))

import make_sliced  # noqa: E402


def main(out: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        stl = Path(tmp) / "wavy.stl"
        make_sliced.write_stl(stl, make_sliced.wavy_cup())
        subprocess.run(["prusa-slicer", "--export-gcode", *make_sliced.COMMON, "--gcode-flavor", "marlin2",
                        "-o", out, str(stl)], check=True, stdout=subprocess.DEVNULL)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "tests" / "data" / "anew" / "wavy-marlin2.gcode"))
