"""What Klipper's own planner makes of a written program, on a time grid: for tests.

Takes a program file and a profile; gives its moves as klippy plans them (``klippy_planner``),
each with its start time (the moves before it and the dwells of the lines at rest before it), and
the position of every move's axes at any time (the trapezoids klippy hands to step generation:
accelerate, cruise, decelerate, exactly).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fbspost.gcode import read_gcode
from klippy_planner import KlippyPlanner


@dataclass
class Executed:
    start_s: np.ndarray  # (n,) each move's start
    moves: list
    start_mm: np.ndarray  # (n, 4)
    end_mm: np.ndarray  # (n, 4)
    duration_s: float  # the last move's end, with the dwells

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """Positions (rows X Y Z E, mm) at the times ``t_s``: within a move along its trapezoid, at
        rest between moves where the last one ended (before the first: its start)."""
        k = np.searchsorted(self.start_s, t_s, "right") - 1
        first = k < 0
        k = np.maximum(k, 0)
        m = [self.moves[i] for i in range(len(self.moves))]
        start_v, cruise_v = np.array([x.start_v for x in m]), np.array([x.cruise_v for x in m])
        accel_t, cruise_t, decel_t = (np.array([getattr(x, a) for x in m]) for a in ("accel_t", "cruise_t", "decel_t"))
        accel = np.array([x.accel_mm_s2 for x in m])
        tau = np.clip(t_s - self.start_s[k], 0.0, (accel_t + cruise_t + decel_t)[k])
        ta = np.minimum(tau, accel_t[k])
        tc = np.clip(tau - accel_t[k], 0.0, cruise_t[k])
        td = np.clip(tau - accel_t[k] - cruise_t[k], 0.0, decel_t[k])
        # distance: the ramp up from start_v, cruise, the ramp down from cruise_v (klippy's trapq)
        s = (start_v[k] * ta + 0.5 * accel[k] * ta**2 + cruise_v[k] * tc + cruise_v[k] * td - 0.5 * accel[k] * td**2)
        delta = self.end_mm - self.start_mm
        length = np.linalg.norm(delta[:, :3], axis=1)
        length = np.where(length > 0, length, np.abs(delta[:, 3]))
        direction = delta / np.where(length > 0, length, 1.0)[:, None]
        out = self.start_mm[k] + direction[k] * s[:, None]
        out[first] = self.start_mm[0]
        return out


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
    durations = np.array([m.duration_s for m in moves])
    start = np.concatenate([[0.0], np.cumsum(durations)[:-1]]) + np.array(dwells)
    return Executed(start, moves, np.array([m.start_pos[:4] for m in moves]), np.array([m.end_pos[:4] for m in moves]),
                    float(start[-1] + durations[-1]) if moves else planner.dwell_s)
