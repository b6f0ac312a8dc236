"""Machine profiles: read and validate a TOML profile, list the bundled ones, write one.

Takes a bundled profile name or a path to a ``.toml`` file; gives a ``MachineProfile`` with the
sample rate, the planner settings, the firmware's own limits (``[firmware]``, optional: Klipper's
defaults when absent) and, per compensated axis, its kinematic limits and modal dynamics. The modal
residues are rescaled so every axis has a DC gain of exactly 1 (a
position-controlled axis holds a constant command exactly).

Errors are raised as ``ProfileError`` with a one-line message naming the file and the key.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

AXIS_NAMES = "XYZABCUVWE"


class ProfileError(ValueError):
    """A profile that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Mode:
    """One mode (alpha + beta s) / (s^2 + 2 damping w s + w^2), w = 2 pi frequency_hz."""

    frequency_hz: float
    damping: float
    alpha: float  # 1/s^2
    beta: float  # 1/s
    frequency_tolerance: float = 0.0  # relative spread of frequency_hz the compensation must cover
    damping_tolerance: float = 0.0  # relative spread of damping (docs/robust.md)

    @property
    def omega_rad_s(self) -> float:
        return 2.0 * math.pi * self.frequency_hz


@dataclass(frozen=True)
class PositionTable:
    """An axis' modes against an axis' position: every frequency times ``frequency_scales``
    at ``positions_mm`` (increasing), linear between them, flat beyond them."""

    axis: str
    positions_mm: tuple[float, ...]
    frequency_scales: tuple[float, ...]


@dataclass(frozen=True)
class AxisProfile:
    name: str
    max_velocity_mm_s: float
    max_acceleration_mm_s2: float
    max_jerk_mm_s3: float | None
    modes: tuple[Mode, ...]  # DC gain normalized to 1; empty: the axis is not compensated
    moving_mass_kg: float | None = None  # the axis carries the print: the modes' mass, the print adds to it
    filament_density_g_cm3: float = 1.24  # of what is printed onto it (PLA)
    modes_by_position: PositionTable | None = None  # the modes change along an axis
    position_min_mm: float | None = None  # the machine's travel (None: the firmware's default, ``with_travel``)
    position_max_mm: float | None = None


@dataclass(frozen=True)
class LinuxCNCSettings:
    """The INI and startup settings LinuxCNC's trajectory planner runs with (LinuxCNC 2.9's
    defaults): ``[firmware]`` keys without the unit suffix (``servo_period``, ``g64_p``, ...)."""

    servo_period_s: float = 0.001  # [EMCMOT] SERVO_PERIOD (ns there)
    arc_blend_enable: bool = True  # [TRAJ] ARC_BLEND_ENABLE
    arc_blend_fallback_enable: bool = False  # [TRAJ] ARC_BLEND_FALLBACK_ENABLE
    arc_blend_optimization_depth: int = 50  # [TRAJ] ARC_BLEND_OPTIMIZATION_DEPTH
    arc_blend_gap_cycles: int = 4  # [TRAJ] ARC_BLEND_GAP_CYCLES
    arc_blend_ramp_freq_hz: float = 100.0  # [TRAJ] ARC_BLEND_RAMP_FREQ
    arc_blend_kink_ratio: float = 0.1  # [TRAJ] ARC_BLEND_KINK_RATIO
    # [TRAJ] MAX_LINEAR_VELOCITY, the speed along the path, which no G-code raises (inf: none below
    # the axes'; LinuxCNC's sample configurations set it)
    max_linear_velocity_mm_s: float = math.inf
    # [RS274NGC] RS274NGC_STARTUP_CODE's G64 P and Q (mm): the blending the machine starts in
    # and the output restores (0: LinuxCNC's G64 without P or Q)
    g64_p_mm: float = 0.0
    g64_q_mm: float = 0.0
    # [RS274NGC] PARAMETER_FILE, LinuxCNC's var file ("": not given), and G54..G59.3's X Y Z offsets
    # (mm) read from it as the profile loads (None: a system rotated by R): a switch between them
    # is then a planned move, not a jump from an unknown place
    parameter_file: str = ""
    work_offsets_mm: tuple[tuple[float, float, float] | None, ...] = ()


# [firmware] key -> LinuxCNCSettings field
_LINUXCNC_KEYS = {"servo_period": "servo_period_s", "arc_blend_enable": "arc_blend_enable",
                  "arc_blend_fallback_enable": "arc_blend_fallback_enable",
                  "arc_blend_optimization_depth": "arc_blend_optimization_depth",
                  "arc_blend_gap_cycles": "arc_blend_gap_cycles", "arc_blend_ramp_freq": "arc_blend_ramp_freq_hz",
                  "arc_blend_kink_ratio": "arc_blend_kink_ratio", "g64_p": "g64_p_mm", "g64_q": "g64_q_mm",
                  "max_linear_velocity": "max_linear_velocity_mm_s"}


@dataclass(frozen=True)
class FirmwareProfile:
    """What the machine's firmware does with the blocks it is sent (``[firmware]``). Klipper's
    names and defaults (klippy/toolhead.py, kinematics/extruder.py) where it has the setting."""

    steps_per_mm: dict[str, float] = field(default_factory=dict)  # per axis; an axis not given: unknown
    # the user's input shaping (restored after the compensated motion)
    shaper_frequency_hz: dict[str, float] = field(default_factory=dict)
    block_buffer: int = 16  # Marlin BLOCK_BUFFER_SIZE: look-ahead over this many blocks
    max_line_rate_hz: float | None = None  # most lines per second the machine takes (None: no limit)
    max_velocity_mm_s: float | None = None  # Klipper max_velocity (None: the slower of X and Y's max_velocity)
    minimum_cruise_ratio: float = 0.5  # Klipper >= 2024: accel_to_decel = accel * (1 - ratio)
    max_accel_to_decel_mm_s2: float | None = None  # klippy before 2024 (fixed, min'd with accel): replaces the ratio
    instantaneous_corner_velocity_mm_s: float = 1.0  # the extruder's speed change allowed at a junction
    max_extrude_only_velocity_mm_s: float | None = None  # None: Klipper's max_velocity * extrude ratio
    max_extrude_only_accel_mm_s2: float | None = None  # None: Klipper's max_accel * extrude ratio
    filament_diameter_mm: float = 1.75
    nozzle_diameter_mm: float = 0.4
    min_segment_time_s: float = 0.02  # Marlin MIN_SEGMENT_TIME (M205 B) while the buffer is under half full
    min_steps_per_segment: int = 6  # Marlin MIN_STEPS_PER_SEGMENT: shorter blocks are merged with the next
    dda_ring_length: int = 50  # RepRapFirmware's DDA ring (M595 P; Move.h DdaRingLength on Duet 3)
    flavor: str | None = None  # the machine's firmware (one of FLAVORS): wins over the file's hints
    linuxcnc: LinuxCNCSettings = field(default_factory=LinuxCNCSettings)

    @property
    def extrude_ratio(self) -> float:
        """Klipper's def_max_extrude_ratio: filament mm per mm of path at 4 nozzle^2 cross-section."""
        return 4.0 * self.nozzle_diameter_mm**2 / (math.pi * (0.5 * self.filament_diameter_mm) ** 2)


@dataclass(frozen=True)
class MachineProfile:
    name: str
    description: str
    source: str  # the file it was read from
    sample_rate_hz: float
    planner_acceleration_mm_s2: float
    planner_square_corner_velocity_mm_s: float
    axes: dict[str, AxisProfile]
    firmware: FirmwareProfile = field(default_factory=FirmwareProfile)
    home_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # X Y Z where G28 leaves the homed axes

    @property
    def work_offsets_mm(self) -> tuple:
        """LinuxCNC's G54..G59.3 X Y Z offsets from its parameter file (empty: not given)."""
        return self.firmware.linuxcnc.work_offsets_mm

    @property
    def toolhead_max_velocity_mm_s(self) -> float:
        """Klipper's max_velocity: the firmware table's, else the slower of X and Y (inf: neither)."""
        if self.firmware.max_velocity_mm_s is not None:
            return self.firmware.max_velocity_mm_s
        return min((self.axes[a].max_velocity_mm_s for a in "XY" if a in self.axes), default=math.inf)

    def path_velocity_mm_s(self, firmware: str | None) -> float:
        """The speed along the path ``firmware`` caps a program at: Klipper's max_velocity,
        LinuxCNC's [TRAJ] MAX_LINEAR_VELOCITY (which no G-code raises); inf for the others (Marlin's
        and RepRapFirmware's M203 cap each axis)."""
        if firmware == "klipper":
            return self.toolhead_max_velocity_mm_s
        return self.firmware.linuxcnc.max_linear_velocity_mm_s if firmware == "linuxcnc" else math.inf

    @property
    def extrude_only_velocity_mm_s(self) -> float:
        """max_extrude_only_velocity: the table's, else Klipper's default max_velocity * ratio."""
        return self._extrude_only(self.firmware.max_extrude_only_velocity_mm_s, self.toolhead_max_velocity_mm_s)

    @property
    def extrude_only_accel_mm_s2(self) -> float:
        """max_extrude_only_accel: the table's, else Klipper's default max_accel * ratio."""
        return self._extrude_only(self.firmware.max_extrude_only_accel_mm_s2, self.planner_acceleration_mm_s2)

    def _extrude_only(self, given: float | None, toolhead_limit: float) -> float:
        return given if given is not None else toolhead_limit * self.firmware.extrude_ratio

    def travel_mm(self, axes: str) -> tuple[list[float], list[float]]:
        """The lowest and the highest position of each of ``axes`` (-inf / inf where not given)."""
        given = [self.axes.get(a) for a in axes]
        return ([-math.inf if a is None or a.position_min_mm is None else a.position_min_mm for a in given],
                [math.inf if a is None or a.position_max_mm is None else a.position_max_mm for a in given])


def with_travel(profile: MachineProfile, flavor: str) -> MachineProfile:
    """``profile`` with the firmware's default travel where it gives none: Klipper's
    ``position_min`` (0), Marlin's X_MIN_POS and Y_MIN_POS and RepRapFirmware's M208 minimum (0 in
    their example configurations) on X and Y, lowered to the home position if that is below;
    LinuxCNC has none (its INI gives the travel: the profile must)."""
    if flavor == "linuxcnc":
        return profile
    axes = dict(profile.axes)
    for a, home_mm in zip("XY", profile.home_mm[:2], strict=True):
        if a in axes and axes[a].position_min_mm is None:
            axes[a] = replace(axes[a], position_min_mm=min(0.0, home_mm))
    return replace(profile, axes=axes)


_TOP_KEYS = {"name", "description", "motion", "planner", "firmware", "axes", "home"}
_HOME_KEYS = {"X", "Y", "Z"}
_MOTION_KEYS = {"sample_rate"}
_PLANNER_KEYS = {"acceleration", "square_corner_velocity"}
_TOLERANCE_KEYS = ("frequency_tolerance", "damping_tolerance")
_AXIS_KEYS = {
    "max_velocity",
    "max_acceleration",
    "max_jerk",
    "modes",
    "moving_mass",
    "filament_density",
    "modes_by_position",
    "position_min",
    "position_max",
    *_TOLERANCE_KEYS,
}
_POSITION_KEYS = {"axis", "position", "frequency_scale"}
_MODE_KEYS = {"frequency", "damping", "alpha", "beta", *_TOLERANCE_KEYS}
# [firmware] key -> FirmwareProfile field, for the optional positive numbers
_FIRMWARE_NUMBERS = {
    "max_line_rate": "max_line_rate_hz", "max_velocity": "max_velocity_mm_s",
    "max_accel_to_decel": "max_accel_to_decel_mm_s2",
    "max_extrude_only_velocity": "max_extrude_only_velocity_mm_s",
    "max_extrude_only_accel": "max_extrude_only_accel_mm_s2",
    "filament_diameter": "filament_diameter_mm", "nozzle_diameter": "nozzle_diameter_mm",
}
FLAVORS = ("marlin", "klipper", "reprap", "linuxcnc")  # the firmwares fbspost writes for
_FIRMWARE_KEYS = {*_FIRMWARE_NUMBERS, "flavor", "steps_per_mm", "shaper_frequency", "block_buffer",
                  "minimum_cruise_ratio", "instantaneous_corner_velocity", "min_segment_time",
                  "min_steps_per_segment", "dda_ring_length", "parameter_file", *_LINUXCNC_KEYS}


def bundled_profiles() -> dict[str, Path]:
    """Name -> path of every profile shipped with fbspost (the repository's ``machines/``)."""
    try:  # a namespace package: iterate it, its str() is not a path
        entries = [Path(str(entry)) for entry in resources.files("fbspost.machines").iterdir()]
    except ModuleNotFoundError:  # a source tree on sys.path, not installed
        entries = list((Path(__file__).resolve().parent.parent / "machines").iterdir())
    return {p.stem: p for p in sorted(entries) if p.suffix == ".toml"}


def load_profile(name_or_path: str | Path) -> MachineProfile:
    """Load a bundled profile by name, or a profile file by path."""
    path = Path(name_or_path)
    bundled = bundled_profiles()
    if str(name_or_path) in bundled and not path.is_file():
        path = bundled[str(name_or_path)]
    elif not path.is_file():
        known = ", ".join(sorted(bundled))
        raise ProfileError(f"{name_or_path}: no such profile file or bundled profile (bundled: {known})")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"{path}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: not valid TOML: {exc}") from None
    return parse_profile(data, str(path))


class _Checker:
    """The checks of one profile file ``source``: each failure a ``ProfileError`` naming the key."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, key: str, message: str) -> ProfileError:
        return ProfileError(f"{self.source}: {key}: {message}")

    def table(self, parent: dict, key: str, where: str, allowed: set[str]) -> dict:
        if key not in parent:
            raise self.fail(where, "missing")
        value = parent[key]
        if not isinstance(value, dict):
            raise self.fail(where, "must be a table")
        for k in value:
            if k not in allowed:
                raise self.fail(f"{where}.{k}", f"unknown key (expected one of {', '.join(sorted(allowed))})")
        return value

    def number(self, parent: dict, key: str, where: str, *, positive: bool = False, optional: bool = False):
        if key not in parent:
            if optional:
                return None
            raise self.fail(where, "missing")
        value = parent[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(where, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(where, f"must be > 0, got {value!r}")
        return float(value)


def parse_profile(data: dict, source: str) -> MachineProfile:
    """Validate the parsed TOML ``data`` of the file ``source``."""
    check = _Checker(source)
    fail, table, number = check.fail, check.table, check.number
    for k in data:
        if k not in _TOP_KEYS:
            raise fail(k, f"unknown key (expected one of {', '.join(sorted(_TOP_KEYS))})")
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        raise fail("name", "missing" if name is None else "must be a non-empty string")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise fail("description", "must be a string")

    motion = table(data, "motion", "motion", _MOTION_KEYS)
    sample_rate = number(motion, "sample_rate", "motion.sample_rate", positive=True)
    planner = table(data, "planner", "planner", _PLANNER_KEYS)
    acceleration = number(planner, "acceleration", "planner.acceleration", positive=True)
    scv = number(planner, "square_corner_velocity", "planner.square_corner_velocity")
    if scv < 0:
        raise fail("planner.square_corner_velocity", f"must be >= 0, got {scv!r}")

    home = table(data, "home", "home", _HOME_KEYS) if "home" in data else {}
    home_mm = tuple(number(home, a, f"home.{a}", optional=True) or 0.0 for a in "XYZ")

    axes_table = table(data, "axes", "axes", set(AXIS_NAMES))
    if not axes_table:
        raise fail("axes", "no axis defined")
    axes = {axis_name: _parse_axis(check, axes_table, axis_name, sample_rate) for axis_name in axes_table}
    firmware = FirmwareProfile()
    if "firmware" in data:
        firmware = _parse_firmware(table(data, "firmware", "firmware", _FIRMWARE_KEYS), fail, number)
        if "parameter_file" in data["firmware"]:
            linuxcnc = _with_work_offsets(firmware.linuxcnc, data["firmware"]["parameter_file"], source, fail)
            firmware = replace(firmware, linuxcnc=linuxcnc)
    return MachineProfile(name.strip(), description, source, sample_rate, acceleration, scv, axes, firmware,
                          home_mm)


def _parse_axis(check: _Checker, axes_table: dict, axis_name: str, sample_rate: float) -> AxisProfile:
    """The axis ``axis_name`` of the profile's [axes]: limits, modes scaled to DC gain 1, load."""
    fail, number = check.fail, check.number
    where = f"axes.{axis_name}"
    axis = check.table(axes_table, axis_name, where, _AXIS_KEYS)
    max_velocity = number(axis, "max_velocity", f"{where}.max_velocity", positive=True)
    max_acceleration = number(axis, "max_acceleration", f"{where}.max_acceleration", positive=True)
    max_jerk = number(axis, "max_jerk", f"{where}.max_jerk", positive=True, optional=True)
    travel = {f"position_{end}_mm": number(axis, f"position_{end}", f"{where}.position_{end}", optional=True)
              for end in ("min", "max")}
    if None not in travel.values() and travel["position_min_mm"] >= travel["position_max_mm"]:
        raise fail(f"{where}.position_max", f"must be above position_min, got {travel['position_max_mm']!r}")
    raw_modes = axis.get("modes")
    if raw_modes is None:
        raise fail(f"{where}.modes", "missing (use modes = [] for an axis without dynamics)")
    if not isinstance(raw_modes, list):
        raise fail(f"{where}.modes", "must be a list of tables")
    axis_tolerances = [_tolerance(axis, key, f"{where}.{key}", 0.0, fail, number) for key in _TOLERANCE_KEYS]
    modes = [_parse_mode(check, raw, f"{where}.modes[{i}]", sample_rate, axis_tolerances)
             for i, raw in enumerate(raw_modes)]
    if modes:
        dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in modes)
        if not dc_gain > 0:
            raise fail(f"{where}.modes", f"DC gain sum(alpha/w^2) = {dc_gain:g} must be > 0 for a position axis")
        modes = [replace(m, alpha=m.alpha / dc_gain, beta=m.beta / dc_gain) for m in modes]
    load = {"moving_mass_kg": number(axis, "moving_mass", f"{where}.moving_mass", positive=True, optional=True),
            "filament_density_g_cm3": number(axis, "filament_density", f"{where}.filament_density", positive=True,
                                             optional=True)}
    if load["filament_density_g_cm3"] is not None and load["moving_mass_kg"] is None:
        raise fail(f"{where}.filament_density", "needs moving_mass (the mass the modes were measured with)")
    if "modes_by_position" in axis:
        if load["moving_mass_kg"] is not None:
            raise fail(f"{where}.modes_by_position", "and moving_mass together: the modes follow one or the other")
        load["modes_by_position"] = _parse_position_table(check, axis, f"{where}.modes_by_position", modes,
                                                          sample_rate)
    return AxisProfile(axis_name, max_velocity, max_acceleration, max_jerk, tuple(modes),
                       **{k: v for k, v in (load | travel).items() if v is not None})


def _parse_position_table(check: _Checker, axis: dict, where: str, modes: list[Mode],
                          sample_rate: float) -> PositionTable:
    """The axis' ``modes_by_position`` table: the axis, its positions (mm) and the factors there."""
    fail = check.fail
    table = check.table(axis, "modes_by_position", where, _POSITION_KEYS)
    name, names = table.get("axis"), [a for a in AXIS_NAMES if a != "E"]
    if name not in names:
        raise fail(f"{where}.axis", f"must be one of {', '.join(names)}, got {name!r}")
    columns = []
    for key in ("position", "frequency_scale"):
        values = table.get(key)
        if not isinstance(values, list) or len(values) < 2:
            raise fail(f"{where}.{key}", "must be a list of at least two numbers")
        columns.append(tuple(check.number({key: v}, key, f"{where}.{key}[{i}]", positive=key != "position")
                             for i, v in enumerate(values)))
    positions, scales = columns
    if len(positions) != len(scales):
        raise fail(f"{where}.frequency_scale", f"has {len(scales)} values for {len(positions)} positions")
    if any(b <= a for a, b in itertools.pairwise(positions)):
        raise fail(f"{where}.position", "must increase")
    top_hz = max((m.frequency_hz for m in modes), default=0.0) * max(scales)
    if top_hz >= sample_rate / 2:
        raise fail(f"{where}.frequency_scale", f"takes a mode to {top_hz:g} Hz, above the Nyquist frequency "
                   f"{sample_rate / 2:g} Hz")
    return PositionTable(name, positions, scales)


def _parse_mode(check: _Checker, raw, where: str, sample_rate: float, axis_tolerances: list) -> Mode:
    """One mode table at ``where``, as written (unscaled); its tolerances default to the axis'."""
    fail, number = check.fail, check.number
    if not isinstance(raw, dict):
        raise fail(where, "must be a table")
    for k in raw:
        if k not in _MODE_KEYS:
            raise fail(f"{where}.{k}", f"unknown key (expected one of {', '.join(sorted(_MODE_KEYS))})")
    frequency = number(raw, "frequency", f"{where}.frequency", positive=True)
    if frequency >= sample_rate / 2:
        raise fail(f"{where}.frequency", f"must be below the Nyquist frequency {sample_rate / 2:g} Hz")
    damping = number(raw, "damping", f"{where}.damping")
    if not 0 < damping < 1:
        raise fail(f"{where}.damping", f"must be in (0, 1), got {damping!r}")
    tolerances = [_tolerance(raw, key, f"{where}.{key}", default, fail, number)
                  for key, default in zip(_TOLERANCE_KEYS, axis_tolerances, strict=True)]
    return Mode(frequency, damping, number(raw, "alpha", f"{where}.alpha"), number(raw, "beta", f"{where}.beta"),
                *tolerances)


def _tolerance(raw: dict, key: str, where: str, default: float, fail, number) -> float:
    """A relative tolerance in [0, 0.5) (``fail`` and ``number`` as in ``parse_profile``)."""
    value = number(raw, key, where, optional=True)
    if value is None:
        return default
    if not 0 <= value < 0.5:
        raise fail(where, f"must be in [0, 0.5), got {value!r}")
    return value


def _parse_firmware(raw: dict, fail, number) -> FirmwareProfile:
    """The ``[firmware]`` table (``fail`` and ``number`` as in ``parse_profile``)."""

    def integer(key: str, default: int) -> int:
        value = raw.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise fail(f"firmware.{key}", f"must be a whole number >= 1, got {value!r}")
        return value

    values = {attr: number(raw, key, f"firmware.{key}", positive=True, optional=True)
              for key, attr in _FIRMWARE_NUMBERS.items()}
    values = {attr: value for attr, value in values.items() if value is not None}
    if "minimum_cruise_ratio" in raw and "max_accel_to_decel" in raw:
        raise fail("firmware.max_accel_to_decel", "give minimum_cruise_ratio or max_accel_to_decel, not both")
    ratio = number(raw, "minimum_cruise_ratio", "firmware.minimum_cruise_ratio", optional=True)
    if ratio is not None and not 0 <= ratio < 1:
        raise fail("firmware.minimum_cruise_ratio", f"must be in [0, 1), got {ratio!r}")
    corner = number(raw, "instantaneous_corner_velocity", "firmware.instantaneous_corner_velocity", optional=True)
    if corner is not None and corner < 0:
        raise fail("firmware.instantaneous_corner_velocity", f"must be >= 0, got {corner!r}")
    segment_time = number(raw, "min_segment_time", "firmware.min_segment_time", optional=True)
    if segment_time is not None and segment_time < 0:
        raise fail("firmware.min_segment_time", f"must be >= 0, got {segment_time!r}")
    if values.get("filament_diameter_mm", 1.75) < values.get("nozzle_diameter_mm", 0.4):
        raise fail("firmware.filament_diameter", "must be >= nozzle_diameter (as Klipper requires)")
    steps, shaper = (_axis_table(raw, key, what, fail, number) for key, what in
                     (("steps_per_mm", "steps per mm"), ("shaper_frequency", "input shaper frequency (Hz)")))
    optional = {"minimum_cruise_ratio": ratio, "instantaneous_corner_velocity_mm_s": corner,
                "min_segment_time_s": segment_time}
    values.update({attr: value for attr, value in optional.items() if value is not None})
    flavor = raw.get("flavor")
    if flavor is not None and flavor not in FLAVORS:
        raise fail("firmware.flavor", f"must be one of {', '.join(FLAVORS)}, got {flavor!r}")
    if flavor is not None:
        values["flavor"] = flavor
    return FirmwareProfile(steps_per_mm=steps, shaper_frequency_hz=shaper, block_buffer=integer("block_buffer", 16),
                           min_steps_per_segment=integer("min_steps_per_segment", 6),
                           dda_ring_length=integer("dda_ring_length", 50), linuxcnc=_parse_linuxcnc(raw, fail, number),
                           **values)


def _parse_linuxcnc(raw: dict, fail, number) -> LinuxCNCSettings:
    """The ``[firmware]`` keys of LinuxCNC's settings, checked as LinuxCNC reads them (INI
    integers and booleans; ARC_BLEND_KINK_RATIO in (0, 1])."""
    values = {}
    for key, attr in _LINUXCNC_KEYS.items():
        if key not in raw:
            continue
        value, default = raw[key], getattr(LinuxCNCSettings, attr)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise fail(f"firmware.{key}", f"must be true or false, got {value!r}")
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise fail(f"firmware.{key}", f"must be a whole number >= 0, got {value!r}")
        else:
            value = number(raw, key, f"firmware.{key}",
                           positive=key in ("servo_period", "arc_blend_ramp_freq", "max_linear_velocity"))
            if value < 0 or (key == "arc_blend_kink_ratio" and not 0 < value <= 1):
                raise fail(f"firmware.{key}", f"must be {'in (0, 1]' if 'kink' in key else '>= 0'}, got {value!r}")
        values[attr] = value
    return LinuxCNCSettings(**values)


def _with_work_offsets(settings: LinuxCNCSettings, name, source: str, fail) -> LinuxCNCSettings:
    """``settings`` with LinuxCNC's var file ``name`` (relative to the profile's folder) and the
    work offsets in it: parameter 5221 + 20 k + axis (G54 k = 0 .. G59.3 k = 8), 5230 + 20 k the
    rotation; a parameter the file leaves out is 0, as LinuxCNC reads it."""
    if not isinstance(name, str) or not name:
        raise fail("firmware.parameter_file", f"must be a file name, got {name!r}")
    path = Path(source).parent / Path(name).expanduser()
    values = {}
    try:
        with open(path, encoding="utf-8") as f:
            for n, text in enumerate(f, 1):
                words = text.split()
                if len(words) >= 2:
                    try:
                        values[int(words[0])] = float(words[1])
                    except ValueError:
                        raise fail("firmware.parameter_file", f"{path}:{n}: not a parameter and its value") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise fail("firmware.parameter_file", f"cannot read {path}: {exc}") from None
    offsets = tuple(None if values.get(5230 + 20 * k, 0.0) else
                    tuple(values.get(5221 + 20 * k + i, 0.0) for i in range(3)) for k in range(9))
    return replace(settings, parameter_file=str(path), work_offsets_mm=offsets)


def _axis_table(raw: dict, key: str, what: str, fail, number) -> dict[str, float]:
    """The ``[firmware]`` table ``key`` of positive numbers per axis."""
    values = raw.get(key, {})
    if not isinstance(values, dict):
        raise fail(f"firmware.{key}", f"must be a table of axis = {what}")
    for axis in values:
        if axis not in AXIS_NAMES:
            raise fail(f"firmware.{key}.{axis}", f"unknown axis (expected one of {', '.join(AXIS_NAMES)})")
    return {axis: number(values, axis, f"firmware.{key}.{axis}", positive=True) for axis in values}


def format_profile(profile: MachineProfile) -> str:
    """The TOML text of ``profile`` in the layout above, which ``load_profile`` reads back to the
    same values (floats in their shortest exact form; the modes as they are, so the DC gain of 1
    is computed again on reading, equal up to rounding). Comments are not kept."""

    def number(value: float) -> str:
        text = repr(float(value))  # shortest round-trip form: valid TOML (1e-05, 15797.5, 2e+20)
        return text if any(c in text for c in ".en") else text + ".0"

    def string(value: str) -> str:
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return '"' + "".join(c if c >= " " and c != "\x7f" else f"\\u{ord(c):04x}" for c in escaped) + '"'

    lines = [f"name = {string(profile.name)}", f"description = {string(profile.description)}", "",
             "[motion]", f"sample_rate = {number(profile.sample_rate_hz)}", "",
             "[planner]", f"acceleration = {number(profile.planner_acceleration_mm_s2)}",
             f"square_corner_velocity = {number(profile.planner_square_corner_velocity_mm_s)}"]
    if any(profile.home_mm):
        lines += ["", "[home]", *(f"{a} = {number(v)}" for a, v in zip("XYZ", profile.home_mm, strict=True))]
    lines += _format_firmware(profile.firmware, number, string)
    for name, axis in profile.axes.items():
        lines += ["", f"[axes.{name}]", f"max_velocity = {number(axis.max_velocity_mm_s)}",
                  f"max_acceleration = {number(axis.max_acceleration_mm_s2)}"]
        if axis.max_jerk_mm_s3 is not None:
            lines.append(f"max_jerk = {number(axis.max_jerk_mm_s3)}")
        lines += [f"position_{end} = {number(value)}" for end, value in
                  (("min", axis.position_min_mm), ("max", axis.position_max_mm)) if value is not None]
        if axis.moving_mass_kg is not None:
            lines += [
                f"moving_mass = {number(axis.moving_mass_kg)}",
                f"filament_density = {number(axis.filament_density_g_cm3)}",
            ]
        if axis.modes_by_position is not None:
            table = axis.modes_by_position
            lines.append(f"modes_by_position = {{ axis = {string(table.axis)}, position = "
                         f"[{', '.join(map(number, table.positions_mm))}], frequency_scale = "
                         f"[{', '.join(map(number, table.frequency_scales))}] }}")
        modes = [f"  {{ frequency = {number(m.frequency_hz)}, damping = {number(m.damping)}, "
                 f"alpha = {number(m.alpha)}, beta = {number(m.beta)}"
                 + "".join(f", {key} = {number(getattr(m, key))}" for key in _TOLERANCE_KEYS if getattr(m, key))
                 + " }," for m in axis.modes]
        lines += ["modes = [", *modes, "]"] if modes else ["modes = []"]
    return "\n".join(lines) + "\n"


def _format_firmware(firmware: FirmwareProfile, number, string) -> list[str]:
    """The ``[firmware]`` lines of ``format_profile`` (none when every value is the default)."""
    if firmware == FirmwareProfile():
        return []
    lines = ["", "[firmware]"] + ([f'flavor = "{firmware.flavor}"'] if firmware.flavor else [])
    for key, table in (("steps_per_mm", firmware.steps_per_mm), ("shaper_frequency", firmware.shaper_frequency_hz)):
        if table:
            lines.append(f"{key} = {{ {', '.join(f'{axis} = {number(value)}' for axis, value in table.items())} }}")
    lines += [f"block_buffer = {firmware.block_buffer}", f"min_steps_per_segment = {firmware.min_steps_per_segment}",
              f"dda_ring_length = {firmware.dda_ring_length}"]
    values = {"minimum_cruise_ratio": firmware.minimum_cruise_ratio,
              "instantaneous_corner_velocity": firmware.instantaneous_corner_velocity_mm_s,
              "min_segment_time": firmware.min_segment_time_s,
              **{key: getattr(firmware, attr) for key, attr in _FIRMWARE_NUMBERS.items()}}
    if firmware.max_accel_to_decel_mm_s2 is not None:
        del values["minimum_cruise_ratio"]
    lines += [f"{key} = {number(value)}" for key, value in values.items() if value is not None]
    for key, attr in _LINUXCNC_KEYS.items():
        value = getattr(firmware.linuxcnc, attr)
        if value != getattr(LinuxCNCSettings, attr):  # (TOML's true / false; INI integers as such)
            text = str(value).lower() if isinstance(value, bool) else str(value)
            lines.append(f"{key} = {text if isinstance(value, (bool, int)) else number(value)}")
    if firmware.linuxcnc.parameter_file:
        lines.append(f"parameter_file = {string(firmware.linuxcnc.parameter_file)}")
    return lines
