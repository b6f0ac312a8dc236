"""Streaming: a program planned, compensated and written a stretch at a time comes out byte for byte
as the same program done whole, with all its blocks and samples in memory at once."""
import math
from pathlib import Path

import pytest

from fbspost.job import axes
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.plan import lookahead, planner
from fbspost.profile import load_profile
from fbspost.write import runs, samples

pytestmark = pytest.mark.slow  # whole programs, streamed and whole (memory: bench/streaming_memory.py)

ROOT = Path(__file__).resolve().parent.parent
WHOLE = 10**9  # blocks or samples: more than any program here has


@pytest.mark.parametrize("name, profile, output_format, streams", [
    ("tests/data/tube-marlin2.gcode", "bedslinger-example", "dense", True),
    # Klipper macros, the raise as SET_VELOCITY_LIMIT
    ("tests/data/pocket-klipper.gcode", "bedslinger-example", "dense", True),
    # 10 kHz, limits binding at corners; 3 s, shorter than the optimizer's last window: held whole
    ("samples/butterfly-dense.gcode", "patent-xy-stage", "dense", False),
    ("samples/butterfly-polyline.gcode", "patent-xy-stage", "g5", False),  # g5 holds each run
])
def test_streamed_output_is_the_whole_programs(tmp_path, monkeypatch, name, profile, output_format, streams):
    source, profile = ROOT / name, load_profile(profile)
    options = CompensateOptions(output_format=output_format)
    held = []
    ensure = samples.SampleWindow.ensure

    def ensure_and_count(window, stop):
        ensure(window, stop)
        held.append(len(window.command))

    monkeypatch.setattr(samples.SampleWindow, "ensure", ensure_and_count)
    outputs, reports = [], []
    # Whole: every block planned at once, one chunk of samples, the block ends searched over each
    # run at once. Streamed: odd sizes, so that batches of blocks and chunks of samples cut runs,
    # scans, optimizer windows and blocks anywhere. (Scans in chunks of 257 pieces, both ways: to
    # carry them over chunks too.)
    monkeypatch.setattr(lookahead, "SCAN_CHUNK", 257)
    for batch, chunk, feed, flush in ((WHOLE, WHOLE, WHOLE, math.inf), (13, 997, 331, 0.5)):
        monkeypatch.setattr(planner, "BATCH_BLOCKS", batch)
        monkeypatch.setattr(runs, "_FLUSH_S", flush)
        monkeypatch.setattr(axes, "_CHUNK", chunk)
        monkeypatch.setattr(runs, "_FEED", feed)
        held.clear()
        target = tmp_path / f"{chunk}.gcode"
        reports.append(compensate_file(source, target, profile, options))
        outputs.append(target.read_bytes())
    if streams:  # the look-ahead (2000 samples after a block end, the optimizer's last window), not 274k or more
        assert max(held) < 20000
    assert outputs[1] == outputs[0]
    whole, streamed = reports
    assert streamed.lines_out == whole.lines_out and streamed.warnings == whole.warnings
    for axis in whole.axes:
        # the same errors, summed in another order
        assert streamed.axes[axis].rms_error_after_um == pytest.approx(whole.axes[axis].rms_error_after_um, rel=1e-9)
        assert streamed.axes[axis].max_error_before_um == pytest.approx(whole.axes[axis].max_error_before_um, rel=1e-9)


def raster(path: Path, rows: int) -> Path:
    """A LinuxCNC finishing pass, 121 segments of 0.25 mm per row: one run of motion as long as
    the program (bench/streaming_memory.py's long program)."""
    lines = ["G21 G90 G17", "G0 X0 Y0 Z1", "G1 Z0 F600"]
    for row in range(rows):
        xs = [i * 0.25 for i in range(121)][:: 1 if row % 2 == 0 else -1]
        lines += [f"G1 X{x:.3f} Y{row * 0.5 % 30:.3f} Z{0.2 * math.sin(x / 5):.4f} F3000" for x in xs]
    path.write_text("\n".join(lines + ["M2", ""]))
    return path


