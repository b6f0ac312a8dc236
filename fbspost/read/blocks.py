"""What the G-code reader gives: one ``Block`` per line, and the columns of its positions.

Takes nothing; gives the types every stage after the reader uses: ``Block`` (a line: its bytes,
its ``Kind``, its linear pieces in machine mm, its ``PlannerLimits`` changes, its ``Modal`` state
after it), the columns of every position array (``AXES``: X Y Z E, then LinuxCNC's A B C U V W),
the length a move's feed is along (``feed_lengths``), the tolerance of the chords curves are cut
into (``CHORD_TOLERANCE_MM``), and ``NeedsInterpreter`` (what only LinuxCNC's interpreter runs).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

AXES = ("X", "Y", "Z", "E", "A", "B", "C", "U", "V", "W")  # column order of every position array
E_AXIS = 3
EXTRA_AXES = tuple(range(4, len(AXES)))  # LinuxCNC's rotary and other axes: followed exactly (no modes)
DEGREES = (4, 5, 6)  # A B C: degrees, whatever G20/G21 say
OTHER_AXES = "".join(AXES[i] for i in EXTRA_AXES)
CHORD_TOLERANCE_MM = 0.0005  # largest distance between an arc or Bezier and its linear pieces
EXPAND_HINT = "--expand runs it through LinuxCNC's interpreter"


def feed_lengths(delta_mm: np.ndarray, xyz_moves: np.ndarray | None = None,
                 still_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The length each move's feed is along, and where XYZ do not move: the XYZ length where XYZ
    move (``xyz_moves``; by default where the XYZ length is above ``still_mm``), else the U V W
    length, else the A B C length (LinuxCNC's rule for its feed, docs "Feed Rate"), else |dE|
    (the printers' extrude-only moves)."""
    def norm(columns):
        return np.sqrt(np.einsum("ij,ij->i", delta_mm[:, columns], delta_mm[:, columns]))

    xyz, uvw, abc = norm(slice(0, 3)), norm(slice(7, 10)), norm(slice(4, 7))
    still = ~(xyz > still_mm) if xyz_moves is None else ~xyz_moves
    other = np.where(uvw > still_mm, uvw, np.where(abc > still_mm, abc, np.abs(delta_mm[:, E_AXIS])))
    return np.where(still, other, xyz), still


class NeedsInterpreter(InputError):
    """A LinuxCNC feature fbspost does not interpret itself (parameters, O-words, canned cycles,
    ...): ``--expand`` runs the program through LinuxCNC's own interpreter first."""

    def __init__(self, path: str | Path, line: int, feature: str, message: str):
        super().__init__(path, line, message)
        self.line, self.feature = line, feature
        self._parts = (path, line, feature, message)


class Kind(enum.Enum):
    MOVE = "move"  # motion fbspost plans and rewrites
    PASS = "pass"  # no motion: passes through byte-exact at its time, the motion goes on through it
    STOP = "stop"  # passes through byte-exact; the machine is at rest when it runs


@dataclass(frozen=True)
class PlannerLimits:
    """Planner settings changed by one line; ``None`` (or a missing axis) means unchanged."""

    # M204 S/P, Klipper ACCEL: moves that extrude (all moves if no travel value)
    acceleration_mm_s2: float | None = None
    travel_acceleration_mm_s2: float | None = None  # M204 T (Marlin, RRF): moves that do not extrude
    max_velocity_mm_s: float | None = None  # Klipper VELOCITY
    square_corner_velocity_mm_s: float | None = None  # Klipper SQUARE_CORNER_VELOCITY
    junction_deviation_mm: float | None = None  # Marlin M205 J
    minimum_cruise_ratio: float | None = None  # Klipper SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO
    accel_to_decel_mm_s2: float | None = None  # Klipper SET_VELOCITY_LIMIT ACCEL_TO_DECEL (before 2024)
    axis_max_velocity_mm_s: dict[str, float] = field(default_factory=dict)  # M203
    min_feed_mm_s: float | None = None  # RepRapFirmware M203 I: the slowest a move runs
    axis_max_acceleration_mm_s2: dict[str, float] = field(default_factory=dict)  # M201


@dataclass(frozen=True)
class Modal:
    """The state that decides how coordinates are written, after a line."""

    absolute_xyz: bool = True  # G90 / G91
    absolute_e: bool = True  # M82 / M83 (G90 / G91 set it too, as Marlin and RRF do)
    inches: bool = False  # G20 / G21
    offsets_mm: tuple[float, ...] = (0.0,) * len(AXES)  # program = machine - offset (G92)
    plane: int = 17  # G17 / G18 / G19: the G5 writer needs G17


@dataclass
class Block:
    line_no: int  # 1-based
    raw: bytes  # the line exactly as read, line ending included
    kind: Kind
    modal: Modal  # after this line
    position_mm: np.ndarray  # (len(AXES),) machine position after this line; NaN where unknown
    # MOVE: (k, len(AXES)) machine-coordinate end points of its k >= 1 linear pieces
    points_mm: np.ndarray | None = None
    feed_mm_s: float | None = None  # a line that moves: requested feed along the path; math.inf for a rapid (G0)
    dwell_s: float = 0.0  # STOP: time at rest (G4)
    limits: PlannerLimits | None = None  # planner changes made by this line
    # axes (indices into AXES) whose program position this line sets where the machine is (G92)
    sets_position: tuple[int, ...] = ()
    # a line that moves by the motion mode in force (LinuxCNC: axis words without G0-G5 of its own): that mode
    inherited_motion: float | None = None
