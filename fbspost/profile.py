"""Machine profiles: read and validate a TOML profile, list the bundled ones, write one.

Takes a bundled profile name or a path to a ``.toml`` file; gives a ``MachineProfile`` with the
sample rate, the planner settings and, per compensated axis, its kinematic limits and modal
dynamics. The modal residues are rescaled so every axis has a DC gain of exactly 1 (a
position-controlled axis holds a constant command exactly).

Errors are raised as ``ProfileError`` with a one-line message naming the file and the key.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
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

    @property
    def omega_rad_s(self) -> float:
        return 2.0 * math.pi * self.frequency_hz


@dataclass(frozen=True)
class AxisProfile:
    name: str
    max_velocity_mm_s: float
    max_acceleration_mm_s2: float
    max_jerk_mm_s3: float | None
    modes: tuple[Mode, ...]  # DC gain normalized to 1; empty: the axis is not compensated


@dataclass(frozen=True)
class MachineProfile:
    name: str
    description: str
    source: str  # the file it was read from
    sample_rate_hz: float
    planner_acceleration_mm_s2: float
    planner_square_corner_velocity_mm_s: float
    axes: dict[str, AxisProfile]
    home_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # X Y Z where G28 leaves the homed axes


_TOP_KEYS = {"name", "description", "motion", "planner", "axes", "home"}
_HOME_KEYS = {"X", "Y", "Z"}
_MOTION_KEYS = {"sample_rate"}
_PLANNER_KEYS = {"acceleration", "square_corner_velocity"}
_AXIS_KEYS = {"max_velocity", "max_acceleration", "max_jerk", "modes"}
_MODE_KEYS = {"frequency", "damping", "alpha", "beta"}


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


def parse_profile(data: dict, source: str) -> MachineProfile:
    """Validate the parsed TOML ``data`` of the file ``source``."""

    def fail(key: str, message: str) -> ProfileError:
        return ProfileError(f"{source}: {key}: {message}")

    def table(parent: dict, key: str, where: str, allowed: set[str]) -> dict:
        if key not in parent:
            raise fail(where, "missing")
        value = parent[key]
        if not isinstance(value, dict):
            raise fail(where, "must be a table")
        for k in value:
            if k not in allowed:
                raise fail(f"{where}.{k}", f"unknown key (expected one of {', '.join(sorted(allowed))})")
        return value

    def number(parent: dict, key: str, where: str, *, positive: bool = False, optional: bool = False):
        if key not in parent:
            if optional:
                return None
            raise fail(where, "missing")
        value = parent[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise fail(where, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise fail(where, f"must be > 0, got {value!r}")
        return float(value)

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
    axes = {}
    for axis_name in axes_table:
        where = f"axes.{axis_name}"
        axis = table(axes_table, axis_name, where, _AXIS_KEYS)
        max_velocity = number(axis, "max_velocity", f"{where}.max_velocity", positive=True)
        max_acceleration = number(axis, "max_acceleration", f"{where}.max_acceleration", positive=True)
        max_jerk = number(axis, "max_jerk", f"{where}.max_jerk", positive=True, optional=True)
        raw_modes = axis.get("modes")
        if raw_modes is None:
            raise fail(f"{where}.modes", "missing (use modes = [] for an axis without dynamics)")
        if not isinstance(raw_modes, list):
            raise fail(f"{where}.modes", "must be a list of tables")
        modes = []
        for i, raw in enumerate(raw_modes):
            mwhere = f"{where}.modes[{i}]"
            if not isinstance(raw, dict):
                raise fail(mwhere, "must be a table")
            for k in raw:
                if k not in _MODE_KEYS:
                    raise fail(f"{mwhere}.{k}", f"unknown key (expected one of {', '.join(sorted(_MODE_KEYS))})")
            frequency = number(raw, "frequency", f"{mwhere}.frequency", positive=True)
            if frequency >= sample_rate / 2:
                raise fail(f"{mwhere}.frequency", f"must be below the Nyquist frequency {sample_rate / 2:g} Hz")
            damping = number(raw, "damping", f"{mwhere}.damping")
            if not 0 < damping < 1:
                raise fail(f"{mwhere}.damping", f"must be in (0, 1), got {damping!r}")
            modes.append(Mode(frequency, damping, number(raw, "alpha", f"{mwhere}.alpha"),
                              number(raw, "beta", f"{mwhere}.beta")))
        if modes:
            dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in modes)
            if not dc_gain > 0:
                raise fail(f"{where}.modes", f"DC gain sum(alpha/w^2) = {dc_gain:g} must be > 0 for a position axis")
            modes = [Mode(m.frequency_hz, m.damping, m.alpha / dc_gain, m.beta / dc_gain) for m in modes]
        axes[axis_name] = AxisProfile(axis_name, max_velocity, max_acceleration, max_jerk, tuple(modes))

    return MachineProfile(name.strip(), description, source, sample_rate, acceleration, scv, axes, home_mm)


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
        lines += ["", "[home]", *(f"{a} = {number(v)}" for a, v in zip("XYZ", profile.home_mm))]
    for name, axis in profile.axes.items():
        lines += ["", f"[axes.{name}]", f"max_velocity = {number(axis.max_velocity_mm_s)}",
                  f"max_acceleration = {number(axis.max_acceleration_mm_s2)}"]
        if axis.max_jerk_mm_s3 is not None:
            lines.append(f"max_jerk = {number(axis.max_jerk_mm_s3)}")
        modes = [f"  {{ frequency = {number(m.frequency_hz)}, damping = {number(m.damping)}, "
                 f"alpha = {number(m.alpha)}, beta = {number(m.beta)} }}," for m in axis.modes]
        lines += ["modes = [", *modes, "]"] if modes else ["modes = []"]
    return "\n".join(lines) + "\n"
