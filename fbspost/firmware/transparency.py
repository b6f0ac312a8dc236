"""Firmware settings around the compensated motion: what makes the firmware run the written blocks
as written, and what gives it back the program's own settings.

Takes the flavor, the settings the program starts with (the profile's planner and firmware
values) and the program's changes to them as its lines pass (``note``); gives the lines that
make the firmware transparent (``apply``) and those that restore the program's settings
(``restore``), in the flavor's syntax, and header notes on what cannot be restored.

Why these values. The dense blocks already carry the command's speed changes: block to block
the speed steps by at most a_cmd / fs (10 mm/s at 10 m/s^2 and 1 kHz). The firmware ramps each
step at its acceleration A, inside the block, and so arrives (dv)^2 / (2 A v) late (v the higher
of the two speeds; at most dv / (2 A)) and at most (dv)^2 / (2 A) behind within the block.
Klipper (ACCEL = 1e8 mm/s^2): at most 0.05 us and 0.5 nm per junction, typically 0.005 us (dv
10, v 100); the writer makes that time up in the next block. 1e7 was not enough: the centripetal
limit below held a command that wiggles block to block at 130 mm/s travel back by 3-5 um, and
the ramps' time, made up only approximately, drifted 0.6 us/s (klippy's own planner on a sliced
print's first 1000 lines: 6.6 um largest distance from the command at 1e7, 0.7 um at 1e8). Marlin
and RepRapFirmware keep block accelerations in 32-bit steps/s^2 (times
2^24 / timer rate in Marlin): 1e6 mm/s^2 fits at up to 250 steps/mm, at most 5 us and 50 nm per
junction (Marlin: with M201 E raised too, a printing block's acceleration is otherwise its E limit
over the E per mm; the writer makes up these ramps' time as Klipper's).
Junctions: Klipper's limit R * scv^2 (sqrt2 - 1) (R = sin(t/2) / (1 - sin(t/2)), t the
angle between the blocks) does not depend on ACCEL; SQUARE_CORNER_VELOCITY 10000 mm/s lets every
junction turning less than 179 degrees pass at 500 mm/s, and its centripetal limit
move_d tan(t/2) A / 2 passes a turn of d at speed v once A > v d / block time, the command's own
normal acceleration. Marlin: J 0.3 mm (the most M205 J accepts) and jerk 1000 mm/s.
Klipper's minimum cruise ratio and Marlin's minimum segment time (M205 B) would slow short
blocks: 0. Input shaping on top of the compensation would correct twice: off.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

from ..profile import MachineProfile
from ..read.blocks import Block, Modal, PlannerLimits

KLIPPER_ACCEL_MM_S2 = 1e8
KLIPPER_SCV_MM_S = 1e4
STEPPED_ACCEL_MM_S2 = 1e6  # Marlin, RepRapFirmware
MARLIN_JUNCTION_DEVIATION_MM = 0.3
# RepRapFirmware's: lower, because RRF does not take a speed step up that it would ramp in under 10
# step clocks (RecalculateMove: at 1e6 mm/s^2, 13 mm/s) and cruises on at the slower speed: at 1e6
# the gear's first 2000 lines ran 0.94% long (1.3 s in such blocks) at 3.89 um RMS contour error,
# at 1e5 +0.54% at 3.29 um, at 3e4 +0.46% at 3.37 um (the RRF model, from an SD card); the
# ramps between the blocks' speeds that this leaves are made up (``Transparency.ramp_mm_s2``)
RRF_STEPPED_ACCEL_MM_S2 = 1e5
JERK_MM_S = 1000.0  # Marlin M205 X Y, RepRapFirmware M566 (mm/min there)
RRF_MIN_FEED_MM_S = 0.01  # RepRapFirmware M203 I: the lowest it takes (its default 0.5 runs slow blocks fast)
RRF_DEFAULT_MIN_FEED_MM_S = 0.5  # DefaultMinFeedrate, restored where the program sets none
_SHAPED_AXES = "XY"
# Marlin and RRF limit a printing block's acceleration by M201 E / (E per mm) too (planner.cpp
# LIMIT_ACCEL; RRF: per drive, E included): about 5000 / 0.033 mm/s^2, whose ramps would slow
# every block by microseconds
_M201_AXES = {"marlin": "XYE", "reprap": "XYE"}
# The program's own input shaping: Klipper SET_INPUT_SHAPER SHAPER_FREQ_X=..., Marlin M593 [X|Y] F...
_KLIPPER_SHAPER = re.compile(rb"^\s*SET_INPUT_SHAPER\b", re.IGNORECASE)
_KLIPPER_FREQ = re.compile(rb"SHAPER_FREQ_([XY])\s*=\s*([\d.]+)", re.IGNORECASE)
_MARLIN_SHAPER = re.compile(rb"^\s*M0*593(?![\d.])([^;]*)", re.IGNORECASE)
_BLEND = re.compile(rb"[Gg]\s*0*6\s*(?:4(?:\s*[PpQq]\s*[-+]?[\d.]+)*|1(?:\s*\.\s*1)?)(?![\d.])")


@dataclass(frozen=True)
class FirmwareSettings:
    """The settings the program has the firmware at (``None``: not known to fbspost)."""

    acceleration_mm_s2: float
    travel_acceleration_mm_s2: float | None = None  # Marlin, RRF: M204 T
    square_corner_velocity_mm_s: float | None = None  # Klipper; classic jerk (M205 X Y, M566)
    minimum_cruise_ratio: float | None = None  # Klipper
    max_accel_to_decel_mm_s2: float | None = None  # klippy before 2024, where the profile says so
    junction_deviation_mm: float | None = None  # Marlin M205 J
    min_segment_time_us: float | None = None  # Marlin M205 B
    axis_max_acceleration_mm_s2: dict[str, float] = field(default_factory=dict)  # M201
    shaper_frequency_hz: dict[str, float] = field(default_factory=dict)  # input shaping per axis
    blend_words: str | None = None  # LinuxCNC: the program's blending mode, as it wrote it (None: the startup's)
    startup_blend_mm: tuple[float, float] = (0.0, 0.0)  # LinuxCNC: the startup code's G64 P and Q (mm; 0: none)
    min_feed_mm_s: float | None = None  # RepRapFirmware M203 I (None: its default)
    max_velocity_mm_s: float | None = None  # Klipper max_velocity, along the path (None: not known, not raised)
    axis_max_velocity_mm_s: dict[str, float] = field(default_factory=dict)  # Marlin, RRF M203 as the program set it
    # the compensated command's own limit per axis (the profile's axes): what the raised limits let through
    command_velocity_mm_s: dict[str, float] = field(default_factory=dict)
    command_acceleration_mm_s2: dict[str, float] = field(default_factory=dict)

    @classmethod
    def from_profile(cls, profile: MachineProfile) -> FirmwareSettings:
        """What the firmware is configured with, as far as the profile tells."""
        fw = profile.firmware
        return cls(profile.planner_acceleration_mm_s2, startup_blend_mm=(fw.linuxcnc.g64_p_mm, fw.linuxcnc.g64_q_mm),
                   square_corner_velocity_mm_s=profile.planner_square_corner_velocity_mm_s,
                   minimum_cruise_ratio=fw.minimum_cruise_ratio, max_accel_to_decel_mm_s2=fw.max_accel_to_decel_mm_s2,
                   min_segment_time_us=fw.min_segment_time_s * 1e6, shaper_frequency_hz=dict(fw.shaper_frequency_hz),
                   max_velocity_mm_s=fw.max_velocity_mm_s,
                   command_velocity_mm_s={a: profile.axes[a].max_velocity_mm_s for a in "XYZ" if a in profile.axes},
                   command_acceleration_mm_s2={a: profile.axes[a].max_acceleration_mm_s2 for a in profile.axes})

    def restored_m201(self, flavor: str) -> dict[str, float]:
        """The M201 per axis the output restores: the program's; on RepRapFirmware else the profile's
        axis limits (its retractions and Z moves take M201 alone, M204 applies to X Y moves only:
        left raised, the copied moves ran at 1e5 mm/s^2, unlike the plan and the original)."""
        if flavor == "reprap":
            return {**self.command_acceleration_mm_s2, **self.axis_max_acceleration_mm_s2}
        return self.axis_max_acceleration_mm_s2

    def raised_velocity(self) -> tuple[float | None, dict[str, float]]:
        """The velocity limits to raise around the compensated motion: Klipper's max_velocity to what
        the axes allow together (None: not raised: not known, or not below that), the M203 axes the
        program set below the command's limit ({}: none)."""
        together = math.hypot(*self.command_velocity_mm_s.values())
        path = together if self.max_velocity_mm_s is not None and self.max_velocity_mm_s < together else None
        axes = {a: v for a, v in self.command_velocity_mm_s.items()
                if a in "XY" and self.axis_max_velocity_mm_s.get(a, math.inf) < v}
        return path, axes

    def changed(self, limits: PlannerLimits) -> FirmwareSettings:
        """These settings after a program line that changes ``limits``."""
        accel = limits.acceleration_mm_s2 or self.acceleration_mm_s2
        ratio, to_decel = limits.minimum_cruise_ratio, limits.accel_to_decel_mm_s2
        if to_decel is not None and self.max_accel_to_decel_mm_s2 is None and ratio is None:
            ratio = 1.0 - min(1.0, to_decel / accel)  # Klipper 2024 reads ACCEL_TO_DECEL so (as the planner)
        return replace(
            self, acceleration_mm_s2=accel,
            minimum_cruise_ratio=first_given(ratio, self.minimum_cruise_ratio),
            max_accel_to_decel_mm_s2=self.max_accel_to_decel_mm_s2 if self.max_accel_to_decel_mm_s2 is None
            else first_given(to_decel, self.max_accel_to_decel_mm_s2),
            travel_acceleration_mm_s2=first_given(limits.travel_acceleration_mm_s2, self.travel_acceleration_mm_s2),
            square_corner_velocity_mm_s=first_given(limits.square_corner_velocity_mm_s,
                                                    self.square_corner_velocity_mm_s),
            junction_deviation_mm=first_given(limits.junction_deviation_mm, self.junction_deviation_mm),
            axis_max_acceleration_mm_s2={**self.axis_max_acceleration_mm_s2, **limits.axis_max_acceleration_mm_s2},
            min_feed_mm_s=first_given(limits.min_feed_mm_s, self.min_feed_mm_s),
            max_velocity_mm_s=first_given(limits.max_velocity_mm_s, self.max_velocity_mm_s),
            axis_max_velocity_mm_s={**self.axis_max_velocity_mm_s, **limits.axis_max_velocity_mm_s})


def first_given(*values):
    return next((v for v in values if v is not None), None)


class Transparency:
    """Which settings are in force, and the lines that change them.

    Two parts are kept apart: the planner's limits (a program line that sets a limit undoes them,
    mid-motion too, and they are set again before the next compensated block) and input shaping
    (Klipper flushes its look-ahead to change it: it is switched only where the machine is at
    rest, before a run and before a copied move)."""

    def __init__(self, flavor: str, program: FirmwareSettings, tolerance_mm: float):
        self.flavor, self.program, self.tolerance_mm = flavor, program, tolerance_mm
        self.limits_set = self.shaping_off = False
        self.inches = False  # the program's units (G20) where the settings are restored
        self.left_off = ""  # the axes whose shaping the last restore could not turn on again
        # the acceleration the firmware then ramps between the blocks' speeds at, where the time
        # that loses is made up (Klipper: verified on its own planner; Marlin and RRF: the raised one)
        self.ramp_mm_s2 = {"klipper": KLIPPER_ACCEL_MM_S2, "marlin": STEPPED_ACCEL_MM_S2,
                           "reprap": RRF_STEPPED_ACCEL_MM_S2}.get(flavor, math.inf)

    def note(self, block: Block) -> None:
        """A copied program line: the program's settings (planner limits, LinuxCNC's blending mode
        G61, G61.1, G64 P Q) and the firmware's change with it."""
        self.inches = block.modal.inches
        if block.limits is not None:
            self.program = self.program.changed(block.limits)
            self.limits_set = False
        blend = _BLEND.search(block.raw) if self.flavor == "linuxcnc" else None
        if blend:
            self.program = replace(self.program, blend_words=" ".join(blend.group().decode().upper().split()))
            self.limits_set = False
        shaping = _program_shaping(self.flavor, block.raw)
        if shaping:  # the program's own: restored after the motion, and switched off again before it
            self.program = replace(self.program, shaper_frequency_hz={**self.program.shaper_frequency_hz, **shaping})
            self.shaping_off = False

    def header(self) -> list[str]:
        """Comments for the output's header: what the output sets, and what it cannot restore."""
        if self.flavor == "linuxcnc":
            return ["fbspost firmware settings: the compensated motion runs in G64 with the tolerance as P; "
                    "acceleration is the machine's INI setting"]
        notes = ["fbspost firmware settings: limits raised around the compensated motion (to run its blocks as "
                 "written), the program's own restored before every move copied unchanged and at the end"]
        program = self.program
        kept = [f"input shaping on {a}" for a in self.unknown_shaping()]
        if self.flavor in ("marlin", "reprap"):
            kept += [f"M201 {a}" for a in _M201_AXES[self.flavor] if a not in program.restored_m201(self.flavor)]
        if self.flavor == "marlin" and program.junction_deviation_mm is None:
            kept.append("M205 J")
        if kept:
            notes.append(
                f"fbspost firmware settings not known, so left as the output sets them after the compensated motion: "
                f"{', '.join(kept)} (give them in the profile's [firmware] table or the program)"
            )
        return notes

    def apply(self, at_rest: bool, modal: Modal) -> list[str]:
        """Lines that make the firmware transparent before a compensated block (empty: it is);
        ``at_rest``: the machine is at rest there (shaping may be switched)."""
        lines, self.inches = [], modal.inches
        if not self.limits_set:
            lines += transparent_limits(self.flavor, self.tolerance_mm / (25.4 if modal.inches else 1.0),
                                        self.program)
            self.limits_set = True
        if at_rest:
            lines += self.shaping_off_lines()
        return lines

    def shaping_off_lines(self) -> list[str]:
        """The lines that switch input shaping off, where the machine is at rest (empty: it is off)."""
        if self.shaping_off:
            return []
        self.shaping_off = True
        return _shaping_lines(self.flavor, {a: 0.0 for a in _SHAPED_AXES})

    def restore(self, shaping: bool = True) -> list[str]:
        """Lines that give the firmware back the program's settings (empty: it has them);
        ``shaping`` False: its limits only (before a move of E alone, which shaping does not touch)."""
        lines = _program_limits(self.flavor, self.program, self.inches) if self.limits_set else []
        self.limits_set = False
        if shaping and self.shaping_off:
            lines += _shaping_lines(self.flavor, self.program.shaper_frequency_hz)
            self.shaping_off = False
            self.left_off = self.unknown_shaping()
        return lines

    def unknown_shaping(self) -> str:
        """The axes whose input shaping the output turns off but cannot turn on again: neither the
        profile nor the program says what it was ("" for none, and where the firmware has none)."""
        if self.flavor not in ("klipper", "marlin", "reprap"):
            return ""
        known = {} if self.flavor == "reprap" else self.program.shaper_frequency_hz  # (RRF: the type is needed)
        return "".join(a for a in _SHAPED_AXES if a not in known)


def transparent_limits(flavor: str, tolerance: float, program: FirmwareSettings | None = None) -> list[str]:
    """The lines that raise the firmware's limits around the compensated motion, in ``flavor``'s
    syntax (``tolerance``: LinuxCNC's G64 P, in the program's units; ``program``: its velocity
    limits, raised where they are known to be below the command's, ``FirmwareSettings.raised_velocity``)."""
    path_mm_s, axes_mm_s = program.raised_velocity() if program is not None else (None, {})
    if flavor == "klipper":
        velocity = f" VELOCITY={_num(path_mm_s, 3)}" if path_mm_s is not None else ""
        return [f"SET_VELOCITY_LIMIT ACCEL={_num(KLIPPER_ACCEL_MM_S2)} ACCEL_TO_DECEL={_num(KLIPPER_ACCEL_MM_S2)} "
                f"MINIMUM_CRUISE_RATIO=0 SQUARE_CORNER_VELOCITY={_num(KLIPPER_SCV_MM_S)}{velocity}"]
    accel = _num(RRF_STEPPED_ACCEL_MM_S2 if flavor == "reprap" else STEPPED_ACCEL_MM_S2)
    stepped = [f"M201 X{accel} Y{accel} E{accel}", f"M204 P{accel} T{accel}"]
    if flavor == "marlin":
        return stepped + [f"M205 B0 J{_num(MARLIN_JUNCTION_DEVIATION_MM, 3)} X{_num(JERK_MM_S)} Y{_num(JERK_MM_S)}"] + \
            ([_m203(flavor, axes_mm_s)] if axes_mm_s else [])
    if flavor == "reprap":  # M203 I: RRF runs a move at 0.5 mm/s at least, the slowest blocks too fast
        return stepped + [f"M566 X{_num(JERK_MM_S * 60)} Y{_num(JERK_MM_S * 60)}",
                          _m203(flavor, axes_mm_s, RRF_MIN_FEED_MM_S)]
    # LinuxCNC: blend within the tolerance, never stop; Q0: no naive-CAM merging of the blocks
    # (Q is P when not given, and merged blocks would lose their speeds)
    return [f"G64 P{_num(tolerance, 6)} Q0"]


def _m203(flavor: str, axes_mm_s: dict[str, float], slowest_mm_s: float | None = None) -> str:
    """M203 with the axes' maximum feeds (and RRF's slowest, I), in the flavor's units (RRF: mm/min)."""
    scale = 60.0 if flavor == "reprap" else 1.0
    words = [f"{a}{_num(v * scale, 3)}" for a, v in axes_mm_s.items()]
    return " ".join(["M203", *words] + ([f"I{_num(slowest_mm_s * scale, 3)}"] if slowest_mm_s is not None else []))


def _program_limits(flavor: str, program: FirmwareSettings, inches: bool) -> list[str]:
    accel = _num(program.acceleration_mm_s2)
    travel = _num(first_given(program.travel_acceleration_mm_s2, program.acceleration_mm_s2))
    scv = program.square_corner_velocity_mm_s
    axes = program.restored_m201(flavor)
    # Marlin and RRF: M201 for X, Y and E, as the program or the profile gave them (else they stay raised)
    m201 = " ".join(f"{a}{_num(axes[a])}" for a in _M201_AXES.get(flavor, "") if a in axes)
    lines = [f"M201 {m201}"] if m201 and flavor in ("marlin", "reprap") else []
    if flavor == "klipper":
        # Klipper >= 2024 reads MINIMUM_CRUISE_RATIO (and ignores ACCEL_TO_DECEL then), klippy before reads
        # ACCEL_TO_DECEL only: both, each as the profile's firmware has it
        to_decel = program.max_accel_to_decel_mm_s2
        if to_decel is None:
            ratio = first_given(program.minimum_cruise_ratio, 0.5)
            to_decel = program.acceleration_mm_s2 * (1.0 - ratio)
        else:
            ratio = 1.0 - min(1.0, to_decel / program.acceleration_mm_s2)
        words = [f"ACCEL={accel}", f"ACCEL_TO_DECEL={_num(to_decel, 3)}", f"MINIMUM_CRUISE_RATIO={_num(ratio, 3)}"]
        if scv is not None:
            words.append(f"SQUARE_CORNER_VELOCITY={_num(scv, 3)}")
        if program.raised_velocity()[0] is not None:
            words.append(f"VELOCITY={_num(program.max_velocity_mm_s, 3)}")
        return [f"SET_VELOCITY_LIMIT {' '.join(words)}"]
    raised = {a: program.axis_max_velocity_mm_s[a] for a in program.raised_velocity()[1]}
    if flavor == "marlin":
        words = [f"B{_num(first_given(program.min_segment_time_us, 20000.0))}"]  # Marlin's default 20 ms
        if program.junction_deviation_mm is not None:
            words.append(f"J{_num(program.junction_deviation_mm, 4)}")
        if scv is not None:
            words += [f"X{_num(scv, 3)}", f"Y{_num(scv, 3)}"]
        lines += [f"M204 P{accel} T{travel}", f"M205 {' '.join(words)}"]
        return lines + ([_m203(flavor, raised)] if raised else [])
    if flavor == "reprap":
        jerk = [f"M566 X{_num(scv * 60, 3)} Y{_num(scv * 60, 3)}"] if scv is not None else []
        slowest = first_given(program.min_feed_mm_s, RRF_DEFAULT_MIN_FEED_MM_S)
        return lines + [f"M204 P{accel} T{travel}"] + jerk + [_m203(flavor, raised, slowest)]
    if program.blend_words is not None:
        return [program.blend_words]
    # the startup code's G64 P Q, in the program's units where they are restored; Q always written
    # with P (without it Q is P)
    p, q = (value / (25.4 if inches else 1.0) for value in program.startup_blend_mm)
    return [f"G64 P{_num(p, 6)} Q{_num(q, 6)}" if p or q else "G64"]


def _program_shaping(flavor: str, raw: bytes) -> dict[str, float]:
    """The input shaping frequencies (Hz, 0: off) a program line sets, per axis ({}: none)."""
    if flavor == "klipper" and _KLIPPER_SHAPER.match(raw):
        return {a.decode().upper(): float(f) for a, f in _KLIPPER_FREQ.findall(raw.split(b"#", 1)[0])}
    marlin = _MARLIN_SHAPER.match(raw) if flavor == "marlin" else None
    if marlin:
        words = dict(re.findall(r"([XYFD])\s*([-+]?[\d.]*)", marlin.group(1).decode(errors="replace").upper()))
        if re.fullmatch(r"\d+\.?\d*|\.\d+", words.get("F", "")):
            axes = [a for a in _SHAPED_AXES if a in words] or list(_SHAPED_AXES)  # (no X or Y: both)
            return {a: float(words["F"]) for a in axes}
    return {}


def _shaping_lines(flavor: str, frequency_hz: dict[str, float]) -> list[str]:
    """The flavor's input shaping set to ``frequency_hz`` per axis (0: off; axes not given: none)."""
    axes = [a for a in _SHAPED_AXES if a in frequency_hz]
    if not axes or flavor == "linuxcnc":
        return []
    if flavor == "klipper":
        return ["SET_INPUT_SHAPER " + " ".join(f"SHAPER_FREQ_{a}={_num(frequency_hz[a], 3)}" for a in axes)]
    if flavor == "marlin":
        if all(frequency_hz[a] == 0.0 for a in axes):
            return ["M593 F0"]
        return [f"M593 {a} F{_num(frequency_hz[a], 3)}" for a in axes]
    # RepRapFirmware: restoring needs the shaper's type, not known to fbspost
    return ['M593 P"none"'] if all(frequency_hz[a] == 0.0 for a in axes) else []


def _num(value: float, decimals: int = 0) -> str:
    """Shortest decimal with at most ``decimals`` places: 1e7 -> "10000000"; 0.30, 4 -> "0.3"."""
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text
