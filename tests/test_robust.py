"""Robust FBS (a set of models), modes that vary with the print, and `simulate --model-error`,
against independent truths: the modes' frequency response in closed form, a brute-force least
squares of the stacked models written out with scipy's lsim, the state carried through the
windows against lsim, and a time-varying machine simulated exactly per sample (reference.py).
The figures on the gear print are predictions: fbspost's model of the machine, not a firmware's plan."""
import dataclasses
import json
import math
import re

import numpy as np
import pytest
from click.testing import CliRunner

from fbspost.cli import main
from fbspost.contour import PathDistance
from fbspost.fbs.dynamics import AxisDynamics, ModelSet, modal_response, scaled_mode
from fbspost.fbs.optimizer import AxisCompensator
from fbspost.fbs.settings import AxisLimits, FBSSettings
from fbspost.fbs.varying import load_modes, position_modes
from fbspost.firmware.verify import contour_um, modelled, printed_path
from fbspost.job.axes import varying_modes
from fbspost.job.pipeline import compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import Mode, PositionTable, ProfileError, format_profile, load_profile, parse_profile
from fbspost.read.blocks import AXES
from fbspost.tools.simulate import MODEL_ERRORS, model_error, simulate_program
from firmware_results import LoadedBed, klippy_run, move_ends, shaped_plans
from klippy_planner import klippy_or_skip
from reference import simulate_lsim, simulate_varying, unbudgeted
from test_optimizer import brute_force_problem, smooth_move

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

DATA = "tests/data"
NOMINAL = load_profile("printer-two-mode")
ROBUST = load_profile(f"{DATA}/printer-two-mode-robust.toml")
PATENT_X = load_profile("patent-xy-stage").axes["X"].modes
T = 1e-3


def with_tolerances(modes, frequency, damping):
    return tuple(dataclasses.replace(m, frequency_tolerance=frequency, damping_tolerance=damping) for m in modes)


def profile_text(axis_keys: str = "", mode_keys: str = "") -> dict:
    """printer-two-mode's TOML with keys added to [axes.X] and to its first mode."""
    text = open("machines/printer-two-mode.toml").read()
    text = text.replace("[axes.X]\n", "[axes.X]\n" + axis_keys + "\n")
    text = text.replace("beta = 0.0 },    # 80%", f"beta = 0.0 {mode_keys}}},    # 80%", 1)
    return tomllib.loads(text)


def test_tolerances_and_moving_mass_in_the_profile():
    profile = parse_profile(profile_text("frequency_tolerance = 0.1\ndamping_tolerance = 0.3\nmoving_mass = 1.5",
                                         ", frequency_tolerance = 0.02"), "p.toml")
    x = profile.axes["X"]
    assert [(m.frequency_tolerance, m.damping_tolerance) for m in x.modes] == [(0.02, 0.3), (0.1, 0.3)]
    assert (x.moving_mass_kg, x.filament_density_g_cm3) == (1.5, 1.24)
    assert profile.axes["Y"].modes[0].frequency_tolerance == 0.0 and profile.axes["Y"].moving_mass_kg is None
    again = parse_profile(tomllib.loads(format_profile(profile)), "again.toml")
    assert again.axes["X"].modes[0].frequency_tolerance == 0.02 and again.axes["X"].moving_mass_kg == 1.5
    for keys, message in [("frequency_tolerance = 0.5", "axes.X.frequency_tolerance: must be in [0, 0.5), got 0.5"),
                          ("filament_density = 1.2", "axes.X.filament_density: needs moving_mass"),
                          ("moving_mass = 0", "axes.X.moving_mass: must be > 0")]:
        with pytest.raises(ProfileError, match="^" + re.escape(f"p.toml: {message}")):
            parse_profile(profile_text(keys), "p.toml")


def test_modes_by_position_in_the_profile():
    """A table of frequency factors against an axis' position: linear between its points, flat
    beyond them; the level in force is the nearest power of 1.01 (0 where the position is not known)."""
    table = "modes_by_position = {{ axis = {}, position = {}, frequency_scale = {} }}"
    profile = parse_profile(profile_text(table.format('"Y"', "[0, 100, 220]", "[1.0, 0.9, 0.85]")), "p.toml")
    x = profile.axes["X"].modes_by_position
    assert x == PositionTable("Y", (0.0, 100.0, 220.0), (1.0, 0.9, 0.85))
    assert parse_profile(tomllib.loads(format_profile(profile)), "again.toml").axes["X"].modes_by_position == x
    varying = varying_modes(profile, profile.axes["X"])
    assert varying.column == AXES.index("Y") and varying.level(math.nan) == 0
    for y, scale in [(-10.0, 1.0), (50.0, 0.95), (160.0, 0.875), (300.0, 0.85)]:
        assert varying.scale(y) == pytest.approx(scale, abs=1e-12)
        assert varying.level(y) == round(math.log(scale) / math.log(1.01))
        assert varying.modes_at(varying.level(y))[1].frequency_hz == pytest.approx(96.0 * scale, rel=0.005)
    where = "p.toml: axes.X.modes_by_position"
    for keys, message in [
        (table.format('"E"', "[0, 1]", "[1, 1]"), ".axis: must be one of X, Y, Z, A, B, C, U, V, W, got 'E'"),
        (table.format('"Y"', "[0, 0]", "[1, 1]"), ".position: must increase"),
        (table.format('"Y"', "[0]", "[1]"), ".position: must be a list of at least two numbers"),
        (table.format('"Y"', "[0, 100, 200]", "[1, 0.9]"), ".frequency_scale: has 2 values for 3 positions"),
        (table.format('"Y"', "[0, 100]", "[1, 0]"), ".frequency_scale[1]: must be > 0"),
        (table.format('"Y"', "[0, 100]", "[1, 6]"), ".frequency_scale: takes a mode to 576 Hz, above the Nyquist"),
        (table.format('"Y"', "[0, 100]", "[1, 1]") + "\nmoving_mass = 1", ": and moving_mass together"),
        ('modes_by_position = { axis = "Y", position = [0, 1], frequency_scale = [1, 1], at = 2 }',
         ".at: unknown key"),
    ]:
        with pytest.raises(ProfileError, match="^" + re.escape(where + message)):
            parse_profile(profile_text(keys), "p.toml")


@pytest.mark.parametrize("kind", ["load", "position"])
def test_the_varying_machine_simulated_as_the_exact_stepped_machine(kind):
    """``varying.simulate``: lfilter per stretch of one level, the state carried across the
    switches, against the machine integrated exactly per sample at the same levels
    (reference.simulate_varying); two modes, a command going back and forth."""
    modes = NOMINAL.axes["X"].modes
    there_and_back = np.concatenate([smooth_move(20.0, 0.15, 0.1, T), 20.0 - smooth_move(20.0, 0.15, 0.1, T)[1:]])
    command = 5.0 + np.tile(there_and_back, 4)
    if kind == "load":
        varying, state = load_modes(modes, T, 0.1, 0.25), np.linspace(3.0, 123.0, command.size)
    else:
        varying = position_modes(modes, T, AXES.index("Y"), (0.0, 50.0, 200.0), (1.1, 1.0, 0.8))
        state = 100.0 + 90.0 * np.sin(np.linspace(0.0, 3.0 * np.pi, command.size))
    levels = varying.levels(state)
    assert levels.tolist() == [varying.level(s - (3.0 if kind == "load" else 0.0)) for s in state.tolist()]
    assert np.count_nonzero(np.diff(levels)) >= (12 if kind == "load" else 40)
    truth = simulate_varying(modes, T, command, 1.01 ** levels)
    assert np.abs(varying.simulate(command, levels) - truth).max() < 1e-9
    assert np.abs(simulate_varying(modes, T, command, np.ones(command.size)) - truth).max() > 1e-2  # (it varies)


def test_a_scaled_mode_is_the_mode_in_scaled_time_with_its_dc_gain():
    """G_s(j w) = G(j w / s): the closed form of a mode whose dynamics run s times faster."""
    mode = Mode(30.0, 0.08, 2.0e4, 35.0)
    frequency_hz = np.linspace(0.0, 200.0, 81)
    for scale in (0.87, 1.13):
        expected = modal_response([mode], frequency_hz / scale)
        assert scaled_mode(mode, scale, 1.4) == Mode(30.0 * scale, 0.08 * 1.4, 2.0e4 * scale**2, 35.0 * scale)
        assert np.allclose(modal_response([scaled_mode(mode, scale)], frequency_hz), expected, rtol=1e-12)
    spread = ModelSet.spread(with_tolerances(PATENT_X, 0.1, 0.2), T)
    scales = [(m.modes[0].frequency_hz / PATENT_X[0].frequency_hz, m.modes[2].damping / PATENT_X[2].damping)
              for m in spread.models]
    assert np.allclose(scales, [(1, 1), (0.9, 1), (1, 0.8), (1.1, 1), (1, 1.2)])
    assert spread.weights == (1.0, 1.5, 3.0, 1.0, 1.0)  # the low ends weigh more
    assert len(ModelSet.spread(PATENT_X, T).models) == 1


def stacked_truth(desired, variants, settings, weights=None):
    """The weighted mean squared error over ``variants`` (lists of modes) minimized by brute force:
    every model's rows of the optimizer's problem (brute_force_problem, lsim) stacked, each times
    the square root of its weight, the end conditions."""
    problems = [brute_force_problem(desired, modes, settings, T) for modes in variants]
    roots = np.sqrt(weights if weights is not None else np.ones(len(variants)))
    a = np.vstack([r * p[0] for r, p in zip(roots, problems, strict=True)])
    b = np.concatenate([r * p[1] for r, p in zip(roots, problems, strict=True)])
    c, d, command = problems[0][2:]
    particular = np.linalg.lstsq(c, d, rcond=None)[0]
    null = np.linalg.svd(c)[2][c.shape[0]:].T
    return command(particular + null @ np.linalg.lstsq(a @ null, b - a @ particular, rcond=None)[0])


def test_robust_complete_lookahead_equals_brute_force_over_the_model_set():
    desired = smooth_move(3.0, 0.12, 0.03, T)
    settings = FBSSettings(knot_spacing_samples=10, settle_samples=200)
    modes = with_tolerances(PATENT_X, 0.1, 0.25)
    compensator = AxisCompensator(AxisDynamics(modes, T), AxisLimits(), settings, "complete", ModelSet.spread(modes, T))
    ours = compensator(desired).command_mm
    variants = [PATENT_X] + [[Mode(m.frequency_hz * f, m.damping * z, m.alpha * f * f, m.beta * f) for m in PATENT_X]
                             for f, z in ((0.9, 1), (1, 0.75), (1.1, 1), (1, 1.25))]
    truth = stacked_truth(desired, variants, compensator.settings, [1.0, 1.5, 3.0, 1.0, 1.0])
    assert np.abs(ours - truth).max() <= 1e-7 * np.ptp(desired)
    nominal_only = stacked_truth(desired, variants[:1], compensator.settings)
    assert np.abs(ours - nominal_only).max() > 1e-3 * np.ptp(desired)  # the set changes the command


def carried_outputs(stream, compensator):
    """Each model's output at the first sample the stream has not decided, from the carried state."""
    models = compensator.model_set(stream.level).models
    states = np.split(compensator.carry.state(stream.z), np.cumsum([d.n_states for d in models])[:-1])
    return np.array([d.C @ x for d, x in zip(models, states, strict=True)])


@pytest.mark.parametrize("varying", [None, "load", "position"])
def test_limited_lookahead_carries_every_models_state(varying):
    """At every cut, the carry holds each model's state: its output is that of the command so far
    through the model (lsim), or with varying modes through the machine whose frequencies step to
    each window's level at the window's start, simulated exactly (reference.simulate_varying).
    The modes vary with the filament extruded or with another axis' position, going back and forth."""
    modes = with_tolerances(NOMINAL.axes["Y"].modes, 0.13, 0.2)
    there_and_back = np.concatenate([smooth_move(20.0, 0.15, 0.1, T), 20.0 - smooth_move(20.0, 0.15, 0.1, T)[1:]])
    desired = np.tile(there_and_back, 3)
    state = {None: np.zeros(desired.size), "load": np.linspace(0.0, 120.0, desired.size),
             "position": 100.0 + 90.0 * np.sin(np.linspace(0.0, 3.0 * np.pi, desired.size))}[varying]
    load = {None: None, "load": load_modes(modes, T, 0.1, 0.25),  # 30 g onto 100 g: 12% lower at the end
            "position": position_modes(modes, T, AXES.index("X"), (0.0, 50.0, 200.0), (1.1, 1.0, 0.8))}[varying]
    compensator = AxisCompensator(AxisDynamics(modes, T), AxisLimits.from_profile(NOMINAL.axes["Y"]),
                                  models=ModelSet.spread(modes, T), varying=load)
    rows = compensator.settings.commit_spans * compensator.settings.knot_spacing_samples
    starts = np.arange(0, desired.size, rows)
    level = np.repeat([load.level(state[s]) for s in starts] if varying else np.zeros(starts.size), rows)
    variants = [d.modes for d in compensator.model_set(0).models]
    stream, pushed, cuts = compensator.stream(), [], []
    for piece in np.array_split(np.arange(desired.size), 9):
        pushed.append(stream.push(desired[piece], state[piece]))
        done = sum(p.size for p in pushed)  # samples decided: nothing later changes them
        if done:
            assert stream.level == level[done - 1]  # the last window's; the next may switch
            cuts.append((done, carried_outputs(stream, compensator)))
    command = np.append(np.concatenate(pushed + [stream.finish().command_mm]), 0.0)
    truth = np.array([simulate_varying(v, T, command, 1.01 ** level[:command.size]) if varying
                      else simulate_lsim(v, T, command) for v in variants])
    for done, carried in cuts:
        assert np.allclose(carried, truth[:, done], rtol=0, atol=1e-9)
    assert level.min() <= -10 if varying else True
    assert level.max() >= 5 if varying == "position" else True  # (up and down again)
    assert len(np.flatnonzero(np.diff(level))) >= 10 if varying == "position" else True


def test_remap_keeps_every_modes_output_and_rate():
    """Closed form: y = alpha q + beta q', y' = alpha q' + beta (u - w^2 q - 2 z w q') for each mode."""
    modes = with_tolerances(PATENT_X, 0.1, 0.2)
    load = load_modes(modes, T, 1.0, 1.0)
    rng = np.random.default_rng(4)
    old, new = load.models(0), load.models(-7)
    x, u = rng.normal(size=old.n_states), 0.37
    R, r = load.remap(0, -7)
    x_new = R @ x + r * u

    def physical(models, state):
        q = state.reshape(-1, 2)
        modes = [m for d in models.models for m in d.modes]
        return np.array([[m.alpha * a + m.beta * b,
                          m.alpha * b + m.beta * (u - m.omega_rad_s**2 * a - 2 * m.damping * m.omega_rad_s * b)]
                         for m, (a, b) in zip(modes, q, strict=True)])
    assert np.allclose(physical(new, x_new), physical(old, x), rtol=1e-12, atol=1e-9)


# ---- must show, on the corner-rich sliced print (predictions: fbspost's model of the machine) ----

@pytest.fixture(scope="module")
def gear_head(tmp_path_factory):
    path = tmp_path_factory.mktemp("robust") / "gear-700.gcode"
    with open(f"{DATA}/gear-marlin2.gcode") as f:
        path.write_text("".join(f.readlines()[:700]))
    return path


@pytest.fixture(scope="module")
def nominal_sim(gear_head):
    return simulate_program(gear_head, NOMINAL)


@pytest.mark.slow
def test_robust_fbs_at_most_the_best_shaper_on_every_perturbed_machine(gear_head, nominal_sim):
    robust = model_error(simulate_program(gear_head, ROBUST))
    nominal = model_error(nominal_sim)
    for (f, d, errors), (_, _, plain) in zip(robust, nominal, strict=True):
        best = min(v for k, v in errors.items() if k not in ("original", "fbs"))
        assert errors["fbs"] <= best, (f, d, errors)
        if (f, d) == (1.0, 1.0):  # the gain (RMS contour error removed) at the nominal model
            assert errors["fbs"] > plain["fbs"]  # robustness costs something there ...
            assert errors["original"] - errors["fbs"] >= 0.8 * (plain["original"] - plain["fbs"])  # ... at most 20%
    assert any(
        plain["fbs"] > min(v for k, v in plain.items() if k not in ("original", "fbs")) for _, _, plain in nominal
    )


@pytest.mark.slow
def test_robust_fbs_as_klipper_runs_it_at_most_the_best_shaper(tmp_path, gear_head):
    """Firmware results: the original and the robust profile's output (a Klipper program, no line
    budget) run by klippy's own planner, then through every perturbed machine's modes; the shapers
    on klippy's plan of the original."""
    klippy_or_skip()
    target = tmp_path / "robust.gcode"
    compensate_file(gear_head, target, unbudgeted(ROBUST), CompensateOptions(flavor="klipper"))
    _, moves, original = klippy_run(gear_head, NOMINAL, "klipper")
    written = klippy_run(target, NOMINAL, "klipper")[2]
    path, _ = printed_path(*move_ends(moves))
    shaped = shaped_plans(original, NOMINAL)
    for f, d in MODEL_ERRORS:
        machine = dataclasses.replace(NOMINAL, axes={a: dataclasses.replace(
            spec, modes=tuple(scaled_mode(m, f, d) for m in spec.modes)) for a, spec in NOMINAL.axes.items()})
        fbs = contour_um(modelled(written, machine), written, path, True)[0]
        best = min(contour_um(modelled(c, machine), padded, path, True)[0] for c, padded, _ in shaped.values())
        assert fbs <= best, (f, d, fbs, best)


def _varying_gains(sim, varied, column: int, scale: np.ndarray) -> tuple[float, float, float]:
    """The contour error removed on the machine whose axis ``column`` has every frequency times
    ``scale`` at each sample, simulated exactly (reference.simulate_varying): by ``sim``'s FBS on
    the machine it models (constant), by ``varied``'s FBS (the varying profile), by ``sim``'s FBS
    (the fixed profile)."""
    assert np.array_equal(varied.desired_mm, sim.desired_mm)
    distance, mask = PathDistance(sim.path_start_mm, sim.path_end_mm), sim.contour_mask
    modes = NOMINAL.axes[AXES[column]].modes

    def contour_rms(method, varying):
        actual = method.actual_mm.copy()
        if varying:
            actual[:, column] = simulate_varying(modes, T, method.command_mm[:, column], scale)
        return float(np.sqrt(np.mean(distance(actual[mask, :3])[0] ** 2)))

    (original, fbs), varying_fbs = sim.methods[:2], varied.methods[1]
    before = contour_rms(original, True)
    return (1.0 - contour_rms(fbs, False) / contour_rms(original, False),
            1.0 - contour_rms(varying_fbs, True) / before, 1.0 - contour_rms(fbs, True) / before)


@pytest.mark.slow
def test_load_dependent_profile_keeps_the_gain_on_a_bed_whose_frequency_falls(gear_head, nominal_sim):
    """Y carries the print: its frequency falls 15% over the program (a bed of 0.46 g: the whole
    print's mass growth in its first 26 s)."""
    e = nominal_sim.desired_mm[:, AXES.index("E")]
    extruded = e - e[np.isfinite(e)][0]
    bed = LoadedBed.falling_to(0.85, np.nanmax(extruded))
    scale = bed.scale(extruded)
    assert scale[-1] == pytest.approx(0.85)
    axes = dict(NOMINAL.axes, Y=dataclasses.replace(NOMINAL.axes["Y"], moving_mass_kg=bed.mass_kg))
    loaded = simulate_program(gear_head, dataclasses.replace(NOMINAL, axes=axes))
    exact_gain, load_gain, fixed_gain = _varying_gains(nominal_sim, loaded, AXES.index("Y"), scale)
    assert load_gain >= 0.9 * exact_gain
    assert fixed_gain < load_gain - 0.05  # the fixed model loses what the load-dependent one keeps


@pytest.mark.slow
def test_load_dependent_profile_as_klipper_runs_it_keeps_the_gain(tmp_path, gear_head, nominal_sim):
    """Firmware results for the bed above: the original, the load-dependent profile's output and
    the fixed profile's (Klipper programs, no line budget) planned by klippy's own planner; Y then
    through the machine whose frequency falls with the filament extruded by that time in each
    plan, simulated exactly per sample (reference.simulate_varying), X through its fixed modes;
    the exact model's gain is the fixed profile's output on the fixed machine. Klipper's shapers,
    on klippy's plan of the original at the profiled frequencies, through the same varying machine."""
    klippy_or_skip()
    e = nominal_sim.desired_mm[:, AXES.index("E")]
    bed = LoadedBed.falling_to(0.85, np.nanmax(e - e[np.isfinite(e)][0]))
    loaded = dataclasses.replace(NOMINAL, axes=dict(NOMINAL.axes, Y=dataclasses.replace(
        NOMINAL.axes["Y"], moving_mass_kg=bed.mass_kg)))
    plans = {}
    for name, profile in (("load", loaded), ("fixed", NOMINAL)):
        compensate_file(gear_head, tmp_path / f"{name}.gcode", unbudgeted(profile), CompensateOptions(flavor="klipper"))
        plans[name] = klippy_run(tmp_path / f"{name}.gcode", NOMINAL, "klipper")[2]
    _, moves, original = klippy_run(gear_head, NOMINAL, "klipper")
    path, _ = printed_path(*move_ends(moves))

    def contour(command, reference, varying: bool) -> float:
        actual = bed.actual(command, NOMINAL) if varying else modelled(command, NOMINAL)
        return contour_um(actual, reference, path, True)[0]

    before = contour(original, original, True)
    exact_gain = 1.0 - contour(plans["fixed"], plans["fixed"], False) / contour(original, original, False)
    load_gain = 1.0 - contour(plans["load"], plans["load"], True) / before
    fixed_gain = 1.0 - contour(plans["fixed"], plans["fixed"], True) / before
    shaped = {name: contour(c, padded, True) for name, (c, padded, _) in shaped_plans(original, NOMINAL).items()}
    print(f"klippy: gain exact model {exact_gain:.3f}, load-dependent {load_gain:.3f}, fixed {fixed_gain:.3f}; "
          f"RMS um original {before:.2f}, load-dependent {before * (1 - load_gain):.2f}, best shaper "
          f"{min(shaped.values()):.2f} ({min(shaped, key=shaped.get)})")
    assert load_gain >= 0.9 * exact_gain
    assert fixed_gain < load_gain - 0.05  # the fixed model loses what the load-dependent one keeps
    assert before * (1 - load_gain) < min(shaped.values())


@pytest.mark.slow
def test_position_dependent_profile_keeps_the_gain_where_the_modes_change_along_an_axis(gear_head, nominal_sim):
    """X's modes fall 15% from one side of the part to the other along Y (a gantry whose X
    stiffness changes with Y, compressed onto this part), at the planned Y."""
    along = nominal_sim.desired_mm[:, AXES.index("Y")]
    low, high = float(np.nanmin(along[nominal_sim.contour_mask])), float(np.nanmax(along[nominal_sim.contour_mask]))
    table = PositionTable("Y", (low, high), (1.0, 0.85))
    scale = np.interp(np.nan_to_num(along, nan=low), table.positions_mm, table.frequency_scales)
    assert scale[nominal_sim.contour_mask].min() < 0.86
    axes = dict(NOMINAL.axes, X=dataclasses.replace(NOMINAL.axes["X"], modes_by_position=table))
    varied = simulate_program(gear_head, dataclasses.replace(NOMINAL, axes=axes))
    exact_gain, position_gain, fixed_gain = _varying_gains(nominal_sim, varied, AXES.index("X"), scale)
    # simulate models the varying machine: the original's X as the stepped machine runs it
    stepped = simulate_varying(NOMINAL.axes["X"].modes, T, varied.desired_mm[:, 0],
                               1.01 ** varying_modes(varied.profile, axes["X"]).levels(along))
    assert np.abs(varied.methods[0].actual_mm[:, 0] - stepped).max() < 1e-9
    # and so does --model-error: its unperturbed row is simulate's own figures
    (_, _, unperturbed), = model_error(varied, [(1.0, 1.0)])
    for method in varied.methods:
        assert unperturbed[method.name] == pytest.approx(method.path.rms_contour_error_um, rel=1e-9)
    print(f"gain: exact model {exact_gain:.3f}, position-dependent {position_gain:.3f}, fixed {fixed_gain:.3f}")
    assert position_gain >= 0.9 * exact_gain
    assert fixed_gain < position_gain - 0.05  # the fixed model loses what the position-dependent one keeps


@pytest.mark.slow
def test_model_error_cli_table_and_json(gear_head, nominal_sim):
    """The nominal row is the simulation's own contour error; one row per perturbed machine."""
    result = CliRunner().invoke(main, ["simulate", str(gear_head), "-m", "printer-two-mode", "--shapers", "zv,mzv",
                                       "--model-error", "--json"])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.output)["model_error"]
    assert [(r["frequency_scale"], r["damping_scale"]) for r in rows] == list(MODEL_ERRORS)
    nominal = next(r for r in rows if (r["frequency_scale"], r["damping_scale"]) == (1.0, 1.0))
    for method in nominal_sim.methods:
        if method.name in nominal["rms_contour_error_um"]:
            assert nominal["rms_contour_error_um"][method.name] == pytest.approx(
                method.path.rms_contour_error_um, rel=1e-9
            )
    text = CliRunner().invoke(main, ["simulate", str(gear_head), "-m", "printer-two-mode", "--shapers", "zv",
                                     "--model-error"]).output.splitlines()
    table = text[text.index(next(t for t in text if t.startswith("frequency damping"))) + 1:]
    assert table[0].split()[:2] == ["x0.900", "x1.00"] and len([t for t in table if t.startswith("x")]) == 11


def test_zero_tolerances_write_the_same_bytes_as_none(tmp_path, gear_head):
    text = open("machines/printer-two-mode.toml").read()
    zero = tmp_path / "zero.toml"
    zero.write_text(text.replace("[axes.X]\n", "[axes.X]\nfrequency_tolerance = 0.0\ndamping_tolerance = 0\n"))
    head = tmp_path / "head.gcode"
    head.write_text("".join(open(gear_head).readlines()[:300]))
    outputs = []
    for machine in ("printer-two-mode", zero):
        out = tmp_path / f"out{len(outputs)}.gcode"
        assert (
            CliRunner().invoke(main, ["compensate", str(head), "-m", str(machine), "-o", str(out), "-q"]).exit_code == 0
        )
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]
