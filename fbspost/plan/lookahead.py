"""The look-ahead: the min-plus scans over the pieces' squared speeds and what they decide.

Takes each new piece's junction limit and 2 a d (and Klipper's smoothed 2 a d); gives the
forward and backward passes (``forward_pass``, ``backward_pass``) and how many of the pieces
not yet settled no later piece can change, with their speeds (``LookAhead``). The scans run in
chunks of ``SCAN_CHUNK`` pieces from piece 0 on, so their bits are those of one scan however the
program is batched.
"""
from __future__ import annotations

import math

import numpy as np

from . import klipper_rules

SCAN_CHUNK = 4096  # pieces per chunk of the min-plus scans (bounds the cumulative-sum magnitude), from piece 0 on


def forward_pass(limit_v2: np.ndarray, delta_v2: np.ndarray, chunk: int = SCAN_CHUNK,
                 carry: float = math.inf) -> np.ndarray:
    """F[0] = min(L[0], carry), F[i] = min(L[i], F[i-1] + delta[i-1]): the squared speed reachable
    at every junction accelerating from the earlier ones. ``limit_v2`` has one more entry than
    ``delta_v2`` (2 a d of the piece between junctions i and i+1), or as many (the last piece
    leads to a junction not given).

    Computed as F[i] = min(L[i], C[i] + min_{k<i}(L[k] - C[k])), C the sequential cumulative sum
    of delta from the chunk's start (chunks from entry 0 on); the chunk's first entry carries
    the previous chunk's result. The exclusive minimum keeps a junction's own limit exact; a
    limit inherited from an earlier junction is at least delta[i-1], and its rounding error is a
    few ulps of C. An entry depends only on the entries before it, from its chunk's start."""
    out = np.empty_like(limit_v2)
    n = limit_v2.size
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        lim = limit_v2[s:e].copy()
        lim[0] = min(lim[0], carry)
        c = np.zeros(e - s)
        np.cumsum(delta_v2[s:e - 1], out=c[1:])
        prefix = np.minimum.accumulate(lim - c)
        res = lim
        res[1:] = np.minimum(lim[1:], c[1:] + prefix[:-1])
        out[s:e] = res
        if e < n:
            carry = res[-1] + delta_v2[e - 1]
    return out


def backward_pass(limit_v2: np.ndarray, delta_v2: np.ndarray, chunk: int = SCAN_CHUNK) -> np.ndarray:
    """B[n] = L[n], B[i] = min(L[i], B[i+1] + delta[i]): the squared speed from which every
    later junction can still be reached decelerating.

    Computed as B[i] = min(L[i], min_{k>i}(L[k] + C[k]) - C[i]), C the sequential cumulative sum
    of delta from the chunk's start (chunks from entry 0 on, as in ``forward_pass``, so that a
    batch of junctions cut anywhere gives the same bits wherever its result is decided); the
    chunk's last candidate is the next chunk's first result. Monotone in every L: a lower or
    higher end gives a lower or higher result, bits included."""
    out = np.empty_like(limit_v2)
    n = limit_v2.size
    later = math.inf  # the next chunk's first result
    for s in range(((n - 1) // chunk) * chunk, -1, -chunk):
        e = min(s + chunk, n)
        c = np.zeros(e - s + 1)
        np.cumsum(delta_v2[s:e], out=c[1:1 + min(e, n - 1) - s])  # c[e - s]: the next chunk's first junction
        candidate = np.empty(e - s + 1)
        candidate[:-1] = limit_v2[s:e] + c[:-1]
        candidate[-1] = later + c[-1] if e < n else math.inf
        suffix = np.minimum.accumulate(candidate[::-1])[::-1]
        out[s:e] = np.minimum(limit_v2[s:e], suffix[1:] - c[:-1])
        later = out[s]
    return out



class LookAhead:
    """The look-ahead's min-plus scans over the pieces not yet settled (see the module docstring).

    Takes each new piece's junction limit and 2 a d, and Klipper's smoothed 2 a d (``extend``);
    gives how many of the pending pieces no later piece can change, with their squared speeds
    (``decided``). The scans start at a chunk boundary with the forward pass carried into it, so
    their bits are those of one scan from piece 0."""

    def __init__(self, klipper: bool):
        self._klipper = klipper
        self._s0 = 0  # the scans' first junction (a chunk start) ...
        self._limit, self._delta = np.zeros(0), np.zeros(0)  # ... its limits and deltas on
        self._carry = math.inf  # the forward pass arriving at _s0
        self._smooth = np.zeros(0)  # Klipper: the smoothed pass' deltas from _s0 on ...
        self._smooth_carry = math.inf  # ... and its forward pass arriving at _s0
        self._peak_carry = 0.0  # Klipper: the cruise a decelerating run carries past the last settled piece
        self._reach = self._reach_smooth = None  # the last decision's forward passes

    def extend(self, pieces: dict) -> None:
        self._limit = np.concatenate([self._limit, pieces["limit_v2"]])
        self._delta = np.concatenate([self._delta, pieces["delta_v2"]])
        self._smooth = np.concatenate([self._smooth, pieces["smooth_delta_v2"]])

    def decided(self, pending: dict, p0: int, ends_at_rest: bool) -> tuple:
        """(n, v2, speeds): the first n of the ``pending`` pieces (piece p0 on) are decided, with
        their squared junction speeds v2 (n + 1), or Klipper's (start, cruise, end) squared speeds."""
        s0 = self._s0
        limit = np.append(self._limit, 0.0 if ends_at_rest else math.inf)
        reach = self._reach = forward_pass(limit, self._delta, SCAN_CHUNK, self._carry)
        v2 = backward_pass(reach, self._delta, SCAN_CHUNK)
        if self._klipper:
            n, speeds, self._reach_smooth = self._klipper_speeds(pending, p0, reach, v2, ends_at_rest)
            if n:
                self._peak_carry = float(speeds[4][n - 1])
            return n, None, [x[:n] for x in speeds[:3]]
        n = len(pending["block"])
        if not ends_at_rest:  # settle the pieces whose both junctions are decided
            reach[-1] = 0.0
            differ = np.flatnonzero(backward_pass(reach, self._delta, SCAN_CHUNK)[p0 - s0:] != v2[p0 - s0:])
            n = max(int(differ[0]) - 1, 0) if differ.size else n
        return n, v2[p0 - s0:p0 - s0 + n + 1], None

    def restart(self, p0: int) -> None:
        """The pieces before ``p0`` are settled: the scans restart at the chunk of piece p0."""
        s0, s1 = self._s0, (p0 // SCAN_CHUNK) * SCAN_CHUNK
        if s1 > s0:
            self._carry = self._reach[s1 - 1 - s0] + self._delta[s1 - 1 - s0]
            self._limit, self._delta = self._limit[s1 - s0:], self._delta[s1 - s0:]
            if self._klipper:
                self._smooth_carry = self._reach_smooth[s1 - 1 - s0] + self._smooth[s1 - 1 - s0]
            self._smooth = self._smooth[s1 - s0:]
            self._s0 = s1

    def _klipper_speeds(self, pending: dict, p0: int, reach: np.ndarray, v2: np.ndarray, ends_at_rest: bool) -> tuple:
        """Klipper's smoothed look-ahead over the pending pieces (``klipper_rules.cruise_speeds``):
        how many are settled and their speeds. ``reach`` and ``v2`` are the forward and backward
        passes from the scans' start; a piece is settled when its speeds are the same however
        the program goes on: the junction speeds it and the next piece depend on are decided
        (as in ``decided``, for both passes) and so is the piece that sets its peak."""
        s0, smooth = self._s0, self._smooth
        reach_smooth = forward_pass(reach, smooth, SCAN_CHUNK, self._smooth_carry)
        smoothed = backward_pass(reach_smooth, smooth, SCAN_CHUNK)
        speeds = klipper_rules.cruise_speeds(v2[p0 - s0:], smoothed[p0 - s0:], pending["delta_v2"],
                                             pending["smooth_delta_v2"], pending["max_v"] ** 2, self._peak_carry)
        n = len(pending["block"])
        if not ends_at_rest:
            low, low_smooth = reach.copy(), reach_smooth.copy()
            low[-1] = low_smooth[-1] = 0.0
            differ = np.flatnonzero((backward_pass(low, self._delta, SCAN_CHUNK)[p0 - s0:] != v2[p0 - s0:])
                                    | (backward_pass(low_smooth, smooth, SCAN_CHUNK)[p0 - s0:] != smoothed[p0 - s0:]))
            decided = speeds[3][:max(int(differ[0]) - 2, 0)] if differ.size else speeds[3]
            n = int(np.flatnonzero(decided)[-1]) + 1 if decided.any() else 0
        return n, speeds, reach_smooth

