"""Speed changes keep the output: the same program and settings give the same bytes however the
work is spread (the compensated axes on threads or one after the other), on programs whose
limits bind (windows that need the QP)."""
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from fbspost.pipeline import CompensateOptions, compensate_file
from fbspost.profile import load_profile

DATA = Path(__file__).parent / "data"


@pytest.mark.parametrize("program, lines, machine", [
    ("gear-marlin2.gcode", 1200, "printer-two-mode"),  # corners on every layer, two modes on X
    ("bracket-reprapfirmware-relative-e.gcode", 900, "printer-two-mode"),
    ("tube-marlin2.gcode", 1500, "bedslinger-example"),
])
@pytest.mark.slow
def test_axes_on_threads_write_the_serial_output_byte_for_byte(tmp_path, program, lines, machine):
    source = tmp_path / program
    with open(DATA / program, "rb") as f:
        source.write_bytes(b"".join(f.readline() for _ in range(lines)))
    profile, outputs = load_profile(machine), {}
    for parallel in (True, False):
        outputs[parallel] = tmp_path / f"parallel-{parallel}.gcode"
        report = compensate_file(
            source, outputs[parallel], profile, replace(CompensateOptions(), parallel_axes=parallel)
        )
        assert len(report.axes) == 2 and report.print_time_s > 20.0
        assert (
            0
            < sum(axis.qp_windows for axis in report.axes.values())
            < sum(axis.windows for axis in report.axes.values())
        )
    assert outputs[True].read_bytes() == outputs[False].read_bytes()


def test_help_loads_no_scipy():
    """`fbspost --help` (and a bad argument) answer without loading scipy, osqp or DAQP: the
    commands import the stages they run."""
    code = ("import sys; from click.testing import CliRunner; from fbspost.cli import main; "
            "assert CliRunner().invoke(main, ['--help']).exit_code == 0; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'osqp', 'daqp', 'matplotlib'}))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            cwd=DATA.parent.parent).stdout
    assert loaded.strip() == "[]"
