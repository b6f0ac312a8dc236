"""Benchmark: the memory of a long program's compensation does not grow with its length.

Run from the repository root:  python bench/streaming_memory.py [--rows 300 600] [--chunk-lines 6000]

A LinuxCNC finishing raster (tests/test_streaming.py's ``raster``: 121 segments of 0.25 mm a row,
one run of motion as long as the program) compensated on bedslinger-example, once per row count,
each in this process under tracemalloc: the peak of the memory Python and numpy allocate. Held
whole, the plan alone grew by about 0.5 kB per move. The axes' processes, which these programs
go to, are sent the plan up to 65536 samples ahead of the writer, whose process holds those
blocks: the peak stops growing after about 25k moves, so the shortest program should be longer
than that. The model of LinuxCNC's planner, which times the original (linuxcnc_time) and checks
the output (verify), holds a chunk of the program at a time: ``--chunk-lines`` (verify's
CHUNK_LINES) should divide each program into chunks as long as each other, so that each program
has several full ones, as a long one does (with 20k-line chunks, the 36k-line program's second
chunk was 16k lines and its peak 15% below the 73k-line one's).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from fbspost.firmware import verify  # noqa: E402
from fbspost.job.pipeline import compensate_file  # noqa: E402
from fbspost.profile import load_profile  # noqa: E402
from test_streaming import raster  # noqa: E402


def peak_mb(rows: int, folder: Path) -> tuple[int, float, float]:
    """(the program's lines, the traced peak MB, the wall time s) of compensating a raster of ``rows``."""
    source = raster(folder / f"raster-{rows}.ngc", rows)
    started = time.perf_counter()
    tracemalloc.start()
    compensate_file(source, folder / "out.ngc", load_profile("bedslinger-example"))
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return len(source.read_bytes().splitlines()), peak, time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[300, 600])
    parser.add_argument("--chunk-lines", type=int, default=6000)
    args = parser.parse_args()
    verify.CHUNK_LINES = args.chunk_lines
    with tempfile.TemporaryDirectory() as tmp:
        results = [peak_mb(rows, Path(tmp)) for rows in args.rows]
    for lines, peak, wall_s in results:
        print(f"{lines} lines: peak traced memory {peak:.1f} MB ({peak / results[0][1]:.3f} x the first), "
              f"{wall_s:.0f} s wall")


if __name__ == "__main__":
    main()
