"""A simulated ADXL345 on the moving part, written as Klipper writes it: for tests and benches.

Takes the commanded motion as a firmware ran it (X and Y positions on a fine uniform grid of
machine time, e.g. klippy's executed moves, ``klippy_motion.executed(...).at(t)``) and the true
modes per axis; gives Klipper's raw CSV (ACCELEROMETER_MEASURE, the resonance test's raw data:
``#time,accel_x,accel_y,accel_z``, s and mm/s^2). The true position of each axis comes from the
continuous modal model (``reference.continuous_model`` through ``scipy.signal.lsim``, the command
linear between samples: nothing of fbspost's dynamics), its acceleration from second differences,
an ideal anti-alias filter, then samples at the chip's rate on the chip's own clock (an offset and
a drift: its time stamps are not the machine's), noise per axis, gravity on Z and optionally a
little of each axis' acceleration read by the other (a chip mounted slightly askew).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import signal

from reference import continuous_model

GRAVITY_MM_S2 = 9810.0


@dataclass(frozen=True)
class Accelerometer:
    """The chip and its mounting."""

    rate_hz: float = 3200.0  # ADXL345 at Klipper's default rate
    offset_s: float = 1234.5  # its clock's reading at machine time 0
    drift_ppm: float = 100.0  # its clock runs this much fast
    noise_mm_s2: float = 100.0  # RMS per axis
    coupling: float = 0.0  # fraction of X's acceleration read on Y and of Y's on X
    seed: int = 0

    def chip_time_s(self, machine_s):
        return self.offset_s + (1.0 + 1e-6 * self.drift_ppm) * np.asarray(machine_s)

    def machine_time_s(self, chip_s):
        return (np.asarray(chip_s) - self.offset_s) / (1.0 + 1e-6 * self.drift_ppm)


def true_position_mm(modes, t_s: np.ndarray, command_mm: np.ndarray) -> np.ndarray:
    """The axis' actual position (mm) for the command at ``t_s`` (uniform), from rest at the first
    sample; an axis without modes follows its command."""
    if not modes:
        return np.asarray(command_mm, dtype=float).copy()
    u = command_mm - command_mm[0]
    _, y, _ = signal.lsim(continuous_model(modes), u, t_s - t_s[0], interp=True)
    return np.asarray(y) + command_mm[0]


def true_accel_mm_s2(modes, t_s: np.ndarray, command_mm: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """The actual acceleration, low-passed below ``cutoff_hz`` without phase (the chip's filter,
    idealized)."""
    position = true_position_mm(modes, t_s, command_mm)
    accel = np.gradient(np.gradient(position, t_s), t_s)
    return signal.sosfiltfilt(signal.butter(8, cutoff_hz, fs=1.0 / (t_s[1] - t_s[0]), output="sos"), accel)


def record(t_s: np.ndarray, xy_mm: np.ndarray, modes: dict, chip: Accelerometer = Accelerometer()) -> np.ndarray:
    """Rows (chip time s, accel x, y, z mm/s^2) of the motion ``xy_mm`` (columns X, Y) at the
    uniform machine times ``t_s``, through ``modes`` (by axis name), sampled at the chip's rate on
    its clock from the first to the last machine time."""
    cutoff_hz = 0.3125 * chip.rate_hz  # (an ADXL345's bandwidth is half its rate: 1000 Hz at 3200)
    ax, ay = (true_accel_mm_s2(modes.get(name, ()), t_s, xy_mm[:, i], cutoff_hz) for i, name in enumerate("XY"))
    chip_s = np.arange(chip.chip_time_s(t_s[0]), chip.chip_time_s(t_s[-1]), 1.0 / chip.rate_hz)
    at = chip.machine_time_s(chip_s)
    x, y = np.interp(at, t_s, ax), np.interp(at, t_s, ay)
    noise = chip.noise_mm_s2 * np.random.default_rng(chip.seed).standard_normal((3, chip_s.size))
    return np.column_stack([chip_s, x + chip.coupling * y + noise[0], y + chip.coupling * x + noise[1],
                            GRAVITY_MM_S2 + noise[2]])


def write_csv(path: Path, rows: np.ndarray) -> Path:
    """Klipper's raw accelerometer CSV of ``rows`` (as ``record`` gives them)."""
    with open(path, "w") as f:
        f.write("#time,accel_x,accel_y,accel_z\n")
        np.savetxt(f, rows, fmt=("%.6f", "%.3f", "%.3f", "%.3f"), delimiter=",")
    return path
