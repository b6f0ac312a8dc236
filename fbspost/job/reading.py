"""A program read and planned as a stream, for the job.

Takes the program's path, its flavor and the profile; gives its blocks a batch at a time
(``read_blocks``: the time to ``stages["read"]``, the fraction read to ``progress``).
"""
from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path

from ..plan.planner import BATCH_BLOCKS
from ..profile import MachineProfile
from ..read.blocks import Block
from ..read.gcode import read_on_machine


def _count_lines(path: str | Path) -> int:
    with open(path, "rb") as f:
        return max(1, sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b"")))


def read_blocks(read_path, flavor: str, profile: MachineProfile, stages: dict[str, float],
                progress=None) -> Iterator[Block]:
    """The program's blocks (a move beyond the profile's travel refused), read a batch at a time:
    the time taken goes to ``stages["read"]``, and ``progress`` is told the fraction of the lines
    read after each batch. (Timed block by block, a CAM program's reading took a tenth longer.)"""
    blocks = read_on_machine(read_path, flavor, profile, within_travel=True)
    total_lines = _count_lines(read_path) if progress else 1

    def batches() -> Iterator[list[Block]]:
        while True:
            clock = time.perf_counter()
            batch = list(itertools.islice(blocks, BATCH_BLOCKS))
            stages["read"] += time.perf_counter() - clock
            if progress:
                progress(min(batch[-1].line_no / total_lines, 1.0) if batch else 1.0)
            if not batch:
                return
            yield batch

    return itertools.chain.from_iterable(batches())

