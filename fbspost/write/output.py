"""The output program's text, counted, and its line rate.

Takes lines to write (the written blocks' text, the writer's own lines, dwells) and the
program's lines to copy; gives them to the binary stream in order, counting them in
``WriteStats`` and the most lines in any second (``Output``, ``_LineRate``). Also the lines of
a flavor's dwell (``dwell_line``) and of a change of modes (``mode_lines``).
"""
from __future__ import annotations

import numpy as np

from ..read.blocks import Modal
from .options import WriteStats


def mode_lines(flavor: str, have: Modal, want: Modal) -> list[str]:
    """Lines that bring the controller from modes ``have`` to ``want`` (plane, distance modes,
    units)."""
    lines = [f"G{want.plane}"] if have.plane != want.plane else []
    if have.inches != want.inches:
        lines.append("G20" if want.inches else "G21")
    if have.absolute_xyz != want.absolute_xyz:
        lines.append("G90" if want.absolute_xyz else "G91")
        if flavor != "linuxcnc":  # G90/G91 set E's mode too
            have = Modal(want.absolute_xyz, want.absolute_xyz, want.inches, have.offsets_mm)
    if flavor != "linuxcnc" and have.absolute_e != want.absolute_e:
        lines.append("M82" if want.absolute_e else "M83")
    return lines


def dwell_line(flavor: str, dwell_s: float) -> tuple[str, float]:
    """The flavor's G4 for about ``dwell_s`` seconds, and how long it dwells: Klipper and LinuxCNC
    read a fraction (to the microsecond here), Marlin and RepRapFirmware whole milliseconds."""
    if flavor in ("klipper", "linuxcnc"):
        us = round(dwell_s * 1e6)
        value = us / 1e6 if flavor == "linuxcnc" else us / 1e3  # LinuxCNC: P in seconds
        return f"G4 P{value:.6f}".rstrip("0").rstrip("."), us / 1e6
    ms = round(dwell_s * 1e3)
    return f"G4 P{ms}", ms / 1e3



class _LineRate:
    """The most lines in any second, from the lines' times as they come (non-decreasing)."""

    def __init__(self):
        self.recent = np.zeros(0)  # the times within a second of the last
        self.max_per_s = 0

    def add(self, times_s) -> None:
        times = np.concatenate([self.recent, np.atleast_1d(np.asarray(times_s, dtype=float))])
        if len(times) > len(self.recent):
            new = np.arange(len(self.recent), len(times))
            inside = new + 1 - np.searchsorted(times, times[new] - 1.0, "right")  # in (t - 1 s, t]
            self.max_per_s = max(self.max_per_s, int(inside.max()))
            self.recent = times[np.searchsorted(times, times[-1] - 1.0, "right"):]



class Output:
    """The output program's text. Takes lines to write (each ended by the program's newline,
    counted in ``stats`` and in the line rate at ``written_until_s``) and the program's lines to
    copy as they are; a copied line without a line ending gets one when more follows it."""

    def __init__(self, out, flavor: str):
        self._out, self._flavor = out, flavor
        self.stats = WriteStats()
        self.newline = b"\n"
        self.rate = _LineRate()
        self.written_until_s = 0.0  # the end of the last block written: the time of lines written now
        self._unterminated = False  # the last copied line had no line ending (the end of the file)

    def text(self, text: bytes, count: int) -> None:
        """Write ``count`` lines, each ended by the newline."""
        if count:
            self._out.write((self.newline if self._unterminated else b"") + text)
            self.stats.lines_out += count
            self._unterminated = False

    def lines(self, *lines: str) -> None:
        self.text(b"".join(x.encode() + self.newline for x in lines), len(lines))
        self.rate.add([self.written_until_s] * len(lines))

    def dwell(self, seconds: float) -> float:
        """A G4 for about ``seconds`` (none where it rounds to nothing); gives how long it dwells."""
        line, dwell_s = dwell_line(self._flavor, seconds)
        if dwell_s > 0:
            self.lines(line)
        return dwell_s

    def copy(self, raw: bytes) -> None:
        """One of the program's lines, byte for byte."""
        self._out.write(raw)
        self._unterminated = not raw.endswith((b"\n", b"\r"))
        self.stats.lines_out += 1
        self.stats.passthrough_lines += 1

