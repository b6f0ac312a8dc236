"""LinuxCNC's example programs through fbspost: what compensates, what is refused and why, and
no silently wrong output.

Every .ngc program of Debian's linuxcnc-uspace (files whose code is all inside O-word
subroutines left out) that LinuxCNC's interpreter rs274 runs without error is compensated for
the patent's stage (``--flavor linuxcnc``, expanded by rs274 where it needs it). rs274 is tried
as a user would run it: with the sim configuration's sim.tbl and no INI, else with each INI of
the program's own configuration (the nearest directory above it that has one; rs274 in the INI's
directory, the INI's tool table), for its subroutine paths and remapped codes. Programs rs274
runs without any motion (remaps that end the program without LinuxCNC's HAL) are counted apart.
For every compensated program: the program fbspost compensated, re-read by fbspost with
compensation off, follows rs274's canonical path within the tolerance (1 um, plus rs274's printed
rounding), and rs274 run on fbspost's output gives the same non-motion commands (G33's pitch
among them), in order, and the same probe targets.

    python bench/linuxcnc.py [--limit N] [--only NAME ...] [--travel-mm T] [-v]
"""
from __future__ import annotations

import argparse
import collections
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from canon_check import command_problems, path_problems  # noqa: E402
from fbspost.errors import InputError  # noqa: E402
from fbspost.job.pipeline import compensate_file  # noqa: E402
from fbspost.job.report import CompensateOptions  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.read.blocks import NeedsInterpreter  # noqa: E402
from fbspost.read.expand import MOTION_CALLS, canonical_calls, expand  # noqa: E402
from fbspost.read.gcode import read_gcode  # noqa: E402

TOOL_TABLE = Path("/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/sim.tbl")
SAMPLE_CONFIGS = TOOL_TABLE.parent.parent
_SUBROUTINE = re.compile(r"^\s*o\s*(<[^>]*>|\d+)\s*sub\b.*?^\s*o\s*\1\s*endsub[^\n]*$",
                         re.IGNORECASE | re.MULTILINE | re.DOTALL)
_END = re.compile(r"%|[mM]0*(?:2|30)")


def example_programs() -> list[Path]:
    """linuxcnc-uspace's .ngc files with code outside their O-word subroutines (other than % and M2/M30)."""
    listed = subprocess.run(["dpkg", "-L", "linuxcnc-uspace"], capture_output=True, text=True).stdout.split()
    programs = []
    for name in sorted(p for p in listed if p.endswith(".ngc")):
        text = _SUBROUTINE.sub("", Path(name).read_text(encoding="utf-8", errors="replace"))
        code = (re.sub(r"\([^)]*\)|;.*", "", line).strip() for line in text.splitlines())
        if any(c and not _END.fullmatch(c) for c in code):
            programs.append(Path(name))
    return programs


def invocations(program: Path) -> list[tuple[Path, Path | None]]:
    """(tool table, INI) to run ``program`` with: sim.tbl alone, then its configuration's INIs."""
    found = []
    for folder in program.parents:
        found = sorted(folder.glob("*.ini"))
        if found or folder == SAMPLE_CONFIGS or SAMPLE_CONFIGS not in folder.parents:
            break
    return [(TOOL_TABLE, None)] + [(_ini_tool_table(ini), ini) for ini in found]


def _ini_tool_table(ini: Path) -> Path:
    m = re.search(r"^\s*TOOL_TABLE\s*=\s*(\S+)", ini.read_text(encoding="utf-8", errors="replace"), re.MULTILINE)
    table = ini.parent / m.group(1) if m else TOOL_TABLE
    return table if table.is_file() else TOOL_TABLE


def runnable(program: Path) -> tuple[tuple[Path, Path | None] | None, bool]:
    """The first invocation rs274 runs ``program`` with (None: none), and whether it moves."""
    for table, ini in invocations(program):
        try:
            calls = canonical_calls(program, table, ini, timeout_s=60)
        except InputError:
            continue
        return (table, ini), any(name in MOTION_CALLS for name, _ in calls)
    return None, False


def needs_expansion(program: Path) -> bool:
    try:
        for _ in read_gcode(program, "linuxcnc"):
            pass
    except NeedsInterpreter:
        return True
    except InputError:
        pass
    return False


def outcome(program: Path, profile, work: Path, table: Path, ini: Path | None) -> tuple[str, str]:
    """'compensated', 'WRONG: ...' or the refusal's reason (its message without file, line, numbers);
    verified on the model of LinuxCNC's planner as the command line does by default: where the
    original was kept, or the model failed, the outcome says so. And the check's verdict, if any."""
    output = work / "out.ngc"
    options = CompensateOptions(flavor="linuxcnc", tool_table=table, ini=ini, verify=None)
    try:
        report = compensate_file(program, output, profile, options)
    except InputError as exc:
        message = str(exc).split(": ", 1)[1] if ": " in str(exc) else str(exc)
        message = re.sub(r"^line \d+ of its expansion: ", "", message)
        return re.sub(r"-?\d+(?:\.\d+)?", "N", message), ""
    except Exception as exc:  # noqa: BLE001 (a crash is an outcome to count, not the end of the bench)
        return f"CRASH: {type(exc).__name__}: {str(exc)[:80]}", ""
    expanded = needs_expansion(program)
    read = program
    if expanded:
        read = work / "expanded.ngc"
        expand(program, read, "check", table, ini)
    try:
        problems = (path_problems(program, read, expanded, table, ini=ini)
                    + command_problems(program, output, table, ini))
    except InputError as exc:
        problems = [f"rs274 or the reader refuses what fbspost wrote: {exc}"]
    verdict = report.verified.summary() if report.verified else ""
    if problems:
        return "WRONG: " + "; ".join(problems), verdict
    if report.original_kept:
        return "the original kept: the output no better on LinuxCNC's planner (model)", verdict
    failed = [w for w in report.warnings if "its model failed" in w]
    return (f"compensated, not verified: {re.sub(r'-?[0-9.]+', 'N', failed[0])}" if failed else "compensated"), verdict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=int, help="only the first N programs")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only the programs of these file names")
    parser.add_argument("--travel-mm", type=float, help="the stage's X and Y travel +-this (default: the profile's)")
    parser.add_argument("-v", "--verbose", action="store_true", help="one line per program")
    args = parser.parse_args()
    profile = load_profile("patent-xy-stage")
    if args.travel_mm:
        profile = replace(profile, axes={name: replace(axis, position_min_mm=-args.travel_mm,
                                                       position_max_mm=args.travel_mm) if name in "XY" else axis
                                         for name, axis in profile.axes.items()})
    programs = [p for p in example_programs() if not args.only or p.name in args.only][: args.limit]
    runs, still = {}, []
    for program in programs:
        how, moves = runnable(program)
        if how is not None and moves:
            runs[program] = how
        elif how is not None:
            still.append((program, how))
    with_ini = sum(ini is not None for _, ini in [*runs.values(), *(how for _, how in still)])
    print(f"{len(programs)} example programs (subroutine-only files left out), {len(runs) + len(still)} run "
          f"through rs274 without error ({with_ini} of them with their configuration's INI); {len(still)} of these "
          f"make no motion in rs274 (left out below): {', '.join(p.name for p, _ in still)}")
    counts = collections.Counter()
    started = time.perf_counter()
    for program, (table, ini) in runs.items():
        with tempfile.TemporaryDirectory() as work:
            result, verdict = outcome(program, profile, Path(work), table, ini)
        counts[result] += 1
        if args.verbose:
            print(f"  {program}: {result}" + (f" ({verdict})" if verdict else ""), flush=True)
    total = len(runs)
    print("\n| outcome | programs | share |\n|---|---|---|")
    for result, n in sorted(counts.items(), key=lambda item: (item[0] != "compensated", -item[1], item[0])):
        print(f"| {result} | {n} | {100 * n / total:.0f}% |")
    wrong = sum(n for r, n in counts.items() if r.startswith("WRONG"))
    print(f"\ncompensated with exit 0: {counts['compensated']} of {total}; silently wrong: {wrong}; "
          f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
