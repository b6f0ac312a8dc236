"""How fast FBS loses its gain as the machine drifts from its profile, robust or not, and with modes
that move with the print (docs/robust.md).

Run from the repository root:  python bench/robust.py [--tradeoff | --minmax] [LINES]  (default: the
first 8000 lines of tests/data/gear-marlin2.gcode, on printer-two-mode and
tests/data/printer-two-mode-robust.toml; 3000 lines with --tradeoff or --minmax).

1. Predictions (fbspost's model of the machine): ``fbspost simulate --model-error`` for the
   nominal and the robust profile; RMS contour error of FBS and of the best input shaper on every
   perturbed machine, and the gain (RMS contour error removed) at the nominal.
2. Firmware results: the original and both compensated programs (as Klipper programs) through
   klippy's own planner (bench/firmware.py), then through each perturbed machine's modes; the
   shapers applied to klippy's plan of the original. 2b: the same on the first 3000 lines of two
   prints the robust set was not tuned on, the bracket and a twisted star (sliced here).
3. Load-dependent modes: Y carries the print and its frequency falls 15% by the end of the
   program (the bed's mass chosen so); the machine simulated exactly per sample
   (tests/reference.py simulate_varying). Gains: FBS on the machine it models (constant), the
   load-dependent profile's FBS and the fixed profile's FBS on the varying machine; predictions
   (fbspost's plan), then firmware results (klippy's plan of each program, and the best shaper
   on klippy's plan of the original through the varying machine).
4. Speed: ``fbspost compensate`` of the program, its optimizer's time per window (--report),
   nominal and robust.
5. With ``--tradeoff`` instead: the robust set's trade-off (predictions), on the gear and on two
   prints it was not tuned on, the bracket and a twisted star (sliced here with PrusaSlicer): for
   tolerances from none to 16% in frequency and 25% in damping, on how many of the 11 machines
   FBS is at or below the best shaper, by how much it is above at worst, and how much of the
   nominal FBS's gain it keeps at the nominal machine (as error removed and as a ratio). Two
   processes; about 20 minutes at 3000 lines.
6. With ``--minmax`` instead: the best any weighting of the set can do (predictions), on the same
   three prints. The set is the 11 machines themselves; their weights are found by multiplicative
   weights (each multiplied by its FBS over best shaper ratio cubed, then divided by the best
   shaper's squared error), which converges to the weighting whose FBS is least above the best
   shaper at its worst machine; the trajectory is smoothed as for any set (fbspost/fbs/smoothing.py).
   If that worst ratio stays above 1, no weighting of a set of these models meets "at or below
   the best shaper everywhere" on that print. Two processes; about 10 minutes at 3000 lines.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "bench")]

from fbspost.contour import PathDistance  # noqa: E402
from fbspost.fbs.dynamics import AxisDynamics, ModelSet, scaled_mode  # noqa: E402
from fbspost.firmware.shapers import SHAPERS  # noqa: E402
from fbspost.firmware.verify import contour_um, modelled, printed_path  # noqa: E402
from fbspost.profile import format_profile, load_profile  # noqa: E402
from fbspost.read.blocks import AXES  # noqa: E402
from fbspost.tools.simulate import MODEL_ERRORS, model_error, simulate_program  # noqa: E402
from firmware_results import LoadedBed, klippy_run, move_ends, shaped_plans  # noqa: E402

sys.path.insert(0, str(ROOT / "tests" / "data"))
import make_sliced  # noqa: E402

PROGRAM = "tests/data/gear-marlin2.gcode"
MACHINES = {"nominal": "printer-two-mode", "robust": "tests/data/printer-two-mode-robust.toml"}
TRADEOFF_PROGRAMS = {"gear": PROGRAM, "bracket": "tests/data/bracket-reprapfirmware-relative-e.gcode"}
TOLERANCES = [(0.0, 0.0), (0.05, 0.1), (0.1, 0.16), (0.13, 0.2), (0.16, 0.25)]
MINMAX_ITERATIONS = 16


def perturbed(profile, frequency_scale, damping_scale):
    axes = {
        name: dataclasses.replace(axis, modes=tuple(scaled_mode(m, frequency_scale, damping_scale) for m in axis.modes))
        for name, axis in profile.axes.items()
    }
    return dataclasses.replace(profile, axes=axes)


def predictions(program: Path) -> dict:
    print(f"1. predictions (fbspost's model): {program.name}, RMS contour error um")
    sims = {name: simulate_program(program, load_profile(machine)) for name, machine in MACHINES.items()}
    tables = {name: model_error(sim) for name, sim in sims.items()}
    _table([(f, d, {"original": e["original"], "fbs nominal": e["fbs"], "fbs robust": r["fbs"],
                    **_best(e)}) for (f, d, e), (_, _, r) in zip(tables["nominal"], tables["robust"], strict=True)])
    return sims


def firmware(program: Path, heading: str) -> None:
    print(f"\n{heading} firmware results (klippy's planner, then each perturbed machine's modes): {program.name}, "
          "RMS contour error um")
    profile = load_profile(MACHINES["nominal"])
    with tempfile.TemporaryDirectory() as tmp:
        plans = {}
        for name, machine in MACHINES.items():
            output = Path(tmp) / f"{name}.gcode"
            subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(program), "-m", machine, "-o",
                            str(output), "--flavor", "klipper", "-q"], cwd=ROOT, check=True)
            plans[f"fbs {name}"] = klippy_run(output, profile, "klipper")[2]
        _, moves, original = klippy_run(program, profile, "klipper")
    path, _ = printed_path(*move_ends(moves))
    commands = {"original": (original, original), **{n: (p, p) for n, p in plans.items()},
                **{n: (c, padded) for n, (c, padded, _) in shaped_plans(original, profile).items()}}
    rows = []
    for f, d in MODEL_ERRORS:
        machine = perturbed(profile, f, d)
        errors = {n: contour_um(modelled(c, machine), ref, path, True)[0] for n, (c, ref) in commands.items()}
        rows.append((f, d, {k: errors[k] for k in ("original", "fbs nominal", "fbs robust")} | _best(errors)))
    _table(rows)


def load_dependent(sim) -> None:
    print("\n3. load-dependent modes: Y 15% lower at the end (the machine simulated exactly per sample)")
    profile = sim.profile
    e = sim.desired_mm[:, AXES.index("E")]
    bed = LoadedBed.falling_to(0.85, float(np.nanmax(e - e[np.isfinite(e)][0])))
    loaded_profile = dataclasses.replace(profile, axes=dict(profile.axes, Y=dataclasses.replace(
        profile.axes["Y"], moving_mass_kg=bed.mass_kg)))
    loaded = simulate_program(sim.program, loaded_profile)
    distance, y = PathDistance(sim.path_start_mm, sim.path_end_mm), AXES.index("Y")

    def rms(method, varying):
        actual = method.actual_mm.copy()
        if varying:
            actual[:, y] = bed.actual(method.command_mm, profile)[:, y]
        return float(np.sqrt(np.mean(distance(actual[sim.contour_mask, :3])[0] ** 2))) * 1e3

    original, fbs = sim.methods[:2]
    print(f"  moving mass {bed.mass_kg * 1e3:.3g} g; RMS contour error um, gain = removed")
    print("  a. predictions (fbspost's plan)")
    before = rms(original, True)
    _gains(rms(original, False), rms(fbs, False), before, rms(loaded.methods[1], True), rms(fbs, True))
    print("  b. firmware results (klippy's planner; shapers on its plan of the original)")
    with tempfile.TemporaryDirectory() as tmp:
        plans = {}
        for name, machine in (("load", loaded_profile), ("fixed", profile)):
            output = Path(tmp) / f"{name}.gcode"
            profile_path = Path(tmp) / f"{name}.toml"
            profile_path.write_text(format_profile(machine))
            subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(sim.program), "-m",
                            str(profile_path), "-o", str(output), "--flavor", "klipper", "-q"], cwd=ROOT, check=True)
            plans[name] = klippy_run(output, profile, "klipper")[2]
        _, moves, plan = klippy_run(sim.program, profile, "klipper")
    path, _ = printed_path(*move_ends(moves))

    def contour(command, reference, varying=True):
        return contour_um(bed.actual(command, profile) if varying else modelled(command, profile), reference, path,
                          True)[0]

    before = contour(plan, plan)
    _gains(contour(plan, plan, False), contour(plans["fixed"], plans["fixed"], False), before,
           contour(plans["load"], plans["load"]), contour(plans["fixed"], plans["fixed"]))
    shaped = {name: contour(c, padded) for name, (c, padded, _) in shaped_plans(plan, profile).items()}
    best = min(shaped, key=shaped.get)
    print(f"  {'best shaper, varying machine':38} {shaped[best]:8.3f} of {before:8.3f}   gain "
          f"{100 * (1 - shaped[best] / before):5.1f}%  ({best})")


def _gains(original_fixed: float, fbs_fixed: float, original_varying: float, load_varying: float,
           fbs_varying: float) -> None:
    for label, error, base in (("fbs, constant machine it models", fbs_fixed, original_fixed),
                               ("fbs load-dependent, varying machine", load_varying, original_varying),
                               ("fbs fixed profile, varying machine", fbs_varying, original_varying)):
        print(f"  {label:38} {error:8.3f} of {base:8.3f}   gain {100 * (1 - error / base):5.1f}%")


def speed(program: Path) -> None:
    print("\n4. speed: fbspost compensate, the optimizer's time per window (--report; a loaded machine: noisy)")
    with tempfile.TemporaryDirectory() as tmp:
        for name, machine in MACHINES.items():
            report = Path(tmp) / "report.json"
            subprocess.run([sys.executable, "-m", "fbspost.cli", "compensate", str(program), "-m", machine, "-o",
                            str(Path(tmp) / "out.gcode"), "--report", str(report), "-q"], cwd=ROOT, check=True)
            data = json.loads(report.read_text())
            windows = sum(a["windows"] for a in data["axes"].values())
            optimize_s = data["stage_time_s"]["optimize"]
            print(f"  {name:8} {windows:6d} windows  "
                  f"optimize {optimize_s:7.2f} s  {1e3 * optimize_s / windows:6.2f} ms/window")


def _tradeoff_rows(program: Path, frequency_tolerance: float, damping_tolerance: float) -> list[tuple]:
    """(frequency x, damping x, original, FBS, best shaper) per perturbed machine, RMS contour um,
    FBS made with every mode's tolerances set so."""
    profile = load_profile(MACHINES["nominal"])
    axes = {name: dataclasses.replace(axis, modes=tuple(
        dataclasses.replace(m, frequency_tolerance=frequency_tolerance, damping_tolerance=damping_tolerance)
        for m in axis.modes)) for name, axis in profile.axes.items()}
    table = model_error(simulate_program(program, dataclasses.replace(profile, axes=axes)))
    return [(f, d, e["original"], e["fbs"], min(v for k, v in e.items() if k in SHAPERS)) for f, d, e in table]


def tradeoff(heads: dict[str, Path]) -> None:
    print("5. the robust set's trade-off (predictions, fbspost's model): tolerances -> FBS against the best shaper "
          "on the 11 machines, and the gain kept at the nominal machine")
    with ProcessPoolExecutor(2) as pool:
        jobs = {(name, f, d): pool.submit(_tradeoff_rows, head, f, d)
                for name, head in heads.items() for f, d in TOLERANCES}
        for name in heads:
            print(f"  {name}: {'tol f':>6} {'tol d':>6} {'<= best':>8} {'worst x best':>12} {'nominal um':>10} "
                  f"{'removed kept':>12} {'ratio kept':>10}")
            plain = next(r for r in jobs[(name, *TOLERANCES[0])].result() if r[:2] == (1.0, 1.0))
            for f, d in TOLERANCES:
                rows = jobs[name, f, d].result()
                at_or_below = sum(fbs <= best for *_, fbs, best in rows)
                worst = max(fbs / best for *_, fbs, best in rows)
                _, _, original, fbs, _ = next(r for r in rows if r[:2] == (1.0, 1.0))
                removed = (original - fbs) / (original - plain[3])
                ratio = (original / fbs) / (original / plain[3])
                print(f"  {'':{len(name) + 1}} {f:6.3f} {d:6.2f} {at_or_below:5d}/11 {worst:12.3f} {fbs:10.3f} "
                      f"{removed:12.1%} {ratio:10.1%}", flush=True)


def _minmax_rows(program: Path) -> list[str]:
    """Per iteration of the multiplicative weights: the worst FBS over best shaper ratio, the gain
    kept at the nominal (error removed, relative to the nominal FBS's) and the 11 ratios."""
    profile = load_profile(MACHINES["nominal"])
    table = model_error(simulate_program(program, profile))
    best = np.array([min(v for k, v in e.items() if k in SHAPERS) for *_, e in table])
    original, plain = (table[MODEL_ERRORS.index((1.0, 1.0))][2][k] for k in ("original", "fbs"))
    share, rows = np.ones(len(MODEL_ERRORS)), []
    for _ in range(MINMAX_ITERATIONS):
        def spread(cls, modes, sample_period_s, weights=share / best**2):
            return cls([AxisDynamics(tuple(scaled_mode(m, f, d) for m in modes), sample_period_s)
                        for f, d in MODEL_ERRORS], list(weights))

        with mock.patch.object(ModelSet, "spread", classmethod(spread)):
            fbs = np.array([e["fbs"] for *_, e in model_error(simulate_program(program, profile, shapers=()))])
        ratio = fbs / best
        removed = (original - fbs[MODEL_ERRORS.index((1.0, 1.0))]) / (original - plain)
        rows.append(f"{ratio.max():6.3f} {removed:7.1%}  " + " ".join(f"{r:.3f}" for r in ratio))
        share *= ratio**3
        share /= share.sum()
    return rows


def minmax(heads: dict[str, Path]) -> None:
    print("6. the best weighting of the 11 machines as the set (predictions, fbspost's model): multiplicative "
          "weights; per iteration the worst FBS over best shaper, the gain kept at the nominal, the 11 ratios")
    print(f"  machines (frequency x, damping x): {' '.join(f'{f:g}/{d:g}' for f, d in MODEL_ERRORS)}")
    with ProcessPoolExecutor(2) as pool:
        jobs = {name: pool.submit(_minmax_rows, head) for name, head in heads.items()}
        for name, job in jobs.items():
            rows = job.result()
            for i, row in enumerate(rows):
                print(f"  {name:12} {i:2d} {row}")
            print(f"  {name:12} lowest worst ratio: {min(float(r.split()[0]) for r in rows):.3f}", flush=True)


def _best(errors: dict) -> dict:
    best = min((n for n in errors if n in SHAPERS), key=errors.get)
    return {f"best shaper ({best})": errors[best]}


def _table(rows) -> None:
    print(f"  {'freq':6} {'damp':5} " + " ".join(f"{k.split(' (')[0]:>12}" for k in rows[0][2]) + "  best shaper")
    for f, d, errors in rows:
        best = next(k for k in errors if k.startswith("best"))
        print(f"  x{f:<5.3f} x{d:<4.2f} " + " ".join(f"{v:12.3f}" for v in errors.values()) + f"  {best[13:-1]}"
              + ("" if errors["fbs robust"] <= errors[best] else "  (robust fbs above the best shaper)"))
    nominal = next(e for f, d, e in rows if (f, d) == (1.0, 1.0))
    gains = {k: nominal["original"] - nominal[k] for k in ("fbs nominal", "fbs robust")}
    print(f"  at the nominal, the robust FBS keeps {100 * gains['fbs robust'] / gains['fbs nominal']:.1f}% of the "
          f"nominal FBS's gain (RMS contour error removed)")
    ratios = [e["fbs robust"] / next(v for k, v in e.items() if k.startswith("best")) for *_, e in rows]
    print(f"  robust FBS at or below the best shaper on {sum(r <= 1 for r in ratios)}/{len(rows)} machines; "
          f"at worst {max(ratios):.3f} times it")


def twisted_star(folder: str) -> Path:
    """The twisted star of ``make_sliced``, sliced as Marlin 2: ten sharp corners on every
    perimeter, moving from layer to layer."""
    stl, out = Path(folder) / "twisted-star.stl", Path(folder) / "twisted-star.gcode"
    make_sliced.write_stl(stl, make_sliced.twisted_star())
    subprocess.run(["prusa-slicer", "--export-gcode", *make_sliced.COMMON, "--gcode-flavor", "marlin2", "-o",
                    str(out), str(stl)], check=True, stdout=subprocess.DEVNULL)
    return out


def _head(program: str | Path, lines: int, folder: str) -> Path:
    head = Path(folder) / f"{Path(program).stem}-head-{lines}.gcode"
    with open(ROOT / program, "rb") as f:
        head.write_bytes(b"".join(itertools.islice(f, lines)))
    return head


if __name__ == "__main__":
    sweep = next((a for a in sys.argv[1:] if a in ("--tradeoff", "--minmax")), None)
    arguments = [a for a in sys.argv[1:] if a != sweep]
    lines = int(arguments[0]) if arguments else (3000 if sweep else 8000)
    with tempfile.TemporaryDirectory() as folder:
        if sweep:
            programs = {**TRADEOFF_PROGRAMS, "twisted star": twisted_star(folder)}
            heads = {name: _head(program, lines, folder) for name, program in programs.items()}
            (tradeoff if sweep == "--tradeoff" else minmax)(heads)
            sys.exit()
        head = _head(PROGRAM, lines, folder)
        sims = predictions(head)
        firmware(head, "2.")
        untuned = {"bracket": TRADEOFF_PROGRAMS["bracket"], "twisted star": twisted_star(folder)}
        for program in untuned.values():
            firmware(_head(program, 3000, folder), "2b. a print it was not tuned on (3000 lines),")
        load_dependent(sims["nominal"])
        speed(head)
