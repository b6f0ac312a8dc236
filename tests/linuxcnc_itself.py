"""LinuxCNC 2.9 itself, headless: a program run by its own task, interpreter and trajectory
planner on a sim configuration with the profile's limits and ``[firmware]`` LinuxCNC settings
(bench/linuxcnc_sim: servo period, arc blends, the startup G64 P Q), recording the joints'
commands every servo period. Takes a program and a profile; gives the X Y Z joint commands
from the program's first motion until it is at rest (None where linuxcnc-uspace is not
installed). One LinuxCNC at a time (its shared memory and FIFO are the machine's): runs wait
on a lock file."""
from __future__ import annotations

import fcntl
import math
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from fbspost.firmware.linuxcnc_segments import LinuxCNCConfig
from fbspost.read.blocks import Kind
from fbspost.read.gcode import read_on_machine

SIM = Path(__file__).resolve().parents[1] / "bench" / "linuxcnc_sim"
_LOCK = Path(tempfile.gettempdir()) / "fbspost-linuxcnc.lock"
END_MM = 0.01  # how near the program's last X Y a record must end


def installed() -> bool:
    return shutil.which("linuxcnc") is not None


def ini_text(profile, tmp: str) -> str:
    """The sim configuration's INI for ``profile`` (its files in ``tmp``)."""
    # the axes' limits the model of LinuxCNC's planner gives them (an axis the profile leaves out,
    # Z on an XY stage, the slowest given axis'): its Z moves run in the same time as the model's
    config = LinuxCNCConfig.from_profile(profile)
    limits = {f"{kind}{a}": values[k] for k, a in enumerate("XYZ")
              for kind, values in (("v", config.axis_velocity_mm_s), ("a", config.axis_acceleration_mm_s2))}
    limits.update(vA=config.other_velocity[0], aA=config.other_acceleration[0])  # (A: the sim's rotary axis)
    lc = profile.firmware.linuxcnc
    # (RS274NGC_STARTUP_CODE = G64 alone left LinuxCNC 2.9 running no motion of the dense butterfly)
    startup = f"RS274NGC_STARTUP_CODE = G64 P{lc.g64_p_mm!r} Q{lc.g64_q_mm!r}" if lc.g64_p_mm or lc.g64_q_mm else ""
    return (SIM / "sim.ini.in").read_text().format(
        here=SIM, tmp=tmp, servo_ns=round(lc.servo_period_s * 1e9), blend_enable=int(lc.arc_blend_enable),
        blend_fallback=int(lc.arc_blend_fallback_enable), blend_depth=lc.arc_blend_optimization_depth,
        blend_gap=lc.arc_blend_gap_cycles, blend_ramp=lc.arc_blend_ramp_freq_hz, blend_kink=lc.arc_blend_kink_ratio,
        # (no limit along the path: one far above the axes')
        max_linear=lc.max_linear_velocity_mm_s if math.isfinite(lc.max_linear_velocity_mm_s) else 1e9,
        startup=startup, **limits)


def joint_commands(program: Path, profile, timeout_s: float = 900.0) -> np.ndarray | None:
    """(n, 3) X Y Z joint commands every servo period of ``program`` run by LinuxCNC itself,
    from its first motion to the period after its last (the machine first moved by MDI to the
    program's first X Y, and Z where it gives one: where the path fbspost reads starts, its first
    move from an unknown position being no part of it); None where LinuxCNC is not installed."""
    if not installed():
        return None
    blocks = list(read_on_machine(program, "linuxcnc", profile))
    start = next(b.position_mm[:3] for b in blocks if not np.isnan(b.position_mm[:2]).any())
    given = np.isfinite(start)
    last = next(b.position_mm[:2] for b in reversed(blocks) if not np.isnan(b.position_mm[:2]).any())
    for _ in range(3):  # (now and then a run records no motion: LinuxCNC still ending the last one)
        joints = _record(program, profile, start, timeout_s)
        # the MDI move to the start may still run when the record starts: from where it is done
        # (halsampler prints 6 decimals; a closed path also ends at the start: the first time there
        # that motion follows)
        at = [k for k in np.flatnonzero(np.all(np.abs(joints[:, given] - start[given]) < 2e-6, axis=1))[:1]
              if np.any(joints[k:] != joints[k])]
        joints = joints[at[0] if at else 0:]
        # (a record that stops before the program's end is no run of it: never figures from it.
        # Under load the dense butterfly's records have ended 1 to 3 um off its end, either side of
        # its last line, not traced: within END_MM)
        if np.any(joints != joints[0]) and np.abs(joints[-1, :2] - last).max() < END_MM:
            return from_first_motion(joints)
        time.sleep(2.0)
    raise RuntimeError(f"LinuxCNC ran no whole run of {program} ({len(joints)} periods recorded, "
                       f"ending at X Y {joints[-1, :2]} for {last})")


def _record(program: Path, profile, first: np.ndarray, timeout_s: float) -> np.ndarray:
    """The joint commands LinuxCNC records while it runs ``program`` from ``first`` (X Y Z; Z NaN:
    where it is)."""
    with tempfile.TemporaryDirectory() as tmp, open(_LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        ini = Path(tmp) / "sim.ini"
        ini.write_text(ini_text(profile, tmp))
        (Path(tmp) / "sim.var").touch()
        (Path(tmp) / "tool.tbl").touch()
        env = {**os.environ, "TP_PROGRAM": str(program.resolve()), "TP_OUT": f"{tmp}/joints.txt",
               "TP_START": " ".join(repr(float(v)) for v in first if np.isfinite(v)),  # (numpy's repr: np.float64(..))
               "RTAPI_FIFO_PATH": f"{tmp}/.rtapi_fifo"}
        command = ["linuxcnc", str(ini)]
        if os.geteuid() == 0:  # rtapi_app refuses root without a user to drop to
            env["RTAPI_UID"] = "65534"
            os.chmod(tmp, 0o777)
            # (not real-time here: ahead of the other tests' work, its task keeps its queue fed)
            command = ["nice", "-n", "-10", *command]
        subprocess.run(command, env=env, cwd=tmp, capture_output=True, timeout=timeout_s)
        return np.loadtxt(f"{tmp}/joints.txt", ndmin=2)[:, :3]


def on_grid(joints: np.ndarray, period_s: float, sample_rate_hz: float) -> np.ndarray:
    """(n, 4) X Y Z E (E 0) of joint commands every ``period_s``, linear between them, on the
    profile's sample grid."""
    t = np.arange(math.floor((len(joints) - 1) * period_s * sample_rate_hz) + 1) / sample_rate_hz
    grid = np.arange(len(joints)) * period_s
    return np.column_stack([np.interp(t, grid, joints[:, i]) for i in range(3)] + [np.zeros(len(t))])


def as_written(blocks, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X Y Z E on the sample grid, move starts, move ends) of ``blocks`` run exactly as written:
    every piece at its F, at rest for a dwell; a move that stops the machine (from an unknown
    place) takes no time."""
    times, points, starts, ends = [0.0], [np.zeros(4)], [], []
    for block in blocks:
        here = points[-1]
        if block.kind is Kind.STOP:
            here = np.where(np.isnan(block.position_mm[:4]), here, block.position_mm[:4])
            times += [times[-1], times[-1] + block.dwell_s]
            points += [here, here]
        elif block.kind is Kind.MOVE and block.points_mm is not None:
            for point in block.points_mm[:, :4]:
                point = np.where(np.isnan(point), here, point)
                times.append(times[-1] + np.linalg.norm(point[:3] - here[:3]) / block.feed_mm_s)
                points.append(point)
                starts.append(here)
                ends.append(point)
                here = point
    times, points = np.array(times), np.array(points)
    t = np.arange(math.floor(times[-1] * sample_rate_hz) + 2) / sample_rate_hz
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    span = np.maximum(times[k + 1] - times[k], 1e-300)
    frac = np.clip((t - times[k]) / span, 0.0, 1.0)[:, None]
    return points[k] + (points[k + 1] - points[k]) * frac, np.array(starts), np.array(ends)


def follows(executed_mm: np.ndarray, written_mm: np.ndarray, path, sample_rate_hz: float,
            min_speed_mm_s: float = 10.0) -> tuple[float, float]:
    """How closely motion ``executed_mm`` follows the command ``written_mm`` (rows X Y Z ... on
    the same grid, both from their first motion) whose path is ``path`` (contour.PathDistance):
    (the largest distance from the path, mm; the largest lag, s: at each sample where the
    command moves faster than ``min_speed_mm_s``, the executed position's offset along the
    command's velocity over its speed, the time the command takes to cover it; negative: ahead)."""
    n = min(len(executed_mm), len(written_mm))
    velocity = np.gradient(written_mm[:n, :3], axis=0) * sample_rate_hz
    speed = np.linalg.norm(velocity, axis=1)
    fast = speed > min_speed_mm_s
    offset_mm = executed_mm[:n, :3][fast] - written_mm[:n, :3][fast]
    ahead_s = np.einsum("ij,ij->i", offset_mm, velocity[fast]) / speed[fast] ** 2
    distance_mm, _ = path(executed_mm[:, :3])
    return float(distance_mm.max()), float(np.abs(ahead_s).max(initial=0.0))


def turns(x_mm: np.ndarray) -> np.ndarray:
    """The samples where ``x_mm`` turns back (its last sample before it moves the other way)."""
    moves = np.flatnonzero(np.diff(x_mm) != 0.0)
    direction = np.sign(np.diff(x_mm)[moves])
    return moves[1:][direction[1:] != direction[:-1]]


def from_first_motion(samples: np.ndarray) -> np.ndarray:
    """``samples`` (rows X Y Z ...) from the last still one before the first motion to the first
    still one after the last."""
    moving = np.flatnonzero(np.any(np.diff(samples[:, :3], axis=0) != 0.0, axis=1))
    return samples[moving[0]:moving[-1] + 2]


def rest_to_rest_ends(text: str, begin: str, end: str, accel_mm_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Every G1 between the lines ``begin`` and ``end`` of a LinuxCNC sweep (fbspost excite's),
    read here: (its line index, when it ends from ``begin``, each block from rest to rest at
    ``accel_mm_s2``: L / F + F / a, the closed form of a trapezoid)."""
    lines = text.splitlines()
    first = lines.index(begin)
    x = next(float(m[1]) for line in reversed(lines[:first]) if (m := re.match(r"G1 X([-\d.]+)", line)))
    index, ends_s, end_s = [], [], 0.0
    for i in range(first + 1, lines.index(end)):
        m = re.fullmatch(r"G1 X([-\d.]+) F([\d.]+)", lines[i])
        feed_mm_s = float(m[2]) / 60.0
        end_s += abs(float(m[1]) - x) / feed_mm_s + feed_mm_s / accel_mm_s2
        x = float(m[1])
        index.append(i)
        ends_s.append(end_s)
    return np.array(index), np.array(ends_s)
