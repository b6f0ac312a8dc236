"""Modes that move with the machine's state (the patent's claim 11): an axis that carries the print.

Takes an axis' modes, the moving mass they were measured with (``moving_mass``, kg) and the
filament (grams per mm of it); gives, for the filament extruded so far (mm), the level of the
model in force: every mode's frequency scaled by sqrt(m0 / (m0 + printed mass)) (a spring's mode
with a heavier load), rounded to steps of ``STEP`` (1%). Per level: the model set the optimizer
uses (``dynamics.ModelSet.spread`` of the scaled modes, so a level keeps the profile's
tolerances), and the map of the carried state from one level to another that keeps each mode's
output and its rate continuous: the machine does not jump when the model is switched.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import linalg

from .dynamics import ModelSet, scaled_mode
from .profile import Mode

STEP = 0.01  # relative frequency step between levels: within a level the model is off by 0.5% at most


@dataclass(frozen=True)
class LoadModes:
    """The modes of an axis whose moving mass grows by the filament printed onto it."""

    modes: tuple[Mode, ...]
    sample_period_s: float
    moving_mass_kg: float
    filament_g_per_mm: float

    def scale(self, extruded_mm: float) -> float:
        """Every frequency's factor after ``extruded_mm`` of filament (a negative amount: none)."""
        printed_kg = max(0.0, extruded_mm) * self.filament_g_per_mm * 1e-3
        return math.sqrt(self.moving_mass_kg / (self.moving_mass_kg + printed_kg))

    def level(self, extruded_mm: float) -> int:
        """The level in force: the frequency factor (1 + STEP)^level nearest to ``scale``."""
        return round(math.log(self.scale(extruded_mm)) / math.log1p(STEP))

    def modes_at(self, level: int) -> tuple[Mode, ...]:
        return tuple(scaled_mode(m, (1.0 + STEP) ** level) for m in self.modes)

    def models(self, level: int) -> ModelSet:
        return ModelSet.spread(self.modes_at(level), self.sample_period_s)

    def remap(self, old: int, new: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, r): the stacked state of level ``new``'s models is R x + r u for the state x of
        level ``old``'s and the command u held before it: every mode of every model keeps its
        output y = alpha q + beta q' and its rate y' = alpha q' + beta q'' (q'' takes u)."""
        blocks, offsets = [], []
        for before, after in zip(self.models(old).models, self.models(new).models, strict=True):
            for a, b in zip(before.modes, after.modes, strict=True):
                (to_a, u_a), (to_b, u_b) = _physical(a), _physical(b)
                blocks.append(linalg.solve(to_b, to_a))
                offsets.append(linalg.solve(to_b, u_a - u_b))
        return linalg.block_diag(*blocks), np.concatenate(offsets)


def _physical(mode: Mode) -> tuple[np.ndarray, np.ndarray]:
    """(P, p): the mode's output and rate [y, y'] = P [q, q'] + p u, from q'' = u - w^2 q - 2 z w q'."""
    w, z = mode.omega_rad_s, mode.damping
    return (np.array([[mode.alpha, mode.beta], [-mode.beta * w * w, mode.alpha - 2.0 * z * w * mode.beta]]),
            np.array([0.0, mode.beta]))
