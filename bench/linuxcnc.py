"""LinuxCNC's example programs through fbspost: what compensates, what is refused and why, and
no silently wrong output.

Every .ngc program of Debian's linuxcnc-uspace (subroutine-only files left out) that LinuxCNC's
interpreter rs274 runs without error (tool table: the sim configuration's sim.tbl) is
compensated for the patent's stage (``--flavor linuxcnc``, expanded by rs274 where it needs it).
For every compensated program: the program fbspost compensated, re-read by fbspost with
compensation off, follows rs274's canonical path within the tolerance (1 um, plus rs274's printed
rounding), and rs274 run on fbspost's output gives the same non-motion commands, in order.

    python bench/linuxcnc.py [--limit N] [-v]
"""
from __future__ import annotations

import argparse
import collections
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from canon_check import command_problems, path_problems  # noqa: E402
from fbspost.expand import canonical_calls, expand  # noqa: E402
from fbspost.gcode import NeedsInterpreter, read_gcode  # noqa: E402
from fbspost.pipeline import CompensateOptions, compensate_file  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.trajectory import InputError  # noqa: E402

TOOL_TABLE = Path("/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/sim.tbl")
_SUB_ONLY = re.compile(r"\s*o\s*(?:<[^>]*>|\d+)\s*sub\b", re.IGNORECASE)


def example_programs() -> list[Path]:
    """linuxcnc-uspace's .ngc files, subroutine-only ones (first code line ``o<name> sub``) left out."""
    listed = subprocess.run(["dpkg", "-L", "linuxcnc-uspace"], capture_output=True, text=True).stdout.split()
    programs = []
    for name in sorted(p for p in listed if p.endswith(".ngc")):
        with open(name, encoding="utf-8", errors="replace") as f:
            code = next((c for c in (re.sub(r"\([^)]*\)|;.*", "", t).strip() for t in f) if c), "")
        if not _SUB_ONLY.match(code):
            programs.append(Path(name))
    return programs


def needs_expansion(program: Path) -> bool:
    try:
        for _ in read_gcode(program, "linuxcnc"):
            pass
    except NeedsInterpreter:
        return True
    except InputError:
        pass
    return False


def outcome(program: Path, profile, work: Path) -> str:
    """'compensated', 'WRONG: ...' or the refusal's reason (its message without file, line, numbers)."""
    output = work / "out.ngc"
    options = CompensateOptions(flavor="linuxcnc", tool_table=TOOL_TABLE)
    try:
        compensate_file(program, output, profile, options)
    except InputError as exc:
        message = str(exc).split(": ", 1)[1] if ": " in str(exc) else str(exc)
        message = re.sub(r"^line \d+ of its expansion: ", "", message)
        return re.sub(r"-?\d+(?:\.\d+)?", "N", message)
    except Exception as exc:  # noqa: BLE001 (a crash is an outcome to count, not the end of the bench)
        return f"CRASH: {type(exc).__name__}: {str(exc)[:80]}"
    expanded = needs_expansion(program)
    read = program
    if expanded:
        read = work / "expanded.ngc"
        expand(program, read, "check", TOOL_TABLE)
    try:
        problems = path_problems(program, read, expanded, TOOL_TABLE) + command_problems(program, output, TOOL_TABLE)
    except InputError as exc:
        problems = [f"rs274 or the reader refuses what fbspost wrote: {exc}"]
    return "WRONG: " + "; ".join(problems) if problems else "compensated"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, help="only the first N programs")
    parser.add_argument("-v", "--verbose", action="store_true", help="one line per program")
    args = parser.parse_args()
    profile = load_profile("patent-xy-stage")
    programs = example_programs()[: args.limit]
    runnable = []
    for program in programs:
        try:
            canonical_calls(program, TOOL_TABLE, timeout_s=60)
            runnable.append(program)
        except InputError:
            pass
    print(f"{len(programs)} example programs (subroutine-only files left out), {len(runnable)} run through rs274 "
          "without error")
    counts = collections.Counter()
    started = time.perf_counter()
    for program in runnable:
        with tempfile.TemporaryDirectory() as work:
            result = outcome(program, profile, Path(work))
        counts[result] += 1
        if args.verbose:
            print(f"  {program}: {result}", flush=True)
    total = len(runnable)
    print(f"\n| outcome | programs | share |\n|---|---|---|")
    for result, n in sorted(counts.items(), key=lambda item: (item[0] != "compensated", -item[1], item[0])):
        print(f"| {result} | {n} | {100 * n / total:.0f}% |")
    wrong = sum(n for r, n in counts.items() if r.startswith("WRONG"))
    print(f"\ncompensated with exit 0: {counts['compensated']} of {total}; silently wrong: {wrong}; "
          f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
