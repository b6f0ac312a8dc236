"""Marlin's merge of short blocks, and block ends moved onto whole steps.

Takes block ends in written units (rows of integers, the controller's start before them), the
steps per unit and Marlin's MIN_STEPS_PER_SEGMENT; gives the ends with every block Marlin would
merge moved onto the end before it (``marlin_merged``), and, for the ends moved onto the crossings of
steps, their whole steps through each axis' rounding (``rounded_ends``), their times
(``moved_in_time``) and the last end that later blocks cannot change (``last_in_both``).
"""
from __future__ import annotations

import numpy as np

from ..firmware.steps import ModalRounding, lattice_counts, settled_before


def moved_in_time(kept: np.ndarray, shift_s: np.ndarray, durations_s: np.ndarray,
                  ends_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows' durations and end times with the ``kept`` rows' ends moved by ``shift_s``, the
    next row taking up the difference (the last kept row is not moved)."""
    durations_s, ends_s = durations_s.copy(), ends_s.copy()
    durations_s[kept] += shift_s
    durations_s[kept[:-1] + 1] -= shift_s[:-1]
    ends_s[kept] += shift_s
    return durations_s, ends_s


def last_in_both(plain: np.ndarray, kept: np.ndarray, ends_s: np.ndarray) -> int | None:
    """The last row kept both by Marlin's merge of the rows rounded (``plain``: row 0 the start)
    and in the end (``kept``), but for the merge's last (a later row may merge it), that ends
    (``ends_s``) where the lattice has settled its end given the rows up to that one
    (``steps.settled_before``); None: none."""
    both = np.intersect1d(kept, np.flatnonzero((np.diff(plain, axis=0) != 0).any(axis=1))[:-1])
    if len(both):
        both = both[ends_s[both] < settled_before(ends_s[both[-1]])]
    return int(both[-1]) if len(both) else None


def rounded_ends(rounding: list, rounding_state: list, ends: np.ndarray, spu: np.ndarray, knots_s: np.ndarray,
                 kept: np.ndarray, exact_last: bool, times_s: np.ndarray, units: np.ndarray,
                 knot_from: np.ndarray, plain: np.ndarray, min_steps: int) -> tuple:
    """The kept blocks' ``ends`` (written units, at ``knots_s[1:]``; ``knots_s[0]`` the end
    before them, at ``knot_from``) with X Y Z on whole steps, each axis by its ``rounding``
    (``steps``) from its ``rounding_state``: the axes with modes together on the lattice
    (``steps.Lattice``: the chords between the ends solved through the modes against the
    wanted rows, ``units`` at ``times_s``, row 0 the start; X and Y rounded together, their error
    along the path: ``steps.lattice_counts``), each block kept by Marlin's merge
    (``min_steps`` on some axis; the other axes' steps as in ``plain``, the merge's ends, row 0
    the start); and the rounding's states before each row and after the last."""
    rounded, states = np.rint(ends).astype(np.int64), [None] * 3
    before = np.searchsorted(kept, np.arange(len(units)))  # each row: how many kept rows come before it
    later = times_s > knots_s[0]  # the wanted motion from the end before the kept ones
    wanted_s = np.append(knots_s[0], times_s[later])
    on_lattice = np.array([isinstance(r, ModalRounding) for r in rounding] + [False] * (len(spu) - 3)) & (spu > 0)
    lattices = []
    for i in np.flatnonzero(spu[:3] > 0):
        wanted = ends[:, i] * spu[i]
        wanted = np.where(np.abs(wanted - np.rint(wanted)) < 1e-6, np.rint(wanted), wanted)  # (on a step)
        if on_lattice[i]:
            last = float(np.rint(wanted[-1])) if exact_last else None
            lattices.append(rounding[i].lattice(wanted_s, np.append(knot_from[i], units[later, i]) * spu[i],
                                                knots_s[1:], rounding_state[i], last, wanted))
            continue
        counts, st = rounding[i].round(wanted, np.diff(knots_s), rounding_state[i])
        rounded[:, i], states[i] = np.rint(counts / spu[i]), st[before]
    others = np.flatnonzero((spu > 0) & ~on_lattice)
    at_steps = np.rint(plain[np.append(0, kept + 1)][:, others] * spu[others])
    axes = np.flatnonzero(on_lattice).tolist()
    plane = (axes.index(0), axes.index(1), 1.0 / spu[0], 1.0 / spu[1]) if {0, 1} <= set(axes) else None
    lattice_counts(lattices, (np.abs(np.diff(at_steps, axis=0)) >= min_steps).any(axis=1), min_steps, plane)
    for i, lattice in zip(np.flatnonzero(on_lattice), lattices, strict=True):
        rounded[:, i], states[i] = np.rint(lattice.counts / spu[i]), lattice.states[before]
    if exact_last:
        for st in states:
            if st is not None:
                st[-1] = 0.0
    return rounded, states



def marlin_merged(start: np.ndarray, ints: np.ndarray, steps_per_unit: np.ndarray, min_steps: int,
                  exact_last: bool) -> np.ndarray:
    """Block ends (rows of written units; ``start``: where the controller is) with every block
    that Marlin would merge (fewer than ``min_steps`` steps on every axis from the last block
    kept, steps as Marlin rounds the positions) moved back onto that block's end: a block of no
    motion, whose time the next block takes. With ``exact_last`` the last end is kept, merging
    instead the kept blocks before it that are near it."""
    ends = np.vstack([start, ints])
    stepped = steps_per_unit > 0  # (the other columns never step)
    at_steps = np.rint(ends[:, stepped] * steps_per_unit[stepped])
    following = _next_far(at_steps, min_steps)
    if following == list(range(1, len(ends) + 1)):
        return ints
    # The kept rows: the start, then from each kept row the next one far from it.
    kept, k, n = [], 0, len(ends)
    while k < n:
        kept.append(k)
        k = following[k]
        if k < 0:
            k = _next_far_of(at_steps, kept[-1], min_steps)
    if exact_last and kept[-1] != len(ints):  # the kept rows near the last end go instead
        while len(kept) > 1 and np.abs(at_steps[kept[-1]] - at_steps[-1]).max(initial=0.0) < min_steps:
            kept.pop()
        kept.append(len(ints))
    source = np.repeat(kept, np.diff(np.append(kept, n)))  # each row: the last kept at or before it
    return ends[source[1:]]


# Rows looked ahead at once for the next row far from each. On the gear at Marlin's steps most
# find it 3 to 6 rows ahead; the 2% further go row by row (8: the merge 30% faster than 16).
_NEAR_ROWS = 8


def _next_far(at_steps: np.ndarray, min_steps: int) -> list[int]:
    """For each row, the first later row at least ``min_steps`` from it on some column (the
    row count where there is none; -1 where it is more than ``_NEAR_ROWS`` ahead: see
    ``_next_far_of``)."""
    n = len(at_steps)
    following = np.full(n, -1, dtype=np.int64)
    rows = np.arange(n)
    columns = [np.ascontiguousarray(at_steps[:, j]) for j in range(at_steps.shape[1])]
    # (whole columns a row apart: faster than gathering the rows still open, most of them are)
    for ahead in range(1, min(_NEAR_ROWS, n - 1) + 1):
        far = np.zeros(n - ahead, dtype=bool)
        for column in columns:
            far |= np.abs(column[ahead:] - column[:-ahead]) >= min_steps
        found = far & (following[:-ahead] < 0)
        following[:-ahead][found] = rows[:-ahead][found] + ahead
        if (following[:-ahead] >= 0).all():
            break
    following[(following < 0) & (rows >= n - 1 - _NEAR_ROWS)] = n  # every later row looked at
    return following.tolist()


def _next_far_of(at_steps: np.ndarray, row: int, min_steps: int) -> int:
    """The first row after ``row`` at least ``min_steps`` from it on some column (the row count
    where there is none), looked for in ever longer stretches."""
    first, size = row + 1, 4 * _NEAR_ROWS
    while first < len(at_steps):
        gap = np.abs(at_steps[first:first + size] - at_steps[row]).max(axis=1, initial=0.0)
        far = np.flatnonzero(gap >= min_steps)
        if len(far):
            return first + int(far[0])
        first, size = first + size, 2 * size
    return len(at_steps)

