"""Firmware results for tests and benches: a program as Klipper's own planner runs it, through a
machine's modes, its contour error, and the input shapers on the same plan.

Takes program files and a profile; gives klippy's plan sampled on the profile's grid
(``klippy_run``), the path of its moves (``move_ends``, for ``fbspost.firmware.verify.printed_path``)
and every shaper of ``fbspost simulate``, tuned to the profile's dominant modes, applied to a
plan (``shaped_plans``). The modelled motion and the contour error are ``fbspost.firmware.verify``'s;
``LoadedBed`` models a bed whose Y frequency falls as the print's mass grows on it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fbspost.firmware.shapers import SHAPERS, klipper_shaper, shape
from fbspost.firmware.verify import modelled
from fbspost.read.blocks import AXES
from fbspost.read.gcode import read_gcode
from fbspost.tools.simulate import shaper_settings
from klippy_planner import KlippyPlanner, sample_moves
from reference import simulate_varying


def klippy_run(path: Path, profile, flavor: str):
    """(print time s, the moves klippy plans, their samples (n, 4)) of ``path``."""
    planner = KlippyPlanner(profile)
    moves = planner.run(list(read_gcode(path, flavor)))
    return planner.clock_s, moves, sample_moves(moves, profile.sample_rate_hz, planner.clock_s)


def move_ends(moves) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends): X Y Z E of klippy's moves, one row each."""
    return np.array([m.start_pos[:4] for m in moves]), np.array([m.end_pos[:4] for m in moves])


def shaped_plans(plan: np.ndarray, profile, shapers: dict[str, dict] | None = None, shape_axis=None
                 ) -> dict[str, tuple[np.ndarray, np.ndarray, float]]:
    """Every shaper on ``plan`` (samples of klippy's plan of the original), tuned to the profile's
    dominant modes, or the ``shapers`` given (by name, a ``fbspost.firmware.shapers.Shaper`` per axis): by
    name, (the shaped command, the plan padded to its length, the shaper's lag s: the time it adds).
    ``shape_axis(samples, period_s, shaper, axis)`` shapes a column (default ``shapers.shape``; a
    firmware's own, through whole steps: ``fbspost.firmware.shaping``). A jump (a move from an
    unknown place, which a firmware model puts in no time: see ``verify.modelled``) is carried
    through unshaped: shaped, it would be split into jumps to points off every path."""
    period = 1.0 / profile.sample_rate_hz
    if shapers is None:
        settings = shaper_settings(profile)
        shapers = {name: {a: klipper_shaper(name, *settings[a]) for a in settings} for name in SHAPERS}
    pad = math.ceil(max(s.lead_s + s.lag_s for row in shapers.values() for s in row.values()) / period) + 1
    padded = np.pad(plan, ((pad, pad), (0, 0)), mode="edge")
    out = {}
    for name, row in shapers.items():
        command = padded.copy()
        for axis, shaper in row.items():
            column = padded[:, AXES.index(axis)]
            step = np.diff(column, prepend=column[:1])
            jumps = np.cumsum(np.where(np.abs(step) > 2.0 * profile.axes[axis].max_velocity_mm_s * period, step, 0.0))
            column = column - jumps
            command[:, AXES.index(axis)] = jumps + (shape_axis(column, period, shaper, axis) if shape_axis
                                                    else shape(column, period, shaper))
        out[name] = (command, padded, max(s.lag_s for s in row.values()))
    return out


@dataclass(frozen=True)
class LoadedBed:
    """Y carries the print: every Y frequency times sqrt(m / (m + printed)), m the bed's mass,
    the printed mass the filament (1.75 mm PLA) extruded by each sample."""
    mass_kg: float
    g_per_mm: float = math.pi * 0.875**2 * 1.24e-3

    @classmethod
    def falling_to(cls, fall: float, extruded_mm: float) -> LoadedBed:
        """The bed whose Y frequency is ``fall`` times its own once ``extruded_mm`` are printed."""
        return cls(extruded_mm * cls.g_per_mm * 1e-3 / (1 / fall**2 - 1))

    def scale(self, extruded_mm: np.ndarray) -> np.ndarray:
        return np.sqrt(self.mass_kg / (self.mass_kg + np.maximum(extruded_mm, 0.0) * self.g_per_mm * 1e-3))

    def actual(self, command: np.ndarray, profile) -> np.ndarray:
        """``modelled(command, profile)``, but Y on this bed, simulated exactly per sample
        (reference.simulate_varying), the filament counted from the command's first E."""
        actual, y, e = modelled(command, profile), AXES.index("Y"), command[:, AXES.index("E")]
        actual[:, y] = simulate_varying(profile.axes["Y"].modes, 1.0 / profile.sample_rate_hz, command[:, y],
                                        self.scale(e - e[0]))
        return actual
