"""LinuxCNC programs through LinuxCNC's own interpreter: ``--expand``.

Takes a LinuxCNC program that uses what fbspost does not interpret itself (parameters and
expressions, O-word subroutines and control flow, canned cycles, cutter compensation, inverse
time feed, ...), runs it through ``rs274`` (Debian's ``linuxcnc-uspace``: LinuxCNC's standalone
interpreter, 2.9) and gives the program it executes as plain G-code: its canonical moves as G0,
G1, G2/G3, with the spindle, coolant, tool changes, I/O, dwells, messages, stops, motion control
mode and program end written back as G-code at their places. The expanded program is in mm (G21),
absolute (G90, incremental arc centres G91.1); the program's G92 and tool length offsets (from the
tool table given) are added into its coordinates (G49 in its header). The machine's own G92
offsets (LinuxCNC keeps them from program to program) stay on, as for the original, whose G92
offsets are rs274's plus them (a G92 is relative to where the tool is), until the program takes
its offsets off (G92.1, G92.2): there G92.2 is written (it keeps the machine's stored; G92.1 would
zero them; a G92.3 after it, which puts the machine's back for the original, is not
reproduced); work coordinate
systems are selected as the program selects them, and offsets the program sets itself (G10 L2,
L20) are written back as G10 L2. Coordinates are rs274's: 4 decimals in the program's units
(0.1 um in mm, 2.54 um in inches); a helix narrower than those digits is its axis' line. With
the machine's INI, rs274 runs in the INI's directory, as LinuxCNC does (relative subroutine
paths, remaps).

G5/G5.1 splines, which rs274 prints without their control points, are run in a copy of the
program that reports them (``rs274_splines``) and written back as G5/G5.1 in mm. Probes are written
back as the program's G38 (its code reported the same way, ``rs274_probes``) to rs274's target at
the program's feed; the next move writes X Y Z; a program whose later motion depends on where a
probe stops is refused (``rs274_probes``: rs274 run again with every probe's target moved).
Spindle-synchronized moves (START_SPEED_FEED_SYNC ... STOP_SPEED_FEED_SYNCH: G33, G76) are
written as G33 with rs274's pitch K in mm (6 printed digits of it: 1e-6 of the unit per revolution).

Refused (``InputError``): what rs274 reports without its data (G5.2 NURBS: ``NURBS_FEED`` gives
no control points; M66 waits), probes that later motion depends on, an arc, spline or inverse
time move right after a probe, synchronized arcs, feed per revolution, coordinate rotation,
U V W, and rs274's own errors (with the line it names; for G6.2, that this
install's rs274, LinuxCNC 2.9, does not run it). ``check_remaps``: a machine INI that remaps a
code fbspost writes itself.
"""
from __future__ import annotations

import functools
import math
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError
from .rs274_probes import DELTA, check_probes, check_static, probe_calls, probe_lines
from .rs274_splines import instrumented, spline_calls

INSTALL_HINT = "LinuxCNC's interpreter rs274 is not installed: apt-get install linuxcnc-uspace"
_CALL = re.compile(r"\s*\d+\s+N\S*\s+([A-Z0-9_]+)\((.*)\)\s*$")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_G62 = re.compile(r"(?<![A-Za-z#<])G\s*0*6\s*\.\s*2(?!\d)", re.IGNORECASE)
_M66 = re.compile(r"^[^;(]*?(?<![A-Za-z#<])M\s*0*66(?![\d.])", re.IGNORECASE)
_PLANES = {"CANON_PLANE_XY": (0, 1, 2, 17), "CANON_PLANE_YZ": (1, 2, 0, 19), "CANON_PLANE_XZ": (2, 0, 1, 18)}
_WCS = ["G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3"]
# M2/M30 print SET_G5X_OFFSET, then some of these (its resets), then PROGRAM_END; M6 prints
# START_CHANGE ... CHANGE_TOOL
_END_RESETS = {"SET_XY_ROTATION", "SELECT_PLANE", "SET_FEED_MODE", "SET_FEED_RATE", "STOP_SPINDLE_TURNING",
               "SET_SPINDLE_MODE", "PALLET_SHUTTLE", "MIST_OFF", "FLOOD_OFF", "COMMENT", "SET_MOTION_CONTROL_MODE",
               "SET_NAIVECAM_TOLERANCE", "USE_LENGTH_UNITS", "SET_G92_OFFSET", "USE_TOOL_LENGTH_OFFSET"}
# canonical calls that are state fbspost writes in its own way (or nothing at all)
STATE_CALLS = {"USE_LENGTH_UNITS", "SET_G5X_OFFSET", "SET_G92_OFFSET", "SET_XY_ROTATION", "SET_FEED_REFERENCE",
               "ON_RESET", "USE_TOOL_LENGTH_OFFSET", "SET_FEED_RATE", "SET_FEED_MODE", "SELECT_PLANE",
               "SET_SPINDLE_MODE", "COMMENT", "SET_NAIVECAM_TOLERANCE"}
MOTION_CALLS = {"STRAIGHT_TRAVERSE", "STRAIGHT_FEED", "ARC_FEED", "NURBS_FEED", "SPLINE_FEED", "STRAIGHT_PROBE"}
_SIMPLE = {  # canonical call -> G-code, {0}, {1} its arguments
    "SET_SPINDLE_SPEED": "S{1}{s0}", "START_SPINDLE_CLOCKWISE": "M3{s0}", "START_SPINDLE_COUNTERCLOCKWISE": "M4{s0}",
    "STOP_SPINDLE_TURNING": "M5{s0}", "ORIENT_SPINDLE": "M19 R{1} P{2}{s0}", "MIST_ON": "M7", "FLOOD_ON": "M8",
    "DWELL": "G4 P{0}", "SELECT_TOOL": "T{0}", "MESSAGE": "(MSG,{0})",
    "LOG": "(LOG,{0})", "LOGOPEN": "(LOGOPEN,{0})", "LOGAPPEND": "(LOGAPPEND,{0})", "LOGCLOSE": "(LOGCLOSE)",
    "SET_MOTION_OUTPUT_BIT": "M62 P{0}", "CLEAR_MOTION_OUTPUT_BIT": "M63 P{0}", "SET_AUX_OUTPUT_BIT": "M64 P{0}",
    "CLEAR_AUX_OUTPUT_BIT": "M65 P{0}", "SET_MOTION_OUTPUT_VALUE": "M67 E{0} Q{1}",
    "SET_AUX_OUTPUT_VALUE": "M68 E{0} Q{1}", "PROGRAM_STOP": "M0", "OPTIONAL_PROGRAM_STOP": "M1",
    "ENABLE_FEED_OVERRIDE": "M50 P1", "DISABLE_FEED_OVERRIDE": "M50 P0", "ENABLE_SPEED_OVERRIDE": "M51 P1{s0}",
    "DISABLE_SPEED_OVERRIDE": "M51 P0{s0}", "ENABLE_ADAPTIVE_FEED": "M52 P1", "DISABLE_ADAPTIVE_FEED": "M52 P0",
    "ENABLE_FEED_HOLD": "M53 P1", "DISABLE_FEED_HOLD": "M53 P0", "FINISH": "", "PALLET_SHUTTLE": "",
    "TURN_PROBE_ON": "", "TURN_PROBE_OFF": "",  # around every G38: LinuxCNC's interpreter does it
}
_REFUSED = {
    "NURBS_FEED": "G5.2 NURBS (or a G5/G5.1 line without its G code, or in a subroutine file) in a program "
                  "that needs LinuxCNC's interpreter (rs274 does not print their control points)",
}


# what fbspost writes itself in a compensated program (its moves, feeds, blending, dwells)
_WRITTEN_CODES = {"F", "G0", "G1", "G4", "G61", "G61.1", "G64"}


def check_remaps(program: str | Path, ini: str | Path) -> None:
    """InputError when the machine's INI remaps a code fbspost writes itself (``REMAP=F ...``):
    each of its thousands of F words (or G1, G4, G64) would run the remap's code."""
    with open(ini, encoding="utf-8", errors="replace") as f:
        for text in f:
            m = re.match(r"\s*REMAP\s*=\s*([A-Za-z][\d.]*)", text)
            if m and _canonical_code(m.group(1)) in _WRITTEN_CODES:
                raise InputError(program, None, f"the machine's INI remaps {m.group(1)} ({Path(ini).name}), a code "
                                                "fbspost writes in every compensated move: not supported")


def _canonical_code(code: str) -> str:
    """G01 -> G1, g64 -> G64, f -> F."""
    letter, number = code[0].upper(), code[1:]
    return letter + (f"{float(number):g}" if number else "")


def canonical_calls(program: str | Path, tool_table: str | Path | None = None, ini: str | Path | None = None,
                    timeout_s: float | None = None, probe_delta: float = 0.0,
                    parameter_file: str | Path | None = None) -> list[tuple[str, list[str]]]:
    """rs274's canonical calls for ``program``: (name, arguments as text), in order, with G5/G5.1
    as SPLINE_FEED and probes' codes (``rs274_probes``; every probe's target moved by
    ``probe_delta``); rs274 starts from a copy of ``parameter_file`` (a LinuxCNC var file: its
    offsets in force) or from none. InputError when rs274 is missing or reports an error (naming
    the program's line it shows)."""
    rs274 = shutil.which("rs274")
    if rs274 is None:
        raise InputError(program, None, INSTALL_HINT)
    with tempfile.TemporaryDirectory(prefix="fbspost-rs274-") as work:  # rs274 writes its .var files here
        table = Path(tool_table).resolve() if tool_table else Path(work, "empty.tbl")
        table.touch(exist_ok=True)
        out = Path(work, "canon.txt")
        if parameter_file:
            shutil.copyfile(parameter_file, Path(work, "rs274ngc.var"))
        folder = Path(work, "program")
        folder.mkdir()
        run = instrumented(program, folder, functools.partial(probe_lines, delta=probe_delta)) or program
        args = [rs274, "-t", str(table), "-v", str(Path(work, "rs274ngc.var")), "-g", str(Path(run).resolve()),
                str(out)]
        if ini:  # LinuxCNC runs in the INI's directory: its relative paths (SUBROUTINE_PATH, ...) are from there
            args[1:1] = ["-i", str(Path(ini).resolve())]
        try:
            # HOME: rs274 keeps its tool table in $HOME/.tool.mmap, which concurrent runs would share
            proc = subprocess.run(args, cwd=Path(ini).resolve().parent if ini else work, stdin=subprocess.DEVNULL,
                                  capture_output=True, text=True, errors="replace", timeout=timeout_s,
                                  env={**os.environ, "HOME": work})
        except subprocess.TimeoutExpired:
            raise InputError(program, None, f"LinuxCNC's interpreter rs274 did not finish in {timeout_s:g} s") from None
        calls = []
        with open(out, encoding="utf-8", errors="replace") as f:
            for text in f:
                m = _CALL.match(text)
                if m:
                    calls.append((m.group(1), _arguments(m.group(2))))
    if proc.returncode != 0:
        raise _rs274_error(program, (proc.stdout + proc.stderr).replace("executing", "").strip().splitlines())
    return probe_calls(spline_calls(calls))


def _arguments(text: str) -> list[str]:
    if text.startswith('"'):
        return [text[1:-1] if text.endswith('"') else text[1:]]
    return [a for a in re.split(r"[,\s]+", text) if a]


def _rs274_error(program: str | Path, lines: list[str]) -> InputError:
    """rs274 prints its message, then the block: the line is found by its text in the program.
    (Its note that it could not update a parameter file is not the error.)"""
    lines = [text for text in lines if not text.startswith("link (updating variable file)")]
    message = lines[-2].strip() if len(lines) >= 2 else (lines[-1].strip() if lines else "failed")
    block = lines[-1].strip() if len(lines) >= 2 else None
    line_no = None
    if block:
        with open(program, encoding="utf-8", errors="replace") as f:
            line_no = next((i for i, text in enumerate(f, 1) if text.strip() == block), None)
    if block and _G62.search(block):  # LinuxCNC 2.10's; Debian's rs274 is 2.9
        message = f"G6.2 (LinuxCNC 2.10's NURBS) is not run by this install's rs274: {message}"
    return InputError(program, line_no, f"LinuxCNC's interpreter: {message}")


def expand(program: str | Path, output: str | Path, reason: str, tool_table: str | Path | None = None,
           ini: str | Path | None = None, timeout_s: float | None = None) -> None:
    """Writes the expanded ``program`` to ``output`` (see the module's docstring); ``reason``
    (why it was expanded) goes into its header."""
    with open(program, encoding="utf-8", errors="replace") as f:
        for line_no, text in enumerate(f, 1):
            if _M66.search(text):
                raise InputError(program, line_no, "M66 (wait for an input) with --expand: rs274 does not report it")
    calls = canonical_calls(program, tool_table, ini, timeout_s)
    if any(name == "STRAIGHT_PROBE" for name, _ in calls):
        check_static(program, ini)
        check_probes(program, calls, canonical_calls(program, tool_table, ini, timeout_s, probe_delta=DELTA))
    header = [f"; fbspost: expanded by LinuxCNC's interpreter rs274 from {Path(program).name}: {reason}",
              "; fbspost: in mm, absolute; the program's G92 and tool length offsets added into the coordinates",
              "G21 G90 G91.1 G17 G94 G40 G49 G80 G54"]
    percent = all(name != "PROGRAM_END" for name, _ in calls)  # a program between % lines, without M2
    writer = _Expander(program, _tool_numbers(tool_table))
    with open(output, "w", encoding="utf-8") as f:
        f.write("\n".join(["%"] * percent + header) + "\n")
        for line in writer.lines(_grouped(calls)):
            f.write(line + "\n")
        f.write("%\n" * percent)


def _tool_numbers(tool_table: str | Path | None) -> list[int]:
    """The tool numbers of the table's lines in order, after 0 (no tool): rs274's tool indices."""
    numbers = [0]
    if tool_table:
        with open(tool_table, encoding="utf-8", errors="replace") as f:
            for text in f:
                m = re.match(r"\s*T\s*(\d+)", text.split(";", 1)[0], re.IGNORECASE)
                if m:
                    numbers.append(int(m.group(1)))
    return numbers


def _grouped(calls: list[tuple[str, list[str]]]) -> Iterator[tuple[str, list[str]]]:
    """The calls with M2/M30's, M6's and M9's groups each as one (PROGRAM_END, [M2|M30]), (M6, []),
    (M9, []) and rs274's start-up state left out."""
    i, n = 0, len(calls)
    while i < n and calls[i][0] != "ON_RESET":
        i += 1
    i += 1
    while i < n:
        name, args = calls[i]
        if name == "SET_G5X_OFFSET":
            j = i + 1
            while j < n and calls[j][0] in _END_RESETS:
                j += 1
            if j < n and calls[j][0] == "PROGRAM_END":
                yield "PROGRAM_END", ["M30" if any(c[0] == "PALLET_SHUTTLE" for c in calls[i:j]) else "M2"]
                return
        if name == "START_CHANGE":
            while i < n and calls[i][0] != "CHANGE_TOOL":
                i += 1
            yield "M6", []
        elif name == "MIST_OFF" and i + 1 < n and calls[i + 1][0] == "FLOOD_OFF":
            i += 1
            yield "M9", []
        else:
            yield name, args
        i += 1


class _Expander:
    """Canonical calls to G-code lines: the offsets and units they are in, where the tool is."""

    def __init__(self, program, tools: list[int]):
        self.program = program
        self.tools = tools  # tool numbers by rs274's index into the table (CHANGE_TOOL_NUMBER gives the index)
        self.scale = 1.0  # mm per program unit
        self.g92 = [0.0] * 6  # mm (deg for A B C)
        self.tool = [0.0] * 6
        self.wcs = 1
        self.g5x = [0.0] * 6  # the work offsets of the system in use, as rs274 has them
        self.g5x_written = {}  # WCS index -> offsets written with G10 L2 (mm)
        self.plane = "CANON_PLANE_XY"
        self.feed = None  # as printed: per minute in the program's units, or of inverse time (G93)
        self.inverse_time = False
        self.feed_written = None
        self.pos = [0.0] * 6  # where the tool is in the output's coordinates (rs274 starts at 0)
        self.fresh = True  # the controller's position is not known to the output's reader: write XYZ
        self.mode = None  # CANON_CONTINUOUS tolerance, waiting for its naive-CAM tolerance
        self.last_pq = None  # P Q (mm) of a G5 just before: a G5 without I J starts with -P -Q
        self.pitch = None  # mm per spindle revolution of the synchronized moves (G33), None: not synchronized

    def lines(self, calls) -> Iterator[str]:
        for name, args in calls:
            if name in _REFUSED:
                raise InputError(self.program, None, f"{_REFUSED[name]}: not supported by --expand")
            if name in MOTION_CALLS and name != "SPLINE_FEED":
                self.last_pq = None
            method = getattr(self, "on_" + name.lower(), None)
            if method is not None:
                yield from method(args)
            elif name in _SIMPLE:
                spindle = f" ${args[0]}" if name in ("SET_SPINDLE_SPEED", "START_SPINDLE_CLOCKWISE",
                                                   "START_SPINDLE_COUNTERCLOCKWISE", "STOP_SPINDLE_TURNING",
                                                   "ORIENT_SPINDLE", "ENABLE_SPEED_OVERRIDE",
                                                   "DISABLE_SPEED_OVERRIDE") and args and args[0] != "0" else ""
                text = _SIMPLE[name].format(*map(_plain, args), s0=spindle)
                if text:
                    yield text
            elif name not in STATE_CALLS:
                raise InputError(self.program, None, f"LinuxCNC's {name} is not supported by --expand")

    # -- state ----------------------------------------------------------------------------------

    def on_use_length_units(self, args):
        self.scale = 25.4 if args[0] == "CANON_UNITS_INCHES" else 1.0
        if args[0] not in ("CANON_UNITS_INCHES", "CANON_UNITS_MM"):
            raise InputError(self.program, None, f"units {args[0]} are not supported by --expand")
        return ()

    def on_set_g92_offset(self, args):
        # the machine's own G92 offsets stay on until the program takes its own off (module docstring)
        values = self.length_values(args)
        suspend, self.g92 = any(self.g92) and not any(values), values
        if suspend:
            self.fresh = True
            yield "G92.2"

    def on_use_tool_length_offset(self, args):
        self.tool = self.length_values(args)
        return ()

    def on_set_xy_rotation(self, args):
        if float(args[0]) != 0.0:
            raise InputError(self.program, None, "coordinate rotation (G10 L2 R) is not supported by --expand")
        return ()

    def on_set_g5x_offset(self, args):
        index, offsets = int(args[0]), self.length_values(args[1:])
        # the tool stays put
        self.pos = [p + old - new for p, old, new in zip(self.pos, self.g5x, offsets, strict=True)]
        self.g5x = offsets
        if any(offsets) and self.g5x_written.get(index) != offsets:  # set by the program (rs274's own are 0)
            self.g5x_written[index] = offsets
            self.fresh = True
            yield f"G10 L2 P{index} " + " ".join(f"{a}{_mm(v)}" for a, v in zip("XYZABC", offsets, strict=True))
        if index != self.wcs:
            self.wcs = index
            self.fresh = True
            yield _WCS[index - 1]

    def on_select_plane(self, args):
        if args[0] not in _PLANES:
            raise InputError(self.program, None, f"plane {args[0]} is not supported by --expand")
        if args[0] != self.plane:
            self.plane = args[0]
            yield f"G{_PLANES[args[0]][3]}"

    def on_set_feed_rate(self, args):
        self.feed = float(args[0])
        return ()

    def on_comment(self, args):
        text = args[0] if args else ""
        if text.startswith("interpreter: feed mode set to"):
            if "revolution" in text:
                raise InputError(self.program, None, "feed per revolution (G95) is not supported by --expand")
            self.inverse_time = "inverse time" in text
            return ()
        if text.startswith("interpreter:"):
            return ()
        return (f"({text})",) if ")" not in text and "(" not in text else ()

    def on_set_motion_control_mode(self, args):
        if args[0] == "CANON_CONTINUOUS":
            self.mode = float(args[1]) * self.scale  # G64 P, its Q follows
            return ()
        return ("G61" if args[0] == "CANON_EXACT_PATH" else "G61.1",)

    def on_set_naivecam_tolerance(self, args):
        if self.mode is None:
            return ()
        p, q, self.mode = self.mode, float(args[0]) * self.scale, None
        return (f"G64 P{_mm(p)} Q{_mm(q)}" if p > 0.0 else "G64",)

    def on_change_tool_number(self, args):
        index = int(args[0])
        return (f"M61 Q{self.tools[index] if index < len(self.tools) else index}",)

    def on_program_end(self, args):
        return (args[0],)

    def on_m6(self, args):
        return ("M6",)

    def on_m9(self, args):
        return ("M9",)

    def length_values(self, args) -> list[float]:
        values = [float(a) for a in args[:6]] + [0.0] * max(0, 6 - len(args))
        return [v * self.scale for v in values[:3]] + values[3:6]

    # -- motion ---------------------------------------------------------------------------------

    def on_straight_traverse(self, args):
        yield self.move("G0", self.target(args))

    def on_straight_feed(self, args):
        target = self.target(args)
        if self.pitch is not None:  # spindle-synchronized (G33, G76): its pitch, never compensated
            yield self.move("G33", target, f" K{_mm(self.pitch)}")
            return
        # LinuxCNC's feed is along XYZ, along A B C for a move of them alone
        length = math.dist(self.pos[:3], target[:3]) or math.dist(self.pos[3:], target[3:])
        yield self.move("G1", target, self.feed_word(length))

    def on_straight_probe(self, args):
        """A probe (``rs274_probes``): the program's G38 to its target at its feed; where it stops is
        unknown (X Y Z NaN: the next move writes them all, an arc from there is refused)."""
        if self.inverse_time:
            raise InputError(self.program, None, "probing (G38) in inverse time feed (G93): not supported")
        target = self.target(args[2:])
        self.feed_written = self.feed * self.scale  # the probe's own F: the output's last F may be another
        yield self.move(args[0], target, f" F{_mm(self.feed_written)}", arc=True)
        self.pos[:3] = [math.nan] * 3

    def on_start_speed_feed_sync(self, args):
        if float(args[1]) != 0.0:
            raise InputError(self.program, None, "feed per revolution (G95) is not supported by --expand")
        self.pitch = float(args[0]) * self.scale
        return ()

    def on_stop_speed_feed_synch(self, args):
        self.pitch = None
        return ()

    def on_arc_feed(self, args):
        self.from_known("an arc")
        first, second, axis, _ = _PLANES[self.plane]
        values = [float(a) for a in args]
        canon = [math.nan] * 6
        canon[first], canon[second], canon[axis] = values[0], values[1], values[5]
        canon[3:6] = values[6:9]
        target = self.to_output(canon)
        center = [values[2] * self.scale + self.g92[first] + self.tool[first],
                  values[3] * self.scale + self.g92[second] + self.tool[second]]
        center = _equidistant(center, (self.pos[first], self.pos[second]), (target[first], target[second]))
        if center == [self.pos[first], self.pos[second]] == [target[first], target[second]]:
            # a helix narrower than rs274's printed digits (0.5e-4 of the unit): its axis' line
            yield self.move("G1", target, self.feed_word(None))
            return
        turns = int(values[4])
        offsets = {first: center[0] - self.pos[first], second: center[1] - self.pos[second]}
        words = " ".join(f"{'IJK'[i]}{_mm(offsets[i])}" for i in sorted(offsets))
        extra = f" P{abs(turns)}" if abs(turns) > 1 else ""
        # rs274 gives an arc's inverse time feed as units per minute itself
        yield self.move("G3" if turns > 0 else "G2", target, f" {words}{extra}" + self.feed_word(None), arc=True)

    def on_spline_feed(self, args):
        """A G5/G5.1 as rs274 evaluated it (``rs274_splines``): the same spline, in mm, X Y only."""
        self.from_known("a G5/G5.1 spline")
        if self.plane != "CANON_PLANE_XY" or self.inverse_time:
            raise InputError(self.program, None, "G5/G5.1 outside G17 or in inverse time (G93): not supported "
                                                 "by --expand")
        code, dx, dy = args[0], float(args[1]) * self.scale, float(args[2]) * self.scale
        i, j, p, q = (None if v is None else float(v) * self.scale for v in args[3:7])
        if code == "G5" and i is None:
            if self.last_pq is None:
                raise InputError(self.program, None, "a G5 without I and J not right after a G5: not supported "
                                                     "by --expand")
            i, j = -self.last_pq[0], -self.last_pq[1]
        self.last_pq = (p, q) if code == "G5" else None
        target = list(self.pos)
        target[0] += dx
        target[1] += dy
        words = f"X{_mm(target[0])} Y{_mm(target[1])} I{_mm(i)} J{_mm(j)}"
        if code == "G5":
            words += f" P{_mm(p)} Q{_mm(q)}"
        self.pos = target
        yield f"{code} {words}{self.feed_word(None)}"

    def from_known(self, what: str) -> None:
        """InputError for ``what`` from a probe's unknown end (its path is from where the tool
        is) or synchronized with the spindle (only straight G33 moves are)."""
        if any(math.isnan(p) for p in self.pos[:3]):
            raise InputError(self.program, None, f"{what} right after a probe (G38), from where it stopped: not "
                                                 "supported by --expand")
        if self.pitch is not None:
            raise InputError(self.program, None, f"{what} synchronized with the spindle: not supported by --expand")

    def target(self, args) -> list[float]:
        if any(float(a) != 0.0 for a in args[6:9]):
            raise InputError(self.program, None, "U V W axes are not supported by --expand")
        values = [float(a) for a in args[:6]]
        return self.to_output(values + [0.0] * (6 - len(values)))

    def to_output(self, canon) -> list[float]:
        return [(c * (self.scale if i < 3 else 1.0)) + self.g92[i] + self.tool[i] for i, c in enumerate(canon)]

    def feed_word(self, length_mm: float | None) -> str:
        """The F of a feed move (mm/min): the program's, or of a line in inverse time (G93) its
        length over its time (``length_mm``; None: the feed is per minute)."""
        if self.feed is None or self.feed <= 0.0:
            raise InputError(self.program, None, "a feed move without a feed rate")
        inverse = self.inverse_time and length_mm is not None
        if inverse and math.isnan(length_mm):
            raise InputError(self.program, None, "an inverse time (G93) move right after a probe (G38), from where it "
                                                 "stopped: not supported by --expand")
        feed = length_mm * self.feed if inverse else self.feed * self.scale
        if feed == self.feed_written and not inverse:
            return ""
        self.feed_written = feed
        return f" F{_mm(max(feed, 1e-6))}"

    def move(self, code: str, target: list[float], rest: str = "", arc: bool = False) -> str:
        """Writes every axis that changed; all of XYZ while the position is unknown (start, new WCS)."""
        words = [f"{a}{_mm(v)}" for i, (a, v) in enumerate(zip("XYZABC", target, strict=True))
                 if (self.fresh or arc) and i < 3 or v != self.pos[i]]
        self.pos, self.fresh = list(target), False
        return f"{code} {' '.join(words)}{rest}".rstrip()


def _equidistant(center, start, end) -> list[float]:
    """The centre moved onto the perpendicular bisector of start and end (by rs274's rounding of
    its 4 printed decimals at most), so that the arc ends on its circle."""
    du, dv = end[0] - start[0], end[1] - start[1]
    chord = math.hypot(du, dv)
    if chord == 0.0:
        return center
    nu, nv = -dv / chord, du / chord
    mu, mv = 0.5 * (start[0] + end[0]), 0.5 * (start[1] + end[1])
    along = (center[0] - mu) * nu + (center[1] - mv) * nv
    return [mu + along * nu, mv + along * nv]


def _mm(value: float) -> str:
    """A coordinate in mm: 6 decimals, trailing zeros off (rs274's 4 decimals of an inch are exact)."""
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _plain(arg: str) -> str:
    """A numeric argument without trailing zeros; text as it is."""
    if _NUMBER.fullmatch(arg):
        return _mm(float(arg))
    return arg
