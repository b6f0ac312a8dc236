"""Benchmark the whole pipeline on sliced prints of about 1 min, 10 min, 1 h and 6 h and on a 100 MB
CNC program, then complete vs limited look-ahead on the patent's butterfly.

Run from the repository root:  python bench/pipeline.py [--sizes 1m,10m,cnc,gear1h] [--cache bench/.programs]

The prints are the tube of tests/data/make_sliced.py (smooth circles, for bedslinger-example), a
spur gear (sharp corners on every layer, for printer-two-mode: X 52 + 96 Hz, Y 34 Hz) and the
twisted star of make_sliced (ten corners on every perimeter, moving from layer to layer: a print
the speed work was not tuned on, printer-two-mode; star6h as long as the 6.6 h print of issue 15),
scaled and sliced with PrusaSlicer 2.5 (`prusa-slicer` on PATH) the first time and kept in the
cache folder. The CNC program (LinuxCNC) is a raster finishing pass over a wavy surface, 0.25 mm
segments at 50 mm/s, about 2.8 million lines, generated the first time (bedslinger-example).
Each program is compensated in a fresh process, so that its peak memory is its own.
Per program: wall time and times faster than real time, peak memory, samples per second of
every stage, the share of the optimizer's windows that needed the QP and the fallback's share
of the wall time.
"""
from __future__ import annotations

import argparse
import gc
import math
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the fbspost command (fbspost/__init__.py); numpy loads next
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "data")]  # this checkout's fbspost, not an installed one

import make_sliced  # noqa: E402  (the corpus' models and slicer settings)
import numpy as np  # noqa: E402
from engine import butterfly_table  # noqa: E402

from fbspost.job.pipeline import compensate_file  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402

# Size -> (model, scale of the 20 x 4 mm model, profile); scales chosen so that PrusaSlicer's
# estimate is near the size.
SCALES = {"1m": ("tube", 0.45, "bedslinger-example"), "10m": ("tube", 1.45, "bedslinger-example"),
          "1h": ("tube", 3.25, "bedslinger-example"), "6h": ("tube", 7.0, "bedslinger-example"),
          "gear1h": ("gear", 2.9, "printer-two-mode"), "gear6h": ("gear", 6.3, "printer-two-mode"),
          "star1h": ("star", 3.5, "printer-two-mode"), "star6h": ("star", 7.7, "printer-two-mode")}
CNC = "cnc"  # the size name of the CNC program
CNC_PROFILE = "bedslinger-example"
STAGES = ("read", "plan", "optimize", "fallback", "write")


def gear(teeth: int = 24, root_mm: float = 8.5, tip_mm: float = 10.0, hole_mm: float = 3.0):
    """A spur gear 20 mm across and 4 mm tall with straight-flanked teeth and a round hole:
    four sharp corners per tooth on every perimeter and infill line ends against them."""
    step = 2 * np.pi / teeth
    angles = np.arange(teeth)[:, None] * step + np.array([0.0, 0.2, 0.45, 0.65]) * step
    radii = np.tile([root_mm, tip_mm, tip_mm, root_mm], teeth)
    t = angles.ravel()
    outer = np.column_stack([radii * np.cos(t), radii * np.sin(t)])
    return make_sliced.ring(outer, make_sliced.circle(hole_mm, len(outer)), 0.0, 4.0)


MODELS = {"tube": make_sliced.tube, "gear": gear, "star": make_sliced.twisted_star}


def sliced_program(size: str, cache: Path) -> Path:
    """The size's model at its scale, sliced once: slicing is not what is measured, and a 6 h
    print is best sliced only once. Written under a temporary name, so the cache never holds
    half a program."""
    model, scale, _ = SCALES[size]
    path = cache / f"{model}-{size.removeprefix(model)}.gcode"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            stl, out = Path(tmp) / f"{model}.stl", Path(tmp) / path.name
            make_sliced.write_stl(stl, MODELS[model]())
            subprocess.run(["prusa-slicer", "--export-gcode", *make_sliced.COMMON, "--gcode-flavor", "marlin2",
                            "--scale", f"{scale:g}", "-o", str(out), str(stl)], check=True,
                           stdout=subprocess.DEVNULL)
            out.replace(path)
    return path


def cnc_program(cache: Path, size_mb: float = 100.0) -> Path:
    """Raster rows 60 mm long, 0.25 mm segments, stepping 0.5 mm in Y over a 60 mm square again
    and again, Z on a smooth surface, until the program has ``size_mb`` MB."""
    path = cache / "cnc-100MB.ngc"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        x = np.linspace(0.0, 60.0, 241)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            out = Path(tmp) / path.name
            with open(out, "w") as f:
                f.write("%\nG21 G90 G17\nG0 Z5\nG0 X0 Y0\nG1 Z-1 F600\n")
                row = 0
                while f.tell() < size_mb * 1e6:
                    y = (row * 0.5) % 60.0
                    xs = x if row % 2 == 0 else x[::-1]
                    z = -1.0 + 0.5 * np.sin(xs / 7.0) * math.cos(y / 9.0)
                    f.write("".join(f"G1 X{a:.4f} Y{y:.4f} Z{b:.4f} F3000\n" for a, b in zip(xs, z, strict=True)))
                    row += 1
                f.write("G0 Z5\nM2\n")
            out.replace(path)
    return path


def measure(program: Path, profile_name: str) -> tuple[dict, float, float, float]:
    """Runs in a fresh process: (report, wall time s, CPU time s of all its threads and of the
    axes' processes it starts, peak resident memory MB of it and them together)."""
    profile = load_profile(profile_name)
    gc.freeze()  # as the fbspost command (cli.compensate)
    peak = _PeakMemory()
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        cpu = time.process_time(), resource.getrusage(resource.RUSAGE_CHILDREN)
        report = compensate_file(program, Path(tmp) / program.name, profile)
        wall_s = time.perf_counter() - started
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu_s = (time.process_time() - cpu[0] + children.ru_utime + children.ru_stime
                 - cpu[1].ru_utime - cpu[1].ru_stime)
    return report.as_dict(), wall_s, cpu_s, peak.stop() / 1024


class _PeakMemory:
    """The largest resident memory (kB) of this process and its children together, read from
    /proc every 20 ms: each peaks at its own time, so adding their peaks would overstate it."""

    def __init__(self):
        self.peak_kb, self._done = 0, threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        own = os.getpid()
        while not self._done.wait(0.02):
            self.peak_kb = max(self.peak_kb, sum(_rss_kb(pid) for pid in [own, *_children(own)]))

    def stop(self) -> int:
        self._done.set()
        self._thread.join()
        return max(self.peak_kb, _rss_kb(os.getpid(), "VmHWM"))


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _rss_kb(pid: int, field: str = "VmRSS") -> int:
    try:
        return next(int(line.split()[1]) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                    if line.startswith(field + ":"))
    except (OSError, StopIteration):
        return 0


def pipeline_table(sizes: list[str], cache: Path) -> None:
    print("Whole pipeline: wall time without interpreter start, CPU time (all threads and the axes' processes:\n"
          "on two idle cores the wall time is at least half of it), peak memory of them all; samples/s (S/s)\n"
          "per stage, samples = print time x sample rate, once per compensated axis for optimize and\n"
          "fallback; QP %: the optimizer's windows that needed the QP; fallback %: its share of the wall time;\n"
          "ref ms: the machine's speed just before (machine_reference_ms: lower is faster)")
    print(f"{'program':16} {'profile':19} {'lines':>8} {'print s':>8} "
          f"{'wall s':>8} {'cpu s':>8} {'x real':>7} {'peak MB':>8} "
          + " ".join(f"{stage + ' S/s':>12}" for stage in STAGES) + f" {'QP %':>5} {'fallback %':>10} {'ref ms':>6}")
    for size in sizes:
        program = cnc_program(cache) if size == CNC else sliced_program(size, cache)
        profile = CNC_PROFILE if size == CNC else SCALES[size][2]
        reference_ms = machine_reference_ms()
        with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
            report, wall_s, cpu_s, peak_mb = pool.submit(measure, program, profile).result()
        samples = report["print_time_s"] * load_profile(profile).sample_rate_hz
        rates_s = {stage: samples / max(report["stage_time_s"][stage], 1e-9) for stage in STAGES}
        for stage in ("optimize", "fallback"):
            rates_s[stage] *= len(report["axes"])
        rates = " ".join(f"{rates_s[stage]:12.3g}" for stage in STAGES)
        windows = sum(axis["windows"] for axis in report["axes"].values())
        qp = sum(axis["qp_windows"] for axis in report["axes"].values()) / max(windows, 1)
        print(f"{program.name:16} {profile:19} {report['lines_in']:8d} {report['print_time_s']:8.1f} "
              f"{wall_s:8.2f} {cpu_s:8.2f} "
              f"{report['print_time_s'] / wall_s:7.1f} {peak_mb:8.0f} {rates} {qp:5.0%} "
              f"{report['stage_time_s']['fallback'] / wall_s:10.0%} {reference_ms:6.0f}", flush=True)


def machine_reference_ms() -> float:
    """CPU time (ms) of a fixed pure-Python loop, the median of three: this machine's own speed
    drifts (the same loop took 150 to 420 ms within minutes, and the gear 1 h's CPU time moved
    with it, 17.6 to 22.9 s for the same work), so a slow row beside a slow reference is the machine."""
    times = []
    for _ in range(3):
        started, total = time.process_time(), 0
        for i in range(3_000_000):
            total += i * i % 7
        times.append(time.process_time() - started)
    return sorted(times)[1] * 1e3


def size_list(text: str) -> list[str]:
    sizes = text.split(",")
    unknown = set(sizes) - set(SCALES) - {CNC}
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown size {', '.join(sorted(unknown))}; sizes: {', '.join(SCALES)}, {CNC}"
        )
    return sizes


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=size_list, default=[*SCALES, CNC],
                        help=f"comma-separated subset of {','.join(SCALES)},{CNC} (default: all)")
    parser.add_argument("--cache", type=Path, default=ROOT / "bench" / ".programs",
                        help="folder of the sliced programs (made when missing)")
    args = parser.parse_args()
    pipeline_table(args.sizes, args.cache)
    print()
    butterfly_table(load_profile("patent-xy-stage"))


if __name__ == "__main__":
    main()
