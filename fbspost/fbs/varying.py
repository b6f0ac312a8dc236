"""Modes that move with the machine's state (the patent's claim 11): an axis that carries the
print, or whose modes change along another axis.

Takes an axis' modes and what moves them; gives, for the state they follow (one column of the
planned samples, ``column``), the level of the model in force: every mode's frequency scaled by
one factor, rounded to steps of ``STEP`` (1%). ``load_modes``: the moving mass the modes were
measured with (``moving_mass``, kg) and the filament (grams per mm of it); the factor
sqrt(m0 / (m0 + printed mass)) (a spring's mode with a heavier load), for the filament extruded
since the first known E position. ``position_modes``: a table of factors against an axis'
position (mm), linear between its points and flat beyond them. Per level: the model set the
optimizer uses (``dynamics.ModelSet.spread`` of the scaled modes, so a level keeps the profile's
tolerances), and the map of the carried state from one level to another that keeps each mode's
output and its rate continuous: the machine does not jump when the model is switched.
"""
from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy import linalg, signal

from ..profile import Mode
from ..read.blocks import AXES
from .dynamics import AxisDynamics, ModelSet, scaled_mode

STEP = 0.01  # relative frequency step between levels: within a level the model is off by 0.5% at most


@dataclass(frozen=True)
class LoadLaw:
    """The frequency factor of modes whose moving mass grows by the filament printed onto it:
    sqrt(m0 / (m0 + printed mass)), the state the filament extruded since its first known value."""

    moving_mass_kg: float
    filament_g_per_mm: float
    column = AXES.index("E")
    since_first = True  # the state counts from its first known value

    def scale(self, extruded_mm):
        """Every frequency's factor after ``extruded_mm`` of filament (a negative amount: none; a
        number or an array)."""
        printed_kg = np.maximum(0.0, extruded_mm) * self.filament_g_per_mm * 1e-3
        return np.sqrt(self.moving_mass_kg / (self.moving_mass_kg + printed_kg))


@dataclass(frozen=True)
class PositionLaw:
    """The frequency factor of modes that change along an axis (``column`` of AXES): ``scales`` at
    ``positions_mm`` (increasing), linear between them and flat beyond."""

    column: int
    positions_mm: tuple[float, ...]
    scales: tuple[float, ...]
    since_first = False  # the state is the position as it is

    def scale(self, position_mm):
        """Every frequency's factor at ``position_mm`` (a number or an array)."""
        return np.interp(position_mm, self.positions_mm, self.scales)


@dataclass(frozen=True)
class VaryingModes:
    """An axis' modes, every frequency scaled by one factor of a state (``law``): the levels, the
    model sets and the remaps between them."""

    modes: tuple[Mode, ...]
    sample_period_s: float
    law: LoadLaw | PositionLaw

    @property
    def column(self) -> int:
        """The plan's column that holds the state."""
        return self.law.column

    @property
    def since_first(self) -> bool:
        return self.law.since_first

    def scale(self, state):
        return self.law.scale(state)

    def level(self, state: float) -> int:
        """The level in force: the frequency factor (1 + STEP)^level nearest to ``scale`` (0 where
        the state is not known)."""
        if math.isnan(state):
            return 0
        return round(math.log(self.scale(state)) / math.log1p(STEP))

    def modes_at(self, level: int) -> tuple[Mode, ...]:
        return tuple(scaled_mode(m, (1.0 + STEP) ** level) for m in self.modes)

    def models(self, level: int) -> ModelSet:
        return ModelSet.spread(self.modes_at(level), self.sample_period_s)

    def levels(self, state: np.ndarray) -> np.ndarray:
        """The level at each sample of ``state`` (the plan's ``column``; counted from its first
        known value where ``since_first``), as ``level`` gives it."""
        state = np.asarray(state, dtype=float)
        if self.since_first and np.isfinite(state).any():
            state = state - state[np.isfinite(state)][0]
        with np.errstate(invalid="ignore"):
            levels = np.rint(np.log(self.scale(state)) / math.log1p(STEP))
        return np.nan_to_num(levels).astype(np.int64)

    def simulate(self, command_mm: np.ndarray, levels: np.ndarray) -> np.ndarray:
        """The axis' actual position for ``command_mm`` (held over each sample, from rest at the
        first), its modes at each sample's level (``levels``): in each stretch of one level, each
        mode's filter from the state it was left in, the state mapped where the level changes
        (``remap`` of the nominal modes)."""
        command_mm = np.asarray(command_mm, dtype=float)
        u = command_mm - command_mm[0]
        actual = np.zeros(u.size)
        x = np.zeros(2 * len(self.modes))
        for first, stop in itertools.pairwise([0, *(np.flatnonzero(np.diff(levels)) + 1).tolist(), u.size]):
            level = int(levels[first])
            if first:
                to_new, from_command = _remap_modes(self.modes_at(int(levels[first - 1])), self.modes_at(level))
                x = to_new @ x + from_command * u[first - 1]
            for i, (b, a, observe) in enumerate(_mode_filters(self.modes_at(level), self.sample_period_s)):
                rows = slice(2 * i, 2 * i + 2)
                # lfilter's state (direct form II transposed, b[0] = 0) holds the free response's
                # next two outputs: C x and C A x + a1 C x
                y0, y1 = observe @ x[rows]
                y, (z0, z1) = signal.lfilter(b, a, u[first:stop], zi=[y0, y1 + a[1] * y0])
                actual[first:stop] += y
                x[rows] = np.linalg.solve(observe, [z0, z1 - a[1] * z0])
        return actual + command_mm[0]

    def remap(self, old: int, new: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, r): the stacked state of level ``new``'s models is R x + r u for the state x of
        level ``old``'s and the command u held before it (``_remap_modes`` of every model)."""
        maps = [_remap_modes(before.modes, after.modes)
                for before, after in zip(self.models(old).models, self.models(new).models, strict=True)]
        return linalg.block_diag(*(to_new for to_new, _ in maps)), np.concatenate([offset for _, offset in maps])


@functools.lru_cache(maxsize=1024)
def _remap_modes(before: tuple[Mode, ...], after: tuple[Mode, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(R, r): the state of modes ``after`` is R x + r u for the state x of ``before`` and the
    command u held before it: every mode keeps its output y = alpha q + beta q' and its rate
    y' = alpha q' + beta q'' (q'' takes u)."""
    blocks, offsets = [], []
    for a, b in zip(before, after, strict=True):
        (to_a, u_a), (to_b, u_b) = _physical(a), _physical(b)
        blocks.append(linalg.solve(to_b, to_a))
        offsets.append(linalg.solve(to_b, u_a - u_b))
    return linalg.block_diag(*blocks), np.concatenate(offsets)


@functools.lru_cache(maxsize=256)
def _mode_filters(modes: tuple[Mode, ...], sample_period_s: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per mode, discretized: its lfilter (b, a), and [C; C A], from its state (q, q') to its next
    two outputs at rest."""
    dynamics = AxisDynamics(modes, sample_period_s)
    filters = []
    for i, (b, a) in enumerate(dynamics.mode_filters):
        rows = slice(2 * i, 2 * i + 2)
        filters.append((b, a, np.array([dynamics.C[rows], dynamics.C[rows] @ dynamics.A[rows, rows]])))
    return filters


def load_modes(modes: tuple[Mode, ...], sample_period_s: float, moving_mass_kg: float,
               filament_g_per_mm: float) -> VaryingModes:
    """The modes of an axis whose moving mass grows by the filament printed onto it."""
    return VaryingModes(modes, sample_period_s, LoadLaw(moving_mass_kg, filament_g_per_mm))


def position_modes(modes: tuple[Mode, ...], sample_period_s: float, column: int, positions_mm: tuple[float, ...],
                   scales: tuple[float, ...]) -> VaryingModes:
    """The modes of an axis that change along the axis of ``column`` (AXES): every frequency's
    factor at ``positions_mm`` (increasing) is ``scales``."""
    return VaryingModes(modes, sample_period_s, PositionLaw(column, positions_mm, scales))


def _physical(mode: Mode) -> tuple[np.ndarray, np.ndarray]:
    """(P, p): the mode's output and rate [y, y'] = P [q, q'] + p u, from q'' = u - w^2 q - 2 z w q'."""
    w, z = mode.omega_rad_s, mode.damping
    return (np.array([[mode.alpha, mode.beta], [-mode.beta * w * w, mode.alpha - 2.0 * z * w * mode.beta]]),
            np.array([0.0, mode.beta]))
