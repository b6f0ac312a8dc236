"""Block ends in whole motor steps, rounded where the axis feels the rounding least.

Marlin and RepRapFirmware move every block to a whole step (``lround(mm * steps_per_mm)``). A
dense compensated program has a block every few ms, so each block end's rounding (up to half a
step: 6 um at 80 steps/mm) is a new small error, and the axis' modes ring with them.

Takes, per X Y Z axis with steps, its modes (``profile.Mode``; none: no modelled dynamics), and
run by run the wanted block ends in steps (floats) and the blocks' durations (s); gives whole
step counts (``round``), each the one below or above the wanted end:

- an axis with modes (``ModalRounding``): the one that leaves the least error in the axis'
  position. The rounding errors, joined linearly in time as the firmware joins the block ends,
  drive the axis' modes (continuous modal model, exact over each block); of the two choices the
  one is taken whose error energy (the integral of the squared position error) over the block
  and after it is least, had the error then ramped back to zero over as long a block;
- an axis without modes (``FedBackRounding``): each count rounded with the error of the one
  before fed back, so the errors sum to within half a step: they drift nowhere.

The state carried between runs is a plain array per axis, kept for every block end so that a
caller that holds blocks back can restart from any of them.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from scipy import linalg

from .profile import Mode


class FedBackRounding:
    """First-order error feedback. State: [error of the counts so far, steps]."""

    size = 1

    def round(self, wanted: np.ndarray, durations_s: np.ndarray, state: np.ndarray,
              chords: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Whole steps for the block ends ``wanted`` (steps), from ``state``; and the state before
        each count and after the last (rows)."""
        counts, errors = np.empty(len(wanted)), np.empty((len(wanted) + 1, 1))
        error = errors[0, 0] = state[0]
        for k, w in enumerate(wanted.tolist()):
            counts[k] = round(w - error)
            error = errors[k + 1, 0] = counts[k] - (w - error)
        return counts, errors


class ModalRounding:
    """Rounding against the axis' modes. State: [modal states of the rounding error's response, last error]."""

    def __init__(self, modes: tuple[Mode, ...] | list[Mode]):
        blocks_a = [np.array([[0.0, 1.0], [-m.omega_rad_s ** 2, -2.0 * m.damping * m.omega_rad_s]]) for m in modes]
        self.n = n = 2 * len(modes)
        self.size = n + 1
        # augmented by the input u and its slope v: a block's error ramps linearly between its ends
        self.M = np.zeros((n + 2, n + 2))
        self.M[:n, :n], self.M[n, n + 1] = linalg.block_diag(*blocks_a), 1.0
        self.M[:n, n] = np.tile([0.0, 1.0], len(modes))
        self.c = np.zeros(n + 2)
        self.c[:n] = np.concatenate([[m.alpha, m.beta] for m in modes])
        # free-response energy of a modal state: z' gramian z = integral of (C e^(At) z)^2 dt
        self.gramian = linalg.solve_continuous_lyapunov(self.M[:n, :n].T, -np.outer(self.c[:n], self.c[:n]))

    @functools.lru_cache(maxsize=4096)  # noqa: B019 (the rounding lives as long as its writer; durations recur)
    def block(self, duration_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Over a block of ``duration_us``, for xi = [z0, e0, e1] (modal state, errors at its ends):
        the modal state at its end ``S xi``; the error energy over the block ``xi' W xi``; and
        that plus the energy after it, had the error then ramped back to zero over as long a block
        and stayed there, ``xi' J xi``."""
        n, duration_s = self.n, max(duration_us, 1) * 1e-6
        # Van Loan: exp([[-M', c c'], [0, M]] T) = [[., F12], [0, F22]], energy = F22' F12
        big = np.zeros((2 * n + 4, 2 * n + 4))
        big[:n + 2, :n + 2], big[:n + 2, n + 2:], big[n + 2:, n + 2:] = -self.M.T, np.outer(self.c, self.c), self.M
        f = linalg.expm(big * duration_s)
        step, energy = f[n + 2:, n + 2:], f[n + 2:, n + 2:].T @ f[:n + 2, n + 2:]
        ramp = np.zeros((n + 2, n + 2))  # [z0, e0, e1] -> [z0, u0, v]
        ramp[:n, :n] = np.eye(n)
        ramp[n, n], ramp[n + 1, n], ramp[n + 1, n + 1] = 1.0, -1.0 / duration_s, 1.0 / duration_s
        to_state = (step @ ramp)[:n]
        this = ramp.T @ energy @ ramp
        back = np.zeros((n + 2, n + 2))  # [z0, e0, e1] -> [z1, e1, 0]: the next block, back to zero
        back[:n], back[n, n + 1] = to_state, 1.0
        after = (step @ ramp @ back)[:n]
        total = this + back.T @ ramp.T @ energy @ ramp @ back + after.T @ self.gramian @ after
        return to_state, this, total

    def chord_states(self, times_s: np.ndarray, wanted: np.ndarray, kept: np.ndarray) -> np.ndarray:
        """For each kept row (``kept``, of rows 1..n of ``wanted`` at ``times_s``, row 0 the
        start), the modal state at its end, from rest, of the response to the chord between the
        kept rows before and at it minus the wanted rows between (linear between rows)."""
        out, prev, times_s = np.zeros((len(kept), self.n)), 0, times_s.tolist()
        for j, k in enumerate(kept.tolist()):
            if k - prev > 1:
                lam = (np.asarray(times_s[prev:k + 1]) - times_s[prev]) / (times_s[k] - times_s[prev])
                chord = (wanted[prev] + lam * (wanted[k] - wanted[prev]) - wanted[prev:k + 1]).tolist()
                z = np.zeros(self.n + 2)
                for r in range(prev, k):
                    z[self.n:] = chord[r - prev], chord[r + 1 - prev]
                    z[:self.n] = self.block(round((times_s[r + 1] - times_s[r]) * 1e6))[0] @ z
                out[j] = z[:self.n]
            prev = k
        return out

    def round(self, wanted: np.ndarray, durations_s: np.ndarray, state: np.ndarray,
              chords: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Whole steps for the block ends ``wanted`` (steps), from ``state``; and the state before
        each count and after the last (rows). ``chords``: per block, the modal state of what
        its motion between its ends leaves out (``chord_states``), fed back with the rounding."""
        n = self.n
        counts, states = np.empty(len(wanted)), np.empty((len(wanted) + 1, n + 1))
        states[0] = state
        xi = np.append(state, 0.0)  # [z, e0, e1]
        for k, (w, t_us) in enumerate(zip(wanted.tolist(), np.rint(durations_s * 1e6).astype(int).tolist(),
                                          strict=True)):
            to_state, _, total = self.block(t_us)
            xi[n + 1] = 0.0
            best = -(total[n + 1] @ xi) / total[n + 1, n + 1]  # the cost is quadratic in e1
            counts[k] = min(max(round(w + best), math.floor(w)), math.ceil(w))
            xi[n + 1] = counts[k] - w
            xi[:n] = to_state @ xi
            if chords is not None:
                xi[:n] += chords[k]
            xi[n] = xi[n + 1]
            states[k + 1] = xi[:n + 1]
        return counts, states


def rounding_for(modes) -> FedBackRounding | ModalRounding:
    """The rounding for an axis with ``modes`` (empty or None: no modelled dynamics)."""
    return ModalRounding(modes) if modes else FedBackRounding()


def crossing_ends(times_s: np.ndarray, units: np.ndarray, steps_per_unit: np.ndarray,
                  kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block ends moved in time to where the block's dominant axis crosses a whole step.

    ``times_s`` (n + 1) and ``units`` (n + 1, columns) are the wanted ends, row 0 the first
    block's start, the command linear in time between rows; ``steps_per_unit`` per column (0:
    it does not step; it is moved along in time but decides nothing); ``kept`` the rows (1..n)
    that end a block. For each kept row: its dominant axis (of the most steps from the kept row
    before), that axis' whole step nearest the row, and the time on the neighbouring stretches
    (the row before to the row, else the row to the row after) where the axis reaches it; every
    column there. Not moved: the last kept row (it ends the run, or waits for the next rows),
    and where the crossing is more than half the shorter of the block and the next away. Gives
    the kept rows' times and ends."""
    n, stepped = len(times_s) - 1, steps_per_unit > 0
    steps = units[:, stepped] * steps_per_unit[stepped]
    prev = np.concatenate([[0], kept[:-1]])
    dominant = np.argmax(np.abs(steps[kept] - steps[prev]), axis=1)
    w = steps[kept, dominant]
    c = np.rint(w)
    before, after = steps[kept - 1, dominant], steps[np.minimum(kept + 1, n), dominant]
    with np.errstate(divide="ignore", invalid="ignore"):
        back = (c - before) / (w - before)  # of the stretch before, from its start
        ahead = (c - w) / (after - w)  # of the stretch after
    use_back = (back >= 0.0) & (back <= 1.0)
    use_ahead = ~use_back & (ahead >= 0.0) & (ahead <= 1.0) & (kept < n)
    lo = np.where(use_back, kept - 1, kept)
    frac = np.where(use_back, back, np.where(use_ahead, ahead, 0.0))
    t = times_s[lo] + frac * (times_s[np.minimum(lo + 1, n)] - times_s[lo])
    next_s = np.append(times_s[kept[1:]], np.inf)  # (the last is not moved)
    room = 0.5 * np.minimum(times_s[kept] - times_s[prev], next_s - times_s[kept])
    move = (use_back | use_ahead) & (np.abs(t - times_s[kept]) <= room)
    move[-1] = False
    lo, frac = np.where(move, lo, kept), np.where(move, frac, 0.0)
    ends = units[lo] + frac[:, None] * (units[np.minimum(lo + 1, n)] - units[lo])
    rows = np.flatnonzero(move)
    ends[rows, np.flatnonzero(stepped)[dominant[rows]]] = c[rows] / steps_per_unit[stepped][dominant[rows]]
    return np.where(move, t, times_s[kept]), ends
