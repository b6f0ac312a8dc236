"""What a program does on a machine, compensated or not: the original plan, FBS and Klipper's input
shapers, each through the axes' models, side by side.

Takes a program, a machine profile, the shapers to compare (their frequency and damping per axis,
by default the axis' dominant mode) and optionally a compensated program to execute instead of
compensating now; gives a ``Simulation``: one time grid (the profile's sample period, from the
earliest shaped start to the latest end plus ``settle_s``), the planned positions, the programmed
path, and per method its command, its modelled actual positions and their ``Metrics``.

- Methods: ``original`` (the plan, as the machine's controller runs it), ``fbs`` (the plan
  compensated per run of motion as ``fbspost compensate`` does; or a compensated program run
  block by block at its feed, no acceleration, as its dense output is meant to run), and each
  shaper applied to the plan of every axis with modes (``shapers.shape``).
- Tracking error: planned minus modelled actual position (path: the XYZ distance), over the
  whole grid. Contour error: distance from the modelled actual position to the programmed
  path (the planned pieces' straight lines, arcs as their chords), in XYZ so that a print's
  layers are not taken for each other (Z is the plan's unless Z has modes). If the program
  extrudes at all (a printer), the path is its extruding moves and the samples those where the
  planned E rises on both sides; otherwise the path is its feed moves (every move but LinuxCNC's
  G0) and the samples those inside them. Command contour error: the same for the command itself
  (a shaper's smoothing, its corner rounding; FBS's deliberate pre-distortion).
- Machine: each modelled axis' modes; where the profile makes them vary (``moving_mass``,
  ``modes_by_position``), the modes in force at each sample of the plan (``varying``);
  ``model_error`` scales the modes of every level alike.
- Residual vibration: the largest |actual - final position| over ``settle_s`` after the
  command's last motion. Duration: from the command's first motion (of any axis) to its last.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..contour import PathDistance
from ..errors import InputError
from ..fbs.dynamics import AxisDynamics, scaled_mode
from ..firmware.shapers import SHAPERS, Shaper, klipper_shaper, shape
from ..job.axes import varying_modes
from ..job.pipeline import compensated_samples
from ..plan.margins import RunMargins
from ..plan.pieces import EXTRUDE_ONLY_MM, fill_unknown
from ..plan.planner import Plan, PlanStream, plan_blocks
from ..profile import AxisProfile, MachineProfile, ProfileError, with_travel
from ..read.blocks import AXES, Block, Kind, feed_lengths
from ..read.flavors import detect_flavor
from ..read.gcode import read_on_machine

# --model-error: the machines the commands run on, (frequency scale, damping scale) of every mode
MODEL_ERRORS = (*((1.0 + 0.025 * i, 1.0) for i in range(-4, 5)), (1.0, 0.8), (1.0, 1.25))
SETTLE_PERIODS = 5.0  # residual vibration is watched for this many periods of the lowest mode
MOVING_MM = 1e-9  # a command this far from its rest has left it (shaped rests round to ~1e-13)
_XYZ = slice(0, 3)


@dataclass(frozen=True)
class AxisMetrics:
    rms_tracking_error_um: float
    max_tracking_error_um: float
    residual_vibration_um: float
    max_velocity_mm_s: float  # of the command
    max_acceleration_mm_s2: float  # of the command, second differences on the grid


@dataclass(frozen=True)
class PathMetrics:
    rms_contour_error_um: float
    max_contour_error_um: float
    rms_tracking_error_um: float
    max_tracking_error_um: float
    residual_vibration_um: float
    rms_command_contour_error_um: float
    max_command_contour_error_um: float
    duration_s: float
    added_duration_s: float  # over the original's
    start_advance_s: float  # starts this much before the original
    end_delay_s: float  # ends this much after the original
    max_velocity_mm_s: float  # XYZ
    max_acceleration_mm_s2: float  # XYZ


@dataclass
class Method:
    name: str  # original | fbs | a shaper name
    label: str  # for people: how it was made
    shapers: dict[str, Shaper]  # per axis; empty but for shapers
    command_mm: np.ndarray  # (n, 4) on the grid
    actual_mm: np.ndarray  # (n, 4) modelled
    contour_error_mm: np.ndarray  # at the contour samples
    nearest_mm: np.ndarray  # (k, 3) the path's point nearest to each of those actual positions
    path: PathMetrics | None = None
    axes: dict[str, AxisMetrics] = field(default_factory=dict)


@dataclass
class Simulation:
    program: str
    profile: MachineProfile
    flavor: str
    printer: bool  # the program extrudes: contour error on extruding moves, else on feed moves
    time_s: np.ndarray  # (n,) the grid; 0 is the plan's start
    desired_mm: np.ndarray  # (n, 4) the plan, held at rest before and after
    contour_mask: np.ndarray  # (n,) samples inside the contour moves
    path_start_mm: np.ndarray  # (m, 3) XYZ: the programmed path's pieces
    path_end_mm: np.ndarray
    settle_s: float
    modelled: list[str]  # axes with modes
    methods: list[Method] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """The ``--json`` document (keys documented in docs/simulate.md)."""
        return {
            "program": self.program,
            "profile": self.profile.name,
            "flavor": self.flavor,
            "sample_rate_hz": self.profile.sample_rate_hz,
            "contour_moves": "extruding" if self.printer else "feed",
            "settle_s": self.settle_s,
            "start_s": float(self.time_s[0]),
            "end_s": float(self.time_s[-1]),
            "methods": [{
                "name": m.name,
                "label": m.label,
                "shaper": {a: {"type": s.name, "frequency_hz": s.frequency_hz, "damping": s.damping,
                               "amplitudes": s.amplitudes.tolist(), "times_s": s.times_s.tolist()}
                           for a, s in m.shapers.items()} or None,
                "path": asdict(m.path),
                "axes": {a: asdict(v) for a, v in m.axes.items()},
            } for m in self.methods],
            "warnings": list(self.warnings),
        }


def dominant_mode(axis: AxisProfile):
    """The mode with the highest resonance peak |alpha + j beta w| / (2 damping w^2): the peak a
    resonance test (Klipper's calibrate_shaper) finds."""
    return max(
        axis.modes, key=lambda m: abs(complex(m.alpha, m.beta * m.omega_rad_s)) / (2 * m.damping * m.omega_rad_s**2)
    )


def shaper_settings(profile: MachineProfile, frequency_hz: dict[str, float] | None = None,
                    damping: dict[str, float] | None = None) -> dict[str, tuple[float, float]]:
    """(frequency, damping) of the shapers per axis with modes: the given ones, else the
    dominant mode's. A given axis without modes is an error."""
    modelled = _modelled(profile)
    for given in (frequency_hz or {}, damping or {}):
        for axis in given:
            if axis not in modelled:
                raise ValueError(f"axis {axis} has no modes in {profile.name}: shapers go on {', '.join(modelled)}")
    settings = {}
    for name in modelled:
        mode = dominant_mode(profile.axes[name])
        settings[name] = ((frequency_hz or {}).get(name, mode.frequency_hz), (damping or {}).get(name, mode.damping))
    return settings


def simulate_program(program: str | Path, profile: MachineProfile, shapers: tuple[str, ...] = SHAPERS,
                     settings: dict[str, tuple[float, float]] | None = None, compensated: str | Path | None = None,
                     flavor: str | None = None, margins: RunMargins | None = None) -> Simulation:
    """Every method on ``program`` (see the module docstring); ``settings`` as ``shaper_settings``
    gives them (its default); ``margins`` as ``compensate`` gives the runs (its default), so that
    a compensated program's time matches the plan's."""
    modelled = _modelled(profile)
    if not modelled:
        raise ProfileError(f"{profile.source}: no axis has modes: nothing to simulate")
    flavor = flavor or detect_flavor(program)
    profile = with_travel(profile, flavor)  # (as compensate: the command within the firmware's travel)
    blocks = list(read_on_machine(program, flavor, profile, within_travel=True))
    margins = margins or RunMargins.for_profile(profile, flavor=flavor)
    plan = plan_blocks(blocks, profile, margins=margins, firmware=flavor)
    if not plan.runs:
        raise InputError(program, None, "no motion to simulate")
    settings = settings or shaper_settings(profile)
    shaper_rows = {name: {a: klipper_shaper(name, *settings[a]) for a in modelled} for name in shapers}
    period_s = 1.0 / profile.sample_rate_hz
    executed = None
    if compensated:
        written = read_on_machine(compensated, flavor, profile)
        executed = execute_program(_as_planned(written, profile, flavor))

    # The grid: rest before the earliest shaped start, after the latest end, then the settling.
    leads = [s.lead_s for row in shaper_rows.values() for s in row.values()]
    lags = [s.lag_s for row in shaper_rows.values() for s in row.values()]
    if executed:
        lags.append(executed[0][-1] - (len(plan.positions_mm) - 1) * period_s)
    settle_s = SETTLE_PERIODS / min(m.frequency_hz for a in modelled for m in profile.axes[a].modes)
    before = math.ceil(max(leads, default=0.0) / period_s - 1e-9)
    after = math.ceil(max(lags + [0.0]) / period_s - 1e-9) + math.ceil(settle_s / period_s)
    desired = np.pad(plan.positions_mm, ((before, after), (0, 0)), mode="edge")
    time_s = (np.arange(len(desired)) - before) * period_s
    printer, mask, starts, ends = _contour_moves(blocks, plan, time_s, desired)
    sim = Simulation(str(program), profile, flavor, printer, time_s, desired, mask, starts, ends, settle_s, modelled,
                     warnings=[f"plan: {note}" for note in plan.notes])
    if executed:
        command = np.column_stack([np.interp(time_s, executed[0], executed[1][:, i]) for i in range(len(AXES))])
        # the axes without modes follow the plan in the written program (their copied moves at rest
        # jump here where the plan jumps at the rest's end)
        unmodelled = [i for i, a in enumerate(AXES) if a not in modelled]
        command[:, unmodelled] = desired[:, unmodelled]
        fbs = ("fbs", f"fbs: {compensated} run block by block at its feed", command)
    else:
        optimizer_warnings = []
        command = np.pad(
            compensated_samples(plan, profile, warnings=optimizer_warnings), ((before, after), (0, 0)), mode="edge"
        )
        sim.warnings += [f"fbs: {w}" for w in optimizer_warnings]
        fbs = ("fbs", "fbs: compensated now", command)
    rows = [("original", "original: the plan", desired), fbs]
    for name, row in shaper_rows.items():
        command = desired.copy()
        for axis, shaper in row.items():
            command[:, AXES.index(axis)] = shape(desired[:, AXES.index(axis)], period_s, shaper)
        label = f"{name}: " + ", ".join(f"{a} {s.frequency_hz:.4g} Hz damping {s.damping:.3g}" for a, s in row.items())
        rows.append((name, label, command))

    machines = {AXES.index(a): _machine(profile, a, desired) for a in modelled}
    distance = PathDistance(starts, ends)
    for name, label, command in rows:
        actual = command.copy()
        for column, machine in machines.items():
            actual[:, column] = machine(command[:, column])
        error, nearest = distance(actual[mask, _XYZ])
        sim.methods.append(Method(name, label, shaper_rows.get(name, {}), command, actual, error, nearest))
    _measure(sim, period_s, distance)
    return sim


def _machine(profile: MachineProfile, axis: str, desired_mm: np.ndarray):
    """The axis' actual position as a function of its command (mm, every sample): its modes, or
    where they vary with the print or along an axis, the modes in force at each sample of the
    plan (``desired_mm``)."""
    varying = varying_modes(profile, profile.axes[axis])
    if varying is None:
        return AxisDynamics(profile.axes[axis].modes, 1.0 / profile.sample_rate_hz).simulate
    levels = varying.levels(desired_mm[:, varying.column])
    return lambda command_mm: varying.simulate(command_mm, levels)


def model_error(sim: Simulation, points=MODEL_ERRORS) -> list[tuple[float, float, dict[str, float]]]:
    """Every method's command, as made for the nominal profile, run on machines whose every mode
    has its frequency and damping scaled (where the modes vary, at every level): per (frequency
    scale, damping scale) of ``points``, the RMS contour error (um) by method name."""
    distance = PathDistance(sim.path_start_mm, sim.path_end_mm)
    table = []
    for frequency_scale, damping_scale in points:
        axes = {a: replace(sim.profile.axes[a], modes=tuple(scaled_mode(m, frequency_scale, damping_scale)
                                                              for m in sim.profile.axes[a].modes))
                for a in sim.modelled}
        perturbed = replace(sim.profile, axes={**sim.profile.axes, **axes})
        machines = {AXES.index(a): _machine(perturbed, a, sim.desired_mm) for a in sim.modelled}
        errors = {}
        for method in sim.methods:
            actual = method.command_mm[sim.contour_mask].copy()  # the contour samples' XYZ, once simulated
            for column, machine in machines.items():
                actual[:, column] = machine(method.command_mm[:, column])[sim.contour_mask]
            errors[method.name] = _rms_um(distance(actual[:, _XYZ])[0])
        table.append((frequency_scale, damping_scale, errors))
    return table


def _as_planned(blocks, profile: MachineProfile, flavor: str) -> list[Block]:
    """``blocks`` as the planner takes them: a line that moves no compensated axis (a retraction,
    a Z move) is a rest as long as the controller takes for it (``planner.PlanStream``)."""
    return [block for block, _, _ in PlanStream(blocks, profile, firmware=flavor).blocks()]


def execute_program(blocks: list[Block]) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints (times_s (m,), positions_mm (m, len(AXES))) of ``blocks`` run one after another, every
    linear piece of a MOVE at its block's feed without acceleration (a G5 as its chords, a
    LinuxCNC G0 in no time); a STOP waits its dwell where it puts the machine. Unknown positions
    are held as the planner holds them."""
    points, feeds, dwells = [np.full((1, len(AXES)), np.nan)], [math.inf], [0.0]
    for block in blocks:
        if block.kind is Kind.MOVE and block.points_mm is not None:
            points.append(block.points_mm)
            feeds += [block.feed_mm_s] * len(block.points_mm)
            dwells += [0.0] * len(block.points_mm)
        elif block.kind is Kind.STOP:  # there at once (a jump if it moved the machine), then the dwell
            points.append(np.vstack([block.position_mm, block.position_mm]))
            feeds += [math.inf, math.inf]
            dwells += [0.0, block.dwell_s]
    filled, _ = fill_unknown(np.concatenate(points))
    delta = np.diff(filled, axis=0)
    length = feed_lengths(delta, still_mm=EXTRUDE_ONLY_MM)[0]
    steps = length / np.asarray(feeds[1:]) + np.asarray(dwells[1:])
    return np.concatenate([[0.0], np.cumsum(steps)]), filled


def _modelled(profile: MachineProfile) -> list[str]:
    return [a for a in AXES if a in profile.axes and profile.axes[a].modes]


def _contour_moves(blocks: list[Block], plan: Plan, time_s: np.ndarray, desired_mm: np.ndarray):
    """(printer, the contour samples, the contour pieces' XYZ starts and ends). A printer's
    samples are those where the planned E rises on both sides (inside an extruding move, not at
    its junction with a travel); a CNC's those inside a feed move's time."""
    pieces = plan.pieces
    extruding = pieces.end_mm[:, 3] > pieces.start_mm[:, 3]
    printer = bool(extruding.any())
    if printer:
        chosen = extruding
        rising = np.diff(desired_mm[:, 3]) > 0
        mask = np.append(rising, False) & np.insert(rising, 0, False)
    else:
        chosen = np.isfinite([blocks[b].feed_mm_s for b in pieces.block])
        inside = np.searchsorted(pieces.start_s, time_s, side="right") - 1
        piece = np.maximum(inside, 0)
        mask = (inside >= 0) & chosen[piece] & (time_s <= pieces.start_s[piece] + pieces.duration_s[piece])
    return printer, mask, pieces.start_mm[chosen, _XYZ], pieces.end_mm[chosen, _XYZ]


def _measure(sim: Simulation, period_s: float, distance: PathDistance) -> None:
    """Every method's metrics; the original's timing is the reference for the others'."""
    columns = [AXES.index(a) for a in sim.modelled]
    settle = math.ceil(sim.settle_s / period_s)
    reference = None
    for method in sim.methods:
        command, actual = method.command_mm, method.actual_mm
        # the last sample before the command leaves its start, the first at its end for good
        first = np.argmax(np.abs(command - command[0]).max(axis=1) > MOVING_MM) - 1
        last = len(command) - np.argmax(np.abs(command - command[-1]).max(axis=1)[::-1] > MOVING_MM)
        start_s, end_s = sim.time_s[first], sim.time_s[last]
        reference = reference or (start_s, end_s)
        error = sim.desired_mm - actual
        residual = actual[last:last + settle + 1] - command[last]
        velocity = np.diff(command, axis=0) / period_s
        accel = np.diff(command, 2, axis=0) / period_s**2
        command_error, _ = distance(command[sim.contour_mask, _XYZ])
        method.axes = {sim.modelled[i]: AxisMetrics(
            _rms_um(error[:, c]), _max_um(error[:, c]), _max_um(residual[:, c]),
            float(np.abs(velocity[:, c]).max()), float(np.abs(accel[:, c]).max()))
            for i, c in enumerate(columns)}
        method.path = PathMetrics(
            _rms_um(method.contour_error_mm), _max_um(method.contour_error_mm),
            _rms_um(np.linalg.norm(error[:, _XYZ], axis=1)), _max_um(np.linalg.norm(error[:, _XYZ], axis=1)),
            _max_um(np.linalg.norm(residual[:, _XYZ], axis=1)),
            _rms_um(command_error), _max_um(command_error),
            float(end_s - start_s), float((end_s - start_s) - (reference[1] - reference[0])),
            float(reference[0] - start_s), float(end_s - reference[1]),
            float(np.linalg.norm(velocity[:, _XYZ], axis=1).max()), float(np.linalg.norm(accel[:, _XYZ], axis=1).max()))


def _rms_um(error_mm: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(error_mm)))) * 1e3 if error_mm.size else 0.0


def _max_um(error_mm: np.ndarray) -> float:
    return float(np.abs(error_mm).max(initial=0.0)) * 1e3
