"""The trajectory a robust command tracks: the planned one smoothed by a short Hann window.

Takes one run of one axis' desired positions (mm, on the sample grid), in pieces; gives them
smoothed by a Hann window of ``half_width`` samples either side, narrowed near the run's ends so
that the run starts and ends exactly where it did, at rest. The window is symmetric, so a straight
line at constant speed is kept as it is: only the corners are rounded (a smoothed sample is an
average of the positions within half a window of it), and the same on every axis, so the path
keeps its shape. What it removes is the content near and above the machine's highest mode,
which a command can only track by exciting the modes hard: on a machine a few percent off its
model, that is where the error comes from (docs/robust.md).

The result does not depend on how the run is cut into pieces: a sample is given once the
``half_width`` samples after it are known.
"""
from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def hann_weights(half_width: int) -> np.ndarray:
    """The 2 half_width + 1 weights of a Hann window whose zeros are half_width + 1 samples either
    side of its centre, summing to 1."""
    weights = np.hanning(2 * half_width + 3)[1:-1]
    return weights / weights.sum()


def half_width_samples(highest_mode_hz: float, sample_period_s: float) -> int:
    """The half-width whose window is one period of ``highest_mode_hz`` from zero to zero."""
    return max(0, round(0.5 / (highest_mode_hz * sample_period_s)) - 1)


class RunSmoother:
    """One run's desired positions, smoothed as they arrive (see the module docstring)."""

    def __init__(self, half_width: int):
        self.half_width = half_width
        self._weights = [hann_weights(w) for w in range(half_width + 1)]
        self._held = np.empty(0)  # the samples from run sample ``_held_from`` on
        self._held_from = 0
        self._next = 0  # run sample of the next one to give

    def push(self, desired_mm: np.ndarray) -> np.ndarray:
        """The smoothed samples whose ``half_width`` successors are now known."""
        self._held = np.concatenate([self._held, desired_mm])
        return self._give(self._held_from + self._held.size - self.half_width, run_end=None)

    def finish(self) -> np.ndarray:
        """The rest of the run, its last samples smoothed less and less towards its end."""
        end = self._held_from + self._held.size
        return self._give(end, run_end=end)

    def _give(self, stop: int, run_end: int | None) -> np.ndarray:
        """Smoothed run samples ``_next`` .. ``stop`` - 1."""
        r, first, x = self.half_width, self._next, self._held
        if stop <= first:
            return np.empty(0)
        out = np.empty(stop - first)
        # every sample's own window: narrower within r of the run's start (and end, once known)
        widths = np.minimum(r, np.arange(first, stop))
        if run_end is not None:
            widths = np.minimum(widths, run_end - 1 - np.arange(first, stop))
        full = np.flatnonzero(widths == r)
        if full.size:  # one contiguous stretch
            a, b = first + full[0] - self._held_from, first + full[-1] - self._held_from
            windows = sliding_window_view(x[a - r:b + r + 1], 2 * r + 1)
            centre = x[a:b + 1]
            # as differences from the centre: a sample at rest among equal ones stays bit for bit
            out[full] = centre + (windows - centre[:, None]) @ self._weights[r]
        for i in np.flatnonzero(widths < r):
            w, j = widths[i], first + i - self._held_from
            out[i] = x[j] + (x[j - w:j + w + 1] - x[j]) @ self._weights[w]
        self._next = stop
        keep = max(0, stop - r - self._held_from)
        self._held, self._held_from = self._held[keep:], self._held_from + keep
        return out
