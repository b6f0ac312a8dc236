"""The written program checked on the firmware's planner before it is committed (``--verify``).

Takes the original program, the written one, the profile and the flavor; gives ``Verdict``:
each program's print time and contour error as that firmware plans it (``firmware.replan``:
Klipper's rules, or the model of Marlin's, RepRapFirmware's or LinuxCNC's planner), through the
profile's modes. The contour error is the distance from the modelled position to the original's
commanded path (its extruding pieces for a printer, at the samples where the firmware's E rises
on both sides; every piece for a machine without E, while it moves): what the part shows.

The output is kept only if it is more accurate there (a lower RMS error, a largest error at
most ``MAX_PEAK_RATIO`` of the original's) and lasts at most the margins fbspost added (its lead
and settle time), ``MAX_TIME_INCREASE`` of the original's time and ``TIME_SLACK_S`` longer; else
the writer commits the original instead.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dynamics import AxisDynamics
from .firmware import replan
from .gcode import AXES, read_gcode
from .profile import MachineProfile
from .reprap import commanded_pieces
from .simulate import PathDistance

# Beyond the margins fbspost adds on purpose, more than this is the firmware falling behind the
# written timing (a starved buffer, Marlin's merges, LinuxCNC's short-block cap). Marlin runs a
# dense output about 1% past them (its junctions and ramps; the tube: +1.1%): within.
MAX_TIME_INCREASE = 0.02
TIME_SLACK_S = 0.05  # (a program of a second: a few servo periods or ramps are not a slower print)
# The largest error is one spot, often one neither program changes much (a corner after a copied
# travel): a few percent there must not throw away a gain everywhere else.
MAX_PEAK_RATIO = 1.1
_E = AXES.index("E")


@dataclass
class FirmwareResult:
    """A program as the firmware runs it: print time and contour error (um)."""

    duration_s: float
    rms_um: float
    max_um: float


@dataclass
class Verdict:
    """The original and the output as the firmware of ``flavor`` runs them, and whether to keep the output."""

    flavor: str
    original: FirmwareResult
    output: FirmwareResult
    margins_s: float = 0.0  # the lead and settle time fbspost added (planner.RunMargins)

    @property
    def time_increase(self) -> float:
        return self.output.duration_s / self.original.duration_s - 1.0

    @property
    def better(self) -> bool:
        """The output is more accurate on the firmware and not slower than allowed."""
        return (self.output.rms_um < self.original.rms_um
                and self.output.max_um <= MAX_PEAK_RATIO * self.original.max_um
                and self.output.duration_s <= self.time_allowed_s)

    @property
    def time_allowed_s(self) -> float:
        return (1.0 + MAX_TIME_INCREASE) * self.original.duration_s + self.margins_s + TIME_SLACK_S

    def summary(self) -> str:
        return (f"on {self.flavor}'s planner (fbspost's model of it), original -> output: RMS contour error "
                f"{self.original.rms_um:.4g} -> {self.output.rms_um:.4g} um, max {self.original.max_um:.4g} -> "
                f"{self.output.max_um:.4g} um; print time {self.original.duration_s:.1f} -> "
                f"{self.output.duration_s:.1f} s ({100 * self.time_increase:+.2f}%)")


def verify(original: Path, output: Path, profile: MachineProfile, flavor: str,
           margins_s: float = 0.0) -> Verdict | None:
    """Both programs re-planned as ``flavor``'s firmware plans them and measured on the original's
    path (None: the original has no motion to measure); ``margins_s``: the time fbspost added."""
    blocks = list(read_gcode(original, flavor, profile.home_mm))
    pieces = [piece for _, _, block_pieces in commanded_pieces(blocks) for piece in block_pieces]
    if not pieces:
        return None
    starts, ends = (np.array(column)[:, :_E + 1] for column in zip(*pieces, strict=True))
    if np.abs(ends - starts)[:, :3].max() < 1e-9:  # E alone
        return None
    path, printer = printed_path(starts, ends)
    return Verdict(flavor, *(_result(b, profile, flavor, path, printer)
                             for b in (blocks, list(read_gcode(output, flavor, profile.home_mm)))), margins_s)


def _result(blocks, profile: MachineProfile, flavor: str, path: PathDistance, printer: bool) -> FirmwareResult:
    motion = replan(blocks, profile, flavor)
    command_mm, duration_s = motion.positions_mm[:, :_E + 1].copy(), motion.duration_s
    del motion  # (every axis' samples: hold X Y Z E only)
    rms_um, max_um = contour_um(modelled(command_mm, profile), command_mm, path, printer)
    return FirmwareResult(duration_s, rms_um, max_um)


def printed_path(start_mm: np.ndarray, end_mm: np.ndarray) -> tuple[PathDistance, bool]:
    """(the path, whether it is a printer's) of moves given by their X Y Z E starts and ends:
    the moves of X Y Z (1 nm or more) that extrude, else all of them."""
    delta = end_mm - start_mm
    moves = np.linalg.norm(delta[:, :3], axis=1) >= 1e-9
    extrudes = moves & (delta[:, _E] > 0)
    printer = bool(extrudes.any())
    chosen = extrudes if printer else moves
    return PathDistance(start_mm[chosen, :3], end_mm[chosen, :3]), printer


def modelled(command_mm: np.ndarray, profile: MachineProfile) -> np.ndarray:
    """The actual positions of ``command_mm`` (rows of X Y Z E ...) through the profile's modes
    (axes without modes: as commanded). Where the command jumps (faster than twice the axis'
    top speed: a move from an unknown position, which the firmware runs but no model plans),
    the modes start anew at rest: that motion is not the program's to judge."""
    actual = command_mm.copy()
    for axis, spec in profile.axes.items():
        if spec.modes and axis in AXES:
            i = AXES.index(axis)
            dynamics = AxisDynamics(spec.modes, 1.0 / profile.sample_rate_hz)
            jumps = np.flatnonzero(np.abs(np.diff(command_mm[:, i])) > 2.0 * spec.max_velocity_mm_s
                                   / profile.sample_rate_hz) + 1
            for a, b in itertools.pairwise([0, *jumps, len(command_mm)]):
                actual[a:b, i] = dynamics.simulate(command_mm[a:b, i])
    return actual


def contour_um(actual_mm: np.ndarray, command_mm: np.ndarray, path: PathDistance, printer: bool) -> tuple[float, float]:
    """(RMS, max) contour error in um of ``actual_mm`` at the samples that print (see the module docstring)."""
    if printer:
        rising = np.diff(command_mm[:, _E]) > 0
        mask = np.append(rising, False) & np.insert(rising, 0, False)
    else:
        moving = np.flatnonzero(np.abs(np.diff(command_mm[:, :3], axis=0)).max(axis=1) > 0)
        mask = np.zeros(len(command_mm), bool)
        if len(moving):
            mask[moving[0]:moving[-1] + 2] = True
    if not mask.any():
        return 0.0, 0.0
    error, _ = path(actual_mm[mask, :3])
    return float(np.sqrt(np.mean(error**2))) * 1e3, float(error.max()) * 1e3
