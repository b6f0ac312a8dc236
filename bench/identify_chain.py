"""Issue 30's proof, end to end: from an accelerometer recording to the machine, against the
firmware's own input shaping as Klipper's own shaper_calibrate picks it from the same recordings
(tests/recording_chain.py).

Run from the repository root:  python bench/identify_chain.py [--flavor klipper|marlin|reprap|linuxcnc]
[--as-written] [--drift-ppm PPM] [--lines N] [--duration S]

For each held-out truth (tests/data/truth-a.toml, truth-b.toml: never tuned on), as a Klipper
user with an accelerometer would go: ``fbspost excite`` of X then Y (default sweep, 30 s), each
run by klippy's own planner configured from the user's profile (the truth's limits, no modes;
``--as-written``: a SET_VELOCITY_LIMIT line first that lets klippy run the sweep's blocks as
written), recorded by a simulated ADXL345 through the truth (3200 Hz on its own clock, 1234.5 s
offset and ``--drift-ppm`` drift, default 100; 100 mm/s^2 RMS noise; tests/accel_recording.py),
``fbspost identify --accel-log`` (Y with --merge), and Klipper's shaper_calibrate (klippy's own
``extras/shaper_calibrate.py``, its defaults) on the same recordings. Then on two prints (the
gear's first 8000 lines and the bracket, which no change was tuned on): the original; the chosen
shapers (damping 0.1, Klipper's default) on klippy's plan of the original; fbspost's output with
the profile ``identify --klipper-cfg`` makes of a printer.cfg holding that choice; with the
measured profile (its modes printed); with the exact model (the truth's own modes, a reference).
Also, as the fairer baseline, "TEST_RESONANCES": the shapers shaper_calibrate picks from recordings
of Klipper's own excitation (resonance_tester.py's moves, 5 to 133 Hz at 1 Hz/s, 75 mm/s^2 per Hz,
run by klippy and recorded alike): on fbspost's exponential sweep its PSD weighs low frequencies
more than on the excitation it was written for.

EVERY FIGURE COMES FROM KLIPPY'S PLANNER THROUGH THE TRUTH MODEL: klippy's plan of each program
(a shaper: applied to klippy's plan of the original) run through the truth's modes (exact ZOH
simulation), RMS and max contour error (um) on klippy's path of the original, print time (s)
klippy's (a shaper's plus its lag). "predicted": fbspost's own figure for its output, klippy's
plan of it through the identified modes. A compensate over ``--timeout`` (300 s) is stopped and
its row is NaN. Several minutes per truth.

``--flavor marlin`` / ``reprap``: EVERY FIGURE COMES FROM FBSPOST'S MODEL OF MARLIN'S (RRF'S)
PLANNER THROUGH THE TRUTH MODEL, on whole steps: the sweeps written for that firmware and recorded
from the model's motion; the baseline that firmware's own input shaping through its whole steps
(fbspost/firmware/shaping.py), shaper_calibrate picking among the types it has, damping 0.1 (Marlin:
INPUT_SHAPING's ZV per axis, also at the identified dominant modes, and FT_MOTION's types; RRF: its
M593 types, one shaper for X and Y, each axis' choice on both); fbspost's output written for that
flavor and run by the same model; no --klipper-cfg or TEST_RESONANCES rows.

``--flavor linuxcnc`` (needs linuxcnc-uspace): EVERY FIGURE BUT "predicted" COMES FROM LINUXCNC
2.9 ITSELF THROUGH THE TRUTH MODEL: the held-out CNC truth tests/data/truth-stage.toml, sweeps of
30 s (excite's default; ``--duration``), 5-100 Hz at the middle of the travel, written ``--flavor linuxcnc`` and run
by LinuxCNC itself (its joint commands every servo period), recorded alike; identify plans them
with the model of LinuxCNC's planner; the prints the dense butterfly and the 0.05 mm chords
(samples/), whole, compensated ``--flavor linuxcnc`` and run by LinuxCNC itself (its task is not
real-time here: the load average matters); the baseline Klipper's shaper at shaper_calibrate's
choice (LinuxCNC has none) on LinuxCNC's run of the original; no whole steps (a servo stage);
"predicted" the model of LinuxCNC's planner's run of the output through the identified modes.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from accel_recording import Accelerometer  # noqa: E402
from recording_chain import evaluate, excerpt, measure, modes_text, table  # noqa: E402

TRUTHS = ("tests/data/truth-a.toml", "tests/data/truth-b.toml")
PRINTS = ("tests/data/gear-marlin2.gcode", "tests/data/bracket-reprapfirmware-relative-e.gcode")
LINUXCNC_TRUTHS = ("tests/data/truth-stage.toml",)
LINUXCNC_PRINTS = ("samples/butterfly-dense.gcode", "samples/butterfly-polyline.gcode")
LINUXCNC_SWEEP = ("--end-hz", 100.0)  # (excite's 30 s: at 10 s truth-stage's X can come out 20% off)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--flavor", choices=("klipper", "marlin", "reprap", "linuxcnc"), default="klipper",
                        help="klippy, fbspost's model of Marlin's or RRF's planner, or LinuxCNC itself")
    parser.add_argument("--as-written", action="store_true", help="klippy runs the sweeps as written")
    parser.add_argument("--drift-ppm", type=float, default=100.0, help="the accelerometer clock's drift")
    parser.add_argument("--lines", type=int, default=8000, help="the first LINES lines of each print")
    parser.add_argument("--duration", type=float, default=None, help="sweep seconds (default: excite's)")
    parser.add_argument("--prints", nargs="*", default=None,
                        help="the prints (default: the gear, the bracket; LinuxCNC: both butterflies)")
    parser.add_argument("--timeout", type=float, default=300.0, help="longest compensate, s (then a NaN row)")
    args = parser.parse_args()
    if args.as_written and args.flavor != "klipper":
        parser.error("--as-written is Klipper's SET_VELOCITY_LIMIT: with --flavor klipper only")
    cnc = args.flavor == "linuxcnc"
    sweep = ("--duration", args.duration) if args.duration else ()
    if cnc:
        sweep = (*sweep, *LINUXCNC_SWEEP)
    prints = args.prints or list(LINUXCNC_PRINTS if cnc else PRINTS)
    chip = Accelerometer(drift_ppm=args.drift_ppm)
    how = "as written (SET_VELOCITY_LIMIT first)" if args.as_written else "as the program is"
    runner = {"klipper": "klippy", "linuxcnc": "LinuxCNC itself"}.get(args.flavor,
                                                                     f"the model of {args.flavor}'s planner")
    print(f"sweeps run by {runner} {how}; "
          f"accelerometer clock drift {args.drift_ppm:g} ppm; prints: first {args.lines} lines")
    for truth in LINUXCNC_TRUTHS if cnc else TRUTHS:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.time()
            measured = measure(ROOT / truth, Path(tmp), sweep, args.as_written, chip,
                               klipper_test=args.flavor == "klipper", flavor=args.flavor)
            print(f"\n{truth}: measured in {time.time() - start:.0f} s")
            print("identify's summary:\n" + "\n".join(line for line in measured.identify_output.splitlines()
                                                     if line.startswith(("recording", "axis", "fit error"))))
            print("identified modes:\n" + modes_text(measured.identified))
            print("true modes:\n" + modes_text(ROOT / truth))
            for program in prints:
                start = time.time()
                rows = evaluate(excerpt(program, args.lines, Path(tmp)), ROOT / truth, measured, Path(tmp),
                                args.timeout)
                print(f"\n{truth} on {program} (first {args.lines} lines), {runner} + truth model "
                      f"({time.time() - start:.0f} s):\n{table(rows)}", flush=True)


if __name__ == "__main__":
    main()
