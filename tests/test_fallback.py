"""The fallback to the planned original (fbspost.fbs.fallback), judged by scipy's simulation of the
profile (reference.simulate_lsim), the profile's limits and the plan's own times."""
import re

import numpy as np
import pytest

from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.fallback import FALLBACK, LARGEST, LIMITS, WORSE, AxisGuard
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.plan.planner import plan_blocks
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode
from reference import execute, rms, sample_blocks, simulate_lsim, unbudgeted

PRINTER = unbudgeted(load_profile("bedslinger-example"))
X = PRINTER.axes["X"]
PERIOD_S = 1.0 / PRINTER.sample_rate_hz


class Errors:
    def add(self, error_mm):
        pass


def compensator():
    return AxisCompensator(AxisDynamics(X.modes, PERIOD_S), AxisLimits.from_profile(X))


def guarded(planned, compensated, piece=None):
    """The written command of one run of X (in pieces of ``piece`` samples), and its guard."""
    guard = AxisGuard(compensator(), Errors(), Errors())
    piece = piece or len(planned)
    written = [guard.push(planned[a:a + piece], compensated[a:a + piece], True, a > 0)
               for a in range(0, len(planned), piece)]
    return np.concatenate([*written, guard.finish()]), guard


def modelled_error(desired, command):
    """Desired minus scipy's simulation of the command, over it and 0.5 s of rest after it."""
    desired, command = (np.concatenate([u, np.full(500, u[-1])]) for u in (desired, command))
    return desired - simulate_lsim(X.modes, PERIOD_S, command)


@pytest.fixture(scope="module")
def move():
    """X: 20 mm in 0.3 s (a cosine velocity), then 3.2 s at rest in the same run; its
    compensated command."""
    t = np.arange(3500) * PERIOD_S
    planned = np.where(t < 0.3, 20 * (t / 0.3 - np.sin(2 * np.pi * t / 0.3) / (2 * np.pi)), 20.0)
    return planned, compensator()(planned).command_mm


def test_a_harmful_stretch_falls_back_and_only_there(move):
    """A bump of 0.2 mm in the compensated command 1.2 s after the move (as an optimizer gone
    wrong there would give): compensating as given is worse than the original there, and its
    largest error too. Written: the compensated command through the move, the planned original
    over the bump, and never worse than the original; one stretch: the bump's samples and the
    blend down to the original before them, at most a blend and a decision long; why."""
    planned, command = move
    bump = np.zeros_like(planned)
    bump[1500:1530] = 0.2 * np.sin(np.linspace(0, np.pi, 30)) ** 2
    written, guard = guarded(planned, command + bump)
    before, bumped = modelled_error(planned, planned), modelled_error(planned, command + bump)
    assert rms(bumped[1500:2000]) > rms(before[1500:2000]) and np.abs(bumped).max() > np.abs(before).max()
    after = modelled_error(planned, written)
    assert rms(after) <= rms(before) and np.abs(after).max() <= np.abs(before).max()
    assert rms(after) < rms(before) / 100  # the move stays compensated
    np.testing.assert_array_equal(written[:1000], command[:1000])
    np.testing.assert_allclose(written[1500:1530], planned[1500:1530], rtol=0, atol=1e-9)
    [stretch] = guard.stretches
    moved = np.flatnonzero(bump > 1e-4)  # where it moves the command by 0.1 um or more
    span = guard.ramp + guard.unit
    assert moved[0] - span <= stretch.start <= moved[0] and moved[-1] + 1 <= stretch.stop <= moved[-1] + 1 + span
    assert WORSE in stretch.reasons and LARGEST in stretch.reasons


def test_a_stretch_beyond_the_limits_falls_back_within_them(move):
    """A 15 um step of one sample in the compensated command, in the middle of the move: its
    second differences break X's acceleration limit (10000 mm/s^2), though the command still
    does better than the original there. Written: within the limit everywhere (the planned
    original is), the planned original at the step, the compensated command a ramp away."""
    planned, command = move
    stepped = command.copy()
    stepped[150] += 0.015
    accel = np.abs(np.diff(stepped, 2)) / PERIOD_S**2
    assert accel.max() > X.max_acceleration_mm_s2 >= np.abs(np.diff(planned, 2)).max() / PERIOD_S**2
    written, guard = guarded(planned, stepped)
    assert np.abs(np.diff(written, 2)).max() / PERIOD_S**2 <= X.max_acceleration_mm_s2 * (1 + 1e-7)
    assert written[150] == planned[150]
    before, after = modelled_error(planned, planned), modelled_error(planned, written)
    assert rms(after) <= rms(before) and np.abs(after).max() <= np.abs(before).max()
    np.testing.assert_array_equal(written[1000:], stepped[1000:])
    [stretch] = guard.stretches
    assert stretch.start <= 150 < stretch.stop and LIMITS in stretch.reasons


def test_a_stretch_beyond_the_travel_falls_back_within_it(move):
    """The travel ends at 20 mm, where the move ends; the compensated command (of a compensator
    without the travel's rows) settles onto 20 mm from 39 nm beyond it. Written: within the travel
    everywhere, exactly; the compensated command before the stretch that falls back; no worse than
    the original."""
    planned, command = move
    assert command.max() > 20.0 + 3e-5 and planned.max() == 20.0
    limits = AxisLimits(AxisLimits.from_profile(X).command, position_mm=(0.0, 20.0))
    guard = AxisGuard(AxisCompensator(AxisDynamics(X.modes, PERIOD_S), limits), Errors(), Errors())
    written = np.concatenate([guard.push(planned, command, True, False), guard.finish()])
    assert written.min() >= 0.0 and written.max() <= 20.0
    [stretch] = guard.stretches
    assert LIMITS in stretch.reasons and stretch.start <= np.flatnonzero(command > 20.0)[0]
    np.testing.assert_array_equal(written[:stretch.start], command[:stretch.start])
    before, after = modelled_error(planned, planned), modelled_error(planned, written)
    assert rms(after) <= rms(before) and np.abs(after).max() <= np.abs(before).max()


def test_decisions_do_not_depend_on_the_pieces(move):
    planned, command = move
    bump = np.zeros_like(planned)
    bump[700:760] = 0.05 * np.sin(np.linspace(0, np.pi, 60)) ** 2
    whole, _ = guarded(planned, command + bump)
    pieces, _ = guarded(planned, command + bump, piece=97)
    np.testing.assert_array_equal(pieces, whole)


def test_largest_error_raised_by_the_compensation_falls_back_with_a_warning(tmp_path):
    """2.8 mm of X at F1200 from rest and back to rest: the compensated command's largest
    modelled error is above the original's (scipy). The output keeps the original's largest
    error and follows the original where the compensation is worst; one warning names axis X,
    the time (from the move's start to its end) and line 2."""
    source = tmp_path / "in.gcode"
    source.write_bytes(b"G1 X2.789 Y0 Z0.2 F1200\nG1 X0 Y0 Z0.4\n")
    plan = plan_blocks(list(read_gcode(source, "marlin")), PRINTER)
    planned = plan.positions_mm[:, 0]
    compensated = modelled_error(planned, compensator()(planned).command_mm)
    before = modelled_error(planned, planned)
    assert np.abs(compensated).max() > np.abs(before).max() * 1.2
    # (without lead and settle margins: with them the compensation no longer does this harm)
    options = CompensateOptions(flavor="marlin", lead_time_s=0.0, settle_time_s=0.0)
    report = compensate_file(source, tmp_path / "out.gcode", PRINTER, options)
    [warning] = [w for w in report.warnings if w.startswith(FALLBACK)]
    found = re.fullmatch(rf"{FALLBACK}: axis X, ([\d.]+)-([\d.]+) s, line 2 \((.*)\)", warning)
    assert found and found[3] == LARGEST, warning
    start_s, end_s = float(found[1]), float(found[2])
    assert start_s <= plan.move_start_s[1] + 2 * PERIOD_S and end_s >= plan.line_time_s[1] - 2 * PERIOD_S
    _, output = sample_blocks(execute(tmp_path / "out.gcode").ends, PRINTER.sample_rate_hz)
    after = modelled_error(planned, output[:len(planned), 0])
    assert np.abs(after).max() <= np.abs(before).max() + 2e-4  # the written decimals, the 1 um tolerance
    worst = int(np.argmax(np.abs(compensated)))
    assert abs(output[worst, 0] - planned[worst]) <= 1e-3
    assert report.axes["X"].max_error_after_um <= report.axes["X"].max_error_before_um * (1 + 1e-9)
