"""The fallback to the planned original: the compensated command of one axis only where it does
no harm.

Takes an axis' compensator (``optimizer.AxisCompensator``) and the program's planned and
compensated command of that axis, every sample in order, fed in pieces; gives the command to
write: the compensated command, blended toward the planned original wherever compensating would
do real harm; the stretches where it did; and the modelled error of the planned and of the
written command.

The written command is u = p + w (c - p): p planned, c compensated, w in [0, 1] a level, changed
only by blends (a quintic smoothstep: u stays continuous in acceleration) over ``ramp`` samples,
at least the slowest mode's decay time. Decisions are made at whole units of ``commit_spans``
knot spans (the optimizer's committed window, about 0.1 s) counted from the program's first
sample: they do not depend on how the samples arrive. The dynamics are linear: the modelled error
of u is the planned's minus the response to u - p, whose state x is carried as written, whatever
the optimizer assumed about its own command; the axis is modelled continuously through the rests
(from rest again where the plan jumps, as after a move from an unknown position).

At every moment a *safe plan* is known: w for some units, then blended down to 0 (the planned
original). A decision tries candidates "level a for h units, then blended down" (h from the
longest, ``_LONGEST`` units or four blends, halving) and writes the h units of the one with the
highest a <= 1 that does no harm:

- its sum of squared errors, over a horizon that lasts until the slowest mode has decayed by
  ``_DECAY`` after it, is not above the safe plan's (so no stretch and its settling is worse in
  sum of squares than the original, the first safe plan);
- no error where it writes is above the original's largest over the ``_RECENT_S`` before the
  decision and the horizon after it;
- its command where it writes is within the axis limits and the machine's travel wherever the
  planned original is.

Both over the samples the report counts (motion and the settling after it) and over all of them.
The blend down after a decision is judged for its sum of squares only: it is written only where
no later decision is found, and judging its largest error too would make the guard blend down
early before a sharp corner, doing there the harm it feared. With no candidate, the safe plan's
next unit is written: that stretch falls back, and is reported whole. So: the written sum of
squares is never above the original's but for what the horizon leaves out, and every sample
outside the reported stretches has an error at most the original's largest within ``_RECENT_S``
plus the longest decision before it and the horizon after it.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .optimizer import AxisCompensator
from .settings import LIMIT_TOLERANCE

_LONGEST = 16  # units of the longest candidate, at least (and four ramps)
_RECENT_S = 2.0  # the original's largest error over this much before a decision bounds its errors (and all ahead)
_DECAY = 1e-9  # the horizon: until the slowest mode has decayed by this much
_MOVED_MM = 1e-4  # samples where the fallback moves the command less than this are not reported
_NAMED = 5  # stretches kept for their warnings, per axis (the others only counted)
# Differences below these are rounding, not harm (where the compensation changes nothing, every
# candidate ties with the safe plan): relative, and absolute per sample.
_TIE = 1e-12
_TIE_MM = 1e-12

FALLBACK = "compensation falls back to the planned original"
LIMITS = "it would exceed the axis limits"
WORSE = "it would raise the modelled error"
LARGEST = "it would raise the largest modelled error above the original's"


def _smoothstep(s: np.ndarray) -> np.ndarray:
    """0 to 1 with zero first and second derivatives at both ends."""
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


@dataclass
class Stretch:
    """Samples [start, stop) where the written command is ``_MOVED_MM`` or more from the
    compensated one."""

    start: int
    stop: int
    reasons: set[str] = field(default_factory=set)
    level: float = 1.0  # lowest level in it (0: the planned original)


class _ChangeModel:
    """The axis' modelled response to the written command's change from the planned one, from
    sample ``n`` on. Takes the changes written (``advance``) and the samples where the model
    starts from rest again (``restarts``); gives the response ahead to a change (``moved``)."""

    def __init__(self, dynamics, horizon: int, reach: int):
        self.dynamics = dynamics
        self.free = _krylov(dynamics.A.T, dynamics.C, horizon)  # rows C A^k: the response to a state
        self.inputs = _krylov(dynamics.A, dynamics.B, reach)[::-1].T  # columns A^(L-1-i) B: state after L inputs
        self.powers = {}  # A^L
        self.restarts: list[int] = []  # samples from n on where the model starts from rest again
        self.n = 0
        self.x = np.zeros(dynamics.n_states)  # state of the response to written - planned, at n

    def moved(self, change: np.ndarray, n: int, from_state: bool = True) -> np.ndarray:
        """The first n samples of the response to input ``change`` (zero after it) from the state
        at ``self.n`` (or from zero), from rest again at every restart."""
        x = self.x if from_state else None
        cuts = [r - self.n for r in self.restarts if r - self.n < n]
        if not cuts:
            out = self._forced(change, n)
            return out if x is None else out + self.free[:n] @ x
        out = np.empty(n)
        for a, b in zip([0, *cuts], [*cuts, n], strict=True):
            out[a:b] = self._forced(change[a:b], b - a)
        if x is not None and cuts[0] > 0:
            out[:cuts[0]] += self.free[:cuts[0]] @ x
        return out

    def _forced(self, v: np.ndarray, n: int) -> np.ndarray:
        """The first n samples of the response to ``v`` from the zero state."""
        if not len(v):
            return np.zeros(n)
        if n <= len(v):
            return self.dynamics.filter(v[:n])
        out = np.empty(n)
        out[:len(v)] = self.dynamics.filter(v)
        out[len(v):] = self.free[:n - len(v)] @ self._state(v)
        return out

    def _state(self, v: np.ndarray) -> np.ndarray:
        """The state after input ``v`` from the zero state."""
        return self.inputs[:, -len(v):] @ v

    def advance(self, change: np.ndarray) -> None:
        """``change`` written from n on."""
        size = len(change)
        restarts = [r - self.n for r in self.restarts if r - self.n < size]
        if restarts:  # nothing before the last restart matters after it
            self.x = self._state(change[restarts[-1]:])
            self.restarts = [r for r in self.restarts if r >= self.n + size]
        else:
            if size not in self.powers:
                self.powers[size] = np.linalg.matrix_power(self.dynamics.A, size)
            self.x = self.powers[size] @ self.x + self._state(change)
        self.n += size


class AxisGuard:
    """One axis over a whole program: ``push(planned, compensated, moving, follows)`` with the
    next samples gives the written samples decided so far, ``finish()`` the rest. ``moving``:
    the samples are in a run of motion; ``follows``: False where the first of them may jump
    (they start a rest or a run). The modelled errors of the samples the report counts (runs and
    ``settle_samples`` after each) are added to ``before`` and ``after`` (``.add(error_mm)``);
    ``stretches`` holds the first stretches that fell back, ``more`` how many others and their
    samples."""

    def __init__(self, compensator: AxisCompensator, before, after, enabled: bool = True):
        dynamics, settings = compensator.dynamics, compensator.settings
        self.enabled = enabled  # False: the compensated command everywhere (its errors still modelled)
        self.dynamics, self.before, self.after = dynamics, before, after
        self.period_s = dynamics.sample_period_s
        self.unit = settings.commit_spans * settings.knot_spacing_samples
        self.settle = settings.settle_samples
        self.limits = compensator.limits.command
        self.history = max([*self.limits, 1])
        # the travel, and as judged: as far beyond it as the optimizer's rows accept (clipped when written)
        self.travel = compensator.limits.position_mm
        slack = LIMIT_TOLERANCE * (compensator.limits.position_half_mm or 0.0)
        self.judged_travel = (self.travel[0] - slack, self.travel[1] + slack)
        self.orders = [0] * (compensator.limits.position_half_mm is not None) + sorted(self.limits)
        # Blends last whole units, at least the decay time of the slowest mode: removed faster,
        # the compensation of a lightly damped mode leaves it ringing as much as it cancelled.
        slowest_per_s = float(np.min(-dynamics.poles().real))
        ramp_units = max(1, math.ceil(1.0 / slowest_per_s / (self.unit * self.period_s)))
        self.ramp = ramp_units * self.unit
        longest = max(_LONGEST, 4 * ramp_units)
        # Candidates' lengths, in units: the longest, halved down to a blend's.
        self.lengths = [longest >> k for k in range(longest.bit_length()) if longest >> k >= ramp_units]
        tail = math.ceil(math.log(1.0 / _DECAY) / slowest_per_s / self.period_s)
        self.horizon = longest * self.unit + self.ramp + tail
        self.reach = longest * self.unit + self.ramp + self.history  # compensated samples a decision needs
        self.up = _smoothstep(np.arange(1, self.ramp + 1) / (self.ramp + 1.0))
        self.model = _ChangeModel(dynamics, self.horizon, self.reach)
        # From sample n on: planned, compensated, the planned's modelled error, counted by the report.
        self.planned = self.command = self.error = np.empty(0)
        self.counted = np.empty(0, bool)
        self.response = None
        self.since_motion = self.settle + 1  # samples since the last in motion
        self.n = 0
        self.end = None  # samples in the program, once finished
        self.weights = np.empty(0)  # w of the safe plan from n on (0 after)
        self.level = 0.0  # w at n - 1
        self.written_before = self.planned_before = self.command_before = None  # the last ``history`` samples before n
        self.emitted = 0  # samples given out
        # the planned error's largest in each unit written in the last _RECENT_S: (end, counted, all)
        self.recent = deque()
        self.recent_samples = math.ceil(_RECENT_S / self.period_s)
        self.stretches: list[Stretch] = []
        self.more = [0, 0]  # stretches not kept, their samples
        self.open: Stretch | None = None
        self.reasons: set[str] = set()  # why the checks since the last fully compensated unit fell back
        self.vetted = True  # the samples being written are a decision's, checked for harm

    def push(self, planned_mm, compensated_mm, moving: bool, follows: bool) -> np.ndarray:
        planned_mm = np.asarray(planned_mm, dtype=float)
        if not planned_mm.size:
            return np.empty(0)
        if self.response is None:
            rest = np.full(self.history, planned_mm[0])  # at rest before the program
            self.written_before = self.planned_before = self.command_before = rest
        last = self.planned[-1] if self.planned.size else self.planned_before[-1]
        if self.response is None or (not follows and planned_mm[0] != last):
            self.response = self.dynamics.response(planned_mm[0])
            self.model.restarts.append(self.n + len(self.planned))
        if moving:
            self.since_motion, counted = 0, np.ones(planned_mm.size, bool)
        else:
            counted = self.since_motion + np.arange(1, planned_mm.size + 1) <= self.settle
            self.since_motion += planned_mm.size
        self.planned = np.concatenate([self.planned, planned_mm])
        self.command = np.concatenate([self.command, compensated_mm])
        self.error = np.concatenate([self.error, planned_mm - self.response(planned_mm)])
        self.counted = np.concatenate([self.counted, counted])
        return self._decide()

    def finish(self) -> np.ndarray:
        """The rest of the program's samples; after it the axis rests at its last position (the
        settling counted as after a run)."""
        self.end = self.n + len(self.planned)
        hold = np.full(self.settle + self.horizon + self.reach, self.planned[-1])
        written = self.push(hold, hold, False, True)
        self._close()
        return written

    def _decide(self) -> np.ndarray:
        """Every unit that the samples known so far decide; the program's samples of them."""
        out = []
        while len(self.command) >= self.reach and len(self.error) >= self.horizon and (
                self.end is None or self.n < self.end + self.settle):
            out.append(self._commit(self._check()))
        out = np.concatenate(out) if out else np.empty(0)
        if self.end is not None:  # not the rest after the program
            out = out[:max(0, self.end - self.emitted)]
        self.emitted += len(out)
        return out

    def _check(self) -> int:
        """The next safe plan: compensated, at the highest level up to 1 that does no harm, for
        as many units as it does none; or the safe plan as it was. The samples it decides."""
        horizon, unit, ramp = self.horizon, self.unit, self.ramp
        difference = self.command[:self.reach] - self.planned[:self.reach]
        self.vetted = True
        if not self.enabled or not difference.any():  # w changes nothing here: then compensate at once
            self.weights = np.ones(self.lengths[0] * unit)
            return len(self.weights)
        counted = self.counted[:horizon]
        windows, peaks = (counted, np.ones(horizon, bool)), self._recent_peaks()
        if counted.all():  # one window: the counted samples' recent peak is the stricter
            windows, peaks = windows[1:], peaks[:1]
        planned_error = self.error[:horizon] - self.model.moved(np.empty(0), horizon)  # the original from n on
        safe_error = planned_error - self.model.moved(self.weights * difference[:len(self.weights)], horizon, False)
        allowed = [
            max(peak, np.abs(self.error[:horizon][w]).max(initial=0.0)) for w, peak in zip(windows, peaks, strict=True)
        ]
        budget = [safe_error[w] @ safe_error[w] for w in windows]
        # A change of level steps the command unless the compensated command is the planned one
        # just before n (at rest): blend from the level before to the new one.
        blend = bool(np.any(self.command_before != self.planned_before))
        best, failed = None, set()  # why the best, or the shortest, falls short of level 1
        for h in self.lengths:
            scaled = np.ones(h * unit + ramp)  # w = level * scaled + (the level before) * held
            scaled[-ramp:] = self.up[::-1]
            base = planned_error
            if blend:
                scaled[:ramp] = self.up
                if self.level:
                    base = base - self.model.moved(self.level * self.up[::-1] * difference[:ramp], horizon, False)
            # its largest error is judged where it writes (the blend down after it is written only if
            # no later decision extends it; judged there, a blend that would do harm at a sharp
            # corner ahead makes the guard blend down now, which does the same harm earlier)
            written = np.arange(horizon) < h * unit
            level, short_of = _highest_level(base, self.model.moved(scaled * difference[:len(scaled)], horizon, False),
                                             windows, [w & written for w in windows], allowed, budget)
            if level is not None and best is not None and level <= best[0]:
                continue
            if level is not None:
                weights = level * scaled
                if blend:  # (so that an unchanged level is exactly that)
                    weights[:ramp] = self.level + (level - self.level) * self.up
                if not self._within_limits(weights * difference[:len(weights)], difference, h * unit):
                    level, short_of = None, {LIMITS}
            if level is None:
                if best is None:
                    failed = short_of
                continue
            best, failed = (level, h, weights), short_of
            if level == 1.0:
                break
        self.reasons |= failed
        if best is None:  # the safe plan down to the planned original, then decide again
            self.vetted = False
            return max(1, -(-len(self.weights) // unit)) * unit
        self.weights = best[2]
        return best[1] * unit

    def _recent_peaks(self) -> list[float]:
        """The planned error's largest over the last _RECENT_S written (a unit at least): over the
        counted samples, over all."""
        return [max((r[i] for r in self.recent), default=0.0) for i in (1, 2)]

    def _within_limits(self, change: np.ndarray, difference: np.ndarray, checked: int) -> bool:
        """Is planned + ``change`` (then planned) within the axis' command limits and travel wherever the
        planned original is? (Where the original itself is beyond one, at a junction's velocity
        jump, the controller's junction model governs, for the original as for this.) Over the
        first ``checked`` samples, what the decision writes; after them, the blend down, only
        where the compensated command itself (planned + ``difference``) is beyond a limit: the
        blend is written only if no later decision extends it, and where the compensation holds
        an axis at its velocity limit no blend of it can keep within, which alone is no harm."""
        ahead = self.planned[:len(change) + self.history]
        planned = np.concatenate([self.planned_before, ahead])
        written = np.concatenate([self.written_before, ahead])
        written[self.history:self.history + len(change)] += change
        compensated = np.concatenate([self.command_before, ahead])
        compensated[self.history:self.history + len(change)] += difference[:len(change)]
        for order in self.orders:
            beyond = self._outside(written, order) & ~self._outside(planned, order)
            judged = np.arange(beyond.size) < checked
            judged[checked:] = self._outside(compensated, order)[checked:]
            if np.any(beyond & judged):
                return False
        return True

    def _outside(self, command: np.ndarray, order: int) -> np.ndarray:
        """Where the samples from n of ``command`` (the ``history`` before n first) are beyond the
        travel (``order`` 0) or beyond the limit of their ``order``-th derivative."""
        values = np.diff(command, order)[self.history - order:]
        if order == 0:
            return (values < self.judged_travel[0]) | (values > self.judged_travel[1])
        return np.abs(values) > self.limits[order] * self.period_s**order * (1.0 + LIMIT_TOLERANCE)

    def _commit(self, size: int) -> np.ndarray:
        """Write ``size`` samples from n as the safe plan has them."""
        w = np.zeros(size)
        w[:min(size, len(self.weights))] = self.weights[:size]
        self.weights = self.weights[size:]
        planned, command, error = self.planned[:size], self.command[:size], self.error[:size]
        counted = self.counted[:size]
        written = np.where(w == 1.0, command, np.where(w == 0.0, planned, planned + w * (command - planned)))
        if self.orders[:1] == [0]:  # within the travel exactly, not to the optimizer's tolerance
            written = np.clip(written, *self.travel)
        change = written - planned
        self.before.add(error[counted])
        self.after.add((error - self.model.moved(change, size))[counted])
        self.model.advance(change)
        self.recent.append((self.n + size, *(np.abs(error[w]).max(initial=0.0) for w in (counted, slice(None)))))
        while self.recent[0][0] <= self.n + size - self.recent_samples:
            self.recent.popleft()
        self.level = w[-1]
        # reported: where the compensation is reduced, and every sample of the safe plan's blend
        # (written because no decision was found harmless: the guarantees are on decisions)
        where = np.flatnonzero(np.abs(command - written) > _MOVED_MM) if self.vetted else np.arange(size)
        if where.size:
            if self.open is None:
                self.open = Stretch(self.n + int(where[0]), 0)
            self.open.stop = self.n + int(where[-1]) + 1
            self.open.level = min(self.open.level, self.level)
        elif w.min() == 1.0:
            self._close()
        self.command_before = np.concatenate([self.command_before, command])[-self.history:]
        self.written_before = np.concatenate([self.written_before, written])[-self.history:]
        self.planned_before = np.concatenate([self.planned_before, planned])[-self.history:]
        self.planned, self.command, self.error = self.planned[size:], self.command[size:], self.error[size:]
        self.counted = self.counted[size:]
        self.n += size
        return written

    def _close(self) -> None:
        if self.open is not None:
            self.open.reasons = self.reasons
            if len(self.stretches) < _NAMED:
                self.stretches.append(self.open)
            else:
                self.more[0] += 1
                self.more[1] += self.open.stop - self.open.start
        self.open, self.reasons = None, set()


def _highest_level(base: np.ndarray, response: np.ndarray, windows, peak_windows, allowed, budget,
                   margin: float = 1e-9) -> tuple[float | None, set[str]]:
    """The highest level a in (0, 1] such that the error base - a response stays within
    ``allowed`` in every one of ``peak_windows`` and its sum of squares within ``budget`` in every
    one of ``windows`` (boolean masks; None if there is none), and what a = 1 breaks. The bounds
    on a are found ``margin`` (relative) inside, so that rounding keeps it within."""
    def breaks(error):
        return ({WORSE for w, b in zip(windows, budget, strict=True)
                 if error[w] @ error[w] > b * (1.0 + _TIE) + _TIE_MM**2 * np.count_nonzero(w)}
                | {LARGEST for w, peak in zip(peak_windows, allowed, strict=True)
                   if np.abs(error[w]).max(initial=0.0) > peak * (1.0 + _TIE) + _TIE_MM})

    failed = breaks(base - response)
    if not failed:
        return 1.0, failed
    low, high = 0.0, 1.0
    for w, peak, b, pw in zip(windows, allowed, budget, peak_windows, strict=True):
        e, r = base[pw], response[pw]
        peak *= 1.0 - margin
        flat = r == 0.0  # |e - a r| <= peak, sample by sample
        if np.any(np.abs(e[flat]) > peak):
            return None, failed
        ends = np.array([(e[~flat] - peak) / r[~flat], (e[~flat] + peak) / r[~flat]])
        low, high = max(low, ends.min(axis=0).max(initial=-np.inf)), min(high, ends.max(axis=0).min(initial=np.inf))
        e, r = base[w], response[w]
        a, half_b, c = r @ r, e @ r, e @ e - b * (1.0 - margin)  # a^2 (r r) - 2 a (e r) + e e - b <= 0
        if a == 0.0:
            if c > 0.0:
                return None, failed
            continue
        discriminant = half_b * half_b - a * c
        if discriminant < 0.0:
            return None, failed
        root = math.sqrt(discriminant)
        low, high = max(low, (half_b - root) / a), min(high, (half_b + root) / a)
    if high < low or high <= 0.0 or breaks(base - high * response):
        return None, failed
    return high, failed


def _krylov(matrix: np.ndarray, vector: np.ndarray, n: int) -> np.ndarray:
    """Rows matrix^k vector, k = 0..n-1, by doubling (a row at a time is slow for long horizons)."""
    rows, power = vector[None, :], matrix
    while len(rows) < n:
        rows = np.vstack([rows, rows @ power.T])
        power = power @ power
    return rows[:n]
