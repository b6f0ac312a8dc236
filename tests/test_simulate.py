"""`fbspost simulate` against an independent re-simulation written here: the shapers applied as
2-tap filters per impulse (not the code's interpolation at shifted times), every model through scipy's
lsim, the contour error by reference.segments_distance on the path reference.execute reads, the
contour samples from where the plan's E increases (printers). Inputs taken from fbspost, each
tested on its own: the plan (test_planner), the FBS command computed now (the optimizer per run
of motion, test_optimizer), a compensated program (run here by reference.execute)."""
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost.cli import main
from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits
from fbspost.job.report import CompensateOptions
from fbspost.plan.margins import RunMargins
from fbspost.plan.planner import plan_blocks
from fbspost.profile import format_profile, load_profile
from fbspost.read.flavors import detect_flavor
from fbspost.read.gcode import read_gcode
from reference import execute, rest_limits, rms, sample_blocks, segments_distance, simulate_lsim, unbudgeted

ROOT = Path(__file__).resolve().parent.parent
BUTTERFLY = ROOT / "samples" / "butterfly-dense.gcode"
TUBE = Path(__file__).resolve().parent / "data" / "tube-marlin2.gcode"
TUBE_LINES = 1068  # its first two layers (49 s of motion): the whole 274 s print takes minutes here
SETTLE_PERIODS = 5  # docs/simulate.md: residual vibration over 5 periods of the lowest mode


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def simulate_json(*args) -> dict:
    result = run("simulate", *args, "--json")
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def shaped(x, period_s, amplitudes, times_s):
    """sum_i a_i x(t - t_i) of the samples joined by straight lines: each impulse at (m + f)
    periods is the 2-tap filter (1 - f) x[k - m] + f x[k - m - 1], x held beyond its ends."""
    out = np.zeros_like(x)
    k = np.arange(len(x))
    for a, t in zip(amplitudes, times_s, strict=True):
        m = math.floor(t / period_s)
        f = t / period_s - m
        out += a * ((1 - f) * x[np.clip(k - m, 0, len(x) - 1)] + f * x[np.clip(k - m - 1, 0, len(x) - 1)])
    return out


def resimulate(program, profile, report, compensated=None):
    """Every row of ``report`` recomputed: {name: (command, actual)}, the desired positions, the
    contour samples, the path's segments (XYZ), the modelled axes and the settle time. The FBS
    row: ``compensated`` run block by block at its feeds, or else the optimizer on every run."""
    period_s = 1.0 / profile.sample_rate_hz
    seconds = detect_flavor(program) == "linuxcnc"  # its G4 P
    blocks = list(read_gcode(program, detect_flavor(program), profile.home_mm))
    plan = plan_blocks(blocks, profile, margins=RunMargins.for_profile(profile, flavor=detect_flavor(program)))
    modelled = [a for a in "XYZ" if a in profile.axes and profile.axes[a].modes]
    shapers = {m["name"]: m["shaper"] for m in report["methods"] if m["shaper"]}
    lead = max([-s["times_s"][0] for row in shapers.values() for s in row.values()], default=0.0)
    lag = max([s["times_s"][-1] for row in shapers.values() for s in row.values()], default=0.0)
    if compensated:  # (the written program may end a little after the plan: its dwells are whole ms)
        lag = max(
            lag,
            execute(compensated, profile.sample_rate_hz, seconds, rest_limits(profile)).ends[-1][0]
            - (len(plan.positions_mm) - 1) * period_s,
        )
    settle_s = SETTLE_PERIODS / min(m.frequency_hz for a in modelled for m in profile.axes[a].modes)
    before = math.ceil(lead / period_s - 1e-9)
    after = math.ceil(lag / period_s - 1e-9) + math.ceil(settle_s / period_s)
    desired = np.pad(plan.positions_mm, ((before, after), (0, 0)), mode="edge")
    assert report["start_s"] == pytest.approx(-before * period_s)
    assert report["end_s"] == pytest.approx((len(desired) - 1 - before) * period_s)

    fbs = desired.copy()
    if compensated:
        ends = np.array(execute(compensated, profile.sample_rate_hz, seconds, rest_limits(profile)).ends)
        _, executed = sample_blocks(ends, profile.sample_rate_hz)
        k = executed.shape[1]  # X Y Z E (LinuxCNC's other axes follow the plan)
        fbs[before:before + len(executed), :k] = executed[:len(desired) - before]
        fbs[before + len(executed):, :k] = executed[-1]
        # Z and E follow the plan in the compensated program; reference.execute cannot place them
        # before X and Y are first set.
        unmodelled = [i for i, a in enumerate("XYZE") if a not in modelled]
        fbs[:, unmodelled] = desired[:, unmodelled]
    else:
        for axis in modelled:
            column, limits = "XYZE".index(axis), AxisLimits.from_profile(profile.axes[axis])
            optimizer = AxisCompensator(AxisDynamics(profile.axes[axis].modes, period_s), limits,
                                        CompensateOptions().settings, "limited")
            for first, last in plan.runs:
                fbs[before + first : before + last + 1, column] = optimizer(
                    plan.positions_mm[first : last + 1, column]
                ).command_mm
    commands = {"original": desired, "fbs": fbs}
    for name, row in shapers.items():
        command = desired.copy()
        for axis, s in row.items():
            column = "XYZE".index(axis)
            command[:, column] = shaped(desired[:, column], period_s, s["amplitudes"], s["times_s"])
        commands[name] = command
    rows = {}
    for name, command in commands.items():
        actual = command.copy()
        for axis in modelled:
            column = "XYZE".index(axis)
            actual[:, column] = simulate_lsim(profile.axes[axis].modes, period_s, command[:, column])
        rows[name] = (command, actual)

    # The path and where it is measured, read independently: the program's moves as reference.execute
    # runs them; on a printer its extruding moves and the samples where the plan's E increases.
    path = np.array(execute(program, profile.sample_rate_hz).ends)[:, 1:5]
    e = desired[:, 3]
    if report["contour_moves"] == "extruding":
        extruding = np.diff(path[:, 3]) > 0
        starts, stops = path[:-1][extruding, :3], path[1:][extruding, :3]
        rising = np.diff(e) > 0  # a sample with E rising on both sides is inside an extruding move
        mask = np.append(rising, False) & np.insert(rising, 0, False)
    else:  # the samples inside the feed moves' times (not in the margins' rests, nor a rapid's)
        starts, stops = path[:-1, :3], path[1:, :3]
        t = (np.arange(len(desired)) - before) * period_s
        mask = np.zeros(len(t), bool)
        for i, block in enumerate(blocks):
            if plan.is_move[i] and not re.match(rb"\s*G0?0(?!\d)", block.raw, re.I):
                mask |= (t >= plan.move_start_s[i]) & (t <= plan.line_time_s[i])
    return rows, desired, mask, (starts, stops), modelled, settle_s


def check_rows(report, rows, desired, mask, segments, modelled, settle_s, period_s, names, candidates=16):
    """Each named row of the report within 5 % of the re-simulation (or 0.02 um: rounding).
    ``candidates``: path pieces the reference tries per point (where many passes cross, more)."""
    close = lambda got, want: got == pytest.approx(want, rel=0.05, abs=0.02)  # noqa: E731
    methods = {m["name"]: m for m in report["methods"]}
    settle = math.ceil(settle_s / period_s)
    for name in names:
        command, actual = rows[name]
        path, axes = methods[name]["path"], methods[name]["axes"]
        contour = segments_distance(*segments, actual[mask, :3], candidates=candidates, piece_mm=0.1) * 1e3
        command_contour = segments_distance(*segments, command[mask, :3], candidates=candidates, piece_mm=0.1) * 1e3
        tracking = np.linalg.norm(desired[:, :3] - actual[:, :3], axis=1) * 1e3
        last = np.flatnonzero(np.abs(command - command[-1]).max(axis=1) > 1e-9)[-1] + 1
        residual = np.linalg.norm(actual[last:last + settle + 1, :3] - command[-1, :3], axis=1) * 1e3
        figures = {
            "rms_contour_error_um": rms(contour), "max_contour_error_um": contour.max(),
            "rms_tracking_error_um": rms(tracking), "max_tracking_error_um": tracking.max(),
            "rms_command_contour_error_um": rms(command_contour),
            "max_command_contour_error_um": command_contour.max(),
            "residual_vibration_um": residual.max(),
        }
        for key, value in figures.items():
            assert close(path[key], value), f"{name} {key}: reported {path[key]:.4g}, re-simulated {value:.4g}"
        for axis in modelled:
            error = (desired[:, "XYZE".index(axis)] - actual[:, "XYZE".index(axis)]) * 1e3
            assert close(axes[axis]["rms_tracking_error_um"], rms(error)), (name, axis)
            assert close(axes[axis]["max_tracking_error_um"], np.abs(error).max()), (name, axis)
            velocity = np.abs(np.diff(command[:, "XYZE".index(axis)])).max() / period_s
            assert close(axes[axis]["max_velocity_mm_s"], velocity), (name, axis)


def shaper_timing_checks(report, desired, modelled, period_s):
    """Each axis' shaped motion starts its shaper's lead_s early and ends its lag_s late (the first
    and last impulse), so the program's motion starts and ends by the most of these; FBS neither."""
    moving = np.abs(np.diff(desired, axis=0)) > 1e-9
    first = {a: np.argmax(moving[:, i]) * period_s for i, a in enumerate("XYZE") if moving[:, i].any()}
    last = {
        a: (len(moving) - np.argmax(moving[::-1, i])) * period_s for i, a in enumerate("XYZE") if moving[:, i].any()
    }
    for m in report["methods"]:
        if m["shaper"]:
            shift = {a: (-s["times_s"][0], s["times_s"][-1]) for a, s in m["shaper"].items()}
            early = min(first.values()) - min(t - shift.get(a, (0, 0))[0] for a, t in first.items())
            late = max(t + shift.get(a, (0, 0))[1] for a, t in last.items()) - max(last.values())
            assert m["path"]["start_advance_s"] == pytest.approx(early, abs=1.01 * period_s), m["name"]
            assert m["path"]["end_delay_s"] == pytest.approx(late, abs=1.01 * period_s), m["name"]
            assert m["path"]["added_duration_s"] == pytest.approx(early + late, abs=2.01 * period_s), m["name"]
    # FBS moves only within its lead and settle margins: it starts at most lead_s before the plan's
    # motion and ends at most settle_s after it.
    fbs = report["methods"][1]["path"]
    margins = RunMargins.for_profile(load_profile(report["profile"]))
    assert -period_s <= fbs["start_advance_s"] <= margins.lead_s + period_s
    assert -period_s <= fbs["end_delay_s"] <= margins.settle_s + period_s
    assert fbs["added_duration_s"] <= margins.lead_s + margins.settle_s + 2 * period_s


@pytest.mark.slow
def test_patent_stage_butterfly():
    profile = load_profile("patent-xy-stage")
    report = simulate_json(BUTTERFLY, "--machine", "patent-xy-stage")
    assert [m["name"] for m in report["methods"]] == [
        "original",
        "fbs",
        "zv",
        "mzv",
        "zvd",
        "ei",
        "2hump_ei",
        "3hump_ei",
    ]
    assert report["contour_moves"] == "feed"
    rows, desired, *rest = resimulate(BUTTERFLY, profile, report)
    # The butterfly crosses itself some 40 times at its centre: the reference needs many candidates.
    check_rows(report, rows, desired, *rest, 1 / profile.sample_rate_hz, list(rows), candidates=64)
    fbs = report["methods"][1]["path"]["rms_contour_error_um"]
    for method in report["methods"][2:]:
        assert fbs < method["path"]["rms_contour_error_um"] / 10, method["name"]
    # The default shaper frequency and damping: the axis' highest resonance peak.
    assert report["methods"][2]["shaper"]["X"]["frequency_hz"] == 42.53
    assert report["methods"][2]["shaper"]["Y"]["frequency_hz"] == 25.7
    shaper_timing_checks(report, desired, rest[3], 1 / profile.sample_rate_hz)


@pytest.fixture(scope="module")
def tube_head(tmp_path_factory):
    path = tmp_path_factory.mktemp("tube") / "tube-head.gcode"
    path.write_bytes(b"".join(TUBE.read_bytes().splitlines(keepends=True)[:TUBE_LINES]))
    return path


@pytest.mark.slow
def test_printer_tube(tube_head):
    profile = load_profile("bedslinger-example")
    report = simulate_json(tube_head, "--machine", "bedslinger-example")
    assert report["contour_moves"] == "extruding"
    rows, *rest = resimulate(tube_head, profile, report)
    check_rows(report, rows, *rest, 1 / profile.sample_rate_hz, list(rows))
    fbs = report["methods"][1]["path"]["rms_contour_error_um"]
    for method in report["methods"][2:]:
        assert fbs < method["path"]["rms_contour_error_um"] / 3, method["name"]
        # A shaper's price: its command leaves the path at the corners (smoothing).
        assert method["path"]["max_command_contour_error_um"] > 20, method["name"]
    assert report["methods"][0]["path"]["max_command_contour_error_um"] < 1e-6  # the plan is on the path


@pytest.mark.slow
def test_executing_a_compensated_program(tube_head, tmp_path):
    """--compensated: the written program (default tolerance, 1 ms blocks: no line budget, no
    Marlin steps, whose E-timed blocks a run at the feeds cannot follow) run at its feeds."""
    profile = unbudgeted(load_profile("bedslinger-example"))
    machine = tmp_path / "printer.toml"
    machine.write_text(format_profile(profile))
    compensated = tmp_path / "out.gcode"
    assert run("compensate", tube_head, "--machine", machine, "-o", compensated, "-q").exit_code == 0
    report = simulate_json(tube_head, "--machine", machine, "--compensated", compensated, "--shapers", "none")
    assert [m["name"] for m in report["methods"]] == ["original", "fbs"]
    assert "run block by block" in report["methods"][1]["label"]
    rows, *rest = resimulate(tube_head, profile, report, compensated)
    check_rows(report, rows, *rest, 1 / profile.sample_rate_hz, ["fbs"])


@pytest.mark.slow
def test_given_shaper_frequency_and_damping(tube_head):
    report = simulate_json(tube_head, "--machine", "bedslinger-example", "--shapers", "zv",
                           "--shaper-freq", "X=50,y=30", "--shaper-damping", "Y=0.2")
    zv = report["methods"][2]["shaper"]
    assert (zv["X"]["frequency_hz"], zv["X"]["damping"]) == (50.0, 0.08)  # X's damping: its mode's
    assert (zv["Y"]["frequency_hz"], zv["Y"]["damping"]) == (30.0, 0.2)
    # ZV: two impulses half a damped period apart, the second K = exp(-d pi / sqrt(1 - d^2)) of the first.
    k = math.exp(-0.2 * math.pi / math.sqrt(1 - 0.04))
    assert zv["Y"]["amplitudes"] == pytest.approx([1 / (1 + k), k / (1 + k)])
    assert np.diff(zv["Y"]["times_s"])[0] == pytest.approx(0.5 / (30 * math.sqrt(1 - 0.04)))


@pytest.mark.slow
def test_plots(tmp_path):
    program = tmp_path / "square.gcode"
    program.write_text("G21 G90\nM83\nG1 X10 Y10 F6000\nG1 X40 E1 F3000\nG1 Y40 E1\nG1 X10 E1\nG1 Y10 E1\n")
    png, pdf = tmp_path / "a.png", tmp_path / "b.pdf"
    for target in (png, pdf):
        result = run("simulate", program, "--machine", "bedslinger-example", "--shapers", "mzv,ei", "--plot", target)
        assert result.exit_code == 0, result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 300_000
    # One page per panel: the path, the costs, X and Y against time, the spectrum, the response.
    assert pdf.read_bytes()[:5] == b"%PDF-" and len(re.findall(rb"/Type /Page\b(?!s)", pdf.read_bytes())) == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.pdf", "square.gcode"]  # no temporary files


@pytest.mark.parametrize("args, code, message", [
    (["--shapers", "zv,foo"], 2, "unknown shaper 'foo'"),
    (["--shaper-freq", "Z=40"], 2, "axis Z has no modes"),
    (["--shaper-freq", "X=fast"], 2, "expected AXIS=VALUE"),
    (["--shaper-damping", "X=1.5"], 2, "must be > 0 and < 1"),
    (["--shaper-damping", "X=0.5", "--shapers", "ei"], 2, "ei is defined for damping ratios up to 0.4"),
    (["--plot", "x.svg"], 2, "expected a .png or .pdf"),
])
def test_bad_options(args, code, message):
    result = run("simulate", BUTTERFLY, "--machine", "patent-xy-stage", *args)
    assert result.exit_code == code and message in result.output, result.output


def test_bad_input_is_one_line(tmp_path):
    bad = tmp_path / "bad.gcode"
    bad.write_text("G1 X1 Y1 F600\nG2 X2 Y2\n")
    result = run("simulate", bad, "--machine", "patent-xy-stage")
    assert result.exit_code == 1 and result.output.startswith(f"error: {bad}:") and result.output.count("\n") == 1
    empty = tmp_path / "empty.gcode"
    empty.write_text("; nothing\n")
    result = run("simulate", empty, "--machine", "patent-xy-stage")
    assert result.exit_code == 1 and result.output == f"error: {empty}: no motion to simulate\n"
