"""Streaming: a program compensated a stretch at a time comes out byte for byte as the same program
compensated whole, with all its samples in memory at once."""
from pathlib import Path

import pytest

from fbspost import pipeline, writer
from fbspost.pipeline import CompensateOptions, compensate_file
from fbspost.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
WHOLE = 10**9  # samples: more than any program here has


@pytest.mark.parametrize("name, profile, output_format, streams", [
    ("tests/data/tube-marlin2.gcode", "bedslinger-example", "dense", True),
    ("tests/data/pocket-klipper.gcode", "bedslinger-example", "dense", True),  # Klipper macros, the raise as SET_VELOCITY_LIMIT
    # 10 kHz, limits binding at corners; 3 s, shorter than the optimizer's last window: held whole
    ("samples/butterfly-dense.gcode", "patent-xy-stage", "dense", False),
    ("samples/butterfly-polyline.gcode", "patent-xy-stage", "g5", False),  # g5 holds each run
])
def test_streamed_output_is_the_whole_programs(tmp_path, monkeypatch, name, profile, output_format, streams):
    source, profile = ROOT / name, load_profile(profile)
    options = CompensateOptions(output_format=output_format)
    held = []
    ensure = writer.SampleWindow.ensure

    def ensure_and_count(window, stop):
        ensure(window, stop)
        held.append(len(window.command))

    monkeypatch.setattr(writer.SampleWindow, "ensure", ensure_and_count)
    outputs, reports = [], []
    # Whole: one chunk of samples, the block ends searched over each run at once. Streamed: odd
    # sizes, so that chunks cut runs, optimizer windows and blocks anywhere.
    for chunk, feed in ((WHOLE, WHOLE), (997, 331)):
        monkeypatch.setattr(pipeline, "_CHUNK", chunk)
        monkeypatch.setattr(writer, "_FEED", feed)
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
