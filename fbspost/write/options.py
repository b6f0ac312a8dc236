"""The writer's options and statistics: what a caller asks of the output and what it is told.

Takes nothing; gives ``WriteOptions`` (the flavor, the format, the tolerance, the firmware's
settings and limits), ``WriteStats`` (the lines written, the line rate, the deviation from the
command), ``format_refusal`` (why a flavor cannot run a format) and the shortest block a
firmware runs as written (``shortest_line_s``, ``shortest_block_s``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..firmware.transparency import FirmwareSettings
from ..profile import MachineProfile

# Controllers that run G5: Marlin built with BEZIER_CURVE_SUPPORT, LinuxCNC (XY only). Klipper has
# no G5; RepRapFirmware's is not documented as a timed cubic Bezier.
G5_FLAVORS = ("marlin", "linuxcnc")



@dataclass(frozen=True)
class WriteOptions:
    flavor: str  # marlin | klipper | reprap | linuxcnc
    output_format: str = "dense"  # dense | g5
    tolerance_mm: float = 1e-3
    min_segment_time_s: float = 1e-3
    header: tuple[str, ...] = ()  # comment text, one entry per line
    firmware: FirmwareSettings | None = None  # the program's settings at its start (None: no settings written)
    max_line_rate_hz: float | None = None  # the most lines the machine takes per second
    steps_per_mm: tuple[float, ...] | None = None  # X Y Z E (0: not known): blocks Marlin would merge are merged here
    min_steps_per_segment: int = 0
    axis_modes: tuple = ()  # X Y Z: each axis' profile modes, for the rounding to whole steps (``steps``)
    # RepRapFirmware: it rounds each written end to its nearest step and times the block over the written
    # length, so X Y Z ends are written inside the cell of the step the rounding chooses (``Emitter``)
    step_cells: bool = False


@dataclass
class WriteStats:
    lines_out: int = 0
    motion_blocks: int = 0
    passthrough_lines: int = 0
    max_line_rate_hz: float = 0.0  # the most lines sent in any second of the program's time (no comments)
    max_deviation_mm: float = 0.0  # the largest distance of the written blocks from the command (XYZ, same time)
    max_deviation_s: float = 0.0  # where
    rms_deviation_mm: float = 0.0  # over the samples inside the blocks
    loosened_s: float = 0.0  # time in blocks beyond the tolerance (merged, or stretched for the line rate)
    shaping_left_off: str = ""  # axes whose input shaping the output turns off and cannot turn on (not known)


def format_refusal(flavor: str, output_format: str) -> str | None:
    """Why the flavor's controller cannot run the output format (None: it can)."""
    if output_format == "g5" and flavor not in G5_FLAVORS:
        return (f"{flavor} has no G5 (cubic Bezier) move: use --format dense "
                f"(g5 is for {' and '.join(G5_FLAVORS)})")
    return None



def shortest_line_s(max_line_rate_hz: float | None) -> float:
    """The shortest block at a line rate (None: no limit): a line's share of 90% of it, the rest
    left to the other lines (the copied ones), so that the host stays ahead of the firmware."""
    return 1.0 / (0.9 * (max_line_rate_hz or math.inf))


def shortest_block_s(profile: MachineProfile, flavor: str) -> float:
    """The shortest block time ``flavor``'s firmware runs as written on ``profile``: the line
    budget of the profile's max_line_rate (``shortest_line_s``); on LinuxCNC also 2 servo
    periods (its planner caps a block's speed at length / 1.02 servo periods, and shorter blocks
    ran late and off the path on LinuxCNC itself: docs/linuxcnc.md)."""
    shortest_s = shortest_line_s(profile.firmware.max_line_rate_hz)
    if flavor == "linuxcnc":
        shortest_s = max(shortest_s, 2.0 * profile.firmware.linuxcnc.servo_period_s)
    return shortest_s

