"""LinuxCNC's example programs that contour continuously in XY, through fbspost on the patent
stage: the original and fbspost's default output (``--verify`` on) run by the model of LinuxCNC's
planner (``linuxcnc_tp``) and, with ``--itself``, by LinuxCNC itself (bench/linuxcnc_sim); RMS
and largest contour error against the best input shaper on the original's plan (bench/firmware.py's
``table``).

Which examples (issue 31: "contour continuously in XY: arcs, splines, NURBS or dense lines"):
every example that rs274 runs with motion (bench/linuxcnc.py's list), judged on rs274's canonical
moves in mm (``contouring``; rotary axes not counted): at least ``MIN_FEEDS`` feed moves; at least
``MIN_XY_SHARE`` of the feed moves' XYZ length in XY (not plunging); at least
``MIN_CONTOUR_SHARE`` of the XY feed length in arcs or straight feeds shorter than ``DENSE_MM`` (a
contour, not long straight cuts; splines and NURBS, whose ends rs274 does not print, count only as
feed moves); and at least ``MIN_FEEDS_PER_RAPID`` feed moves per rapid (continuous, not a rapid
between every few cuts).

Each program is expanded by rs274, cut to its first lines that the model of LinuxCNC runs in
about ``EXCERPT_S`` (a whole line's end), and run on the stage's profile with its travel widened
to the program's extent (the stage's travel is an example value) at the given servo period, with
the sim's parameter file (every work offset 0, as LinuxCNC itself runs it here).

    python bench/linuxcnc_examples.py [--list] [--servo-period S] [--itself] [--only NAME ...]
"""
from __future__ import annotations

import argparse
import itertools
import math
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "bench")]

from firmware import compensated, linuxcnc_own_run, linuxcnc_run, table  # noqa: E402
from linuxcnc import example_programs, runnable  # noqa: E402

from fbspost.firmware.linuxcnc_tp import run_linuxcnc  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from fbspost.read.expand import canonical_calls, expand  # noqa: E402
from fbspost.read.gcode import read_gcode  # noqa: E402

MIN_FEEDS, MIN_XY_SHARE, MIN_CONTOUR_SHARE, MIN_FEEDS_PER_RAPID, DENSE_MM = 50, 0.8, 0.5, 10.0, 1.0
EXCERPT_S = 12.0
FIRST_LINES = 3000  # the model runs at most these to find the excerpt's end
STAGE = ROOT / "machines" / "patent-xy-stage.toml"


def contouring(calls: list[tuple[str, list[str]]]) -> dict:
    """rs274's canonical moves summed up (mm): feed moves, rapids, feed length, its XY part and the
    XY length in arcs and short straight feeds. Splines and NURBS count as feed moves without a
    length (rs274 prints no end point for them)."""
    scale, at = 1.0, None
    m = {"feeds": 0, "rapids": 0, "length_mm": 0.0, "xy_mm": 0.0, "contour_mm": 0.0}
    for name, args in calls:
        if name == "USE_LENGTH_UNITS":
            scale = 25.4 if "INCH" in args[0] else 1.0
        if name not in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED", "ARC_FEED", "NURBS_FEED", "SPLINE_FEED"):
            continue
        if name in ("NURBS_FEED", "SPLINE_FEED"):  # no end point in rs274's print: a contour move of unknown length
            m["feeds"] += 1
            continue
        to = np.array([float(v) * scale for v in (args[:3] if name != "ARC_FEED" else (args[0], args[1], args[5]))])
        if at is not None:
            xy_mm = float(np.hypot(*(to[:2] - at[:2])))
            if name == "ARC_FEED":
                xy_mm = _arc_mm(at, to, float(args[2]) * scale, float(args[3]) * scale, int(args[4]))
            length_mm = math.hypot(xy_mm, to[2] - at[2])
            if name == "STRAIGHT_TRAVERSE":
                m["rapids"] += length_mm > 1e-6
            else:
                m["feeds"] += 1
                m["length_mm"] += length_mm
                m["xy_mm"] += xy_mm
                m["contour_mm"] += xy_mm if name == "ARC_FEED" or xy_mm < DENSE_MM else 0.0
        at = to
    return m


def _arc_mm(at: np.ndarray, to: np.ndarray, cx: float, cy: float, turns: int) -> float:
    """The XY length of rs274's ARC_FEED from ``at`` to ``to`` about (cx, cy), ``turns`` signed
    (positive counterclockwise; a full turn where it ends where it starts)."""
    a0, a1 = math.atan2(at[1] - cy, at[0] - cx), math.atan2(to[1] - cy, to[0] - cx)
    sweep = (a1 - a0 if turns > 0 else a0 - a1) % (2 * math.pi) or 2 * math.pi
    return math.hypot(at[0] - cx, at[1] - cy) * (sweep + 2 * math.pi * (abs(turns) - 1))


def chosen(m: dict) -> bool:
    return (m["feeds"] >= MIN_FEEDS and m["length_mm"] > 0 and m["xy_mm"] >= MIN_XY_SHARE * m["length_mm"]
            and m["contour_mm"] >= MIN_CONTOUR_SHARE * m["xy_mm"]
            and m["feeds"] >= MIN_FEEDS_PER_RAPID * max(m["rapids"], 1))


def stage(folder: Path, servo_period_s: float, extent_mm: float) -> Path:
    """The stage's profile at ``servo_period_s`` with its travel widened to +-``extent_mm``."""
    text = STAGE.read_text()
    # the sim's parameter file (tests/linuxcnc_itself.py: empty, every work offset 0)
    (folder / "sim.var").touch()
    text = re.sub(r"(?m)^\[firmware\]$", f'[firmware]\nservo_period = {servo_period_s!r}\nparameter_file = "sim.var"',
                  text)
    text = re.sub(r"(?m)^position_min = .*$", f"position_min = {-extent_mm!r}", text)
    text = re.sub(r"(?m)^position_max = .*$", f"position_max = {extent_mm!r}", text)
    path = folder / f"stage-{servo_period_s:g}.toml"
    path.write_text(text)
    return path


def excerpt(expanded: Path, folder: Path, servo_period_s: float) -> tuple[Path, int, float]:
    """The first lines of ``expanded`` that the model of LinuxCNC runs in about ``EXCERPT_S``, on a
    stage wide enough for them: (their file, how many lines, the stage's half travel)."""
    with open(expanded, "rb") as f:
        head = list(itertools.islice(f, FIRST_LINES))
    wide = stage(folder, servo_period_s, 1000.0)
    (folder / "head.ngc").write_bytes(b"".join(head))
    profile = load_profile(wide)
    blocks = list(read_gcode(folder / "head.ngc", "linuxcnc", work_offsets_mm=profile.work_offsets_mm))
    line_time_s = run_linuxcnc(blocks, profile).line_time_s
    lines = int(np.searchsorted(np.maximum.accumulate(np.nan_to_num(line_time_s)), EXCERPT_S)) + 1
    cut = folder / expanded.name
    cut.write_bytes(b"".join(head[:lines]))
    ends = [b.points_mm[:, :2] for b in read_gcode(cut, "linuxcnc", work_offsets_mm=profile.work_offsets_mm)
            if b.points_mm is not None]
    extent_mm = math.ceil(np.nanmax(np.abs(np.vstack(ends))) / 10.0) * 10.0 + 10.0 if ends else 50.0
    return cut, lines, max(extent_mm, 50.0)


def measure(program: Path, how, servo_period_s: float, itself: bool) -> None:
    with tempfile.TemporaryDirectory(prefix="lcex-") as work:
        folder = Path(work)
        expanded = folder / "expanded" / program.name
        expanded.parent.mkdir()
        expand(program, expanded, "bench", *how)
        cut, lines, extent_mm = excerpt(expanded, folder, servo_period_s)
        machine = stage(folder, servo_period_s, extent_mm)
        profile = load_profile(machine)
        output = compensated(cut, str(machine), "linuxcnc", profile.firmware.max_line_rate_hz)
        label = f"{program.name} (expanded, first {lines} lines, travel +-{extent_mm:g} mm)"
        table(label, lines, "linuxcnc", f"the stage at {servo_period_s * 1e3:g} ms",
              "through the model of LinuxCNC's trajectory planner", profile,
              linuxcnc_run(cut, profile), linuxcnc_run(output, profile))
        kept = output.read_bytes() == cut.read_bytes()
        print(f"  --verify: {'the original written unchanged' if kept else 'the output kept'}", flush=True)
        if itself:
            own = linuxcnc_own_run(cut, profile), linuxcnc_own_run(output, profile)
            if own[0] is not None:
                table(label, lines, "linuxcnc", f"the stage at {servo_period_s * 1e3:g} ms",
                      "run by LinuxCNC itself (its own task and TP)", profile, *own)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="only list the examples and which are chosen")
    parser.add_argument("--servo-period", type=float, default=0.001, help="s (default 0.001)")
    parser.add_argument("--itself", action="store_true", help="also run both on LinuxCNC itself")
    parser.add_argument("--only", nargs="*", help="only these program names")
    args = parser.parse_args()
    picked = []
    for program in example_programs():
        how, moves = runnable(program)
        if how is None or not moves:
            continue
        m = contouring(canonical_calls(program, *how, timeout_s=60))
        ok = chosen(m)
        print(f"{'CHOSEN' if ok else '      '} {program}: {m['feeds']} feeds, {m['rapids']} rapids, "
              f"XY {m['xy_mm']:.0f} of {m['length_mm']:.0f} mm, contour {m['contour_mm']:.0f} mm", flush=True)
        if ok and (not args.only or program.name in args.only):
            picked.append((program, how))
    if args.list:
        return
    for program, how in picked:
        try:
            measure(program, how, args.servo_period, args.itself)
        except (Exception, SystemExit) as exc:  # noqa: BLE001 (a program that fails is reported, not the end)
            print(f"{program.name}: FAILED: {type(exc).__name__}: {str(exc)[:300]}", flush=True)


if __name__ == "__main__":
    main()
