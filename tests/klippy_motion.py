"""What Klipper's own planner makes of a written program, on a time grid: for tests.

Takes a program file and a profile; gives its moves as klippy plans them (``klippy_planner``),
each with its start time (the moves before it and the dwells of the lines at rest before it), and
the position of every move's axes at any time (the trapezoids klippy hands to step generation:
accelerate, cruise, decelerate, exactly).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fbspost.read.gcode import read_gcode
from klippy_planner import KlippyPlanner


@dataclass
class Executed:
    """Moves as klippy planned them (arrays, one row per move) and when each starts."""

    start_s: np.ndarray  # (n,) the moves before it and the dwells of the lines at rest before it
    start_mm: np.ndarray  # (n, 4)
    end_mm: np.ndarray  # (n, 4)
    speeds_mm_s: np.ndarray  # (n, 3) start, cruise, end
    phases_s: np.ndarray  # (n, 3) accelerate, cruise, decelerate
    accel_mm_s2: np.ndarray  # (n,)
    duration_s: float  # the last move's end, with the dwells

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """Positions (rows X Y Z E, mm) at the times ``t_s``: within a move along its trapezoid, at
        rest between moves where the last one ended (before the first: its start)."""
        k = np.maximum(np.searchsorted(self.start_s, t_s, "right") - 1, 0)
        (v0, vc, _), (ta, tc, td), a = self.speeds_mm_s[k].T, self.phases_s[k].T, self.accel_mm_s2[k]
        tau = np.clip(t_s - self.start_s[k], 0.0, ta + tc + td)
        up, cruise, down = np.minimum(tau, ta), np.clip(tau - ta, 0.0, tc), np.clip(tau - ta - tc, 0.0, td)
        s = v0 * up + 0.5 * a * up**2 + vc * (cruise + down) - 0.5 * a * down**2
        delta = self.end_mm - self.start_mm
        length = np.linalg.norm(delta[:, :3], axis=1)
        length = np.where(length > 0, length, np.abs(delta[:, 3]))  # klippy's move_d
        direction = (delta / np.where(length > 0, length, 1.0)[:, None])[k]
        return self.start_mm[k] + direction * s[:, None]


def executed(path, profile, flavor: str = "klipper") -> Executed:
    """The program at ``path`` as klippy plans it, with each move's start time."""
    planner = KlippyPlanner(profile)
    dwells = []  # the dwells before each recorded move
    record = planner._record

    def timed(moves):
        dwells.extend([planner.dwell_s] * len(moves))
        record(moves)

    planner.toolhead._process_moves = timed
    moves = planner.run(list(read_gcode(path, flavor)))
    phases = np.array([(m.accel_t, m.cruise_t, m.decel_t) for m in moves]).reshape(-1, 3)
    durations = phases.sum(axis=1)
    start = np.concatenate([[0.0], np.cumsum(durations)[:-1]]) + np.array(dwells)
    return Executed(start, np.array([m.start_pos[:4] for m in moves]), np.array([m.end_pos[:4] for m in moves]),
                    np.array([(m.start_v, m.cruise_v, m.end_v) for m in moves]), phases,
                    np.array([m.accel_mm_s2 for m in moves]), float(start[-1] + durations[-1]) if moves else 0.0)
