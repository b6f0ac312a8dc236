"""How far the written blocks are from the command.

Takes the blocks as written (their ends and targets, and where the firmware puts them) and the
command (``SampleWindow``); gives the largest deviation and where, its RMS, the time in blocks
beyond the tolerance (``Deviation``), and gives ``report.ExecutedError`` the executed motion
sample by sample.
"""
from __future__ import annotations

import math

import numpy as np

from .samples import SampleWindow


class Deviation:
    """How far the written blocks, each run at constant speed, are from the command at the same
    time, over the samples inside them (XYZ): the largest, where, and the time in blocks beyond
    the tolerance (rounding aside)."""

    def __init__(self, samples: SampleWindow, fs: float, tolerance_mm: float, executed=None):
        self.samples, self.fs, self.tolerance_mm, self.executed = samples, fs, tolerance_mm, executed
        self.last_s = 0.0  # the last written block's end
        self.last_mm = self.last_stepped_mm = None  # its end: as written, as stepped
        self.max_mm = self.at_s = self.loosened_s = self.sum_squares_mm2 = 0.0
        self.count = 0

    def add(self, start_s: float | None, ends_s: np.ndarray, targets_mm: np.ndarray, stepped_mm: np.ndarray) -> None:
        """Blocks from ``start_s`` (None: the last block's end) to each of ``ends_s``: ``targets_mm``
        as written, ``stepped_mm`` where the firmware puts them (its whole steps: executed)."""
        if not len(ends_s):
            return
        # A run starts where the command is; a later batch where the last block ended, so that
        # the chords do not depend on where the stream cut the blocks.
        run_start = start_s is not None or self.last_mm is None
        start_s = self.last_s if start_s is None else start_s
        knots_s = np.append(start_s, ends_s)
        grid_s = np.arange(math.ceil(start_s * self.fs), math.floor(ends_s[-1] * self.fs) + 1) / self.fs

        def chords(ends_mm: np.ndarray, last_mm: np.ndarray | None) -> np.ndarray:
            first_mm = self.samples.at(knots_s[:1], self.fs)[0] if run_start else last_mm
            knots_mm = np.vstack([first_mm, ends_mm])[:, :3]
            return np.column_stack([np.interp(grid_s, knots_s, knots_mm[:, c]) for c in range(3)])

        chord, command = chords(targets_mm, self.last_mm), self.samples.at(grid_s, self.fs)[:, :3]
        off_mm = np.linalg.norm(chord - command, axis=1)
        self.sum_squares_mm2 += float(off_mm @ off_mm)
        self.count += len(off_mm)
        # the largest: of the blocks as the firmware runs them (Marlin's ends on the lattice can be steps away)
        executed = chord if stepped_mm is targets_mm else chords(stepped_mm, self.last_stepped_mm)
        far_mm = np.linalg.norm(executed - command, axis=1)
        if len(far_mm) and far_mm.max() > self.max_mm:
            self.max_mm, self.at_s = float(far_mm.max()), float(grid_s[far_mm.argmax()])
        block = np.searchsorted(ends_s, grid_s, "left")
        worst = np.zeros(len(ends_s))
        np.maximum.at(worst, block, off_mm)
        # (rounding: 0.1 um per axis)
        self.loosened_s += float(np.diff(knots_s)[worst > self.tolerance_mm + 1e-4].sum())
        if self.executed is not None and len(grid_s):
            first = round(grid_s[0] * self.fs)
            self.rest_until(first)
            skip = max(self.executed.next - first, 0)  # (a block's start is the last one's end)
            planned = self.samples.at(grid_s[skip:], self.fs, planned=True)[:, :3]
            self.executed.add(first + skip, executed[skip:], planned)
        self.last_s, self.last_mm, self.last_stepped_mm = float(ends_s[-1]), targets_mm[-1], stepped_mm[-1]

    def rest_until(self, stop: int) -> None:
        """The executed program where the plan has it, from the last sample given up to ``stop``."""
        if self.executed is not None and stop > self.executed.next:
            rest = self.samples.at(np.arange(self.executed.next, stop) / self.fs, self.fs, planned=True)[:, :3]
            self.executed.add(self.executed.next, rest, rest)

