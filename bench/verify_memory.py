"""Benchmark: ``--verify``'s memory does not grow with the program's length (issue 33 item 4).

Run from the repository root:  python bench/verify_memory.py [--copies 1 2] [--chunk-lines 5000] [--slack-mb 40]

The corpus gear stacked as ``bench/verify_long.py`` stacks it, once and twice by default, each
checked against itself on the model of Marlin in a fresh process, with chunks lowered to
``--chunk-lines`` lines so that several chunks are planned even once. Prints per program its
lines, the check's print time, RMS error and peak resident memory (VmHWM: this process's alone;
ru_maxrss would count what a forked parent held); exit status 1 when the longest program's peak
is more than ``--slack-mb`` over the shortest's, or its print time is not the copies' multiple
within 1% (a real run, not a shortcut). Before the check streamed it held about 4 kB a line:
150 MB more for the second gear's 37,000 lines.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from verify_long import stacked_gear

ROOT = Path(__file__).resolve().parents[1]

# Runs in a fresh process: argv = program, chunk lines; prints the print time, RMS error, VmHWM (kB)
_VERIFY = """
import sys
from pathlib import Path
from fbspost.firmware import verify
from fbspost.profile import load_profile
program = Path(sys.argv[1])
verdict = verify.verify(program, program, load_profile("printer-two-mode"), "marlin", chunk_lines=int(sys.argv[2]))
peak_kb = next(l.split()[1] for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(verdict.original.duration_s, verdict.original.rms_um, peak_kb)
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, nargs="+", default=[1, 2], help="copies of the gear, one program each")
    parser.add_argument("--chunk-lines", type=int, default=5000)
    parser.add_argument("--slack-mb", type=float, default=40.0)
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for copies in sorted(args.copies):
            program = Path(tmp) / f"gear{copies}.gcode"
            lines = stacked_gear(copies, program)
            done = subprocess.run([sys.executable, "-c", _VERIFY, str(program), str(args.chunk_lines)], cwd=ROOT,
                                  capture_output=True, text=True, check=True,
                                  env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
            duration_s, rms_um, peak_kb = map(float, done.stdout.split()[-3:])
            results.append((copies, duration_s, peak_kb / 1024))
            print(f"{copies} gear(s), {lines} lines: {duration_s:.1f} s, RMS {rms_um:.4g} um, "
                  f"VmHWM {peak_kb / 1024:.0f} MB", flush=True)
    (c0, d0, m0), (c1, d1, m1) = results[0], results[-1]
    flat = m1 <= m0 + args.slack_mb
    timed = abs(d1 / d0 - c1 / c0) <= 0.01 * c1 / c0  # (the copies' travels between them: within 1%)
    print(f"peak {m0:.0f} -> {m1:.0f} MB ({'flat' if flat else 'GROWS'} within {args.slack_mb:g} MB); print time "
          f"x{d1 / d0:.3f} for x{c1 / c0:g} the length ({'a real run' if timed else 'NOT the multiple'})")
    return 0 if flat and timed else 1


if __name__ == "__main__":
    sys.exit(main())
