"""The margins given to a run of motion: lead before its first motion, settle after its last.

Takes the profile (its lowest mode), the times asked for and the flavor; gives ``RunMargins``:
the lead and settle margins at each run (by what a run's end does: ``BY_END``,
``BY_END_FLAVORS``) and the share of the hard accelerations the travels are planned at
(``TRAVEL_SHARE``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..profile import MachineProfile


@dataclass(frozen=True)
class RunMargins:
    """Time given to a run of motion before its first motion (lead) and after its last (settle),
    where the compensated command may move and the original rests: the optimal command prepares
    a start (right-half-plane zeros, lightly damped modes) and cancels the ringing after a stop.
    Once a program has printed (after its first run whose pieces extrude), ``printing`` and
    ``travel`` (each (lead s, settle s); None: the same everywhere) at a run's end whose piece
    extrudes and at one whose piece does not. Rounded to whole samples. ``travel_share``: the
    margins are paid for in the travel: a piece that moves a compensated axis and does not extrude
    is planned at up to that share of the axes' hard acceleration limits (never below the
    firmware's): the contour error counts only where the print extrudes, and the compensated
    command may use the hard limits anyway (0: as the firmware plans it)."""

    lead_s: float = 0.0
    settle_s: float = 0.0
    printing: tuple[float, float] | None = None
    travel: tuple[float, float] | None = None
    travel_share: float = 0.0

    def lead_at(self, prints: bool | None, fs: float) -> int:
        """The lead (samples at ``fs``) before a run whose first piece extrudes (``prints``), or
        does not, or (None) up to the program's first run that prints."""
        return round(self._times(prints)[0] * fs)

    def settle_at(self, prints: bool | None, fs: float) -> float:
        """The settle margin (s, whole samples at ``fs``) after a run (``prints`` as ``lead_at``'s)."""
        return round(self._times(prints)[1] * fs) / fs

    def _times(self, prints: bool | None) -> tuple[float, float]:
        by_end = None if prints is None else self.printing if prints else self.travel
        return (self.lead_s, self.settle_s) if by_end is None else by_end

    @classmethod
    def for_profile(cls, profile: MachineProfile, lead_s: float | None = None, settle_s: float | None = None,
                    flavor: str | None = None) -> RunMargins:
        """The given times, at every run; each one not given: what the shortest input shaper (ZV)
        for the profile's lowest mode shifts the motion by, half its damped period (no margin
        without modes). With neither given, for a flavor of ``BY_END_FLAVORS``, once the program
        prints: that times ``BY_END``'s fractions."""
        modes = [m for axis in profile.axes.values() for m in axis.modes]
        half_s = 0.0
        if modes:
            lowest = min(modes, key=lambda m: m.frequency_hz)
            half_s = 0.5 / (lowest.frequency_hz * math.sqrt(1.0 - lowest.damping**2))
        margins = cls(half_s if lead_s is None else lead_s, half_s if settle_s is None else settle_s)
        if lead_s is None and settle_s is None and flavor in BY_END_FLAVORS:
            (lead, settle), (travel_lead, travel_settle) = BY_END
            margins = replace(margins, printing=(half_s * lead, half_s * settle),
                              travel=(half_s * travel_lead, half_s * travel_settle), travel_share=TRAVEL_SHARE)
        return margins



# The margins by what a run's end does, in half damped periods of the lowest mode: (lead before,
# settle after) a run's end that prints, and a travel's. A travel's stop needs little settle
# margin: the rest after it (its unretraction) settles it. Before every run some lead: none before
# a travel leaves a transient that rings on into the print. Through klippy, printer-two-mode (half
# period 14.7 ms), the gear's first 8000 lines: 1 everywhere (the other flavors' default) ran 1.33%
# long at 0.361 um RMS contour error, these 0.47% at 0.362 um; a lead of 1/4 before printing
# 0.83 um, none before a travel 1.83 um; no settle after a travel kept the gear's error but cost
# the pocket (a print checked after) 15% of its gain (docs/compensate.md).
BY_END = ((1 / 2, 1 / 3), (1 / 4, 1 / 5))
BY_END_FLAVORS = ("klipper", "marlin", "reprap")  # (LinuxCNC: every move's contour counts, no travel)
# With BY_END, the share of the hard accelerations the travels are planned at (RunMargins.travel_share):
# in fbspost's plan of the gear's and the tube's first 8000 lines for Klipper 0.4 left them +0.20%
# and +0.35%, 0.5 +0.04% and +0.05% (through klippy alike, at 94% and 95% of the old gain).
TRAVEL_SHARE = 0.5

