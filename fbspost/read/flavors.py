"""Which firmware a G-code file is written for, and whether fbspost wrote it.

Takes a file's path; gives the flavor it is written for (one of ``profile.FLAVORS``), from hints
in its first 2000 and last 300 lines (``detect_flavor``), and where fbspost's header says fbspost
compensated it (``compensated_by``).
"""
from __future__ import annotations

import re
from pathlib import Path

from ..errors import InputError
from .words import BINARY, NOT_GCODE, strip_comments

_HEAD_LINES = 2000
_TAIL_LINES = 300
_DECLARED = re.compile(r";\s*(?:gcode_flavor\s*=|FLAVOR\s*:)\s*([A-Za-z0-9_]+)", re.IGNORECASE)
_KLIPPER_HINT = re.compile(
    r"^\s*(?:PRINT_START|START_PRINT|PRINT_END|END_PRINT|SET_VELOCITY_LIMIT|SET_PRESSURE_ADVANCE|"
    r"EXCLUDE_OBJECT_\w+|SET_FAN_SPEED|SET_HEATER_TEMPERATURE|BED_MESH_\w+|SET_GCODE_OFFSET|"
    r"TURN_OFF_HEATERS|SET_RETRACTION|SET_PRINT_STATS_INFO)\b",
    re.IGNORECASE,
)
_REPRAP_HINT = re.compile(r'^\s*(?:M98\s*P\s*"|M550\b|M291\b|M292\b|M929\b|M566\b|'
                          r'(?:if|while|var|global|set|echo|abort)\s)|^\s*[GM]\d+[^;]*[A-Z]"', re.IGNORECASE)
_CNC_HINT = re.compile(r"^\s*(?:%\s*$|[Oo]\s*\d+|.*\(.*\)|.*\b[Gg]0*(?:17|64|61|40|49|54|80|94)\b|"
                       r".*\b[Mm]0*(?:2|30)\b)")
_E_WORD = re.compile(r"\s*(?:[Nn]\d+\s*)?[Gg]0*[0-3](?![\d.])[^(]*?(?<![A-Za-z])[Ee]\s*[-+]?\.?\d")


def detect_flavor(path: str | Path) -> str:
    """The flavor (one of FLAVORS) the file at ``path`` is written for, from hints in its first
    2000 and last 300 lines: a slicer's declaration (``; gcode_flavor = ...``, ``;FLAVOR:...``),
    Klipper commands, RepRapFirmware commands and strings, CNC conventions (``%``, O-words,
    parenthesis comments, M2/M30, G17/G64/... without any E word, or the name ``*.ngc``); Marlin
    otherwise.

    Klipper commands win over a declared Marlin flavor (Klipper printers are often sliced as
    Marlin); a declared Klipper or RepRapFirmware flavor wins over everything. Binary content in
    the code of the first lines (a picture, random bytes) raises ``InputError`` naming its line.
    """
    try:
        lines = _head_and_tail(path)
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    declared = None
    klipper = reprap = cnc = e_words = False
    for i, text in enumerate(lines):
        if i < _HEAD_LINES and BINARY.search(strip_comments(text.split(";", 1)[0]).strip()):
            raise InputError(path, i + 1, NOT_GCODE)  # (before a binary file is taken for LinuxCNC's)
        m = _DECLARED.search(text)
        if m and declared is None:
            declared = m.group(1).lower()
        code = text.split(";", 1)[0]
        if not code.strip():
            continue
        klipper = klipper or bool(_KLIPPER_HINT.match(code))
        if not code.lstrip().upper().startswith(("M862", "M117", "M118")):
            reprap = reprap or bool(_REPRAP_HINT.match(code))
        cnc = cnc or bool(_CNC_HINT.match(code))
        e_words = e_words or bool(_E_WORD.match(code))
    if declared is not None:
        if declared == "klipper":
            return "klipper"
        if declared.startswith("reprap"):
            return "klipper" if klipper else "reprap"
        if declared in ("mach3", "machinekit", "linuxcnc"):
            return "linuxcnc"
    if declared is None and Path(path).suffix.lower() == ".ngc":  # LinuxCNC's own; no slicer writes it
        return "linuxcnc"
    if klipper:
        return "klipper"
    if reprap:
        return "reprap"
    if declared is None and cnc and not e_words:
        return "linuxcnc"
    return "marlin"


_COMPENSATED = re.compile(
    r"^\s*(?:;|\()\s*(fbspost \S+: filtered B-spline compensation for machine profile .*?)\)?\s*$")


def compensated_by(path: str | Path) -> tuple[int, str] | None:
    """(line, header text) where the file at ``path`` says fbspost compensated it (the header
    ``compensate`` writes among the comments before the first code line); None where not."""
    try:
        with open(path, "rb") as f:
            for line_no, raw in enumerate(f, 1):
                text = raw.decode("utf-8", "replace")
                if m := _COMPENSATED.match(text):
                    return line_no, m.group(1)
                if strip_comments(text.split(";", 1)[0]).strip():
                    return None
    except OSError as exc:
        raise InputError(path, 0, f"cannot read: {exc}") from None
    return None


def _head_and_tail(path: str | Path) -> list[str]:
    """The first _HEAD_LINES lines and the last _TAIL_LINES lines (each line once), decoded."""
    out = []
    with open(path, "rb") as f:
        for _ in range(_HEAD_LINES):
            raw = f.readline()
            if not raw:
                break
            out.append(raw)
        head_end = f.tell()
        f.seek(0, 2)
        size = f.tell()
        if size > head_end:
            chunk = 1 << 16
            start = size
            data = b""
            while start > head_end and data.count(b"\n") <= _TAIL_LINES:
                start = max(head_end, start - chunk)
                f.seek(start)
                data = f.read(size - start)
            tail = data.split(b"\n")
            if start > head_end:
                tail = tail[1:]  # a partial line
            out.extend(tail[-_TAIL_LINES - 1:])
    return [raw.decode("utf-8", "replace") for raw in out]
