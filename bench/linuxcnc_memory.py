"""Benchmark: LinuxCNC's own example systems.ngc compensated and verified in under 1 GB.

Run from the repository root:  python bench/linuxcnc_memory.py [--program PATH] [--limit-mb 1000]

systems.ngc (parameters, G5.1 splines on a 1.2e-4 scale; needs linuxcnc-uspace's examples and
rs274) once grew past 14 GB in the verification, and a reference cycle between a window and its
QP later took it to 1.56 GB. Compensated --flavor linuxcnc on patent-xy-stage in a process of its
own under a cap of 2.5 GB of address space (where a MemoryError would only be a warning, so the
verdict line is checked too); prints the verdict and the peak resident memory of fbspost and of
the processes it started (its own VmHWM: its ru_maxrss would count this process's); exit status 1
over the limit or without a verdict on LinuxCNC's planner.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SYSTEMS_NGC = Path("/usr/share/linuxcnc/ncfiles/systems.ngc")
_PEAK_MEMORY = """
import resource, sys
from fbspost.cli import main
try:
    main(sys.argv[1:])
finally:
    own = int(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")))
    print(max(own, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss), file=sys.stderr)
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--program", type=Path, default=SYSTEMS_NGC)
    parser.add_argument("--limit-mb", type=float, default=1000.0)
    args = parser.parse_args()

    def capped():
        resource.setrlimit(resource.RLIMIT_AS, (5 << 29, 5 << 29))

    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", _PEAK_MEMORY, "compensate", str(args.program), "-m",
                               "patent-xy-stage", "--flavor", "linuxcnc", "-o", str(Path(folder) / "out.ngc")],
                              capture_output=True, text=True, preexec_fn=capped,
                              env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=3600)
    wall_s = time.perf_counter() - started
    verdict = next((line for line in done.stderr.splitlines() if "verified on" in line or "kept" in line), "none")
    peak_mb = int(done.stderr.split()[-1]) / 1e3 if done.stderr.split() and done.stderr.split()[-1].isdigit() else None
    print(f"{args.program.name}: exit {done.returncode}, {wall_s:.0f} s wall; verdict: {verdict}")
    print(f"peak resident memory {peak_mb} MB (limit {args.limit_mb:g} MB); load average {os.getloadavg()[0]:.1f}")
    good = (done.returncode == 0 and "verified on linuxcnc's planner" in done.stderr
            and "model failed" not in done.stderr and peak_mb is not None and peak_mb < args.limit_mb)
    if not good:
        print(done.stderr[-2000:])
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
