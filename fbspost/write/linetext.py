"""The text of G1 and G5 lines, formatted many rows at once.

Takes rows of words as integers in units of their last digit (``DECIMALS``, ``FEED_DECIMALS``)
and which words each line shows; gives the lines' bytes with every number the shortest decimal
(``line_text``).
"""
from __future__ import annotations

import numpy as np

from ..read.blocks import AXES

DECIMALS = {**dict.fromkeys(AXES, 4), "E": 5}  # mm: 0.1 um (A B C: 1e-4 degree), E: 10 nm of filament
FEED_DECIMALS = 3  # mm/min (in/min in G20)



def _digits(width: int, form: str) -> np.ndarray:
    """(10**width, width) characters of 0 .. 10**width - 1: zero-padded ("full"), leading zeros
    dropped ("lead": 0 is no text; "lead0": 0 is "0"), trailing zeros dropped ("trail": 0 is no
    text). Dropped characters are NUL."""
    numbers = np.arange(10 ** width)[:, None]
    place = 10 ** np.arange(width - 1, -1, -1)
    keep = {"full": True, "lead": numbers >= place, "lead0": (numbers >= place) | (place == 1),
            "trail": numbers % (10 * place) != 0}[form]
    return (numbers // place % 10 + ord("0")).astype(np.uint8) * keep


def _pointed(chars: np.ndarray) -> np.ndarray:
    """A decimal point before the rows of characters that have any."""
    return np.hstack([np.where(chars.any(axis=1, keepdims=True), ord("."), 0).astype(np.uint8), chars])


def _packed(*tables: np.ndarray) -> np.ndarray:
    """Rows of four characters, the tables one after the other, as one uint32 per row."""
    return np.concatenate(tables).view(np.uint32).ravel()


# line_text writes numbers from four-character pieces looked up by value (plus the offset of
# their form), NUL where the shortest text has no character. The integer part, by four digits:
_INT_PART = _packed(_digits(4, "lead"), _digits(4, "lead0"), _digits(4, "full"))
_LEAD, _LEAD0, _FULL = 0, 10000, 20000
# The fractional part, always at 7 decimals (every DECIMALS and FEED_DECIMALS fit): the point
# and three digits (+ 1000: digits follow), then four digits.
_FRACTION_DECIMALS = 7
_FRACTION_HIGH = _packed(_pointed(_digits(3, "trail")), _pointed(_digits(3, "full")))
_FRACTION_LOW = _packed(_digits(4, "trail"))
_LETTERS = "IJPQ" + "".join(AXES) + "F"
_WORD_HEADS = _packed(np.array([[ord(" "), ord(letter), 0, 0] for letter in _LETTERS], np.uint8))
_MINUS, _G1, _G5 = np.frombuffer(b"\0\0-\0G1\0\0G5\0\0", np.uint32)  # " X" + _MINUS is " X-"


def line_text(values: np.ndarray, shown: np.ndarray, digits: np.ndarray, letters: str, newline: bytes,
              g5: np.ndarray) -> bytes:
    """The text of one line per row of ``values`` (n, k: the words ``letters`` as integers in
    units of 10**-``digits``, at most 7 digits), G5 where ``g5`` else G1, with the words that
    are ``shown``, each line ended by ``newline``. Numbers are the shortest decimal: "12.34",
    "-0.005", "0".

    Formatting value by value takes tens of seconds for a million lines, so the rows are built
    together: every word is the same row of four-character pieces (" X-", the integer digits in
    groups of four, ".ddd", "dddd") looked up by value, the characters the short text does not
    have are NUL, and one pass removes the NULs.
    """
    n, k = values.shape
    scaled = values * 10 ** (_FRACTION_DECIMALS - digits)  # the added zeros trail: dropped like any
    magnitude = np.where(shown, np.abs(scaled), 0)
    whole = magnitude // 10 ** _FRACTION_DECIMALS
    fraction = magnitude - whole * 10 ** _FRACTION_DECIMALS
    int_groups = -(-len(str(int(whole.max(initial=0)))) // 4)
    slots = 3 + int_groups
    words = np.empty((n, k, slots), np.uint32)
    heads = np.take(_WORD_HEADS, [_LETTERS.index(letter) for letter in letters])
    words[:, :, 0] = np.where(shown, heads + (scaled < 0) * _MINUS, 0)
    rest = whole
    for slot in range(int_groups, 0, -1):  # least significant group first: are there digits above?
        above = rest // 10000
        form = np.where(above > 0, _FULL, shown * _LEAD0 if slot == int_groups else _LEAD)
        words[:, :, slot] = np.take(_INT_PART, rest - above * 10000 + form)
        rest = above
    high = fraction // 10000
    low = fraction - high * 10000
    words[:, :, -2] = np.take(_FRACTION_HIGH, high + (low > 0) * 1000)
    words[:, :, -1] = np.take(_FRACTION_LOW, low)
    line = np.empty((n, 2 + k * slots), np.uint32)
    line[:, 0] = np.where(g5, _G5, _G1)
    line[:, 1:-1] = words.reshape(n, k * slots)
    line[:, -1] = np.frombuffer(newline.ljust(4, b"\0"), np.uint32)[0]
    return line.tobytes().translate(None, b"\0")

