"""Sampled trajectories as CSV: one row per sample, a header naming the columns.

Takes a CSV whose header is ``time_s`` (optional) followed by axis letters (``X``, ``Y``, ...),
one row per sample on a uniform grid; gives a ``Trajectory`` of float arrays, and writes one
back in the same layout (the time column's text is kept as read). Malformed input raises
``InputError`` naming the file and line.
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..profile import AXIS_NAMES
from ..write.atomicfile import atomic_write


@dataclass
class Trajectory:
    axes: dict[str, np.ndarray]  # axis letter -> positions, mm
    time_text: list[str] | None  # the time column as written, if there was one


def read_trajectory_csv(path: str | Path, sample_rate_hz: float) -> Trajectory:
    """Read a trajectory and check that its time column, if any, steps at 1 / sample_rate_hz."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    rows = csv.reader(io.StringIO(text))
    header = next(rows, None)
    if not header:
        raise InputError(path, 1, "empty file: expected a header such as time_s,X,Y")
    names = [h.strip() for h in header]
    has_time = names[0] in ("time_s", "t")
    axes = names[1:] if has_time else names
    for name in axes:
        if len(name) != 1 or name not in AXIS_NAMES:
            raise InputError(path, 1, f"column {name!r} is not an axis letter ({AXIS_NAMES}) or time_s")
    if len(set(axes)) != len(axes) or not axes:
        raise InputError(path, 1, "the header must name each axis once")
    values, time_text = [], []
    for lineno, row in enumerate(rows, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) != len(names):
            raise InputError(path, lineno, f"expected {len(names)} values, got {len(row)}")
        try:
            numbers = [float(cell) for cell in row]
        except ValueError:
            raise InputError(path, lineno, f"not a number in {','.join(row)!r}") from None
        if not all(math.isfinite(v) for v in numbers):
            raise InputError(path, lineno, "values must be finite")
        values.append(numbers)
        if has_time:
            time_text.append(row[0].strip())
    if not values:
        raise InputError(path, 2, "no samples")
    data = np.array(values)
    if has_time and len(data) > 1:
        step = np.diff(data[:, 0])
        period_s = 1.0 / sample_rate_hz
        bad = np.flatnonzero(np.abs(step - period_s) > 1e-6 * period_s + 1e-9)
        if bad.size:
            i = int(bad[0])
            raise InputError(path, i + 3, f"time step {step[i]:.9g} s, the profile's sample period is {period_s:.9g} s")
    columns = data[:, 1:] if has_time else data
    return Trajectory({name: columns[:, j].copy() for j, name in enumerate(axes)}, time_text if has_time else None)


def write_trajectory_csv(path: str | Path, trajectory: Trajectory) -> None:
    """Write atomically, positions to 1e-9 mm."""
    names = list(trajectory.axes)
    columns = np.column_stack([trajectory.axes[n] for n in names])
    body = io.StringIO()
    np.savetxt(body, columns, fmt="%.9f", delimiter=",")
    lines = body.getvalue().splitlines()
    if trajectory.time_text is not None:
        names = ["time_s", *names]
        lines = [f"{t},{line}" for t, line in zip(trajectory.time_text, lines, strict=True)]
    payload = (",".join(names) + "\n" + "\n".join(lines) + "\n").encode()
    atomic_write(path, lambda f: f.write(payload))
