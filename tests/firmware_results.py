"""Firmware results for tests and benches: a program as Klipper's own planner runs it, through a
machine's modes, its contour error, and the input shapers on the same plan.

Takes program files and a profile; gives klippy's plan sampled on the profile's grid
(``klippy_run``), the modelled motion of any command (``modelled``), the contour error as
``fbspost simulate`` measures it (``contour_um``: the distance from the modelled position to the
original's path, its extruding moves for a printer, at the samples where the executed E rises on
both sides; every move for a machine without E, while it moves) and every shaper of ``fbspost
simulate``, tuned to the profile's dominant modes, applied to a plan (``shaped_plans``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fbspost.dynamics import AxisDynamics
from fbspost.gcode import AXES, read_gcode
from fbspost.shapers import SHAPERS, klipper_shaper, shape
from fbspost.simulate import PathDistance, shaper_settings
from klippy_planner import KlippyPlanner, sample_moves


def klippy_run(path: Path, profile, flavor: str):
    """(print time s, the moves klippy plans, their samples (n, 4)) of ``path``."""
    planner = KlippyPlanner(profile)
    moves = planner.run(list(read_gcode(path, flavor)))
    return planner.clock_s, moves, sample_moves(moves, profile.sample_rate_hz, planner.clock_s)


def modelled(command: np.ndarray, profile) -> np.ndarray:
    """The actual positions of ``command`` through the profile's modes (axes without modes: as commanded)."""
    actual = command.copy()
    for axis, spec in profile.axes.items():
        if spec.modes and axis in AXES:
            i = AXES.index(axis)
            actual[:, i] = AxisDynamics(spec.modes, 1.0 / profile.sample_rate_hz).simulate(command[:, i])
    return actual


def move_ends(moves) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends): X Y Z E of klippy's moves, one row each."""
    return np.array([m.start_pos[:4] for m in moves]), np.array([m.end_pos[:4] for m in moves])


def printed_path(start_mm: np.ndarray, end_mm: np.ndarray) -> tuple[PathDistance, bool]:
    """(the original's path, whether it is a printer's) from its moves' X Y Z E starts and ends:
    the moves of X Y Z (klippy's kinematic moves: 1 nm or more) that extrude, else all of them."""
    delta = end_mm - start_mm
    moves = np.linalg.norm(delta[:, :3], axis=1) >= 1e-9
    extrudes = moves & (delta[:, 3] > 0)
    printer = bool(extrudes.any())
    chosen = extrudes if printer else moves
    return PathDistance(start_mm[chosen, :3], end_mm[chosen, :3]), printer


def contour_um(actual: np.ndarray, command: np.ndarray, path: PathDistance, printer: bool) -> tuple[float, float]:
    """(RMS, max) contour error in um at the samples that print (see the module docstring)."""
    if printer:
        rising = np.diff(command[:, 3]) > 0
        mask = np.append(rising, False) & np.insert(rising, 0, False)
    else:
        moving = np.flatnonzero(np.abs(np.diff(command[:, :3], axis=0)).max(axis=1) > 0)
        mask = np.zeros(len(command), bool)
        mask[moving[0]:moving[-1] + 2] = True
    error, _ = path(actual[mask, :3])
    return float(np.sqrt(np.mean(error**2))) * 1e3, float(error.max()) * 1e3


def shaped_plans(plan: np.ndarray, profile) -> dict[str, tuple[np.ndarray, np.ndarray, float]]:
    """Every shaper on ``plan`` (samples of klippy's plan of the original): by name, (the shaped
    command, the plan padded to its length, the shaper's lag s: the time it adds)."""
    settings = shaper_settings(profile)
    period = 1.0 / profile.sample_rate_hz
    shapers = {name: {a: klipper_shaper(name, *settings[a]) for a in settings} for name in SHAPERS}
    pad = math.ceil(max(s.lead_s + s.lag_s for row in shapers.values() for s in row.values()) / period) + 1
    padded = np.pad(plan, ((pad, pad), (0, 0)), mode="edge")
    out = {}
    for name, row in shapers.items():
        command = padded.copy()
        for axis, shaper in row.items():
            command[:, AXES.index(axis)] = shape(padded[:, AXES.index(axis)], period, shaper)
        out[name] = (command, padded, max(s.lag_s for s in row.values()))
    return out
