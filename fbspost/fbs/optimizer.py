"""Filtered B-spline (FBS) optimizer: the compensated command of one axis.

Takes one axis' desired trajectory (mm, on the uniform grid of its ``AxisDynamics``), its limits
and settings; gives the command (mm, same grid, same length) whose modelled response tracks the
desired trajectory best in the least-squares sense (patent Eq. 8/9), with derivative tracking
(Eq. 13), rest conditions at both ends (Eq. 11/12) and inequality limits on the command's and,
optionally, the modelled output's derivatives (a QP, solved with OSQP only where the
unconstrained solution breaks a limit).

The command is a degree-m B-spline on uniform knots, K samples apart, aligned with the first
sample. Control points before the start are the starting position, so the command starts at rest
with all its derivatives continuous. It ends at the last desired position with zero velocity and
acceleration at the last sample and is held there; the objective also covers a settling stretch
after the end, so the compensation does not buy accuracy with residual vibration.

Limited look-ahead solves windows of ``commit + overlap`` spans in sequence and keeps the first
``commit`` spans of each. Between windows it carries exactly what the future depends on: the
plant state, the last m control points and the last samples of command and output. With uniform
knots every window has the same matrices, so they are built and factored once. Complete
look-ahead solves the whole trajectory as a single final window.

Limits are on finite differences of the sampled command (and output), the motion a controller
running at the sample rate executes: velocity (u[k] - u[k-1]) / T, acceleration and jerk likewise.

Its parts: ``settings.py`` (limits, settings, result), ``windows.py`` (a window shape's matrices,
the carry, the folded regular window), ``limited_qp.py`` (a window's QP within the limits).
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from .dynamics import AxisDynamics, ModelSet
from .settings import LIMIT_TOLERANCE, AxisLimits, AxisResult, FBSSettings
from .smoothing import RunSmoother
from .varying import VaryingModes
from .windows import Carry, Sweep, Window

_FINAL_CACHE_BYTES = 128 << 20  # per axis (printer-two-mode's X: the final windows of every long run's length, 63 MB)


class AxisCompensator:
    """The compensation of one axis: ``compensator(desired_mm)`` gives an ``AxisResult``, and
    ``compensator.stream()`` an ``AxisStream`` for a run that arrives in pieces.

    Everything that does not depend on the trajectory (the regular window's matrices, their
    factorization, the folded maps and the QP set-up) is built on first use and reused for
    every motion run of a program.

    ``models``: the set whose mean squared error is minimized (robust compensation), the
    nominal ``dynamics`` first; by default ``dynamics`` alone. The carry holds every model's state.
    ``varying``: modes that move with the machine's state (``stream().push``'s ``state``: the
    filament printed, or an axis' position): each window uses the level in force at its start
    (level 0 is ``models``), the carry mapped to it; every level's matrices are built on its first use.
    """

    def __init__(self, dynamics: AxisDynamics, limits: AxisLimits, settings: FBSSettings = FBSSettings(),  # noqa: B008 (frozen)
                 lookahead: str = "limited", models: ModelSet | None = None,
                 varying: VaryingModes | None = None):
        if lookahead not in ("limited", "complete"):
            raise ValueError(f"lookahead must be 'limited' or 'complete', not {lookahead!r}")
        self.dynamics, self.limits, self.lookahead = dynamics, limits, lookahead
        self.models, self.varying = models or ModelSet([dynamics]), varying
        self.settings = settings.resolve(dynamics)
        self.carry = Carry(self.models.n_states, self.settings.degree, limits.history)
        self.state_from = None  # the first state pushed, for ``varying`` that counts from it (mm)
        self._sets = {0: self.models}
        self._rest_units, self._regulars, self._remaps = {}, {}, {}
        # each with its bytes as last counted: a solve adds to them (OSQP keeps its matrix on the
        # window), so a count taken once at build and again at eviction drifted low
        self._finals: OrderedDict[tuple[int, int], tuple[Window, int]] = OrderedDict()
        self._finals_bytes = 0

    def __call__(self, desired_mm: np.ndarray) -> AxisResult:
        stream = self.stream()
        head = stream.push(desired_mm)
        result = stream.finish()
        result.command_mm = np.concatenate([head, result.command_mm])
        return result

    def stream(self) -> AxisStream:
        return AxisStream(self)

    def model_set(self, level: int = 0) -> ModelSet:
        if level not in self._sets:
            self._sets[level] = self.varying.models(level)
        return self._sets[level]

    def rest_unit(self, level: int = 0) -> np.ndarray:
        """The carry at rest at 1 mm (the carry at rest at x mm is x times it)."""
        if level not in self._rest_units:
            models = self.model_set(level)
            self._rest_units[level] = np.concatenate(
                [models.rest_state(1.0), np.ones(self.carry.size - models.n_states)]
            )
        return self._rest_units[level]

    def remap(self, z: np.ndarray, old: int, new: int) -> np.ndarray:
        """The carry ``z`` of level ``old`` as level ``new``'s (``varying.remap``)."""
        if (old, new) not in self._remaps:
            self._remaps[old, new] = self.varying.remap(old, new)
        to_new, from_command = self._remaps[old, new]
        z = z.copy()
        z[: self.carry.n_states] = (
            to_new @ z[: self.carry.n_states] + from_command * self.carry.previous(z)[self.carry.r_max - 1]
        )
        return z

    def regular(self, level: int = 0) -> tuple[Window, Sweep]:
        if level not in self._regulars:
            k = self.settings.knot_spacing_samples
            window = self.settings.commit_spans + self.settings.overlap_spans
            models = self.model_set(level)
            stretch = Window(models, self.settings, self.limits, window * k, window)
            self._regulars[level] = stretch, Sweep(stretch, models, self.carry, self.settings.commit_spans, k)
        return self._regulars[level]

    def final(self, n_rows: int, level: int = 0) -> Window:
        """The final window of a run whose last ``n_rows`` samples it solves. Every run has one;
        its length is at most the samples a regular window needs ahead, so runs share them: the
        most recently used are kept, up to ``_FINAL_CACHE_BYTES`` (a few hundred per axis)."""
        key = level, n_rows
        final, counted = self._finals.pop(key, (None, 0))
        if final is None:
            settings = self.settings
            # The spans up to the last sample; a point whose support starts at the last sample does nothing.
            final = Window(self.model_set(level), settings, self.limits, n_rows + settings.settle_samples,
                             max(1, -(-(n_rows - 1) // settings.knot_spacing_samples)), hold_from=n_rows,
                             end_conditions=True)
        final.reset()
        size = final.nbytes
        self._finals_bytes += size - counted
        self._finals[key] = final, size
        while self._finals_bytes > _FINAL_CACHE_BYTES:
            self._finals_bytes -= self._finals.popitem(last=False)[1][1]
        return final


class AxisStream:
    """One run of one axis, fed in pieces: ``push(desired_mm)`` gives the command samples that
    nothing later can change, ``finish()`` an ``AxisResult`` with the rest. The samples are the
    same, bit for bit, however the run is cut into pieces: every window is computed alike.

    A window runs as a regular one once the samples after its kept spans are known to outlast
    the final window; the buffer holds the samples from the current window's start (and, with
    varying modes, the state they follow there).
    """

    def __init__(self, compensator: AxisCompensator):
        self.owner = compensator
        self.result = AxisResult(np.empty(0), compensator.settings)
        self.buffer = self.state = np.empty(0)
        self.first_sample = 0  # run sample at buffer[0]
        self.z = None  # the carry, once the first sample is known
        self.level = 0  # of the model in force (AxisCompensator.varying)
        half_width = compensator.settings.smoothing_half_width
        self.smoother = RunSmoother(half_width) if half_width else None

    def push(self, desired_mm: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """``state``: what varying modes follow (``varying.column`` of the plan: the filament
        position, an axis' position), at the same samples (unknown: NaN)."""
        desired_mm = np.asarray(desired_mm, dtype=float)
        if desired_mm.ndim != 1 or not np.all(np.isfinite(desired_mm)):
            raise ValueError("the desired trajectory must be a 1-D array of finite positions")
        if self.owner.varying is not None:
            self._note_state(desired_mm.size, state)  # (ahead of the buffer while the smoother holds samples)
        self._take(desired_mm if self.smoother is None else self.smoother.push(desired_mm))
        if self.owner.lookahead == "complete":
            return np.empty(0)
        return self._regular_windows()

    def finish(self) -> AxisResult:
        """The rest of the run: regular windows while they are still regular, then the final one."""
        owner, result = self.owner, self.result
        settings = owner.settings
        if self.smoother is not None:
            self._take(self.smoother.finish())
        if self.first_sample + self.buffer.size == 0:
            raise ValueError("the desired trajectory must be a non-empty 1-D array of finite positions")
        head = self._regular_windows() if owner.lookahead == "limited" else np.empty(0)
        if self.first_sample == 0 and self.buffer.size <= (settings.end_rest_order + 3) * settings.knot_spacing_samples:
            # a few spans: too short to shape, the end conditions would fix every point
            result.command_mm = self.buffer.copy()
            return result
        tail = self._final()
        tail[-1] = self.buffer[-1]  # the last position in exact arithmetic; make it so in floating point too
        result.command_mm = np.concatenate([head, tail])
        return result

    def _take(self, desired_mm: np.ndarray) -> None:
        self.buffer = np.concatenate([self.buffer, desired_mm])
        if self.z is None and self.buffer.size:
            self.level = self._level_at(0)
            self.z = self.owner.rest_unit(self.level) * self.buffer[0]

    def _note_state(self, n: int, state: np.ndarray | None) -> None:
        """Keep the state, counted from the compensator's first known one where ``varying`` says so
        (the filament extruded since then)."""
        owner = self.owner
        state = np.full(n, np.nan) if state is None else np.asarray(state, dtype=float)
        if owner.varying.since_first:
            known = state[np.isfinite(state)]
            if owner.state_from is None and known.size:
                owner.state_from = float(known[0])
            state = state - (owner.state_from or 0.0)
        self.state = np.concatenate([self.state, state])

    def _level_at(self, sample: int) -> int:
        """The level in force at buffer sample ``sample``."""
        return 0 if self.owner.varying is None else self.owner.varying.level(float(self.state[sample]))

    def _regular_windows(self) -> np.ndarray:
        """Run every window known to be regular: followed by more than the final window needs
        in the samples known so far (so whatever comes later)."""
        owner = self.owner
        settings, carry = owner.settings, owner.carry
        k, commit = settings.knot_spacing_samples, settings.commit_spans
        window = commit + settings.overlap_spans
        ahead = (commit + max(window, settings.final_spans)) * k  # samples a regular window needs after its start
        rows = commit * k
        out, start = [], 0
        while start + ahead < self.buffer.size:
            level = self._level_at(start)
            if level != self.level:
                self.z, self.level = owner.remap(self.z, self.level, level), level
            stretch, sweep = owner.regular(level)
            desired = self.buffer[start:start + window * k]
            z = self.z
            at_rest = desired[0] == desired[-1] and np.ptp(desired) == 0.0
            if at_rest and np.array_equal(z, owner.rest_unit(level) * desired[0]):
                command = desired[:rows].copy()  # at rest and staying there: exactly the optimum
            else:
                p = sweep.Gd @ desired - sweep.Gz @ z
                if stretch.has_limits and np.abs(sweep.A @ p + sweep.Az @ z
                                                 + sweep.A_center * stretch.position_center(desired)).max() > 1.0:
                    p = _solve_window(stretch, desired, carry, z, None, self.result, self.first_sample + start,
                                      breaks_limit=True)
                kept = np.concatenate([carry.p_fixed(z), p[:commit]])
                command = sweep.N_kept @ kept
                self.z = sweep.L @ np.concatenate([z, p[:commit]])
            if self.first_sample + start == 0:
                command[0] = desired[0]  # the first position in exact arithmetic; so in floating point
            out.append(command)
            start += rows
            self.result.windows += 1
        self.buffer = self.buffer[start:]
        self.state = self.state[start:]
        self.first_sample += start
        return np.concatenate(out) if out else np.empty(0)

    def _final(self) -> np.ndarray:
        """The final window: from the buffer's start to the end, the end conditions, the settling stretch."""
        owner, desired_mm, z = self.owner, self.buffer, self.z
        settings, carry = owner.settings, owner.carry
        self.result.windows += 1
        if np.ptp(desired_mm) == 0.0 and np.array_equal(z, owner.rest_unit(self.level) * desired_mm[0]):
            return desired_mm.copy()  # at rest and staying there
        n_rows = desired_mm.size
        final = owner.final(n_rows, self.level)
        desired = np.concatenate([desired_mm, np.full(settings.settle_samples, desired_mm[-1])])
        end_values = np.zeros(settings.end_rest_order + 1)
        end_values[0] = desired_mm[-1]
        p_free = _solve_window(final, desired, carry, z, end_values, self.result, self.first_sample)
        command = final.N[:n_rows] @ np.concatenate([carry.p_fixed(z), p_free])
        if self.first_sample == 0:
            command[0] = desired_mm[0]
        return command


def compensate_axis(desired_mm: np.ndarray, dynamics: AxisDynamics, limits: AxisLimits,
                    settings: FBSSettings = FBSSettings(), lookahead: str = "limited") -> AxisResult:  # noqa: B008
    """The compensated command for ``desired_mm`` (sampled at the dynamics' sample period).

    ``lookahead``: "limited" (sliding windows) or "complete" (one solve over everything).
    For several trajectories of one axis, an ``AxisCompensator`` reuses its set-up.
    """
    return AxisCompensator(dynamics, limits, settings, lookahead)(desired_mm)


def _solve_window(stretch: Window, desired, carry: Carry, z: np.ndarray, end_values, result: AxisResult,
                  first_sample: int, breaks_limit: bool = False) -> np.ndarray:
    """Free control points of one window after carry ``z``: the unconstrained optimum, or the QP
    where that breaks a limit (``breaks_limit``: the caller found it does, on the samples whose
    command the window decides)."""
    p_fixed, state = carry.p_fixed(z), carry.state(z)
    target = stretch.target(desired, state, p_fixed)
    p = stretch.unconstrained(target, p_fixed, end_values)
    if not stretch.has_limits:
        return p
    offset = stretch.limit_offset(p_fixed, state, carry.previous(z), desired)
    if not breaks_limit and stretch.violation(p, offset) <= 0.0:
        return p
    result.qp_windows += 1
    p_qp = stretch.constrained(target, p_fixed, offset, end_values, warm=p)
    best = p if p_qp is None else p_qp
    excess = stretch.violation(best, offset)
    if excess <= LIMIT_TOLERANCE:
        return best
    result.warnings.append(f"window from sample {first_sample}: the limits could not be met; "
                           f"the command there exceeds them by up to {excess:.3g} (relative)")
    return best
