"""G5 and G5.1 splines in programs run by LinuxCNC's interpreter rs274: their geometry.

rs274 prints a spline as ``NURBS_FEED(n, ...)``, without its control points. Takes a program;
``instrumented`` gives a copy (None when it has no G5/G5.1 line) in which each G5/G5.1 line is
preceded by the values of its I J P Q words as rs274 evaluates them (``#<_fbspost_i> = [...]``)
and by the current position (#5420, #5421), reported in a ``(DEBUG, ...)`` message, and followed
by the position it ends at; the program runs exactly as before besides these messages.
``spline_calls`` turns each [start message, NURBS_FEED, end message] of rs274's calls into one
``SPLINE_FEED(code, dx, dy, i, j, p, q)``: the spline's end relative to its start and its
control offsets, in the program's units (a G5 without I J: None for them, LinuxCNC takes the
previous G5's -P -Q). A NURBS_FEED without its messages (G5.2, a spline in a subroutine file
or a line without its G code) is left as it is.
"""
from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from ..errors import InputError

_SPLINE_LINE = re.compile(r"(?<![A-Za-z#<_\d.])G\s*0*5(?:\s*\.\s*0*1)?(?![\d.])", re.IGNORECASE)
_MARK = "fbspost-spline"


def without_comments(text: str) -> str:
    """The line without its comments."""
    return re.sub(r"\([^)]*\)", " ", text.split(";", 1)[0])


def value_end(code: str, i: int) -> int:
    """The end of the real value starting at ``code[i]``: a number, a parameter (#1, #<name>,
    #[...], ##1), an expression [...] or a unary function (sin[...], atan[...]/[...])."""
    n = len(code)
    while i < n and code[i] in " \t+-":
        i += 1
    if i < n and code[i] == "#":
        i += 1
        if i < n and code[i] == "<":
            return code.index(">", i) + 1
        if i < n and code[i] in "#[":
            return value_end(code, i)
        m = re.compile(r"\s*\d+").match(code, i)
        return m.end()
    if i < n and code[i].isalpha():
        while code[i].isalpha():
            i += 1
        end = value_end(code, i)
        m = re.compile(r"\s*/\s*\[").match(code, end)  # atan[y]/[x]
        return value_end(code, m.end() - 1) if m else end
    if i < n and code[i] == "[":
        depth = 0
        for j in range(i, n):
            depth += {"[": 1, "]": -1}.get(code[j], 0)
            if depth == 0:
                return j + 1
        raise ValueError("unbalanced [")
    m = re.compile(r"\s*(?:\d+\.?\d*|\.\d+)").match(code, i)
    if m is None:
        raise ValueError("no value")
    return m.end()


def _words(code: str) -> dict[str, str]:
    """The line's words: letter -> value as written (O-words and comments not expected)."""
    words, i = {}, 0
    while i < len(code):
        if code[i].isalpha():
            end = value_end(code, i + 1)
            words[code[i].upper()] = code[i + 1:end].strip()
            i = end
        elif code[i] in " \t":
            i += 1
        else:
            raise ValueError(f"unexpected {code[i]!r}")
    return words


def instrumented(program: str | Path, folder: str | Path,
                 other: Callable[[str], list[str] | None] | None = None) -> Path | None:
    """A copy of ``program`` in ``folder`` that reports its G5/G5.1 lines and replaces the lines
    ``other`` gives lines for (None: it has no such lines). InputError when such a line cannot
    be read."""
    lines = Path(program).read_text(encoding="latin-1").split("\n")  # latin-1: every byte kept as it is
    out, found = [], False
    for line_no, text in enumerate(lines, 1):
        m = _SPLINE_LINE.search(without_comments(text))
        if m is None:
            try:
                replaced = other(text) if other else None
            except (ValueError, IndexError) as exc:
                raise InputError(program, line_no, f"cannot read the words of this line for rs274: {exc}") from None
            out.extend([text] if replaced is None else replaced)
            found |= replaced is not None
            continue
        found = True
        try:
            words = _words(re.sub(r"^\s*[Nn]\d+", "", without_comments(text)))
        except (ValueError, IndexError) as exc:
            raise InputError(program, line_no, f"cannot read the words of this spline for rs274: {exc}") from None
        kind = "G5.1" if "." in m.group() else "G5"
        shown = []
        for letter in "IJPQ":
            if letter in words:
                out.append(f"#<_fbspost_{letter.lower()}> = [{words[letter]}]")
                shown.append(f"{letter}#<_fbspost_{letter.lower()}>")
        out.append(f"(DEBUG,{_MARK} {kind} #5420 #5421 {' '.join(shown)})")
        out.append(text)
        out.append(f"(DEBUG,{_MARK}-end #5420 #5421)")
    if not found:
        return None
    copy = Path(folder) / Path(program).name
    copy.write_text("\n".join(out), encoding="latin-1")
    return copy


def spline_calls(calls: list[tuple[str, list[str]]]) -> list[tuple[str, list[str]]]:
    """``calls`` with each reported spline as one SPLINE_FEED call (see the module's docstring)."""
    out, start = [], None
    for name, args in calls:
        text = args[0] if name == "MESSAGE" and args else ""
        if text.startswith(_MARK + " "):
            start = (len(out), text.split()[1:])
        elif text.startswith(_MARK) and start is not None:
            at, (kind, x0, y0, *given) = start
            nurbs = [i for i in range(at, len(out)) if out[i][0] == "NURBS_FEED"]
            if len(nurbs) == 1:
                x1, y1 = (float(v) for v in text.split()[1:3])
                offsets = {w[0]: w[1:] for w in given}
                del out[nurbs[0]]
                out.append(("SPLINE_FEED", [kind, repr(x1 - float(x0)), repr(y1 - float(y0)),
                                            *(offsets.get(letter) for letter in "IJPQ")]))
            start = None
        elif not text.startswith(_MARK):
            out.append((name, args))
    return out
