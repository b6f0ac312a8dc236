"""Probing (G38.2..G38.5) in programs run by LinuxCNC's interpreter rs274: which probe, and
whether the program's later motion depends on where the probe stops.

rs274 prints a probe as ``STRAIGHT_PROBE(x, y, z, a, b, c, ...)`` without its G code, and only
simulates it: the probe reaches its target (#5061.. are the target, #5070 is 0). Where the real
probe stops is unknown, so the expansion writes the probe back as the program's own G38 line
(to its target) and may only be used when nothing after it depends on where it stopped.

``probe_lines`` gives, for a line of the program copy that rs274 runs (``rs274_splines
.instrumented``), a ``(DEBUG, ...)`` message naming its G38 code and axis words before it, and,
with ``delta``, the line with every axis word's value moved by ``delta`` (program units):
``G38.2 Z#8`` -> ``G38.2 Z[#8+0.0123]``. ``probe_calls`` folds each message into its
STRAIGHT_PROBE: ``(code, axes, x, y, z, ...)``. ``check_probes`` compares rs274's calls of the
program with those of the moved copy: every probe's target must move by exactly ``delta`` on its
own axis words (else it is computed from an earlier probe's result) and every other call must
stay the same (else a later move, offset, message or path depends on the probe's result: a
relative move from the probed position, G10 L20 or G92 after it, a position it leaves where it
was); and the program may not name #5061..#5070 at all (a branch on the result or on #5070,
the success flag, would not show in a small move), nor call subroutine files or remapped codes
that could (they are not read here).
"""
from __future__ import annotations

import re
from pathlib import Path

from ..errors import InputError
from .rs274_splines import value_end, without_comments

MARK = "fbspost-probe"
DELTA = 0.0123  # program units: more than rs274's printed 0.0001, small enough to stay on the machine
_PROBE_LINE = re.compile(r"(?<![A-Za-z#<_\d.])G\s*0*38\s*\.\s*([2-5])(?![\d.])", re.IGNORECASE)
_AXES = "XYZABCUVW"
_RESULT = re.compile(r"#50(?:6[1-9]|70)(?!\d)")
_CALL = re.compile(r"^\s*o\s*(<[^>]*>|\d+)\s*call\b", re.IGNORECASE | re.MULTILINE)
_SUB = re.compile(r"^\s*o\s*(<[^>]*>|\d+)\s*sub\b", re.IGNORECASE | re.MULTILINE)


def probe_lines(text: str, delta: float = 0.0) -> list[str] | None:
    """The lines that replace the program's line ``text`` (None: it probes nothing)."""
    code = without_comments(text)
    m = _PROBE_LINE.search(code)
    if m is None:
        return None
    out, axes, i = [], "", 0
    while i < len(code):  # the words, each axis word's value moved by delta
        c = code[i]
        if c.isalpha():
            end = value_end(code, i + 1)
            value = code[i + 1:end].strip()
            if c.upper() in _AXES:
                axes += c.upper()
                value = f"[{value}+{delta!r}]" if delta else value
            out.append(c + value)
            i = end
        else:
            out.append(c)
            i += 1
    moved = " ".join(out) + " " + " ".join(re.findall(r"\([^)]*\)", text))
    return [f"(DEBUG,{MARK} G38.{m.group(1)} {axes})", moved if delta else text]


def probe_calls(calls: list[tuple[str, list[str]]]) -> list[tuple[str, list[str]]]:
    """``calls`` with each probe's message folded into its STRAIGHT_PROBE (code and axes first;
    None and "" for a probe without its message: in a subroutine file)."""
    out, mark = [], None
    for name, args in calls:
        if name == "MESSAGE" and args and args[0].startswith(MARK + " "):
            mark = (args[0].split() + [""])[1:3]
        elif name == "STRAIGHT_PROBE":
            out.append((name, (mark or [None, ""]) + args))
            mark = None
        else:
            out.append((name, args))
    return out


def check_static(program: str | Path, ini: str | Path | None) -> None:
    """InputError when a probing program names the probe's result (#5061..#5070), or calls
    code not in its file (subroutine files, the INI's remaps) that could."""
    text = Path(program).read_text(encoding="latin-1")
    for line_no, line in enumerate(text.split("\n"), 1):
        m = _RESULT.search(re.sub(r"\s+", "", line))
        if m:
            raise InputError(program, line_no, f"the program uses the probe's result ({m.group()}), which only "
                                               "LinuxCNC knows (rs274 only simulates the probe): not supported")
    outside = {c.lower() for c in _CALL.findall(text)} - {s.lower() for s in _SUB.findall(text)}
    remaps = ini and re.search(r"^\s*REMAP\s*=", Path(ini).read_text(encoding="latin-1"), re.MULTILINE)
    if outside or remaps:
        what = f"subroutine files ({', '.join(sorted(outside))})" if outside else "the INI's remapped codes"
        raise InputError(program, None, f"a probing program that calls {what}: whether they use the probe's "
                                        "result cannot be checked: not supported")


def check_probes(program: str | Path, calls, moved_calls, delta: float = DELTA) -> None:
    """InputError unless the program's calls and those of its copy with every probe moved by
    ``delta`` differ only by the probes' own move (see the module's docstring)."""
    if len(calls) != len(moved_calls):
        raise _depends(program, "the number of canonical calls")
    for (name, args), (moved_name, moved) in zip(calls, moved_calls, strict=True):
        if name != moved_name:
            raise _depends(program, f"{name} becomes {moved_name}")
        if name != "STRAIGHT_PROBE":
            if args != moved:
                raise _depends(program, f"{name}({', '.join(args)})")
            continue
        if args[0] is None:
            raise InputError(program, None, "a probe (G38) in a subroutine file: whether the program depends on "
                                            "its result cannot be checked: not supported")
        for k, (a, b) in enumerate(zip(args[2:], moved[2:], strict=True)):
            expected = delta if k < len(_AXES) and _AXES[k] in args[1] else 0.0
            if abs(float(b) - float(a) - expected) > 2e-4:
                raise _depends(program, f"the target of a probe ({args[0]})")


def _depends(program, what: str) -> InputError:
    return InputError(program, None, f"the program's later motion depends on where a probe (G38) stops ({what} "
                                     "changes with it), which only LinuxCNC knows: not supported")
