"""The reader's machine state between lines: the position, the offsets and the modes.

Takes the flavor; gives ``State``: the machine position (mm, NaN where unknown), the G92
offsets, the distance, unit and plane modes, the last motion mode and the feed, the ``Modal``
state they make (``new_modal``), a line's ``Block`` where the machine is (``block``), and the
position lost (``forget``). The reader's parts read and change it, each through its own calls:
the reader (the modal G codes, the feed), ``commands.Commands``, ``motion.Motion``,
``splines.Splines``.
"""
from __future__ import annotations

import math

import numpy as np

from .blocks import AXES, EXTRA_AXES, Block, Modal

WCS = (54.0, 55.0, 56.0, 57.0, 58.0, 59.0, 59.1, 59.2, 59.3)  # LinuxCNC's work coordinate systems, in order

INCH = 25.4
_NAN = math.nan


class State:
    """The machine's position and modes after the lines read so far."""

    def __init__(self, flavor: str, work_offsets_mm=()):
        self.flavor = flavor
        self.cnc = flavor == "linuxcnc"
        # machine position: XYZ (and LinuxCNC's other axes) unknown, E at 0 (the printers' other axes never move)
        self.pos = [_NAN, _NAN, _NAN, 0.0] + [_NAN if self.cnc else 0.0] * len(EXTRA_AXES)
        self.off = [0.0] * len(AXES)  # program = machine - off (G92)
        self.frame = (0, 1, 2, *EXTRA_AXES) if self.cnc else (0, 1, 2)  # the axes an unknown frame or command loses
        self.abs_xyz = True
        self.abs_e = True  # as given by M82/M83 (and G90/G91 in Marlin)
        self.inches = False
        self.modal = Modal()
        self.eabs = True  # E words are absolute (the effect of G90/G91 and M82/M83 in this flavor)
        self.motion = None  # last motion mode: 0 1 2 3 5
        self.feed = None  # mm/s
        self.plane = 17  # G17 / G18 / G19 (see motion.PLANES)
        self.abs_ijk = False  # G90.1
        self.wcs = 54.0
        self.wcs_chosen = False  # the program has selected a work coordinate system (LinuxCNC)
        # G54..G59.3 -> X Y Z offsets (mm; None: not known), from LinuxCNC's parameter file
        self.work_offsets = dict(zip(WCS, work_offsets_mm, strict=False))
        self.g5x = [0.0] * len(AXES)  # the offsets of the system in use, in its first one's frame
        self.tool_length = False  # G43 active (LinuxCNC)

    def e_absolute(self) -> bool:
        if self.flavor == "klipper":  # Klipper: E is relative under G91 or M83
            return self.abs_e and self.abs_xyz
        return self.abs_e

    def new_modal(self) -> None:
        self.eabs = self.e_absolute()
        self.modal = Modal(self.abs_xyz, self.eabs, self.inches, tuple(self.off), self.plane)

    def block(self, n, raw, kind, **kw) -> Block:
        return Block(n, raw, kind, self.modal, np.array(self.pos), **kw)

    def select_wcs(self, g: float) -> bool:
        """Selects the work coordinate system ``g`` (54.0 .. 59.3); False where that loses the
        position: another system than the one in use, unless both offsets are known and the one
        in use was selected (not the machine's unknown one at the start, which a first selection
        ends; there, the position before it is lost where the offsets are known)."""
        old, self.wcs, chosen, self.wcs_chosen = self.wcs, g, self.wcs_chosen, True
        before, after = self.work_offsets.get(old), self.work_offsets.get(g)
        if before is None or after is None or not chosen:
            return g == old and not (self.work_offsets and not chosen)
        for i in range(3):
            self.g5x[i] += after[i] - before[i]
            self.off[i] += after[i] - before[i]
        return True

    def forget(self, axes, e_too: bool = False) -> None:
        """The machine position of ``axes`` (indices) is unknown after this line."""
        for i in axes:
            self.pos[i] = _NAN
        if e_too and self.eabs and not self.cnc:  # LinuxCNC has no E: it stays at 0
            self.pos[3] = _NAN
