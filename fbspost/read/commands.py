"""The reader's commands other than motion: limits, dwells, the position, the flavors' own.

Takes a line's M codes and its G codes that are neither motion nor a modal setting, with its
words (``words.Words``), and the machine state they change (``state.State``); gives what they do
to the line (``Effects``, gathered in LinuxCNC's order of execution) or its ``Block``: Klipper's
extended commands and macros (``Commands.extended``), Marlin's commands of free text
(``Commands.text``), the M codes (``Commands.mcodes``: M201/M203/M204/M205/M566 per flavor as
``planner_limits``), G4, G92 and its kin, homing, probing and offsets (``Commands.other_gcode``),
and LinuxCNC's spindle (``Spindle``: on, its speed, and G33 timed by it).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from .blocks import AXES, DEGREES, E_AXIS, EXPAND_HINT, Block, Kind, NeedsInterpreter, PlannerLimits
from .words import EXT_PARAM

# M codes that pass while the machine keeps moving (no motion, no waiting)
_PASS_M = {3.0, 4.0, 5.0, 7.0, 8.0, 9.0, 18.0, 73.0, 84.0, 104.0, 105.0, 106.0, 107.0, 114.0,
           115.0, 117.0, 118.0, 140.0, 141.0, 221.0, 486.0, 900.0}
# M codes after which the machine is at rest where it was
_STOP_M = {0.0, 1.0, 2.0, 6.0, 30.0, 60.0, 109.0, 116.0, 190.0, 191.0, 400.0, 593.0, 600.0}  # (M593: input shaping)
_LIMIT_M = {201.0, 203.0, 204.0, 205.0, 566.0}
_KLIPPER_PASS = {"SET_FAN_SPEED", "SET_PRESSURE_ADVANCE", "SET_HEATER_TEMPERATURE",
                 "EXCLUDE_OBJECT_START", "EXCLUDE_OBJECT_END", "EXCLUDE_OBJECT_DEFINE"}
_IO_M = {62.0, 63.0, 64.0, 65.0, 66.0, 67.0, 68.0}  # LinuxCNC I/O: E P Q L are its words
_LINUXCNC_PASS_M = {48.0, 49.0, 50.0, 51.0, 52.0, 53.0, 61.0, 62.0, 63.0, 64.0, 65.0, 67.0, 68.0}
# Marlin-style commands whose arguments are free text (messages, file names, version strings).
TEXT_CMD = re.compile(r"[Mm]\s*0*(?:117|118|23|28|30|32|33|928|115|0|1)(?![\d.])")


@dataclass
class Effects:
    """What a line's commands do, gathered in LinuxCNC's order of execution before its motion."""

    kind: Kind = Kind.PASS
    dwell: float = 0.0
    limits: PlannerLimits | None = None
    unknown: bool = False  # an unknown command: XYZ (and absolute E) unknown afterwards
    modal_changed: bool = False
    motion: float | None = None
    axis_words_used: bool = False  # a non-motion command took the axis words
    sets_position: tuple[int, ...] = ()


class Commands:
    """The commands that set limits or the position, and the flavors' own: what they need besides
    the line is the machine state, the home position (G28), the spindle (M3/M4/M5) and the offsets
    G92.2 keeps for G92.3, which it holds."""

    def __init__(self, words, state, spindle, home_mm=(0.0, 0.0, 0.0)):
        self.words, self.state, self.spindle = words, state, spindle
        self.home_mm = [float(v) for v in home_mm]
        self.saved_off = None  # G92.2 keeps the offsets here for G92.3

    def _forget_machine_g92(self) -> None:
        """LinuxCNC keeps G92 offsets from program to program, which the file does not hold: a
        program's G92.1, G92.2 or G92.3 takes them off or puts them back, so the tool's place in
        the program's frame moves by offsets not known here (a G92 of the program's own is
        relative to where the tool is and carries them on)."""
        if self.state.cnc:
            self.state.forget(self.state.frame)

    def extended(self, n, raw, code) -> Block:
        """Klipper extended commands and macros, RRF meta commands: a name, then NAME=VALUE."""
        name = re.match(r"[A-Za-z_][A-Za-z0-9_]*", code).group().upper()
        if name == "SET_VELOCITY_LIMIT":
            values = {}
            for key, value in EXT_PARAM.findall(code[len(name):]):
                key = key.upper()
                if key in ("VELOCITY", "ACCEL", "SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO", "ACCEL_TO_DECEL"):
                    values[key] = self.words.number(n, key + "=", value.strip('"'))
            for key, value in values.items():
                if value < 0 or (value == 0 and key not in ("SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO")):
                    raise self.words.error(n, f"{key}={value:g} must be positive")
            if values.get("MINIMUM_CRUISE_RATIO", 0.0) >= 1.0:
                raise self.words.error(n, f"MINIMUM_CRUISE_RATIO={values['MINIMUM_CRUISE_RATIO']:g} must be below 1")
            limits = None
            if values:
                limits = PlannerLimits(
                    acceleration_mm_s2=values.get("ACCEL"),
                    travel_acceleration_mm_s2=values.get("ACCEL"),
                    max_velocity_mm_s=values.get("VELOCITY"),
                    square_corner_velocity_mm_s=values.get("SQUARE_CORNER_VELOCITY"),
                    minimum_cruise_ratio=values.get("MINIMUM_CRUISE_RATIO"),
                    accel_to_decel_mm_s2=values.get("ACCEL_TO_DECEL"),
                )
            return self.state.block(n, raw, Kind.PASS, limits=limits)
        if name in _KLIPPER_PASS:
            return self.state.block(n, raw, Kind.PASS)
        if name == "SET_INPUT_SHAPER":  # Klipper flushes its look-ahead to change shaping: at rest
            return self.state.block(n, raw, Kind.STOP)
        # a macro or an unknown command: it may move anything
        self.state.forget(self.state.frame, e_too=True)
        return self.state.block(n, raw, Kind.STOP)

    def text(self, n, raw, code) -> Block:
        """A Marlin-style command whose arguments are free text (``TEXT_CMD``): passes, or a STOP."""
        number = float(re.match(r"[Mm]\s*(\d+)", code).group(1))
        if number in _PASS_M:
            return self.state.block(n, raw, Kind.PASS)
        if number not in _STOP_M:  # M23/M28/M32/M33/M928: files, maybe printed from here
            self.state.forget(self.state.frame, e_too=True)
        return self.state.block(n, raw, Kind.STOP)

    def dwell(self, n, params, junk) -> float:
        if junk is not None:
            raise self.words.error(n, junk)
        s = params.get("S")
        p = params.get("P")
        if self.state.cnc:
            seconds = self.words.number(n, "P", p) if p is not None else 0.0
        elif s is not None:
            seconds = self.words.number(n, "S", s)
        elif p is not None:
            seconds = self.words.number(n, "P", p) / 1000.0
        else:
            seconds = 0.0
        if seconds < 0.0:
            raise self.words.error(n, "dwell time must not be negative")
        return seconds

    def g92(self, n, params, dups, junk, scale) -> tuple[int, ...]:
        """Sets the program position of the axes named (indices into AXES, which it gives)."""
        if junk is not None:
            raise self.words.error(n, junk)
        if dups and dups & set("XYZE"):
            raise self.words.error(n, f"{''.join(sorted(dups))} given twice")
        values = {}
        for i in (*self.state.frame, E_AXIS):
            v = params.get(AXES[i])
            if v is not None:  # E follows G20/G21 too (Marlin)
                values[i] = self.words.number(n, AXES[i], v) * (1.0 if i in DEGREES else scale)
        if not values:
            if self.state.flavor == "klipper":  # Klipper: G92 alone zeroes all axes
                values = {0: 0.0, 1: 0.0, 2: 0.0, 3: 0.0}
            elif self.state.cnc:
                raise self.words.error(n, "G92 needs at least one axis word")
            else:  # Marlin, RRF: nothing to set
                return ()
        pos, off = self.state.pos, self.state.off
        for i, v in values.items():
            if pos[i] != pos[i]:  # unknown machine position: it is now known in this frame
                pos[i] = v + off[i]
            else:
                off[i] = pos[i] - v
        return tuple(values)

    def _reprap_tool_temperatures(self, params) -> bool:
        """RepRapFirmware's G10 P.. S.. R..: a tool's temperatures, no offset (X Y Z), no
        coordinate system (L), no retraction (G10 without P, R and S)."""
        return (self.state.flavor == "reprap" and "P" in params and ("S" in params or "R" in params)
                and not any(a in params for a in "LXYZ"))

    def mcodes(self, n, mcodes, params, junk, scale, fx: Effects) -> None:
        for m in mcodes:
            if self.state.cnc and m in (2.0, 3.0, 4.0, 5.0, 19.0, 30.0):  # the spindle, for G33's speed
                self.spindle.on = m == 3.0 or m == 4.0
            if m == 82.0 or m == 83.0:
                self.state.abs_e = m == 82.0
                fx.modal_changed = True
            elif self.state.cnc and 70.0 <= m <= 73.0:
                raise NeedsInterpreter(self.words.path, n, f"modal state save and restore (M{m:g})",
                                       f"modal state save and restore (M{m:g}) is not supported: {EXPAND_HINT}")
            elif self.state.cnc and (m in _LINUXCNC_PASS_M or m == 66.0):
                fx.axis_words_used |= m in _IO_M  # M66 E0 L3: the input's number, not an extruder
                if m == 66.0:
                    fx.kind = Kind.STOP  # waits for an input
            elif m in _PASS_M or 862.0 <= m < 863.0:
                pass
            elif m in _LIMIT_M:
                if junk is not None:
                    raise self.words.error(n, junk)
                fx.limits = planner_limits(self.words, self.state.flavor, n, m, params, scale)
                if fx.limits is False:
                    fx.unknown = True
                    fx.limits = None
            elif m in _STOP_M:
                fx.kind = Kind.STOP
            else:  # M98 (RRF macro call) and every unknown M code
                fx.unknown = True

    def other_gcode(self, n, g, params, dups, junk, scale, fx: Effects) -> None:
        """A G code that is neither motion nor a modal setting: dwell, G92 and its kin, homing,
        probing, offsets, and the unknown ones."""
        if g == 4.0:
            fx.kind = Kind.STOP
            fx.dwell = self.dwell(n, params, junk)
        elif g == 92.0:
            fx.axis_words_used = True
            fx.sets_position = self.g92(n, params, dups, junk, scale)
            fx.modal_changed |= bool(fx.sets_position)
        elif g == 92.1 or (self.state.cnc and g == 92.2):
            off, g5x = self.state.off, self.state.g5x
            # G92's own part kept (the work offsets' taken off: G92.3 restores it in the system then in use)
            self.saved_off = [o - w for o, w in zip(off, g5x, strict=True)] if g == 92.2 else None
            for i in self.state.frame:
                off[i] = g5x[i]
            fx.modal_changed = True
            self._forget_machine_g92()
        elif g == 92.3 and self.state.cnc:
            if self.saved_off is not None:
                self.state.off = [o + w for o, w in zip(self.saved_off, self.state.g5x, strict=True)]
                self.saved_off = None
                fx.modal_changed = True
            self._forget_machine_g92()
        elif g == 28.0:
            fx.axis_words_used = True
            named = [i for i in self.state.frame if AXES[i] in params] or self.state.frame
            if self.state.cnc:  # LinuxCNC: to the position stored in #5161.., not in the file
                self.state.forget(named)
            else:  # homing: the homed axes are at the machine's home position
                for i in named:
                    self.state.pos[i] = self.home_mm[i]
            fx.kind = Kind.STOP
        elif g == 29.0 or g == 30.0 or 38.0 <= g < 39.0:
            fx.axis_words_used = True
            self.state.forget(self.state.frame)
            fx.kind = Kind.STOP
        elif g == 10.0 and self._reprap_tool_temperatures(params):
            pass  # RRF sets them at once, the motion going on (GCodes::SetOrReportOffsets: no lock, no wait)
        elif g == 10.0 or g == 11.0:
            fx.axis_words_used = True
            fx.kind = Kind.STOP
            if self.state.cnc or "L" in params or any(a in params for a in "XYZ"):
                fx.unknown = True  # coordinate system or tool offsets
                self.state.work_offsets = {}  # the parameter file's no longer
        elif self.state.cnc and 43.0 <= g < 44.0:
            self.state.tool_length = True
            fx.axis_words_used = True
            fx.unknown = True
        else:  # G53, G60/G61 (Marlin), G80 (Prusa mesh levelling), ... and unknown G codes
            fx.axis_words_used = True
            fx.unknown = True


def planner_limits(words, flavor, n, m, params, scale):
    """PlannerLimits of M201/M203/M204/M205/M566, None if nothing is set, False if unknown."""
    def value(letter, factor=1.0, zero_ok=False):
        v = params.get(letter)
        if v is None:
            return None
        x = words.number(n, letter, v) * factor
        if x < 0.0 or (x == 0.0 and not zero_ok):
            raise words.error(n, f"M{m:g} {letter}{v} must be {'non-negative' if zero_ok else 'positive'}")
        return x

    if m == 204.0:
        s, p, t = value("S", scale), value("P", scale), value("T", scale)
        if flavor == "klipper":  # Klipper: one acceleration, S or min(P, T)
            if s is None and p is not None and t is not None:
                s = min(p, t)
            return PlannerLimits(s, s) if s is not None else None
        accel = p if p is not None else s
        travel = t if t is not None else s
        if accel is None and travel is None:
            return None
        return PlannerLimits(acceleration_mm_s2=accel, travel_acceleration_mm_s2=travel)
    if m == 201.0 or m == 203.0:
        factor = scale / 60.0 if (m == 203.0 and flavor == "reprap") else scale
        axes = {a: x for a in AXES if (x := value(a, factor)) is not None}
        slowest = value("I", factor) if (m == 203.0 and flavor == "reprap") else None
        if not axes and slowest is None:
            return None
        if m == 201.0:
            return PlannerLimits(axis_max_acceleration_mm_s2=axes)
        return PlannerLimits(axis_max_velocity_mm_s=axes, min_feed_mm_s=slowest)
    if m == 205.0:
        j = value("J", scale)
        jerks = [x for a in "XY" if (x := value(a, scale, zero_ok=True)) is not None]
        if j is None and not jerks:
            return None
        return PlannerLimits(junction_deviation_mm=j, square_corner_velocity_mm_s=min(jerks) if jerks else None)
    # M566: RRF jerk, mm/min
    if flavor != "reprap":
        return False
    jerks = [x for a in "XY" if (x := value(a, scale / 60.0, zero_ok=True)) is not None]
    return PlannerLimits(square_corner_velocity_mm_s=min(jerks)) if jerks else None

class Spindle:
    """LinuxCNC's spindle as the program sets it, for G33: whether it turns, and how fast."""

    def __init__(self, words):
        self.words = words
        self.rpm = None  # LinuxCNC's S (rev/min; under G96 a surface speed: css)
        self.on = False  # M3/M4 (until M5, M19, M2/M30)
        self.css = False  # G96 constant surface speed

    def synced(self, n, raw, params, start, target, scale, state) -> Block:
        """LinuxCNC's G33: a move at K (distance along its path) per spindle revolution. A rest of
        the compensated motion, copied as written (never compensated): a STOP at its end that
        lasts its length over K S / 60 (0 from an unknown start; the wait for the spindle's
        index, up to a revolution, is not counted)."""
        pitch_mm = self.words.number(n, "K", params.get("K")) * scale
        if pitch_mm <= 0.0:
            raise self.words.error(n, "G33 needs K > 0 (the distance per spindle revolution)")
        if not self.on or self.css or not (self.rpm or 0.0) > 0.0:
            raise self.words.error(n, "G33 needs the spindle turning at a known speed (M3/M4 and S, not G96)")
        state.pos = target
        # along X Y Z (unnamed axes hold the very same floats, NaN included; NaN: an unknown start)
        length_mm = math.hypot(*(t - s for s, t in zip(start[:3], target[:3], strict=True) if s is not t))
        dwell_s = length_mm / (pitch_mm * self.rpm / 60.0) if length_mm == length_mm else 0.0
        return Block(n, raw, Kind.STOP, state.modal, np.array(target), dwell_s=dwell_s)
