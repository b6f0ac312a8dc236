"""Block ends written inside the cells of whole steps (RepRapFirmware).

RRF rounds each written end to its nearest step (``lrintf``) and times the block over the written
length. Takes, per call, the wanted ends and the whole steps chosen for them (``steps``' rounding)
in written units; gives the ends to write: each in its step's cell, an offset from the wanted end
kept from end to end while the cell allows it, so the written lengths, and F, are the command's
(RRF skips a small speed step up, ``reprap.top_speed``: an F jittering with the steps ran the
gear's first 2000 lines 0.4% longer, the RRF model). The offset is carried between calls.
"""
from __future__ import annotations

import numpy as np

# How far inside its step's cell an end is written (of a step either side): RRF rounds in float32
# (lrintf), and the written digits round too (at most 0.004 of a step at 80 steps/mm, 4 decimals).
CELL_SHARE = 0.45


class StepCells:
    """The ends to write for X Y Z (``ends``); state: the offset of the last end from the wanted."""

    def __init__(self):
        self.offset = np.zeros(3)

    def ends(self, units: np.ndarray, stepped: np.ndarray, written: np.ndarray, steps_per_unit: np.ndarray,
             exact_last: bool) -> np.ndarray:
        """``written`` (integer units) with the axes of X Y Z that step (``steps_per_unit`` > 0) at
        the wanted ``units`` plus the offset, moved just into the cell of the whole step
        ``stepped`` is on (within ``CELL_SHARE`` of it) where it leaves it. ``exact_last``: the
        last end is ``written``'s (a run's end, the command's) and the offset restarts."""
        out = written.copy()
        for i in np.flatnonzero(steps_per_unit[:3] > 0):
            spu, counts = steps_per_unit[i], np.rint(stepped[:, i] * steps_per_unit[i])
            lo = ((counts - CELL_SHARE) / spu - units[:, i]).tolist()
            hi = ((counts + CELL_SHARE) / spu - units[:, i]).tolist()
            offset, offsets = self.offset[i], []
            for low, high in zip(lo, hi, strict=True):
                offset = low if offset < low else high if offset > high else offset
                offsets.append(offset)
            self.offset[i] = 0.0 if exact_last else offset
            out[:, i] = np.rint(units[:, i] + offsets)
        if exact_last and len(out):
            out[-1] = written[-1]
        return out
