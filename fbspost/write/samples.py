"""The window of samples the writer reads: the planned and the commanded, as they come.

Takes an iterator of (planned, command) chunks (rows X Y Z E, machine mm) and the plan; gives
rows and interpolated positions at times, dropping the rows the writer no longer needs
(``SampleWindow``).
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..read.blocks import AXES


class SampleWindow:
    """The planned and the commanded samples (rows X Y Z E, machine mm) as an iterator of
    (planned, command) chunks produces them, in order; rows before ``release``'s index are
    dropped, so a long program's samples are never all held. ``plan`` (``PlanStream``) tells
    how many there are once it is done. ``follows_plan`` (len(AXES),) marks the columns the command
    leaves as planned (E, axes without modes): blocks end exactly where the program puts them."""

    def __init__(self, chunks: Iterable[tuple[np.ndarray, np.ndarray]], plan, follows_plan: np.ndarray):
        self._chunks = iter(chunks)
        self._plan = plan
        self.follows_plan = np.asarray(follows_plan, dtype=bool)
        self.base = 0  # sample index of the first row held
        self.planned = self.command = np.zeros((0, len(AXES)))

    @property
    def end(self) -> int:
        return self.base + len(self.command)

    @property
    def n_samples(self) -> int | None:
        """None until the plan is done."""
        return self._plan.n_samples if self._plan.done else None

    def ensure(self, stop: int) -> None:
        """Hold the samples up to ``stop`` - 1 (at most the last)."""
        planned, command, end = [self.planned], [self.command], self.end
        while end < stop:
            try:
                p, c = next(self._chunks)
            except StopIteration:
                break
            planned.append(p)
            command.append(c)
            end += len(c)
        if len(command) > 1:
            self.planned, self.command = np.concatenate(planned), np.concatenate(command)

    def release(self, first: int) -> None:
        """Rows before sample ``first`` are no longer needed."""
        drop = min(max(first - self.base, 0), len(self.command))
        if drop > len(self.command) // 2:  # copy seldom: the rows kept are a fraction of those dropped
            self.planned, self.command = self.planned[drop:].copy(), self.command[drop:].copy()
            self.base += drop

    def rows(self, first: int, stop: int) -> np.ndarray:
        """Commanded samples first .. stop - 1."""
        assert first >= self.base, "samples asked for after their release"
        self.ensure(stop)
        return self.command[first - self.base:stop - self.base]

    def at(self, t_s: np.ndarray, fs: float, planned: bool = False) -> np.ndarray:
        """Linear interpolation of the commanded (or planned) samples at the times ``t_s``."""
        x = np.maximum(t_s * fs, 0.0)
        self.ensure(int(x.max(initial=0)) + 2)
        n = self.n_samples
        if n is not None:  # (else every row asked for is there)
            x = np.minimum(x, n - 1.0)
        k = x.astype(np.int64) if n is None else np.minimum(x.astype(np.int64), max(n - 2, 0))
        assert k.min(initial=self.base) >= self.base, "samples asked for after their release"
        columns = self.planned if planned else self.command
        w = (x - k)[:, None]
        k = k - self.base
        below, above = np.take(columns, k, axis=0), np.take(columns, np.minimum(k + 1, len(columns) - 1), axis=0)
        return below * (1.0 - w) + above * w  # (np.take gathers rows a few times faster than indexing)

