"""bench/linuxcnc_examples.py's rule for LinuxCNC's example programs that contour in XY: its
lengths against closed forms, on rs274's own canonical moves."""
import math
import shutil
import sys
from pathlib import Path

import pytest

from fbspost.read.expand import canonical_calls

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from linuxcnc_examples import chosen, contouring  # noqa: E402

pytestmark = pytest.mark.skipif(shutil.which("rs274") is None,
                                reason="LinuxCNC's rs274 is not installed (apt-get install linuxcnc-uspace)")


@pytest.mark.slow
def test_lengths_in_mm_from_inches(tmp_path):
    # a full circle of radius 0.5 in (G2 back to its start), two turns of radius 0.25 in (P2),
    # a quarter counterclockwise, a 0.01 in line and a 2 in line at 1 in depth; one rapid (from a known
    # position: the first move only sets it)
    program = tmp_path / "p.ngc"
    program.write_text("G20 G90 G17\nG0 X0 Y0 Z0\nG0 X0.5\nG1 X1 F10\nG2 X1 Y0 I-0.5 J0\nG2 X1 Y0 I-0.25 J0 P2\n"
                       "G3 X0.75 Y0.25 I-0.25 J0\nG1 X0.76 Z-1\nG1 X2.76\nM2\n")
    m = contouring(canonical_calls(program))
    arcs_in = math.pi * 1.0 + 2 * math.pi * 0.5 + math.pi * 0.25 / 2
    xy_in = 0.5 + arcs_in + 0.01 + 2
    assert m["rapids"] == 1 and m["feeds"] == 6
    assert m["contour_mm"] == pytest.approx(25.4 * (arcs_in + 0.01), rel=1e-4)
    assert m["xy_mm"] == pytest.approx(25.4 * xy_in, rel=1e-4)
    assert m["length_mm"] == pytest.approx(25.4 * (xy_in - 0.01 + math.hypot(0.01, 1)), rel=1e-4)


def test_rule():
    base = {"feeds": 100, "rapids": 10, "length_mm": 100.0, "xy_mm": 80.0, "contour_mm": 40.0}
    assert chosen(base)
    for key, value in [("feeds", 49), ("rapids", 11), ("xy_mm", 79.0), ("contour_mm", 39.0)]:
        assert not chosen(base | {key: value}), key
