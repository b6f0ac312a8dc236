"""Benchmark ``--verify`` on a long print: peak memory and time with and without it (issue 33 item 4).

Run from the repository root:  python bench/verify_long.py [--copies 12] [--keep DIR]

The print is the corpus gear (tests/data/gear-marlin2.gcode, Marlin, about 30 min on
printer-two-mode as the model of Marlin's planner runs it) stacked ``--copies`` times, each copy
10 mm above the last: 12 copies make a 6 h print. Fresh processes, so that each peak is its
own: compensate with the check (the default for Marlin), compensate without it, and with
``--alone`` the check alone on the written output. Per process: wall time, CPU time (its own and
its axes' processes': on a shared machine the wall time grows with the load, the CPU time
much less), the stages' times, VmHWM (the peak resident memory of the process
that writes, from /proc/self/status) and the largest peak of its child processes (ru_maxrss of
the axes' and the check's, which run beside the writer; a forked child's counts the pages it
shares with the writer too: the sum of the two bounds the whole from above).
"""
from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GEAR = ROOT / "tests" / "data" / "gear-marlin2.gcode"
COPY_MM = 10.0  # the gear is 9.95 mm tall
PROFILE = "printer-two-mode"

# Runs in a fresh process: argv = mode (off | on | alone), input, output, profile; prints one JSON line.
_RUN = """
import json, resource, sys, time
from pathlib import Path
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import load_profile
from fbspost.firmware.verify import verify
mode, source, output = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
profile = load_profile(sys.argv[4])
started = time.perf_counter()
if mode == "alone":
    verdict, stages = verify(source, output, profile, "marlin"), {}
else:
    report = compensate_file(source, output, profile, CompensateOptions(flavor="marlin", verify=mode == "on"))
    verdict, stages = report.verified, report.stage_time_s
wall_s = time.perf_counter() - started
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
children_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(json.dumps(dict(wall_s=wall_s, stages=stages, vmhwm_mb=hwm / 1024, children_mb=children_mb,
                      verdict=verdict.summary() if verdict else None)))
"""


def stacked_gear(copies: int, path: Path) -> int:
    """The gear's layers ``copies`` times, each copy ``COPY_MM`` higher, between its start and end
    code, written to ``path``; gives the number of lines."""
    lines = GEAR.read_bytes().splitlines(keepends=True)
    first = next(i for i, line in enumerate(lines) if line.startswith(b";LAYER_CHANGE"))
    end = max(i for i, line in enumerate(lines) if line.startswith(b";TYPE:Custom")) - 1  # its M107
    z_move = re.compile(rb"^(G1 Z)([-\d.]+)")
    with open(path, "wb") as out:
        out.writelines(lines[:first])
        for copy in range(copies):
            for line in lines[first:end]:
                out.write(z_move.sub(lambda m, c=copy: m.group(1) + b"%.3f" % (float(m.group(2)) + c * COPY_MM), line))
        out.writelines(lines[end:])
    return first + copies * (end - first) + len(lines) - end


def run(mode: str, source: Path, output: Path) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-c", _RUN, mode, str(source), str(output), PROFILE], capture_output=True,
                          text=True, cwd=ROOT, check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # (the axes' processes are waited for: counted)
    cpu_s = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return {**json.loads(done.stdout.splitlines()[-1]), "cpu_s": cpu_s}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=12, help="copies of the gear (12: a 6 h print)")
    parser.add_argument("--keep", type=Path, help="write the programs here (default: a temporary folder)")
    parser.add_argument("--alone", action="store_true", help="also the check alone, in a process of its own")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        source, output = folder / "gear-stacked.gcode", folder / "gear-stacked-out.gcode"
        started = time.perf_counter()
        lines = stacked_gear(args.copies, source)
        print(f"{source.name}: {args.copies} gears stacked, {lines} lines, {source.stat().st_size / 1e6:.1f} MB "
              f"(built in {time.perf_counter() - started:.1f} s); {PROFILE}, Marlin")
        results = {}
        # (verified first: on a loaded machine, where the run may be stopped, its peak memory matters most)
        for mode, title in (("on", "compensate, verified (the default)"), ("off", "compensate, --no-verify"),
                            ("alone", "the check alone"))[:3 if args.alone else 2]:
            results[mode] = r = run(mode, source, output)
            if mode == "off":
                with open(output, "rb") as f:
                    print(f"output: {sum(1 for _ in f)} lines, {output.stat().st_size / 1e6:.1f} MB")
            stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stages"].items())
            print(f"{title}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, VmHWM {r['vmhwm_mb']:.0f} MB, "
                  f"largest child {r['children_mb']:.0f} MB"
                  + (f" (stages s: {stages})" if stages else ""), flush=True)
            if mode == "on":
                print(f"verified: {r['verdict']}", flush=True)
        on, off = results["on"], results["off"]
        print(f"time with the check: {100 * (on['wall_s'] / off['wall_s'] - 1):+.1f}% wall, "
              f"{100 * (on['cpu_s'] / off['cpu_s'] - 1):+.1f}% CPU; "
              f"peak memory with it: the writer {on['vmhwm_mb']:.0f} MB, its largest child {on['children_mb']:.0f} MB",
              flush=True)


if __name__ == "__main__":
    main()
