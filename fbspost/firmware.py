"""What a flavor's firmware does with a written program: its motion on the profile's sample grid.

Takes the blocks of a program (``gcode.read_gcode``), a machine profile (its ``[firmware]``
table) and a flavor; gives ``FirmwareMotion``: the X Y Z E positions at every sample, each
line's time and the print time, as that firmware plans them.

- Klipper: the planner with Klipper's rules (``planner.plan_blocks(..., firmware="klipper")``,
  ``klipper_rules``), proven equal to klippy's own toolhead.py (tests/test_firmware_klipper.py).
  Input shaping, if the machine has it on, is not applied (the writer turns it off).
- Marlin 2 (2.1.x, planner.cpp ``_populate_block``): positions are whole steps (``lround(mm *
  steps_per_mm)`` per axis of the profile's ``steps_per_mm``) and a segment of fewer than
  ``min_steps_per_segment`` steps on every axis is not a block: the planner keeps its position
  and the next segment starts from there (``merge_short_segments``). The merged blocks are
  then planned as the planner module plans a Marlin program: junction deviation (M205 J) or
  classic jerk (M205 X Y), M201 / M203 / M204 P T. Approximated: look-ahead is complete (Marlin
  looks ahead over its ``block_buffer`` only), and the minimum segment time slowdown (M205 B,
  applied while the buffer is under half full, which depends on the host's line rate) is not
  applied: both only slow the machine down from this plan.
- RepRapFirmware and LinuxCNC: the planner module's plan (jerk as M566 gives it, junction
  deviation); not modelled: RRF's M593 input shaping, LinuxCNC's G64 P blending tolerance
  (its corners are planned as junction-deviation corners).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .gcode import AXES, Block, Kind
from .planner import plan_blocks
from .profile import MachineProfile


@dataclass
class FirmwareMotion:
    """A program as a firmware runs it."""

    flavor: str
    positions_mm: np.ndarray  # (n, 4) X Y Z E at t = k / sample_rate_hz
    # (number of blocks,) see planner.Plan.line_time_s (merged Marlin segments: their block's end)
    line_time_s: np.ndarray
    duration_s: float
    merged_lines: list[int]  # Marlin: lines whose segments were too short to be blocks (merged with the next)


def replan(blocks: list[Block], profile: MachineProfile, flavor: str) -> FirmwareMotion:
    """``blocks`` planned as the firmware of ``flavor`` plans them (see the module docstring)."""
    merged: list[int] = []
    if flavor == "marlin":
        blocks, merged = merge_short_segments(blocks, profile)
    plan = plan_blocks(blocks, profile, firmware="klipper" if flavor == "klipper" else None)
    return FirmwareMotion(flavor, plan.positions_mm, plan.line_time_s, plan.duration_s, merged)


def merge_short_segments(blocks: list[Block], profile: MachineProfile) -> tuple[list[Block], list[int]]:
    """Marlin's step quantization and short-segment merge: every MOVE's points at whole steps of
    the axes with ``steps_per_mm``; a point fewer than ``min_steps_per_segment`` steps from the
    last block's end on every axis (E included; an axis without steps_per_mm counts as many
    steps if it moves at all) is dropped, so the next point's block covers its distance.
    Returns the blocks (a MOVE whose points all went keeps none) and the lines of dropped points."""
    steps = profile.firmware.steps_per_mm
    scale = np.array([steps.get(a, np.nan) for a in AXES])
    stepped = ~np.isnan(scale)
    scale = np.where(stepped, scale, 1.0)
    least = profile.firmware.min_steps_per_segment
    last = None  # the planner's position: (steps, mm) of the last block's end (NaN: unknown)
    out, merged = [], []
    for block in blocks:
        if block.kind is Kind.STOP:  # the firmware's position is where the line leaves the machine
            last = (_lround(block.position_mm * scale), block.position_mm)
        if block.kind is not Kind.MOVE or block.points_mm is None:
            out.append(block)
            continue
        kept = []
        for point in block.points_mm:
            target = _lround(point * scale)
            if last is not None:
                moved = np.where(stepped, np.abs(target - last[0]), np.where(point != last[1], np.inf, 0.0))
                if np.nan_to_num(moved).max() < least:
                    merged.append(block.line_no)
                    continue
            last = (target, point)
            kept.append(np.where(stepped, target / scale, point))
        out.append(dataclasses.replace(block, points_mm=np.array(kept) if kept else None))
    return out, merged


def _lround(x: np.ndarray) -> np.ndarray:
    """C's lround: to the nearest whole number, halves away from zero."""
    return np.trunc(x + np.copysign(0.5, x))
