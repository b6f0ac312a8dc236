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

Where the firmware merges short blocks (Marlin's MIN_STEPS_PER_SEGMENT above 1) the blocks it
keeps are few and long, and their chords cannot follow the command: there the ends of the axes
with modes are placed on the lattice of whole steps together (``ModalRounding.lattice``,
``Lattice``, ``lattice_counts``): at the blocks' times, the chords' positions that leave the
modes least error from the wanted motion are solved jointly a stretch at a time, then taken on
whole steps one by one (X and Y together, their error along the path rather than across it:
the contour error is across), every block still moving the firmware's minimum on some axis.

The state carried between runs is a plain array per axis, kept for every block end so that a
caller that holds blocks back can restart from any of them.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from scipy import linalg

from ..profile import Mode

# The chords' own error from the wanted motion, weighed beside its modal response: its
# energy and its slope's (s^2). Without them the solve swings the ends by tens of steps to cancel
# a long block's error, at speeds and accelerations Marlin does not run (the gear's first 700
# lines, the Marlin model: 8.24 um RMS without, 6.79 with these; 6.8 to 7.1 for 0.05..0.5, 1e-6..1e-5).
# The slope's weight is light: the first 2000 lines of every print, the Marlin model, left 0.2% to
# 10% more RMS error at 1e-5 (the bracket at 1e-7: 4% more than at 1e-6).
CHORD_WEIGHT = 0.05
SLOPE_WEIGHT_S2 = 1e-6
# Block ends are solved a stretch of this long at a time, looking ahead over the next stretch
# too: a time constant of the printers' slowest modes (Y at 34 Hz, damping 0.05: 94 ms) or more.
HORIZON_S = 0.15
# X's and Y's ends are rounded together, to the pair of steps (each the one below or above its
# optimum) whose error, weighed by each axis' cost, lies most along the path: the contour error is
# across it. The share along it weighs this much (1: each axis on its nearest step). The bracket's
# first 2000 lines from an SD card, the Marlin model, printer-two-mode, RMS contour error through
# whole steps: 4.61 um at 1, 4.60 at 0.3, 4.52 at 0.4, 4.50 at 0.5, 5.68 at 0 (between the whole-step
# ends, no stepper: 3.63, 3.42, 3.42, 3.47, 4.13; on the stepper's staircase 3.63 at 1, 3.43 at 0.4).
TANGENT_WEIGHT = 0.4
# The longest interval Van Loan's exponential gives a block's energy over (``ModalRounding.block``):
# printer-two-mode's X within 1.6e-9 of an ODE solver's integral at 0.05 s; 2e-8 at 0.1 s, 0.7% at 0.4 s,
# negative at 0.8 s (a 1.1 s block of the 3-copy stacked gear: its output's X swung by 270 m).
VAN_LOAN_S = 0.05
_LINEAR_ENERGY = np.array([[2.0, 1.0], [1.0, 2.0]])  # integral of a linear e over T: T / 6 e' this e


class FedBackRounding:
    """First-order error feedback. State: [error of the counts so far, steps]."""

    size = 1

    def round(self, wanted: np.ndarray, durations_s: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
        # Van Loan: exp([[-M', c c'], [0, M]] T) = [[., F12], [0, F22]], energy = F22' F12. Over a
        # long block F12 grows as F22 decays, and their product loses every digit (X's modes at
        # 0.8 s: an energy of -1.6e13): there over T / 2^k, then doubled k times (W(2T) = W(T) +
        # S(T)' W(T) S(T), S(2T) = S(T)^2: sums of positive terms)
        halvings = max(0, math.ceil(math.log2(duration_s / VAN_LOAN_S)))
        big = np.zeros((2 * n + 4, 2 * n + 4))
        big[:n + 2, :n + 2], big[:n + 2, n + 2:], big[n + 2:, n + 2:] = -self.M.T, np.outer(self.c, self.c), self.M
        f = linalg.expm(big * (duration_s / 2 ** halvings))
        step, energy = f[n + 2:, n + 2:], f[n + 2:, n + 2:].T @ f[:n + 2, n + 2:]
        for _ in range(halvings):
            energy, step = energy + step.T @ energy @ step, step @ step
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

    def round(self, wanted: np.ndarray, durations_s: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whole steps for the block ends ``wanted`` (steps), from ``state``; and the state before
        each count and after the last (rows)."""
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
            xi[n] = xi[n + 1]
            states[k + 1] = xi[:n + 1]
        return counts, states

    def chord_block(self, grid_s: np.ndarray, lam: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One block of a chord against the wanted positions ``wanted`` (steps) at ``grid_s``
        (the block's start, the rows inside it, its end; ``lam`` their fractions of it): over
        v = [z0, d0, d1, 1] (the modal state at its start, its ends' offsets from the wanted),
        the modal state at its end ``A v`` and the error's cost over it ``v' Q v``: the energy
        of its modal response, and a little of the chord's own error and slope."""
        n = self.n
        x = np.zeros((n + 2, n + 3))  # [z, e0, e1] at each stretch's start, over v
        x[:n, :n] = np.eye(n)
        cost = np.zeros((n + 3, n + 3))
        errors = np.zeros((len(grid_s), n + 3))  # the chord minus the wanted, at each grid point
        errors[:, n], errors[:, n + 1] = 1.0 - lam, lam
        errors[:, n + 2] = wanted[0] + lam * (wanted[-1] - wanted[0]) - wanted  # (of the ends' offsets: well scaled)
        for g, t_us in enumerate(np.rint(np.diff(grid_s) * 1e6).astype(int).tolist()):
            to_state, weight = self.chord_stretch(t_us)
            x[n:] = errors[g:g + 2]
            cost += x.T @ weight @ x
            x[:n] = to_state @ x
        return x[:n], cost

    @functools.lru_cache(maxsize=4096)  # noqa: B019 (as block's)
    def chord_stretch(self, duration_us: int) -> tuple[np.ndarray, np.ndarray]:
        """``block``'s state map and energy over a stretch of a chord, the energy with a little
        of the chord's own error and slope (``CHORD_WEIGHT``, ``SLOPE_WEIGHT_S2``) added."""
        to_state, this, _ = self.block(duration_us)
        duration_s, n = max(duration_us, 1) * 1e-6, self.n
        weight = this.copy()
        weight[n:, n:] += CHORD_WEIGHT * duration_s / 6.0 * _LINEAR_ENERGY
        weight[n:, n:] += SLOPE_WEIGHT_S2 / duration_s * np.array([[1.0, -1.0], [-1.0, 1.0]])
        return to_state, weight

    def lattice(self, times_s: np.ndarray, wanted: np.ndarray, knots_s: np.ndarray, state: np.ndarray,
                last: float | None = None, knots_wanted: np.ndarray | None = None) -> Lattice:
        """The chords through block ends at ``knots_s`` against the wanted motion (``wanted``
        steps at ``times_s``, linear between; row 0 the start; ``knots_wanted``: at the ends,
        if given), from ``state``; ``last``: the last end fixed there (steps). See ``Lattice``."""
        return Lattice(self, times_s, wanted, knots_s, state, last, knots_wanted)


class Lattice:
    """One axis' block ends at given times (the firmware runs the chords between them), solved
    through its modes: the ends' positions that leave the least error energy from the wanted
    motion over the blocks of an end's stretch (``HORIZON_S``) and the next, and after them (a
    linear least squares on the filtered hat functions, solved backwards by dynamic programming:
    ``gains``), then taken forwards one by
    one (``best``, ``take``) on whole steps, each with the ends before it as taken and those
    after it free. Variables: each end's offset from the wanted motion there (steps), well
    scaled. ``states``: the rounding's state (``ModalRounding``'s) before each end and after the last."""

    def __init__(self, rounding: ModalRounding, times_s: np.ndarray, wanted: np.ndarray, knots_s: np.ndarray,
                 state: np.ndarray, last: float | None, knots_wanted: np.ndarray | None = None):
        n, k_count = rounding.n, len(knots_s)
        grid = np.union1d(times_s, knots_s)
        w_grid = np.interp(grid, times_s, wanted)
        bounds = np.searchsorted(grid, np.append(times_s[0], knots_s))
        if knots_wanted is not None:  # (the next call starts from these: its ends' offsets are from them)
            w_grid[bounds[1:]] = knots_wanted
        self.blocks = []
        for k in range(k_count):
            g = slice(bounds[k], bounds[k + 1] + 1)
            t = grid[g]
            self.blocks.append(rounding.chord_block(t, (t - t[0]) / (t[-1] - t[0]), w_grid[g]))
        self.wanted, self.last, self.n = w_grid[bounds], last, n
        # Each stretch's ends are solved over it and the next (their look-ahead): what is decided
        # does not depend on where the caller cut the blocks (``settled_before``).
        stretch = np.floor(knots_s / HORIZON_S).astype(np.int64)
        firsts = np.flatnonzero(np.diff(stretch, prepend=stretch[0] - 1))
        stops = np.append(firsts[1:], k_count)
        self.gains = [None] * k_count
        for j, (first, stop) in enumerate(zip(firsts.tolist(), stops.tolist(), strict=True)):
            end = stops[j + 1] if j + 1 < len(stops) else k_count
            gains = self._solved(rounding, knots_s, times_s, first, end)
            self.gains[first:stop] = gains[:stop - first]
        self.states = np.empty((k_count + 1, n + 1))
        self.states[0] = state
        self.v = np.concatenate([state, [0.0, 1.0]])  # [z, d0, d1, 1]
        self.counts = np.empty(k_count)
        self.prev = self.wanted[0] + state[n]  # where the axis is

    def _solved(self, rounding: ModalRounding, knots_s: np.ndarray, times_s: np.ndarray, first: int,
                end: int) -> list[np.ndarray]:
        """The cost-to-go's quadratic forms of ends ``first`` .. ``end`` - 1, solved backwards
        from after end - 1 (its error ramped back to zero over as long a block, then free; or
        the fixed last end)."""
        n, last, k_count = self.n, self.last, len(knots_s)
        before_s = knots_s[end - 2] if end > 1 else times_s[0]
        _, _, total = rounding.block(round((knots_s[end - 1] - before_s) * 1e6))
        value = np.zeros((n + 2, n + 2))  # over [z, d, 1], d the end's offset from the wanted
        value[:n + 1, :n + 1] = total[:n + 1, :n + 1]
        keep = [*range(n + 1), n + 2]
        gains = [None] * (end - first)
        for k in range(end - 1, first - 1, -1):
            a, q = self.blocks[k]
            to_next = np.zeros((n + 2, n + 3))  # [z0, d0, d1, 1] -> [z1, d1, 1]
            to_next[:n], to_next[n, n + 1], to_next[n + 1, n + 2] = a, 1.0, 1.0
            m = gains[k - first] = q + to_next.T @ value @ to_next
            if k == k_count - 1 and last is not None:  # d1 fixed: substituted
                fix = np.zeros((n + 3, n + 2))
                fix[keep, range(n + 2)] = 1.0
                fix[n + 1, n + 1] = last - self.wanted[-1]
                value = fix.T @ m @ fix
            else:
                value = m[np.ix_(keep, keep)] - np.outer(m[keep, n + 1], m[n + 1, keep]) / m[n + 1, n + 1]
        return gains

    def best(self, k: int) -> tuple[float, float]:
        """End k's best position (steps), the ends before it taken; and the cost's curvature there."""
        n, m, v = self.n, self.gains[k], self.v
        if k == len(self.counts) - 1 and self.last is not None:
            return self.last, math.inf
        v[n + 1] = 0.0
        return self.wanted[k + 1] - (m[n + 1] @ v) / m[n + 1, n + 1], m[n + 1, n + 1]

    def take(self, k: int, count: float) -> None:
        """End k at ``count`` steps."""
        n, v = self.n, self.v
        self.counts[k] = count
        v[n + 1] = count - self.wanted[k + 1]
        v[:n] = self.blocks[k][0] @ v
        v[n] = v[n + 1]
        self.states[k + 1] = v[:n + 1]
        self.prev = count


def settled_before(last_settled_s: float) -> float:
    """The time before which the ends a ``Lattice`` takes are those it takes with every end up
    to ``last_settled_s`` known and none after: the start of the stretch before the one it is in."""
    return (math.floor(last_settled_s / HORIZON_S) - 1) * HORIZON_S


def lattice_counts(lattices: list[Lattice], moved: np.ndarray, min_steps: int,
                   plane: tuple[int, int, float, float] | None = None) -> None:
    """Every ``lattices``' ends taken on whole steps together, block by block: each the step
    nearest its best, or for the two of ``plane`` (their indices in ``lattices``, X's and Y's,
    and the length of each one's step) the pair whose error lies most along the path
    (``_along_path``); where then no axis (nor ``moved``, per block: an axis not on the lattice
    moves its ``min_steps``) moves ``min_steps``, the axis that pays least for it moves them (the
    firmware would merge the block, at the wrong time). Before a fixed last end, the same from
    it (the firmware would merge the block before it with it)."""
    k_count = len(moved)
    for k in range(k_count):
        bests = [lat.best(k) for lat in lattices]
        counts = [float(round(b)) for b, _ in bests]
        if plane is not None:
            _along_path(counts, bests, lattices, k, plane)
        if not moved[k]:
            _apart(counts, bests, [lat.prev for lat in lattices], min_steps)
        if k == k_count - 2 and lattices and lattices[0].last is not None and not moved[k + 1]:
            _apart(counts, bests, [lat.last for lat in lattices], min_steps)
        for lat, c in zip(lattices, counts, strict=True):
            lat.take(k, c)


def _along_path(counts: list[float], bests: list[tuple[float, float]], lattices: list[Lattice], k: int,
                plane: tuple[int, int, float, float]) -> None:
    """``counts`` (in place) of ``plane``'s two axes at end ``k``: of the steps below and above
    each one's optimum, the pair whose error, each axis' scaled by the root of its cost's
    curvature, costs least with its share along the path (the wanted motion from the end before to
    the end after) weighed by ``TANGENT_WEIGHT``."""
    i, j, step_i, step_j = plane
    (best_i, curve_i), (best_j, curve_j) = bests[i], bests[j]
    after = min(k + 2, len(lattices[i].wanted) - 1)
    along = np.array([(lattices[i].wanted[after] - lattices[i].wanted[k]) * step_i,
                      (lattices[j].wanted[after] - lattices[j].wanted[k]) * step_j])
    length = math.hypot(*along)
    if length == 0.0 or not math.isfinite(curve_i + curve_j):
        return
    tangent = along / length
    normal = np.array([-tangent[1], tangent[0]])
    root = np.sqrt([curve_i, curve_j])
    weight = root[:, None] * (np.outer(normal, normal) + TANGENT_WEIGHT * np.outer(tangent, tangent)) * root
    pairs = np.array([(a, b) for a in (math.floor(best_i), math.floor(best_i) + 1)
                      for b in (math.floor(best_j), math.floor(best_j) + 1)], dtype=float)
    errors = pairs - (best_i, best_j)
    counts[i], counts[j] = pairs[np.argmin(np.einsum("pa,ab,pb->p", errors, weight, errors))]


def _apart(counts: list[float], bests: list[tuple[float, float]], anchors: list[float], min_steps: int) -> None:
    """``counts`` (in place) with one at least ``min_steps`` from its anchor: as they are if one
    is, else the one whose cost (``bests``: optimum, curvature) rises least moved there."""
    if any(abs(c - a) >= min_steps for c, a in zip(counts, anchors, strict=True)):
        return
    costs = []
    for (b, curve), c, a in zip(bests, counts, anchors, strict=True):
        far = a + (min_steps if b >= a else -min_steps)
        costs.append((curve * ((far - b) ** 2 - (c - b) ** 2), far))
    i = min(range(len(costs)), key=lambda j: costs[j][0])
    if costs[i][0] < math.inf:
        counts[i] = costs[i][1]


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
