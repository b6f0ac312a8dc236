"""The measurement files identify reads, and the coarse modes of Klipper's.

Takes a file's path; gives its numbers, or ``InputError`` naming the file and line:
``read_frf_csv`` (a measured frequency response), ``read_accel_log`` (an accelerometer recording:
ours or Klipper's raw CSV), ``klipper_psd_mode`` (one coarse mode from the PSD peak of Klipper's
calibrate_shaper CSV), ``klipper_cfg_modes`` and ``klipper_cfg_machine`` (a printer.cfg's
``[input_shaper]`` as coarse modes; its planner's settings in a profile). ``coarse_mode``: the
single mode of a frequency and damping.
"""
from __future__ import annotations

import configparser
import csv
import io
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..profile import MachineProfile, Mode

KLIPPER_DEFAULT_DAMPING = 0.1  # Klipper's damping_ratio_x/y when printer.cfg does not set it
COARSE_FORMS = ("base", "mass")  # the model of a coarse estimate's mode (coarse_mode)


def read_frf_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(frequency_hz, complex response) from a CSV with the header ``frequency_hz,real,imag`` or
    ``frequency_hz,magnitude,phase_deg`` (magnitude a plain ratio, not dB); frequencies > 0 and
    strictly increasing."""
    header, rows = read_numeric_csv(path, {("frequency_hz", "real", "imag"),
                                            ("frequency_hz", "magnitude", "phase_deg")})
    data = np.array([values for _, values in rows])
    lines = [line for line, _ in rows]
    frequency_hz = data[:, 0]
    for i in range(len(frequency_hz)):
        if frequency_hz[i] <= 0:
            raise InputError(path, lines[i], f"frequency {frequency_hz[i]:g} Hz must be > 0")
        if i and frequency_hz[i] <= frequency_hz[i - 1]:
            raise InputError(path, lines[i], f"frequencies must increase: {frequency_hz[i]:g} Hz after "
                                             f"{frequency_hz[i - 1]:g} Hz")
    if header[1] == "real":
        response = data[:, 1] + 1j * data[:, 2]
    else:
        if (data[:, 1] < 0).any():
            i = int(np.argmax(data[:, 1] < 0))
            raise InputError(path, lines[i], "magnitude must be >= 0 (a ratio, not dB)")
        response = data[:, 1] * np.exp(1j * np.radians(data[:, 2]))
    if len(frequency_hz) < 8:
        raise InputError(path, None, f"{len(frequency_hz)} frequencies: at least 8 are needed for a fit")
    return frequency_hz, response


def read_numeric_csv(path, headers: set[tuple[str, ...]], comment: str | None = None):
    """The header (one of ``headers``, cells stripped, extra trailing cells ignored) and the rows as
    (line number, the header's columns as floats); blank lines skipped, lines starting with
    ``comment`` skipped (a header may start with it)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    expected = " or ".join(",".join(h) for h in sorted(headers))
    header, width, rows = None, 0, []
    for lineno, row in enumerate(csv.reader(io.StringIO(text)), start=1):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        if header is None:
            names = tuple(c.lstrip(comment or "") for c in cells)
            header = next((h for h in headers if names[:len(h)] == h), None)
            if header is None:
                if comment and cells[0].startswith(comment):
                    continue
                raise InputError(path, lineno, f"header {','.join(cells)!r}: expected {expected}")
            width = len(header)
            continue
        if comment and cells[0].startswith(comment):
            continue
        if len(cells) < width:
            raise InputError(path, lineno, f"expected {width} values, got {len(cells)}")
        try:
            values = [float(c) for c in cells[:width]]
        except ValueError:
            raise InputError(path, lineno, f"not a number in {','.join(cells[:width])!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(path, lineno, "values must be finite")
        rows.append((lineno, values))
    if header is None:
        raise InputError(path, 1, f"empty file: expected the header {expected}")
    if not rows:
        raise InputError(path, None, "no data rows")
    return header, rows


def read_accel_log(path: str | Path, column: str) -> tuple[np.ndarray, np.ndarray]:
    """(times_s, acceleration) of ``column`` from an accelerometer CSV: header
    ``time_s,accel_x,accel_y,accel_z`` or Klipper's raw ``#time,accel_x,accel_y,accel_z``
    (lines starting with ``#`` before it skipped); times strictly increasing."""
    headers = {("time_s", "accel_x", "accel_y", "accel_z"), ("time", "accel_x", "accel_y", "accel_z")}
    header, rows = read_numeric_csv(path, headers, comment="#")
    if column not in header[1:]:
        raise InputError(path, None, f"no column {column!r} (the columns are {', '.join(header)})")
    data = np.array([values for _, values in rows])
    bad = np.flatnonzero(np.diff(data[:, 0]) <= 0)
    if bad.size:
        raise InputError(path, rows[bad[0] + 1][0], "times must increase")
    if len(data) < 1000:
        raise InputError(path, None, f"{len(data)} samples: too short a recording for a sweep")
    return data[:, 0], data[:, header.index(column)]


def klipper_psd_mode(path: str | Path, axis: str, form: str = "base") -> tuple[Mode, float, float]:
    """One mode of ``form`` (``coarse_mode``) from the ``psd_<axis>`` column of Klipper's
    calibrate_shaper CSV (header ``freq,psd_x,psd_y,psd_z,psd_xyz,...``; the shaper columns
    after it are ignored): the frequency of the PSD peak and the damping from its half-power
    band f1..f2 (where the PSD, a power, falls to half the peak), zeta = (f2 - f1) / (2 f0).
    Gives (mode, f1, f2)."""
    column = f"psd_{axis.lower()}"
    if column not in ("psd_x", "psd_y", "psd_z"):
        raise InputError(path, None, f"no PSD column for axis {axis} (calibrate_shaper has psd_x, psd_y, psd_z)")
    _, rows = read_numeric_csv(path, {("freq", "psd_x", "psd_y", "psd_z", "psd_xyz")})
    data = np.array([values for _, values in rows])
    freq_hz, psd = data[:, 0], data[:, ("psd_x", "psd_y", "psd_z").index(column) + 1]
    lines = [line for line, _ in rows]
    bad = np.flatnonzero(np.diff(freq_hz) <= 0)
    if bad.size:
        raise InputError(path, lines[bad[0] + 1], "frequencies must increase")
    peak = int(np.argmax(psd))
    if not psd[peak] > 0:
        raise InputError(path, None, f"{column} has no positive value")
    half = psd[peak] / 2
    below = np.flatnonzero(psd[:peak] < half)
    above = np.flatnonzero(psd[peak:] < half)
    if not below.size or not above.size:
        raise InputError(path, None, f"{column}: the peak at {freq_hz[peak]:g} Hz does not fall to half power "
                                     "on both sides within the file's band: no damping estimate")
    i, j = below[-1], peak + above[0]  # the crossings, interpolated linearly in the PSD
    f1 = float(np.interp(half, [psd[i], psd[i + 1]], [freq_hz[i], freq_hz[i + 1]]))
    f2 = float(np.interp(half, [psd[j], psd[j - 1]], [freq_hz[j], freq_hz[j - 1]]))
    f0 = float(freq_hz[peak])
    return coarse_mode(f0, (f2 - f1) / (2 * f0), form), f1, f2


def klipper_cfg_modes(path: str | Path, form: str = "base") -> dict[str, Mode]:
    """One mode of ``form`` (``coarse_mode``) per axis (X, Y) from the ``[input_shaper]`` section
    of a Klipper printer.cfg: ``shaper_freq_x/y`` and ``damping_ratio_x/y`` (Klipper's default
    0.1; see ``_klipper_config`` for the SAVE_CONFIG block). Gives {axis: mode} for the axes that
    have a frequency."""
    sections, lines = _klipper_config(path)
    if "input_shaper" not in sections:
        raise InputError(path, None, "no [input_shaper] section (nor one in the #*# SAVE_CONFIG block)")
    values = sections["input_shaper"]
    modes = {}
    for axis in ("x", "y"):
        if f"shaper_freq_{axis}" not in values:
            continue
        frequency = _cfg_number(path, lines, values, f"shaper_freq_{axis}")
        damping = (_cfg_number(path, lines, values, f"damping_ratio_{axis}")
                   if f"damping_ratio_{axis}" in values else KLIPPER_DEFAULT_DAMPING)
        if not frequency > 0 or not 0 < damping < 1:
            raise InputError(path, lines.get(f"shaper_freq_{axis}"),
                             f"shaper_freq_{axis} must be > 0 and damping_ratio_{axis} in (0, 1)")
        modes[axis.upper()] = coarse_mode(frequency, damping, form)
    if not modes:
        raise InputError(path, None, "[input_shaper] has neither shaper_freq_x nor shaper_freq_y")
    return modes


def klipper_cfg_machine(path: str | Path, profile: MachineProfile) -> MachineProfile:
    """``profile`` with what a Klipper printer.cfg says of the firmware fbspost writes for: the
    flavor, ``[printer]`` max_accel (the planner's acceleration), max_velocity,
    square_corner_velocity and minimum_cruise_ratio where given, and ``[input_shaper]``'s
    frequencies (what the output restores after switching shaping off)."""
    sections, lines = _klipper_config(path)
    printer, shaper = sections.get("printer", {}), sections.get("input_shaper", {})
    number = {key: _cfg_number(path, lines, printer, key) for key in
              ("max_accel", "max_velocity", "square_corner_velocity", "minimum_cruise_ratio") if key in printer}
    shaping = {axis.upper(): _cfg_number(path, lines, shaper, f"shaper_freq_{axis}") for axis in "xy"
               if f"shaper_freq_{axis}" in shaper}
    firmware = replace(profile.firmware, flavor="klipper", shaper_frequency_hz={**profile.firmware.shaper_frequency_hz,
                                                                                **shaping},
                       max_velocity_mm_s=number.get("max_velocity", profile.firmware.max_velocity_mm_s),
                       minimum_cruise_ratio=number.get("minimum_cruise_ratio", profile.firmware.minimum_cruise_ratio))
    return replace(profile, firmware=firmware,
                   planner_acceleration_mm_s2=number.get("max_accel", profile.planner_acceleration_mm_s2),
                   planner_square_corner_velocity_mm_s=number.get("square_corner_velocity",
                                                                  profile.planner_square_corner_velocity_mm_s))


def _klipper_config(path: str | Path) -> tuple[dict[str, dict[str, str]], dict[str, int]]:
    """The sections of a Klipper printer.cfg ({section: {key: value}}, the SAVE_CONFIG block's
    ``#*#`` lines at the end, where SHAPER_CALIBRATE saves, overriding the main part as in
    Klipper) and the line of each key, for messages."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    # The main part and the SAVE_CONFIG block, each with the other's lines blank (so configparser's
    # line numbers are the file's); the block's lines before its first section are its banner.
    main, saved, in_section = [], [], False
    for line in text.splitlines():
        block = line.startswith("#*#")
        content = line[3:] if block else ""
        in_section = in_section or (block and content.strip().startswith("["))
        main.append("" if block else line)
        saved.append(content if in_section else "")
    sections: dict[str, dict[str, str]] = {}
    for part in ("\n".join(main), "\n".join(saved)):
        parser = configparser.RawConfigParser(strict=True, inline_comment_prefixes=("#", ";"))
        try:
            parser.read_string(part, source=str(path))
        except configparser.Error as exc:
            raise InputError(
                path, getattr(exc, "lineno", None), f"not a Klipper config: {exc.message.splitlines()[0]}"
            ) from None
        for name in parser.sections():
            sections.setdefault(name, {}).update(parser[name])
    keys = {key for values in sections.values() for key in values}
    lines = {}
    for number, line in enumerate(text.splitlines(), start=1):
        key = line.removeprefix("#*#").split(":", 1)[0].split("=", 1)[0].strip().lower()
        if key in keys:
            lines[key] = number
    return sections, lines


def _cfg_number(path, lines, values, key):
    try:
        value = float(values[key])
    except ValueError:
        raise InputError(path, lines.get(key), f"{key}: not a number: {values[key]!r}") from None
    if not math.isfinite(value):
        raise InputError(path, lines.get(key), f"{key} must be finite")
    return value


def coarse_mode(frequency_hz: float, damping: float, form: str = "base") -> Mode:
    """The single mode of DC gain 1 at ``frequency_hz`` and ``damping``: ``form`` "base", a
    belt- or screw-driven axis, excited through its drive's stiffness and damping, (2 zeta w s +
    w^2) / (s^2 + 2 zeta w s + w^2) (alpha = w^2, beta = 2 zeta w: a zero); "mass", a mass
    pushed by a force, w^2 / (s^2 + 2 zeta w s + w^2) (beta = 0)."""
    w = 2 * math.pi * frequency_hz
    if form not in COARSE_FORMS:
        raise ValueError(f"unknown coarse form {form!r}: expected one of {', '.join(COARSE_FORMS)}")
    return Mode(frequency_hz, damping, w * w, 2 * damping * w if form == "base" else 0.0)
