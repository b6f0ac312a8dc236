"""Where the blocks of a run of motion end: within the tolerance of the command, never too short.

Takes a run's commanded samples (rows X Y Z E, machine mm), the tolerance and the minimum block
length in samples; gives the block ends as sample indices: dense G1 blocks by chords
(``breakpoints``, ``Breaks`` as the samples arrive), or G5 curves fitted by ``bezier.fit_g5``
with G1 blocks where no curve fits (``g5_blocks``, ``Curves``).
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d

from ..read.blocks import AXES
from .bezier import fit_g5

_MAX_SAMPLES = 2000  # longest block, samples
_E = AXES.index("E")
_NOT_IN_G5 = [i for i, a in enumerate(AXES) if a not in "XYE"]



_PIECE = 1 << 16  # samples



class Breaks:
    """Where the blocks of one run end (see ``breakpoints``), found as its command arrives.

    A chord over n sample steps deviates from the samples it spans by at most n^2/8 times their
    largest second difference (the discrete maximum principle), so a block may span
    n = sqrt(8 tolerance / max |second difference| ahead) steps: never more than the tolerance
    allows, never fewer than ``min_samples`` (where that is shorter, the minimum wins). "Ahead"
    is the next ``max_samples`` steps (past the run's end: the last ones mirrored), so a block
    end is known once that much of the command after it is: the ends are the same however the
    command arrives.
    """

    def __init__(self, n_samples: int | None, tolerance_mm: float, min_samples: int, max_samples: int = _MAX_SAMPLES):
        self.n, self.tolerance_mm, self.min_samples, self.size = n_samples, tolerance_mm, min_samples, max_samples
        self.ends = [0]  # found so far (run sample indices)
        self.bend = np.zeros(0)  # |second difference| at samples bend_base + j (bending at the sample after)
        self.bend_base = 0
        self.tail = None  # the last two samples fed, for the next second differences
        self.fed = 0  # samples fed

    def feed(self, command: np.ndarray) -> None:
        """The run's next samples (rows of X Y Z E, mm)."""
        rows = command if self.tail is None else np.concatenate([self.tail, command])
        self.fed += len(command)
        self.tail = rows[-2:]
        # (by pieces: big temporaries cost more than the arithmetic)
        new = [np.linalg.norm(np.diff(rows[a:a + _PIECE + 2], 2, axis=0), axis=1)
               for a in range(0, max(len(rows) - 2, 0), _PIECE)]
        if self.fed == self.n:
            new.append(np.zeros(min(2, self.n)))  # no bend at the last two samples
        self.bend = np.concatenate([self.bend] + new)
        self.find()

    def find(self) -> None:
        """Every block end that the samples fed so far decide."""
        if self.n is not None and self.n <= 2:
            self.ends = list(range(self.n))
            return
        done = self.fed == self.n
        i0 = i = self.ends[-1]  # a block starts here (or it is the last sample)
        # ahead[j] needs bend[j .. j + size - 1]; past the end of the run they are mirrored
        stop = self.n - 1 if done else self.bend_base + len(self.bend) - self.size + 1
        if i0 < stop:
            low = min(i0, max(self.n - self.size, 0)) if done else i0  # the mirror reaches back size - 1
            ahead = maximum_filter1d(self.bend[low - self.bend_base:], size=self.size,
                                     origin=-(self.size // 2))[i0 - low:stop - low]
            with np.errstate(divide="ignore"):
                span = np.floor(np.sqrt(8.0 * self.tolerance_mm / ahead))
            span = np.clip(np.nan_to_num(span, posinf=self.size), self.min_samples, self.size).astype(int)
            # The blocks run i -> i + span[i]. The span is a maximum over the next size steps, so
            # it changes rarely: step through each stretch of one span at once.
            stretch_ends = (np.flatnonzero(np.diff(span)) + 1 + i0).tolist() + [stop]
            pieces = []
            while i < stop:
                step = int(span[i - i0])
                pieces.append(np.arange(i, stretch_ends[bisect.bisect_right(stretch_ends, i)], step))
                i = int(pieces[-1][-1]) + step
            self.ends.extend(np.concatenate(pieces)[1:].tolist())
            self.ends.append(min(i, self.n - 1) if done else i)
        # Keep what later spans need: from the last start, and the stretch the mirror reaches
        # (the run has at least the samples fed).
        keep = max(min(self.ends[-1], (self.fed if self.n is None else self.n) - self.size), self.bend_base)
        self.bend = self.bend[keep - self.bend_base:]
        self.bend_base = keep


def breakpoints(command: np.ndarray, tolerance_mm: float, min_samples: int,
                max_samples: int = _MAX_SAMPLES) -> np.ndarray:
    """Sample indices where the blocks of a run end (``command``: its samples), first and last
    sample included (see ``Breaks``)."""
    breaks = Breaks(len(command), tolerance_mm, min_samples, max_samples)
    breaks.feed(np.asarray(command, dtype=float))
    return np.asarray(breaks.ends)


@dataclass(frozen=True)
class Curves:
    """Which of a sequence of blocks are G5 curves, with their control points (absolute machine
    XY); the other blocks' points mean nothing."""

    curve: np.ndarray  # (m,) bool
    p1_mm: np.ndarray  # (m, 2)
    p2_mm: np.ndarray  # (m, 2)

    def __getitem__(self, rows) -> Curves:
        return Curves(self.curve[rows], self.p1_mm[rows], self.p2_mm[rows])


def g5_blocks(command: np.ndarray, splits: np.ndarray, tolerance_mm: float,
              min_samples: int, step_mm: float = 0.0) -> tuple[np.ndarray, Curves]:
    """Where a run's blocks end (sample indices into ``command``, the run's samples; 0 is its
    start) and which are curves, for the G5 format: every sample in ``splits`` (where copied
    lines run) ends a block.

    The run is fitted whole (fit_g5 searches its blocks in lock step: a call per stretch between
    copied lines is many times slower). Fitted blocks that a split falls inside, in which Z (or
    a LinuxCNC axis other than X Y) moves, or that miss the tolerance (fit_g5 lets the minimum
    length win, and a short block
    before one of its chunk edges may miss where chords do not) become G1 blocks, between the
    splits and the other fitted blocks' ends: ``breakpoints`` of each such stretch, its last two
    blocks sharing their length where the last is shorter than the minimum (each then at least
    half the minimum long, and shorter than the first of them was). A curve whose control points
    lie on its chord's thirds is a straight line at constant speed: G1.
    """
    # (LinuxCNC: E stays 0)
    fit = fit_g5(command[:, [0, 1, _E]], tolerance_mm, min_samples, _MAX_SAMPLES, step_mm=step_mm)
    starts, ends = fit.starts, fit.ends
    # Z and LinuxCNC's other axes move in G1 blocks only
    z_steps = np.concatenate([[0], np.cumsum((np.diff(command[:, _NOT_IN_G5], axis=0) != 0).any(axis=1))])
    as_g1 = ((np.searchsorted(splits, starts, "right") < np.searchsorted(splits, ends, "left"))
             | (z_steps[ends] > z_steps[starts]) | (fit.error_mm > tolerance_mm))
    kept = ~as_g1
    hard = np.union1d(np.concatenate([[0, ends[-1]], starts[kept], ends[kept]]), splits)  # neighbouring G1 blocks merge
    g1 = ~np.isin(hard[1:], ends[kept])  # stretches that are no kept block
    inner = [np.zeros(0, np.int64)]
    for a, b in zip(hard[:-1][g1], hard[1:][g1], strict=True):
        g1_ends = breakpoints(command[a:b + 1], tolerance_mm, min_samples) + a
        if len(g1_ends) > 2 and b - g1_ends[-2] < min_samples:  # a short last block: the last two share
            g1_ends[-2] = (g1_ends[-3] + b) // 2
        inner.append(g1_ends[1:-1])
    all_ends = np.union1d(hard[1:], np.concatenate(inner))
    p0, p3 = command[starts, :2], command[ends, :2]
    straight = np.maximum(np.abs(fit.p1_mm - (p0 + (p3 - p0) / 3.0)).max(axis=1),
                          np.abs(fit.p2_mm - (p3 - (p3 - p0) / 3.0)).max(axis=1)) <= 1e-3 * tolerance_mm
    curve = fit.curve & ~straight & ~as_g1
    block = np.searchsorted(ends, all_ends)  # the fitted block each block ends in (its own, for a curve)
    return all_ends, Curves(np.isin(all_ends, ends[curve]), fit.p1_mm[block], fit.p2_mm[block])

