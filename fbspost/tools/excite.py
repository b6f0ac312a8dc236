"""Excitation programs for identification: a sine sweep of one axis, and reading one back.

Takes an axis' limits, a centre position, a band, a duration, a block time and the firmware's
flavor; gives the G-code of a logarithmic sine sweep (chirp) of that axis' position about the
centre, sampled at the block time (the amplitude falling with frequency so that the sampled
velocity, acceleration and jerk stay within the axis' limits, tapered in and out so the motion
starts and ends at rest), written as ``compensate`` writes its blocks so that the firmware runs
them as written: the firmware made transparent around them (``transparency``), G1 blocks whose F
carries the time residues and ramps (``writer.timed_blocks``), within the line budget. LinuxCNC,
whose planner ramps at the INI's acceleration: one block per half period from rest to rest in
whole servo periods (``linuxcnc_sweep``), each taking L / F + F / a.
``read_sweep`` gives back a sweep program's motion as written, ``firmware_sweep`` as its
firmware runs it (``planners.replan``): what ``identify --accel-log`` relates to an
accelerometer recording of it.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..firmware.planners import replan
from ..firmware.transparency import FirmwareSettings, Transparency
from ..job.pipeline import firmware_steps
from ..profile import FLAVORS, AxisProfile, MachineProfile, bundled_profiles, load_profile
from ..read.blocks import AXES, Kind, Modal
from ..read.gcode import read_gcode
from ..write.options import WriteOptions
from ..write.output import dwell_line
from ..write.writer import timed_blocks

SWEEP_BEGINS = "; fbspost excite: sweep begins"
SWEEP_ENDS = "; fbspost excite: sweep ends"
_HEADER = {"band": re.compile(r"; band: ([0-9.]+) Hz to ([0-9.]+) Hz"), "flavor": re.compile(r"; flavor: (\w+)$"),
           "machine": re.compile(r"; machine: (.+)$"), "mark": re.compile(r"; clock mark at ([0-9.]+) s"),
           "accel": re.compile(r"; acceleration ([0-9.]+) mm/s\^2 \(LinuxCNC's")}
# The clock mark: right after the sweep (a rest inside it would be a dwell, after which Marlin
# waits for its buffer to fill), its first MARK_S again, so that identify can tell the recording's
# clock rate from the machine's (a chip's own clock drifts 100 ppm and more: 3 ms over a 30 s
# sweep, 130 degrees at 120 Hz) from where the same low passage falls twice in the recording: the
# axis' own lag is the same both times.
MARK_S = 2.0
_REST_S = 1.0  # dwell before and after the sweep, so a recording holds the rest on both sides
_POSITION_DECIMALS = 6  # 1 nm
_PLAN_RATE_HZ = 10000.0  # the firmware's plan of a sweep, sampled
# a sweep's plan where its profile is not known: a printer's limits, Klipper's defaults (the program
# sets the firmware's limits around the sweep); its steps_per_mm are a guess
_DEFAULT_PROFILE = "printer-two-mode"


@dataclass(frozen=True)
class Sweep:
    """The commanded motion of a sweep program, in the program's time (0 at the sweep's start)."""

    axis: str
    times_s: np.ndarray  # block ends, times_s[0] = 0 at the start position
    positions_mm: np.ndarray
    start_hz: float
    end_hz: float
    flavor: str = "klipper"  # the firmware the program was written for (its header; before it had one: Klipper)
    machine: str | None = None  # the profile it was written for (its header)
    mark_s: float | None = None  # where the clock mark begins (None: a sweep without one)

    def position(self, times_s: np.ndarray) -> np.ndarray:
        """The commanded position at any times (held before the start and after the end)."""
        return np.interp(times_s, self.times_s, self.positions_mm)


def sweep_samples(axis: AxisProfile, centre_mm: float, start_hz: float, end_hz: float, duration_s: float,
                  amplitude_mm: float, block_s: float, ramp_s: float = 0.5) -> np.ndarray:
    """Positions every ``block_s`` from the centre back to the centre: x = c + A(t) sin(phi(t)),
    phi's frequency rising exponentially from start_hz to end_hz over duration_s (and on at the
    same rate over the raised-cosine ramps of ramp_s added before and after, so the whole band
    is swept at full amplitude), A the largest amplitude (at most amplitude_mm) within 90% of
    the axis' limits at the current frequency; then the clock mark: the first MARK_S again,
    its last ramp_s faded out. Scaled down, if needed, until the finite differences of the
    samples, with the rest before and after, keep every limit."""
    t = np.arange(int(round((duration_s + 2 * ramp_s) / block_s)) + 1) * block_s
    rate = math.log(end_hz / start_hz) / duration_s
    f0 = start_hz * math.exp(-rate * ramp_s)
    phase = 2 * math.pi * f0 * np.expm1(rate * t) / rate
    w = 2 * math.pi * f0 * np.exp(rate * t)
    limits = [(axis.max_velocity_mm_s, 1), (axis.max_acceleration_mm_s2, 2)]
    if axis.max_jerk_mm_s3:
        limits.append((axis.max_jerk_mm_s3, 3))
    # 90% of each limit: the rising frequency and the ramps add a little to the sine's derivatives
    amplitude = np.minimum(amplitude_mm, np.min([0.9 * lim / w**k for lim, k in limits], axis=0))
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip(np.minimum(t, t[-1] - t) / ramp_s, 0.0, 1.0))
    offset = amplitude * ramp * np.sin(phase)
    mark = offset[:int(round(MARK_S / block_s))]
    fade = 0.5 + 0.5 * np.cos(np.pi * np.clip((np.arange(len(mark)) * block_s - MARK_S + ramp_s) / ramp_s, 0, 1))
    offset = np.concatenate([offset, mark[1:] * fade[1:], [0.0]])
    padded = np.concatenate([[0.0] * 3, offset, [0.0] * 3])
    worst = max(np.abs(np.diff(padded, k)).max() / block_s**k / lim for lim, k in limits)
    return centre_mm + offset / max(1.0, worst * (1 + 1e-9))


_TOLERANCE_MM = 1e-3  # LinuxCNC's G64 P: the sweep's blocks are collinear, nothing to blend


def linuxcnc_sweep(axis: AxisProfile, centre_mm: float, start_hz: float, end_hz: float, duration_s: float,
                   amplitude_mm: float, servo_period_s: float) -> tuple[np.ndarray, np.ndarray, int]:
    """A sweep LinuxCNC 2.9 runs as written: (positions at the block ends, each block's F in mm/s,
    the clock mark's first block).

    LinuxCNC ramps at the INI's acceleration a (the axis' max_acceleration), which no G-code
    changes, stops at every reversal, and runs short tangent blocks in ramps whose timing
    depends on where their ends fall between servo periods. So the sweep is one block per
    half period, each from rest to rest (the program runs it in G61.1, exact stop): m servo
    periods at +a, c at F = a m T, m at -a, L = a T^2 m (m + c) (1 nm short, so that it ends
    inside its last period, not on its edge: LinuxCNC starts the next block on the next period,
    and a block that ends on the edge would lose one). A block's time is then a whole number
    n = 2m + c of servo periods, L / F + F / a as written: the half periods of the exponential
    sweep from start_hz to end_hz over duration_s, rounded to periods, m (at least 1, F within
    90% of the axis' velocity) the one that ends the block nearest centre_mm -/+ amplitude_mm.
    Then the move back to the start (from rest to rest at 90% of the axis' velocity or less)
    and the clock mark: the sweep's first MARK_S again."""
    a, T = axis.max_acceleration_mm_s2, servo_period_s
    rate = math.log(end_hz / start_hz) / duration_s
    halves = int(2 * start_hz * math.expm1(rate * duration_s) / rate)
    ends = np.round(np.log1p(np.arange(halves + 1) * rate / (2 * start_hz)) / rate / T).astype(np.int64)
    n = np.diff(ends)
    start_nm = round((centre_mm - amplitude_mm) * 1e6)
    at_nm, steps_nm, feeds = start_nm, [], []
    for k, periods in enumerate(n.tolist()):  # each end the nearest it can be to centre -/+ amplitude
        m = np.arange(1, max(1, periods // 2) + 1)
        m = m[(a * m * T <= 0.9 * axis.max_velocity_mm_s) | (m == 1)]
        step = (1 if k % 2 == 0 else -1) * (np.floor(a * T * T * m * (periods - m) * 1e6) - 1)
        best = int(np.argmin(np.abs(at_nm + step - (centre_mm + (1 if k % 2 == 0 else -1) * amplitude_mm) * 1e6)))
        at_nm += int(step[best])
        steps_nm.append(int(step[best]))
        feeds.append(a * m[best] * T)
    steps_nm, feeds = np.array(steps_nm), np.array(feeds)
    mark = int(np.searchsorted(np.cumsum(n), round(MARK_S / T), side="right"))
    sweep_nm = start_nm + np.cumsum(steps_nm)
    back_mm = abs(sweep_nm[-1] - start_nm) * 1e-6
    back = [min(0.9 * axis.max_velocity_mm_s, math.sqrt(a * back_mm))] if back_mm else []  # (none if there)
    positions_nm = np.concatenate([[start_nm], sweep_nm, [start_nm] * len(back),
                                   start_nm + np.cumsum(steps_nm[:mark])])
    return positions_nm * 1e-6, np.concatenate([feeds, back, feeds[:mark]]), halves + len(back)


def sweep_program(profile: MachineProfile, axis_name: str, positions_mm: np.ndarray, block_s: float,
                  start_hz: float, end_hz: float, flavor: str,
                  linuxcnc: tuple[np.ndarray, int] | None = None) -> tuple[str, list[str]]:
    """The G-code of the sampled sweep for ``flavor``'s firmware: move to the start (at a tenth of
    the axis' maximum velocity), the firmware made transparent (``transparency``: limits raised,
    input shaping off), dwell, the sweep's G1 blocks as ``writer.timed_blocks`` writes them (each
    takes its time as the firmware runs it), the profile's settings restored, dwell; and warnings
    (Marlin: how many blocks its short-segment merge leaves). ``linuxcnc``: a ``linuxcnc_sweep``'s
    blocks (F in mm/s, where the clock mark starts) in G61.1, ``block_s`` its servo period."""
    axis = profile.axes[axis_name]
    options = WriteOptions(flavor, tolerance_mm=_TOLERANCE_MM, firmware=FirmwareSettings.from_profile(profile),
                           max_line_rate_hz=profile.firmware.max_line_rate_hz, **firmware_steps(profile, flavor))
    settings = Transparency(flavor, options.firmware, options.tolerance_mm)
    if linuxcnc is None:
        command = np.zeros((len(positions_mm), len(AXES)))
        command[:, AXES.index(axis_name)] = positions_mm
        blocks, motion = timed_blocks(command, block_s, options), _motion_header(positions_mm, block_s, axis, flavor)
    else:
        # (F rounded up: the block reaches it in whole periods of acceleration, then ends inside its last period)
        blocks = [f"G1 {axis_name}{x:.{_POSITION_DECIMALS}f} F{math.ceil(f * 60e4) / 1e4:.4f}"
                  for x, f in zip(positions_mm[1:], linuxcnc[0], strict=True)]
        motion = _linuxcnc_header(positions_mm, *linuxcnc, block_s, axis)
    applied = settings.apply(True, Modal())  # (LinuxCNC: G61.1 instead; G64 restored after it all the same)
    header = [
        f"fbspost excite: a sine sweep of axis {axis_name} for identification",
        f"machine: {profile.name}",
        f"flavor: {flavor}",
        f"band: {start_hz:g} Hz to {end_hz:g} Hz, exponential, {motion[0]}",
        *motion[1:],
        *(settings.header() if linuxcnc is None else []),
        "Home the machine and make sure the axis is free to move there.",
        "Record an accelerometer on the moving part during the whole program, then:",
        f"  fbspost identify --accel-log LOG.csv --program THIS.gcode --axis {axis_name} --machine PROFILE "
        "-o OUT.toml",
    ]
    written = sum(line.startswith("G1 ") for line in blocks)
    warnings = [f"warning: Marlin merges blocks of fewer than {options.min_steps_per_segment} steps: {written} of "
                f"{len(positions_mm) - 1} blocks written, the sweep is coarser where it moves less per block "
                f"(a larger --amplitude or --block-time helps)"] if options.min_steps_per_segment and \
        written < 0.9 * (len(positions_mm) - 1) else []
    start = np.round(positions_mm[0], _POSITION_DECIMALS)
    # (no parentheses: LinuxCNC refuses a comment inside a ';' comment)
    lines = [f"; {text}" for text in header] + [
        "G21 ; millimetres",
        "G90 ; absolute positions",
        f"G1 {axis_name}{start:.{_POSITION_DECIMALS}f} F{60 * axis.max_velocity_mm_s / 10:.0f}",
        *(applied if linuxcnc is None else ["G61.1 ; exact stop: every block from rest to rest"]),
        dwell_line(flavor, _REST_S)[0],
        SWEEP_BEGINS,
        *blocks,
        SWEEP_ENDS,
        *settings.restore(),
        dwell_line(flavor, _REST_S)[0],
        *(["M2"] if flavor == "linuxcnc" else []),
        "",
    ]
    return "\n".join(lines), warnings


def _motion_header(positions_mm: np.ndarray, block_s: float, axis: AxisProfile, flavor: str) -> list[str]:
    """The header's account of a sampled sweep (its band line's end first)."""
    speed = np.abs(np.diff(positions_mm)).max() / block_s
    accel = np.abs(np.diff(positions_mm, 2)).max() / block_s**2
    return [
        f"{(len(positions_mm) - 1) * block_s:g} s with the ramps and the clock mark in {block_s * 1e3:.9g} ms "
        f"blocks, about {positions_mm[0]:.3f} mm",
        f"clock mark at {(len(positions_mm) - 1 - int(round(MARK_S / block_s))) * block_s:.9g} s: the sweep's first "
        f"{MARK_S:g} s again, for the recording's clock rate",
        f"largest amplitude {np.abs(positions_mm - positions_mm[0]).max():.4f} mm, velocity {speed:.4g} mm/s, "
        f"acceleration {accel:.5g} mm/s^2; the axis' limits: {axis.max_velocity_mm_s:g} mm/s, "
        f"{axis.max_acceleration_mm_s2:g} mm/s^2",
        f"Written for {flavor}: the sweep runs with the firmware's limits raised and input shaping off, so that",
        "its blocks take their written times; the profile's settings are restored after it.",
    ]


def _linuxcnc_header(positions_mm: np.ndarray, feeds_mm_s: np.ndarray, mark: int, servo_period_s: float,
                     axis: AxisProfile) -> list[str]:
    """The header's account of a ``linuxcnc_sweep`` (its band line's end first)."""
    a = axis.max_acceleration_mm_s2
    lengths = np.abs(np.diff(positions_mm))
    times = _rest_to_rest(np.concatenate([[0.0], np.cumsum(lengths / feeds_mm_s)]), feeds_mm_s, a)
    return [
        f"{times[-1]:.9g} s with the move back and the clock mark, one block per half period from rest to rest, "
        f"about {(positions_mm.min() + positions_mm.max()) / 2:.3f} mm",
        f"clock mark at {times[mark]:.9g} s: the sweep's first {MARK_S:g} s again, for the recording's clock rate",
        f"acceleration {a:g} mm/s^2 (LinuxCNC's INI, no G-code raises it): each block of length L at F takes "
        "L / F + F / a",
        f"largest amplitude {lengths.max() / 2:.4f} mm, velocity {feeds_mm_s.max():.4g} mm/s; the axis' limits: "
        f"{axis.max_velocity_mm_s:g} mm/s, {a:g} mm/s^2",
        f"Written for linuxcnc: each block from rest to rest (G61.1) in whole {servo_period_s * 1e3:g} ms servo "
        "periods, so that it takes its written time; G64 is restored after it.",
    ]


_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


def read_sweep(path: str | Path, axis: str) -> Sweep:
    """The motion of a program written by ``sweep_program`` for ``axis`` as written: the position
    at the begin marker, then every G1 (time = length / F) and G4 (P: ms, on LinuxCNC s) up to
    the end marker; and its header's band, flavor and machine."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"cannot read: {exc}") from None
    position = feed = None
    header = {"band": None, "flavor": "klipper", "machine": None, "mark": None, "accel": None}
    times, positions, feeds, inside, ended = [], [], [], False, False
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        for key, pattern in _HEADER.items() if not inside else ():
            if match := pattern.match(stripped):
                header[key] = match.groups() if key == "band" else match[1]
        flavor = header["flavor"]
        if flavor not in FLAVORS:
            raise InputError(path, lineno, f"flavor {flavor!r}: expected one of {', '.join(FLAVORS)}")
        if stripped == SWEEP_BEGINS:
            if position is None:
                raise InputError(path, lineno, f"the sweep begins before any G1 {axis} sets the start position")
            inside, times, positions, feeds = True, [0.0], [position], []
            continue
        if stripped == SWEEP_ENDS:
            ended = inside
            break
        words = [(k.upper(), float(v)) for k, v in _WORD.findall(line.split(";", 1)[0])]
        codes = [int(v) for k, v in words if k == "G"]
        if 91 in codes:
            raise InputError(path, lineno, "G91: a sweep program is in absolute positions")
        if 4 in codes and inside:
            dwell = next((v for k, v in words if k == "P"), 0.0)
            times.append(times[-1] + (dwell if flavor == "linuxcnc" else dwell / 1e3))
            positions.append(position)
            feeds.append(0.0)
        elif {0, 1} & set(codes):
            target = next((v for k, v in words if k == axis), None)
            feed = next((v for k, v in words if k == "F"), feed)
            others = [k for k, _ in words if k in "XYZABCUVWE" and k != axis]
            if inside and (others or target is None or not feed):
                raise InputError(path, lineno, f"a sweep block moves {axis} alone, with a feed")
            if target is not None:
                if inside:
                    times.append(times[-1] + abs(target - position) / (feed / 60))
                    positions.append(target)
                    feeds.append(feed / 60)
                position = target
    if not ended:
        raise InputError(path, None, f"no sweep of axis {axis} between '{SWEEP_BEGINS}' and '{SWEEP_ENDS}': "
                                     "not a program written by fbspost excite?")
    if header["band"] is None:
        raise InputError(path, None, "no '; band: ... Hz to ... Hz' line")
    start_hz, end_hz = (float(f) for f in header["band"])
    if header["accel"] is not None:
        times = _rest_to_rest(np.array(times), np.array(feeds), float(header["accel"]))
    return Sweep(axis, np.array(times), np.array(positions), start_hz, end_hz, flavor, header["machine"],
                 None if header["mark"] is None else float(header["mark"]))


def _rest_to_rest(times_s: np.ndarray, feeds_mm_s: np.ndarray, accel_mm_s2: float) -> np.ndarray:
    """The block ends of a LinuxCNC sweep (``read_sweep``'s, length / F) with each block from
    rest to rest at ``accel_mm_s2`` (its header's): L / F + F / a; dwells (F 0) as written."""
    return np.concatenate([[0.0], np.cumsum(np.diff(times_s) + feeds_mm_s / accel_mm_s2)])


def firmware_sweep(path: str | Path, axis: str, profile: MachineProfile) -> Sweep:
    """The sweep program at ``path`` (checked by ``read_sweep``) as its firmware runs it:
    ``planners.replan`` of the whole program with ``profile`` for the flavor its header names,
    ``axis``' position every 0.1 ms from the begin marker's time to the end of the sweep's last
    block or dwell (times from the begin marker)."""
    written = read_sweep(path, axis)
    blocks = list(read_gcode(path, written.flavor, profile.home_mm))
    # (finely: linear interpolation between samples a fraction of a block off the blocks' ends would
    # low-pass the command, by 5% at 100 Hz at 1 kHz)
    profile = replace(profile, sample_rate_hz=max(profile.sample_rate_hz, _PLAN_RATE_HZ))
    motion = replan(blocks, profile, written.flavor, every_axis=True)  # (the axis may have no modes yet)
    marks = [b.raw.strip() for b in blocks]
    begin, end = marks.index(SWEEP_BEGINS.encode()), marks.index(SWEEP_ENDS.encode())
    # (the model of LinuxCNC's planner times a stop after its dwell, the others before it)
    dwells = [b.dwell_s if b.kind is Kind.STOP and written.flavor != "linuxcnc" else 0.0 for b in blocks]
    begin_s, end_s = _done_s(motion.line_time_s, dwells, 0, begin), _done_s(motion.line_time_s, dwells, begin, end)
    fs = profile.sample_rate_hz
    times_s = np.arange(int(math.ceil((end_s - begin_s) * fs)) + 1) / fs
    grid_s = np.arange(len(motion.positions_mm)) / fs
    positions_mm = np.interp(begin_s + times_s, grid_s, motion.positions_mm[:, AXES.index(axis)])
    # The mark's time as designed (the header's: the sweep's samples, block_s apart, which the
    # firmware is made to run as written) scaled to the plan's length: near enough for identify, which
    # finds it in the plan within 50 ms. (Not the program's own block times: on Marlin its whole
    # steps make those 3% short, which put the mark 0.4 s late on a 12 s sweep.)
    mark_s = written.mark_s and written.mark_s * times_s[-1] / (written.mark_s + MARK_S)
    return replace(written, times_s=times_s, positions_mm=positions_mm, mark_s=mark_s)


def _done_s(line_time_s: np.ndarray, dwells_s: list[float], first: int, stop: int) -> float:
    """When the firmware is done with the lines ``first`` to ``stop`` - 1 (``line_time_s`` as
    ``planners.replan`` gives it, ``dwells_s`` what each line dwells after it): the end of their
    last motion or dwell (Marlin, RRF: a line without motion is timed when the host sends it,
    ahead of the motion, and a comment, not sent, not at all)."""
    return float(np.nanmax([line_time_s[k] + dwells_s[k] for k in range(first, stop)]))


def commanded_sweep(path: str | Path, axis: str, machine: str | Path | None, lines: list[str]) -> Sweep:
    """The sweep program at ``path`` as its firmware runs it (``firmware_sweep``) on the profile
    ``machine`` (a bundled name or a file), else on the bundled profile its header names, else on
    ``_DEFAULT_PROFILE`` (the program's own settings; said in ``lines``)."""
    if machine is None:
        machine = read_sweep(path, axis).machine
        if machine not in bundled_profiles():
            lines.append(f"{Path(path).name}: no --machine and no bundled profile named in it: planned as its "
                         f"firmware runs it with the program's own settings on the profile {_DEFAULT_PROFILE}")
            machine = _DEFAULT_PROFILE
    return firmware_sweep(path, axis, load_profile(machine))
