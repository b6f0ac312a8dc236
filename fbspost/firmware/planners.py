"""What a flavor's firmware does with a written program: its motion on the profile's sample grid.

Takes the blocks of a program (``gcode.read_gcode``), a machine profile (its ``[firmware]``
table) and a flavor; gives ``FirmwareMotion``: the X Y Z E positions at every sample, each
line's time and the print time, as that firmware plans them.

- Klipper: the planner with Klipper's rules (``planner.plan_blocks(..., firmware="klipper")``,
  ``klipper_rules``), proven equal to klippy's own toolhead.py (tests/test_firmware_klipper.py).
  Input shaping, if the machine has it on, is not applied (the writer turns it off).
- Marlin 2.1: ``marlin.run_marlin``, a model of Marlin's planner.cpp and of the host sending the
  program line by line at the profile's ``max_line_rate``: whole steps and the short-segment
  merge, the block buffer and its look-ahead, SLOWDOWN (M205 B), junction deviation (M205 J) or
  classic jerk, the minimum planner speed, the first-move delay; where the buffer runs dry.
- RepRapFirmware 3.5: ``reprap.run_reprap``, a model of its DDA ring read from a file (or from a
  host at ``max_line_rate``): whole-step targets timed over the commanded length, M201/M203/M204
  limits, M566 jerk per drive and its jerk policy, look-ahead over the moves in the ring when a
  move is prepared, RecalculateMove's short-ramp rule; where the ring runs dry. Not modelled:
  M593 input shaping (``firmware_shapers`` gives Marlin's and RRF's shaping of a plan, through
  whole steps, for the benches).
- LinuxCNC 2.9: ``linuxcnc_tp.run_linuxcnc``, a model of its trajectory planner (tp.c, tc.c,
  blendmath.c): the servo period's short-segment cap, G64 P blend arcs, tangent and parabolic
  blends, G61 / G61.1, the look-ahead, ramps and split cycles.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..plan.planner import plan_blocks
from ..profile import MachineProfile
from ..read.blocks import Block
from .linuxcnc_tp import run_linuxcnc
from .marlin import run_marlin
from .reprap import run_reprap

# The models of the firmwares' planners, by flavor: each takes (blocks, profile) and gives a run
# (``at(t)``, ``positions_mm(sample_rate_hz)``, ``line_time_s``, ``duration_s``); Klipper's is the planner's
PLANNER_MODELS = {"marlin": run_marlin, "reprap": run_reprap, "linuxcnc": run_linuxcnc}


@dataclass
class FirmwareMotion:
    """A program as a firmware runs it."""

    flavor: str
    positions_mm: np.ndarray  # (n, len(AXES)) at t = k / sample_rate_hz
    line_time_s: np.ndarray  # (number of blocks,) see planner.Plan.line_time_s (Marlin: see marlin.MarlinRun)
    duration_s: float
    merged_lines: list[int]  # Marlin: lines whose segments were too short to be blocks (merged with the next)
    starved: list[tuple[float, float]] = field(default_factory=list)  # Marlin, RRF: (when, rest s) the buffer ran dry


def replan(blocks: list[Block], profile: MachineProfile, flavor: str, every_axis: bool = False) -> FirmwareMotion:
    """``blocks`` planned as the firmware of ``flavor`` plans them (see the module docstring);
    ``every_axis`` (Klipper and the planner's other flavors): see ``planner.plan_blocks``."""
    if flavor in PLANNER_MODELS:
        run = PLANNER_MODELS[flavor](blocks, profile)
        if flavor == "linuxcnc":
            return FirmwareMotion(flavor, run.positions_mm(profile.sample_rate_hz), run.line_time_s, run.duration_s, [])
        return FirmwareMotion(flavor, run.positions_mm(profile.sample_rate_hz), run.line_time_s, run.duration_s,
                              run.merged_lines, run.starved)
    plan = plan_blocks(blocks, profile, firmware="klipper" if flavor == "klipper" else None, every_axis=every_axis)
    return FirmwareMotion(flavor, plan.positions_mm, plan.line_time_s, plan.duration_s, [])
