"""A G-code line's text to its words: comments, line numbers, checksums and O-words taken
apart, numbers read or refused with the line's one-line error.

Takes a line's bytes, the file's path (for the errors) and whether the program is LinuxCNC's
(which takes several commands on a line); gives the line's code (``Words.code``), its commands
and words (``Words.words``), a word's value as a finite number (``Words.number``) or the line's
``InputError`` (``Words.error``). ``FAST_G01`` matches the common G0/G1 line straight from its
bytes; ``strip_comments`` takes the comments out of a line's text.
"""
from __future__ import annotations

import re

from ..errors import InputError
from .blocks import EXPAND_HINT, NeedsInterpreter

# One word: a letter and its value (a number, NaN or infinity as a C library writes them, so that
# the error can name them, an RRF "string", an RRF {expression}, or nothing), or any other
# non-blank character (junk: an error wherever the line's values are needed).
_WORD = re.compile(
    r'([A-Za-z])\s*([-+]?\s*(?:\d+\.?\d*|\.\d+|(?i:nan|inf(?:inity)?)(?![A-Za-z]))|"(?:[^"]|"")*"?|\{[^}]*\}?|)|(\S)'
)
# The common line, fast, straight from its bytes: [N123] G0/G1 with X Y Z E in this order, F first
# or last, one space between words, [*checksum], [; comment]. Anything else takes the general path.
_NUM = rb"([-+]?[\d.]{1,40})"
FAST_G01 = re.compile(
    rb"(?:N\d+ +)?G0?([01])(?: +F" + _NUM + rb")?(?: +X" + _NUM + rb")?(?: +Y" + _NUM + rb")?(?: +Z" + _NUM
    + rb")?(?: +E" + _NUM + rb")?(?: +F" + _NUM + rb")?(?: *\*\d+)?(?:[ \t]*;.*|\s*)\Z",
    re.DOTALL,
)
_COMMENT_OR_STRING = re.compile(r'"(?:[^"]|"")*"?|\([^)]*\)?|;')
_HEAD = re.compile(r"\s*(?:/\s*)?(?:[Nn]\s*\d+)?\s*")  # block delete, line number
_CHECKSUM = re.compile(r"\*\s*\d*\s*$")
EXT_PARAM = re.compile(r'([A-Za-z_][A-Za-z0-9_]*)\s*=\s*("[^"]*"|\S*)')
_OWORD = re.compile(r"[Oo]\s*(?:\d+|<[^>]*>)\s*([A-Za-z_]*)")
# Control characters (not white space) in a line's code, or a code that starts with bytes that are
# not UTF-8: binary content, not G-code (a comment may hold any bytes: it passes through)
BINARY = re.compile("[\x00-\x08\x0e-\x1f\x7f]|^\ufffd")
NOT_GCODE = "not a G-code file: binary content"
_PARAMETER = re.compile(r"#\s*(?:<[^>]*>?|\d+|\[)|\[[^\]]*\]?")


class Words:
    """The words and values of a program's lines: the path and the flavor's rule of commands
    (LinuxCNC takes several on a line) are all it holds."""

    def __init__(self, path, cnc: bool):
        self.path, self.cnc = path, cnc

    def error(self, line_no: int, message: str) -> InputError:
        return InputError(self.path, line_no, message)

    def number(self, n: int, letter: str, text: str | None) -> float:
        """A word's value as a finite number, or an InputError naming the word."""
        if text is None or text == "":
            raise self.error(n, f"{letter} needs a number")
        try:
            value = float(text.replace(" ", ""))
        except ValueError:
            raise self.error(n, f"{letter}{text} is not a number") from None
        if not -1e300 < value < 1e300:
            raise self.error(n, f"{letter}{text} is not a finite number")
        return value

    def code(self, n: int, raw: bytes) -> str:
        """The code of line ``n``: decoded, without its comments, block delete, line number and
        checksum ("" where nothing is left). Binary content is refused."""
        text = raw.decode("utf-8", "replace")
        if n == 1 and text.startswith("\ufeff"):
            text = text[1:]
        if '"' in text or "(" in text:
            code = strip_comments(text)
        else:
            i = text.find(";")
            code = text[:i] if i >= 0 else text
        code = code.strip()
        if not code:
            return code
        if BINARY.search(code):
            raise self.error(n, NOT_GCODE)
        if code[0] in "Nn/":
            code = code[_HEAD.match(code).end():]
            if not code:
                return code
        if "*" in code:
            code = _CHECKSUM.sub("", code).rstrip()
        return code

    def words(self, n: int, code: str) -> tuple:
        """The words of ``code``: (G numbers, M numbers, T value, {letter: value}, letters given
        twice (None: none), what could not be read (None: nothing)). LinuxCNC takes several
        commands on a line; the printers' firmwares one, the rest its parameters."""
        gcodes = []
        mcodes = []
        tool = None
        params = {}
        dups = None
        junk = None
        multi = self.cnc
        command_seen = False
        for letter, value, bad in _WORD.findall(code):
            if bad:
                if junk is None:
                    junk = bad
                continue
            letter = letter.upper()
            if letter == "G" or letter == "M" or letter == "T":
                if multi or not command_seen:
                    command_seen = True
                    if letter == "T":
                        tool = value
                    else:
                        try:
                            number = float(value)
                        except ValueError:
                            raise self.error(n, f"{letter}{value} is not a number") from None
                        (gcodes if letter == "G" else mcodes).append(number)
                    continue
            elif letter == "N" and not params and not command_seen:
                continue
            if letter in params:
                if dups is None:
                    dups = set()
                dups.add(letter)
            else:
                params[letter] = value
        if junk is not None:
            junk = f"cannot read {code!r}: unexpected {junk!r}"
            if multi:
                raise self.error(n, junk + " (expressions and parameters are not supported)")
        return gcodes, mcodes, tool, params, dups, junk

    def oword(self, n, code) -> None:
        """A plain O-word line (a program's number) passes; subroutines and control flow are refused."""
        m = _OWORD.match(code)
        if m is None:
            raise self.error(n, f"cannot read {code!r}")
        if m.group(1):
            message = f"O-word {m.group(1)!r}: subroutines and control flow are not supported"
            if self.cnc:
                raise NeedsInterpreter(self.path, n, "O-words", f"{message}: {EXPAND_HINT}")
            raise self.error(n, message)

    def interpreted(self, n, code) -> NeedsInterpreter:
        """The error for LinuxCNC's parameters, expressions or polar coordinates in ``code``."""
        feature = _PARAMETER.search(code)
        what = "parameters" if feature and feature.group().startswith("#") else "expressions"
        if feature is None:
            what, feature = "polar coordinates", re.search(r"[@^]\s*[-+.\d]*", code)
        shown = feature.group()
        return NeedsInterpreter(self.path, n, f"{what} ({shown})",
                                f"{what} ({shown}) need --expand (LinuxCNC's interpreter)")


def strip_comments(text: str) -> str:
    """The line without ';' and '( )' comments, keeping RRF "strings" (which may hold ';')."""
    pieces = []
    pos = 0
    for m in _COMMENT_OR_STRING.finditer(text):
        s = m.group()
        if s == ";":
            pieces.append(text[pos:m.start()])
            return " ".join(pieces)
        if s[0] == "(":
            pieces.append(text[pos:m.start()])
            pos = m.end()
    pieces.append(text[pos:])
    return " ".join(pieces)
