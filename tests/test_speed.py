"""Speed changes keep the output: the same program and settings give the same bytes however the
work is spread (the compensated axes on threads or one after the other), on programs whose
limits bind (windows that need the QP)."""
import os
import queue
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fbspost.errors import InputError
from fbspost.fbs import optimizer
from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.fallback import FALLBACK
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits, FBSSettings
from fbspost.fbs.windows import Window
from fbspost.job import offload, planfeed, processes
from fbspost.job.offload import NICENESS, Offloaded, _portable
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.job.verification import CHECK_NICENESS
from fbspost.profile import load_profile
from fbspost.write.marlinmerge import marlin_merged
from test_streaming import raster

DATA = Path(__file__).parent / "data"


@pytest.mark.parametrize("program, lines, machine", [
    ("gear-marlin2.gcode", 1200, "printer-two-mode"),  # corners on every layer, two modes on X
    ("bracket-reprapfirmware-relative-e.gcode", 900, "printer-two-mode"),
    ("tube-marlin2.gcode", 1500, "bedslinger-example"),
])
@pytest.mark.slow
def test_axes_on_threads_write_the_serial_output_byte_for_byte(tmp_path, program, lines, machine):
    here = replace(CompensateOptions(), second_process=False)
    report = _same_outcome(tmp_path, _head(tmp_path, program, lines), machine,
                           replace(here, parallel_axes=True), replace(here, parallel_axes=False))
    assert len(report["axes"]) == 2 and report["print_time_s"] > 20.0
    windows = [(axis["qp_windows"], axis["windows"]) for axis in report["axes"].values()]
    assert 0 < sum(qp for qp, _ in windows) < sum(all_ for _, all_ in windows)


def _head(tmp_path, program: str, lines: int) -> Path:
    """The first ``lines`` lines of ``program`` (tests/data) as a file of their own."""
    source = tmp_path / program
    with open(DATA / program, "rb") as f:
        source.write_bytes(b"".join(f.readline() for _ in range(lines)))
    return source


def _same_outcome(tmp_path, source: Path, machine: str, *variants: CompensateOptions) -> dict:
    """The bytes written and the report (but its times), with each of the options ``variants``:
    asserted equal; gives the report."""
    profile, outputs, reports = load_profile(machine), [], []
    for i, options in enumerate(variants):
        outputs.append(tmp_path / f"variant-{i}.gcode")
        report = compensate_file(source, outputs[-1], profile, options).as_dict()
        reports.append({k: v for k, v in report.items() if k not in ("output", "stage_time_s", "compute_time_s")})
    assert all(output.read_bytes() == outputs[0].read_bytes() for output in outputs[1:])
    assert all(report == reports[0] for report in reports[1:])
    return reports[0]


@pytest.mark.slow
def test_final_windows_kept_or_built_anew_write_the_same_bytes(tmp_path, monkeypatch):
    """The gear's head (corners on every layer: hundreds of runs, most of equal final-window
    lengths) with every final window kept for the next runs of its length, and with none kept."""
    source = _head(tmp_path, "gear-marlin2.gcode", 1200)
    profile, outputs = load_profile("printer-two-mode"), []
    for budget in (optimizer._FINAL_CACHE_BYTES, 0):
        monkeypatch.setattr(optimizer, "_FINAL_CACHE_BYTES", budget)
        outputs.append(tmp_path / f"kept-{budget}.gcode")
        compensate_file(source, outputs[-1], profile, replace(CompensateOptions(), parallel_axes=False))
    assert outputs[0].read_bytes() == outputs[1].read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("batch_samples, forked", [(planfeed.BATCH_SAMPLES, True), (3000, True),
                                                   (planfeed.BATCH_SAMPLES, False)])
def test_axes_in_processes_of_their_own_write_and_report_the_same(tmp_path, monkeypatch, batch_samples, forked):
    """The gear's head, two modes on X and the QP at its corners: each axis compensated in a
    process of its own (offload.py), sent the plan made here (planfeed.py) in batches of the
    default size and in small ones (runs still open at most batches' ends), gives the same bytes
    and the same report as on threads; the processes forked (Linux) or started anew (elsewhere)."""
    if forked and not offload.FORK:
        pytest.skip("processes are forked on Linux only")
    monkeypatch.setattr(planfeed, "BATCH_SAMPLES", batch_samples)
    monkeypatch.setattr(offload, "FORK", forked)
    report = _same_outcome(tmp_path, _head(tmp_path, "gear-marlin2.gcode", 1200), "printer-two-mode",
                           *(replace(CompensateOptions(), second_process=apart) for apart in (True, False)))
    assert len(report["axes"]) == 2 and all(axis["qp_windows"] > 0 for axis in report["axes"].values())


def test_fallback_warnings_come_back_from_the_axes_processes(tmp_path):
    """A move whose compensation falls back (tests/test_fallback.py): the warning, found in the
    axis' process with the program line it names, is the one found here."""
    source = tmp_path / "in.gcode"
    source.write_bytes(b"G1 X2.789 Y0 Z0.2 F1200\nG1 X0 Y0 Z0.4\n")
    options = CompensateOptions(flavor="marlin", lead_time_s=0.0, settle_time_s=0.0)
    report = _same_outcome(tmp_path, source, "bedslinger-example",
                           *(replace(options, second_process=apart) for apart in (True, False)))
    assert any(w.startswith(FALLBACK) and "line 2" in w for w in report["warnings"]), report["warnings"]


def test_the_compensations_end_is_read_after_the_last_sample_is_written(tmp_path):
    """A raster of three rows, whose writer has every sample before it asks past the last chunk:
    what the compensation tells after that chunk (the axes' processes' outcomes, its own time) is
    still read. The report is whole and alike in both modes, and the time positive. (Before:
    an AttributeError from the processes, a negative optimize time on threads.)"""
    source = raster(tmp_path / "raster.ngc", 3)
    variants = [replace(CompensateOptions(), second_process=apart) for apart in (True, False)]
    report = _same_outcome(tmp_path, source, "bedslinger-example", *variants)
    assert set(report["axes"]) == {"X", "Y"}
    for options in variants:
        stages = compensate_file(source, tmp_path / "out.ngc", load_profile("bedslinger-example"), options).stage_time_s
        assert stages["optimize"] > 0.0 and stages["fallback"] > 0.0


@pytest.mark.parametrize("segment_mm", [10.0, 0.25])
def test_axes_go_to_processes_of_their_own_for_long_programs(tmp_path, segment_mm):
    """Over 256 kB, 10 mm moves (5 lines a second) and 0.25 mm ones (200 a second, a CAM
    finishing pass) alike: the axes' processes do not read or plan, so lines cost them nothing.
    A short program stays here (a process takes about 0.5 s to start)."""
    source = tmp_path / "long.gcode"
    source.write_text("G1 F3000\n" + "".join(f"G1 X{i * segment_mm:.2f} Y{i % 2 * 1e-3:.3f}\n" for i in range(16_000)))
    assert source.stat().st_size > processes._SECOND_PROCESS_BYTES
    options = CompensateOptions(flavor="marlin")
    assert processes.in_second_process(source, options)
    assert not processes.in_second_process(source, replace(options, parallel_axes=False))
    short = tmp_path / "short.gcode"
    short.write_bytes(source.read_bytes()[:processes._SECOND_PROCESS_BYTES - 1])
    assert not processes.in_second_process(short, options)


def _talk(channel):
    channel.request()
    yield channel.get()


def test_a_talking_child_ends_quietly(monkeypatch, capfd):
    """A child that reads its parent's messages (offload.Channel, on a thread of its own) and ends
    while the parent still holds its input open: no fatal error at its interpreter's shutdown
    on the user's terminal, and it exits at once."""
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # (the child imports _talk from here)
    requests = queue.Queue()
    with Offloaded(_talk, requests=requests, key=7) as child:
        assert requests.get(timeout=30) == 7
        child.send("hello")
        assert list(child) == ["hello"]
        child._process.wait(timeout=30)  # ended, its input still open
    assert capfd.readouterr().err == ""


def _at_once(channel):
    return "done"
    yield


def test_messages_to_a_child_that_ended_are_dropped_quietly(monkeypatch):
    """A child that ends without reading what it is sent (the check of a program without motion,
    which ends at once): sending to it, and then closing it, raises nothing here (the bytes left
    unsent in the pipe's buffer once broke the empty program's compensation: Broken pipe)."""
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # (a started child imports _at_once from here)
    child = Offloaded(_at_once, requests=queue.Queue())
    assert list(child) == [] and child.value == "done"
    child._process.wait(timeout=30)
    child.send(("out.gcode", 1 << 20, False))  # (more than a pipe holds: some stay in the buffer)
    child.send(b"x" * (1 << 21))
    child.close()


def _until_the_end(channel):
    try:
        while True:
            channel.get()
    except EOFError:
        yield "the end"


@pytest.mark.parametrize("forked", [True, False])
def test_a_child_sees_its_input_end_while_another_child_runs(monkeypatch, forked):
    """Two children, the second started (forked) while the first's input is open here: closing
    that input ends the first. (A forked child that kept its parent's descriptors would hold the
    first's input open, and the first would wait forever.)"""
    if forked and not offload.FORK:
        pytest.skip("processes are forked on Linux only")
    monkeypatch.setattr(offload, "FORK", forked)
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # (a started child imports _until_the_end from here)
    requests = queue.Queue()
    with Offloaded(_until_the_end, requests=requests, key=1) as first, \
            Offloaded(_until_the_end, requests=requests, key=2) as second:
        first._process.stdin.close()
        # (generous: a started child imports numpy and scipy first, slow on a loaded machine;
        # the fault this catches waits forever)
        assert first.get(timeout=180) == "the end"
        second.send("still talking")
        with pytest.raises(queue.Empty):
            second.get(timeout=0.2)
        second._process.stdin.close()
        assert second.get(timeout=180) == "the end"


def test_bad_input_with_the_axes_in_processes_is_the_one_line_error(tmp_path):
    """A bad line after the axes' processes started: the one-line InputError (file and line),
    and compensating writes nothing."""
    source = tmp_path / "bad.gcode"
    source.write_bytes(b"G1 X1 Y1 F3000\nG1 X2 Y1\n" * 1000 + b"G1 X20 F0\n")
    where = rf"{re.escape(str(source))}:2001: feed F0 must be positive"
    profile, options = load_profile("printer-two-mode"), CompensateOptions(flavor="marlin", second_process=True)
    with pytest.raises(InputError, match=where):
        compensate_file(source, tmp_path / "out.gcode", profile, options)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.gcode"]


def test_an_exception_that_does_not_pickle_comes_back_as_its_traceback():
    class Local(Exception):  # (a local class does not pickle)
        pass

    try:
        raise Local("the optimizer failed")
    except Local as error:
        back = _portable(error)
    assert isinstance(back, RuntimeError) and "Local: the optimizer failed" in str(back)
    assert isinstance(_portable(InputError("a.gcode", 3, "bad")), InputError)


def _niceness():
    yield os.nice(0)


@pytest.mark.skipif(not hasattr(os, "nice"), reason="POSIX priorities")
@pytest.mark.parametrize("forked", [True, False])
def test_the_offloaded_work_yields_the_cores_to_its_reader(monkeypatch, forked):
    if forked and not offload.FORK:
        pytest.skip("processes are forked on Linux only")
    monkeypatch.setattr(offload, "FORK", forked)
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # (the child imports _niceness from here)
    parent = os.nice(0)
    with Offloaded(_niceness) as child:
        (niceness,) = list(child)
    assert niceness == min(parent + NICENESS, 19) and (niceness > parent or parent == 19)
    with Offloaded(_niceness, niceness=CHECK_NICENESS) as check:  # (the check's: below the axes')
        (lowest,) = list(check)
    assert lowest == min(parent + CHECK_NICENESS, 19) and (lowest > niceness or niceness == 19)


def test_help_loads_no_scipy():
    """`fbspost --help` (and a bad argument) answer without loading scipy, osqp or DAQP: the
    commands import the stages they run."""
    code = ("import sys; from click.testing import CliRunner; from fbspost.cli import main; "
            "assert CliRunner().invoke(main, ['--help']).exit_code == 0; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'osqp', 'daqp', 'matplotlib'}))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            cwd=DATA.parent.parent).stdout
    assert loaded.strip() == "[]"


def _min_jerk(distance_mm, duration_s, n_samples, period_s):
    """A minimum-jerk move from rest to rest (closed form), then at rest: ``n_samples`` samples."""
    s = np.clip(np.arange(n_samples) * period_s / duration_s, 0.0, 1.0)
    return distance_mm * (10 * s**3 - 15 * s**4 + 6 * s**5)


def test_runs_of_equal_length_share_their_final_window_and_solve_alike():
    """Each run's final window is kept for later runs of its length (AxisCompensator.final): a
    run solved after another of its length gives, bit for bit, what a new compensator gives,
    also where the limits bind there (the QP solved in the final window)."""
    profile = load_profile("printer-two-mode")
    axis, period_s = profile.axes["X"], 1.0 / profile.sample_rate_hz

    def compensator():
        return AxisCompensator(AxisDynamics(axis.modes, period_s), AxisLimits.from_profile(axis),
                               FBSSettings(settle_weight=5.0))

    first, second = _min_jerk(5.0, 0.12, 180, period_s), _min_jerk(-8.0, 0.06, 180, period_s)
    shared = compensator()
    shared(first)
    again = shared(second)
    assert len(shared._finals) == 1 and again.qp_windows >= 1
    alone = compensator()(second)
    assert np.array_equal(again.command_mm, alone.command_mm)
    # the cache's byte count is its windows' as last used: their solves add to what they hold
    # (OSQP's matrix), which a count taken only when a window is built misses
    ((level, n_rows),) = shared._finals
    built = Window(shared.model_set(level), shared.settings, shared.limits, n_rows + shared.settings.settle_samples,
                   -(-(n_rows - 1) // shared.settings.knot_spacing_samples), hold_from=n_rows,
                   end_conditions=True).nbytes
    shared.final(n_rows, level)
    held = sum(window.nbytes for window, _ in shared._finals.values())
    print(f"final window: {built} bytes built, {held} after its solves")
    assert held > built and shared._finals_bytes == held


def _merged_row_by_row(start, ints, steps_per_unit, min_steps, exact_last):
    """Marlin's merge as its docstring says it, one row at a time over every column."""
    ends = np.vstack([start, ints])
    at_steps = np.rint(ends * steps_per_unit)
    kept = [0]
    for k in range(1, len(ends)):
        if np.abs(at_steps[k] - at_steps[kept[-1]]).max() >= min_steps:
            kept.append(k)
    if exact_last and kept[-1] != len(ints):  # the kept rows near the last end give way to it
        while len(kept) > 1 and np.abs(at_steps[kept[-1]] - at_steps[-1]).max() < min_steps:
            kept.pop()
        kept.append(len(ints))
    return np.array([ends[max(j for j in kept if j <= k)] for k in range(1, len(ends))])


@pytest.mark.parametrize("exact_last", [True, False])
@pytest.mark.parametrize("largest_step", [12, 2])
def test_marlin_merge_as_done_row_by_row(exact_last, largest_step):
    """marlinmerge.marlin_merged (which looks a few rows ahead of every row at once, and further only from
    the rows kept, over the stepped columns) against the rule done naively, on blocks of 0 to 5
    steps (about half of them merged) and on slow ones that take tens of rows to be far."""
    rng = np.random.default_rng(7)
    steps_per_unit = np.zeros(10)
    steps_per_unit[:4] = [0.08, 0.08, 0.4, 0.093]  # X Y Z E stepped, per written unit
    ints = np.cumsum(rng.integers(-largest_step, largest_step + 1, size=(3000, 10)), axis=0)
    start = ints[0] - 5
    merged = marlin_merged(start, ints, steps_per_unit, 3, exact_last)
    assert np.array_equal(merged, _merged_row_by_row(start, ints, steps_per_unit, 3, exact_last))
    kept = (np.diff(np.vstack([start, merged]), axis=0) != 0).any(axis=1)
    assert (0.2 < kept.mean() < 0.9) if largest_step == 12 else (kept.mean() < 0.1)


def _silent():
    yield None


@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_reader_that_starts_after_close_ends_quietly():
    """close() may end the child and close its pipe before this process' reader of it has begun
    to read (the reader of a program's bad line, started just before): the reader then ends
    without an error of its own (it raised ValueError on the closed pipe before)."""
    child = Offloaded(_silent, start=False)
    child.close()
    child.start()
    child._receiver.join(timeout=30)
    kind, error = child._items.get(timeout=30)
    assert kind == "error" and "ended unexpectedly" in str(error)
