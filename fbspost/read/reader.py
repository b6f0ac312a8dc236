"""The reader's driver: a line's text to its block, its commands run in LinuxCNC's order.

Takes a program's lines one at a time (number and bytes), its path (for the errors), its flavor
and the home position; gives each line's ``Block`` (at a spline's end, the blocks of the lines
it held). ``Reader`` holds the parts and runs a line through them: its words (``words.Words``),
the machine state (``state.State``) with the modal G codes and the feed it sets here, the other
commands (``commands.Commands``, the spindle ``commands.Spindle``), the motion
(``motion.Motion``) and the splines (``splines.Splines``).
"""
from __future__ import annotations

from pathlib import Path

from .blocks import AXES, EXPAND_HINT, OTHER_AXES, Block, Kind, NeedsInterpreter
from .commands import TEXT_CMD, Commands, Effects, Spindle
from .motion import PLANES, Motion
from .splines import Splines
from .state import INCH, WCS, State
from .words import FAST_G01, Words

_MOTION = {0.0: 0, 1.0: 1, 2.0: 2, 3.0: 3, 5.0: 5}
_UNSUPPORTED_G = {
    41.0: "cutter radius compensation (G41)",
    42.0: "cutter radius compensation (G42)",
    41.1: "dynamic cutter radius compensation (G41.1)",
    42.1: "dynamic cutter radius compensation (G42.1)",
    68.0: "coordinate rotation (G68)",
    51.0: "scaling (G51)",
    93.0: "inverse time feed (G93)",
    95.0: "feed per revolution (G95)",
    73.0: "canned cycles (G73)",
    76.0: "canned cycles (G76)",
    **{float(g): f"canned cycles (G{g})" for g in range(81, 90)},
}
_LINUXCNC_PASS_G = {40.0, 49.0, 61.0, 61.1, 64.0, 80.0, 94.0}
_LINUXCNC_INTERPRETED_G = {  # path-changing LinuxCNC codes that only its interpreter runs (--expand)
    7.0: "lathe diameter mode (G7)", 33.1: "rigid tapping (G33.1)",
    70.0: "lathe cycles (G70)", 71.0: "lathe cycles (G71)", 72.0: "lathe cycles (G72)",
    74.0: "canned cycles (G74)", 71.1: "lathe cycles (G71.1)", 71.2: "lathe cycles (G71.2)",
    72.1: "lathe cycles (G72.1)", 72.2: "lathe cycles (G72.2)",
}
_NURBS_G = {5.1, 5.2, 5.3, 6.2}  # LinuxCNC splines (G6.2: LinuxCNC 2.10's NURBS with its own knots)


class Reader:
    """The interpretation of one line, through the parts that hold the state between lines."""

    def __init__(self, path: str | Path, flavor: str, home_mm=(0.0, 0.0, 0.0), work_offsets_mm=()):
        self.cnc = flavor == "linuxcnc"
        self.words = Words(path, self.cnc)
        self.state = State(flavor, work_offsets_mm if self.cnc else ())
        self.spindle = Spindle(self.words)
        self.commands = Commands(self.words, self.state, self.spindle, home_mm)
        self.moves = Motion(self.words, self.state, self.spindle)
        self.splines = Splines(self.words, self.state)

    def line(self, n: int, raw: bytes) -> Block | list[Block] | None:
        """The line's block; inside a G5.2 NURBS None (held), and at its G5.3 every held line's block."""
        if self.splines.spline is not None:
            block = self.general(n, raw)
            if block.__class__ is Block:  # a comment or blank line inside the NURBS
                self.splines.hold(block)
                return None
            return block
        m = FAST_G01.match(raw)
        if m is not None:
            try:
                block = self.moves.fast_move(n, raw, *m.groups())
            except ValueError:  # "1.2.3": the general path names the word
                block = None
            if block is not None:
                return block
        return self.general(n, raw)

    def general(self, n: int, raw: bytes) -> Block | list[Block] | None:
        state = self.state
        code = self.words.code(n, raw)
        if not code:
            return state.block(n, raw, Kind.PASS)
        c0 = code[0]
        if c0 == "%":
            return state.block(n, raw, Kind.PASS)
        if c0 in "Oo":
            self.words.oword(n, code)
            return state.block(n, raw, Kind.PASS)
        if self.cnc and ("#" in code or "[" in code or "@" in code or "^" in code):
            raise self.words.interpreted(n, code)
        if c0 == "_" or (c0.isalpha() and len(code) > 1 and (code[1].isalpha() or code[1] == "_")):
            return self.commands.extended(n, raw, code)
        if not self.cnc:
            if c0 in "Mm" and TEXT_CMD.match(code):
                return self.commands.text(n, raw, code)
            if "{" in code:  # an RRF/Klipper expression the firmware evaluates
                state.forget(state.frame, e_too=True)
                return state.block(n, raw, Kind.STOP)

        return self.execute(n, raw, *self.words.words(n, code))

    def execute(self, n, raw, gcodes, mcodes, tool, params, dups, junk) -> Block:
        """The block of a line of words, its commands in LinuxCNC's order of execution: modal
        settings, then the others, then motion."""
        words, state, commands = self.words, self.state, self.commands
        fx = Effects()
        others = self._modal_gcodes(n, gcodes, fx)
        scale = INCH if state.inches else 1.0
        commands.mcodes(n, mcodes, params, junk, scale, fx)
        if tool is not None:
            fx.kind = Kind.STOP

        if fx.motion is not None:  # name a bad axis word before anything else on the line
            for a in AXES:
                if a in params:
                    words.number(n, a, params[a])

        if self.cnc and "S" in params:
            self.spindle.rpm = words.number(n, "S", params["S"])
        # feed
        f = params.get("F")
        if f is not None and (self.cnc or fx.motion is not None or not (gcodes or mcodes or tool is not None)):
            feed = words.number(n, "F", f)
            if feed <= 0.0:
                raise words.error(n, f"feed F{f} must be positive")
            state.feed = feed * scale / 60.0

        for g in others:
            commands.other_gcode(n, g, params, dups, junk, scale, fx)
        if fx.modal_changed:
            state.new_modal()
        return self._executed(n, raw, bool(gcodes or mcodes or tool is not None), params, dups, junk, scale, fx)

    def _modal_gcodes(self, n, gcodes, fx: Effects) -> list[float]:
        """The line's motion and modal G codes applied; gives the other G codes, in order."""
        words, state = self.words, self.state
        flavor = state.flavor
        others = []
        for g in gcodes:
            m = _MOTION.get(g)
            if m is not None:
                if fx.motion is not None:
                    raise words.error(n, "two motion commands on one line")
                fx.motion = m
            elif g == 90.0 or g == 91.0:
                state.abs_xyz = g == 90.0
                if flavor == "marlin":
                    state.abs_e = state.abs_xyz
                fx.modal_changed = True
            elif g == 20.0 or g == 21.0:
                state.inches = g == 20.0
                fx.modal_changed = True
            elif g in PLANES:
                state.plane = int(g)
                fx.modal_changed = True
            elif g == 90.1 or g == 91.1:
                state.abs_ijk = g == 90.1
            elif self.cnc and g == 33.0:
                if fx.motion is not None:
                    raise words.error(n, "two motion commands on one line")
                fx.motion = 33
            elif g in _UNSUPPORTED_G or (self.cnc and g in _LINUXCNC_INTERPRETED_G):
                if self.cnc:
                    what = _UNSUPPORTED_G.get(g) or _LINUXCNC_INTERPRETED_G[g]
                    raise NeedsInterpreter(words.path, n, what, f"{what} is not supported: {EXPAND_HINT}")
                raise words.error(n, f"{_UNSUPPORTED_G[g]} is not supported")
            elif g in _NURBS_G or (self.cnc and 5.0 < g < 7.0):
                if self.cnc and g in _NURBS_G:
                    if fx.motion is not None:
                        raise words.error(n, "two motion commands on one line")
                    fx.motion = g
                else:
                    raise words.error(n, f"G{g:g} is not supported (a motion fbspost does not know)")
            elif g in WCS:
                changed = g != state.wcs
                if state.select_wcs(g):
                    fx.modal_changed |= changed
                else:  # another work coordinate system: offsets not known
                    fx.unknown = True
            elif self.cnc and g in _LINUXCNC_PASS_G:
                if g == 49.0 and state.tool_length:
                    state.tool_length = False
                    state.forget((2,))
                    fx.kind = Kind.STOP
            else:
                if self.cnc and (g == 96.0 or g == 97.0):
                    self.spindle.css = g == 96.0
                others.append(g)
        return others

    def _executed(self, n, raw, commanded: bool, params, dups, junk, scale, fx: Effects) -> Block:
        """The line's motion (an explicit G0-G5, or axis words continuing the last motion mode)
        or its block without motion; ``commanded``: the line has a G, M or T command."""
        words, state, splines = self.words, self.state, self.splines
        # motion: an explicit G0-G5, or axis words continuing the last motion mode
        inherited = fx.motion is None
        if inherited and not fx.axis_words_used and (self.cnc or not commanded):
            if ("X" in params or "Y" in params or "Z" in params or "E" in params
                    or (self.cnc and any(a in params for a in OTHER_AXES))):
                fx.motion = state.motion
                if fx.motion is None:
                    raise words.error(n, "axis words without a motion command (G0/G1/G2/G3/G5)")
        if splines.spline is not None or fx.motion in _NURBS_G:
            if (fx.unknown or fx.kind is not Kind.PASS or fx.limits is not None or fx.modal_changed
                    or fx.axis_words_used):
                raise words.error(n, "inside a NURBS only control points (X Y P) and G5.3 are allowed")
            if splines.spline is not None and splines.spline.knots is not None and fx.motion is None:
                fx.motion = 6.2  # a G6.2 line of a knot alone
            state.motion = None if fx.motion == 5.3 else fx.motion
            return splines.spline_line(n, raw, fx.motion, params, dups, junk, scale)
        if fx.motion is not None and not fx.unknown:
            state.motion = fx.motion
            block = self.moves.move(n, raw, fx.motion, params, dups, junk, scale, fx.kind is Kind.STOP)
            if fx.kind is Kind.STOP and block.kind is not Kind.STOP:
                block.kind = Kind.STOP
                block.points_mm = None
            if inherited and block.kind is not Kind.PASS:
                block.inherited_motion = fx.motion
            block.dwell_s += fx.dwell
            block.limits = fx.limits
            return block

        if fx.unknown:  # with a motion too ("G53 G0 Z0"): it moves in a frame fbspost does not know
            if fx.motion is not None:
                state.motion = fx.motion
            state.forget(state.frame, e_too=True)
            fx.kind = Kind.STOP
        return state.block(n, raw, fx.kind, dwell_s=fx.dwell, limits=fx.limits, sets_position=fx.sets_position)
