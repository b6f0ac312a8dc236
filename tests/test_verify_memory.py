"""--verify's memory does not grow with the program's length (issue 33 item 4): the gear stacked
once and twice, each checked in a fresh process with chunks lowered to 5000 lines. (Before
it streamed, verify held every block and sample: about 4 kB a line, 150 MB more for the 37,000
more lines here.)"""
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "verify_long.py"

# verify of a program against itself on the model of Marlin; prints VmHWM (kB): the peak resident
# memory of this process alone (ru_maxrss would count what a forked parent held)
_VERIFY = """
import sys
from pathlib import Path
from fbspost.firmware import verify
from fbspost.profile import load_profile
program = Path(sys.argv[1])
verdict = verify.verify(program, program, load_profile("printer-two-mode"), "marlin", chunk_lines=5000)
print(verdict.original.duration_s, verdict.original.rms_um)
print(next(l.split()[1] for l in open("/proc/self/status") if l.startswith("VmHWM:")))
"""


def stacked(copies: int, path: Path) -> Path:
    """The gear's layers ``copies`` times, each copy 10 mm above the last (bench/verify_long.py's print)."""
    spec = importlib.util.spec_from_file_location("verify_long", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.stacked_gear(copies, path)
    return path


@pytest.mark.slow
def test_verify_memory_is_flat_with_length(tmp_path):
    """Peak memory of the check of 37k and 75k lines: within 40 MB of each other; the print
    twice as long takes twice as long on the model (a real run, not a shortcut)."""
    results = []
    for copies in (1, 2):
        done = subprocess.run([sys.executable, "-c", _VERIFY, str(stacked(copies, tmp_path / f"gear{copies}.gcode"))],
                              capture_output=True, text=True, timeout=1800,
                              env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        assert done.returncode == 0, done.stderr[-2000:]
        (duration_s, rms_um), (peak_kb,) = (map(float, line.split()) for line in done.stdout.splitlines()[-2:])
        results.append((duration_s, rms_um, peak_kb))
    (short_s, short_um, short_kb), (long_s, long_um, long_kb) = results
    assert long_s == pytest.approx(2 * short_s, rel=0.01)  # (the copies' travels between them: within 1%)
    assert long_um == pytest.approx(short_um, rel=0.05)  # the same layers
    assert long_kb < short_kb + 40_000, (short_kb, long_kb)
