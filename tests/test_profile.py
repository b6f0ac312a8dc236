"""Tests of fbspost.profile against the TOML text itself (parsed here with tomllib).

Truths used: the raw numbers in the TOML files, the DC gain sum(alpha_i / w_i^2) computed here
from the raw values, and the key names of the offending entries in deliberately broken files.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import tomllib
from hypothesis import given, settings
from hypothesis import strategies as st

from fbspost.profile import ProfileError, load_profile

MACHINES = Path(__file__).resolve().parents[1] / "machines"
BUNDLED = ["patent-xy-stage", "bedslinger-example", "printer-two-mode"]


def raw_toml(name: str) -> dict:
    return tomllib.loads((MACHINES / f"{name}.toml").read_text(encoding="utf-8"))


def raw_dc_gain(raw_modes: list[dict]) -> float:
    """sum(alpha_i / w_i^2), w_i = 2 pi f_i, straight from the file's numbers."""
    return sum(m["alpha"] / (2.0 * math.pi * m["frequency"]) ** 2 for m in raw_modes)


def assert_matches_raw(profile, raw: dict) -> None:
    """Every value of the loaded profile equals the TOML text (modes: scaled by 1/raw DC gain)."""
    assert profile.name == raw["name"]
    assert profile.description == raw.get("description", "")
    assert profile.sample_rate_hz == raw["motion"]["sample_rate"]
    assert profile.planner_acceleration_mm_s2 == raw["planner"]["acceleration"]
    assert profile.planner_square_corner_velocity_mm_s == raw["planner"]["square_corner_velocity"]
    assert set(profile.axes) == set(raw["axes"])
    for axis_name, raw_axis in raw["axes"].items():
        axis = profile.axes[axis_name]
        assert axis.name == axis_name
        assert axis.max_velocity_mm_s == raw_axis["max_velocity"]
        assert axis.max_acceleration_mm_s2 == raw_axis["max_acceleration"]
        if "max_jerk" in raw_axis:
            assert axis.max_jerk_mm_s3 == raw_axis["max_jerk"]
        else:
            assert axis.max_jerk_mm_s3 is None
        raw_modes = raw_axis["modes"]
        assert len(axis.modes) == len(raw_modes)
        if not raw_modes:
            continue
        dc = raw_dc_gain(raw_modes)
        for mode, rm in zip(axis.modes, raw_modes, strict=True):
            # frequency and damping unchanged; alpha and beta all scaled by the same 1/dc
            assert mode.frequency_hz == rm["frequency"]
            assert mode.damping == rm["damping"]
            assert mode.alpha == pytest.approx(rm["alpha"] / dc, rel=1e-14, abs=0)
            assert mode.beta == pytest.approx(rm["beta"] / dc, rel=1e-14, abs=1e-300)
        # normalized DC gain, computed here from the loaded modes
        assert sum(m.alpha / (2 * math.pi * m.frequency_hz) ** 2 for m in axis.modes) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_by_name_matches_toml_text(name):
    """load_profile(<bundled name>) reads exactly the numbers of machines/<name>.toml."""
    profile = load_profile(name)
    assert Path(profile.source).resolve() == (MACHINES / f"{name}.toml").resolve()
    assert_matches_raw(profile, raw_toml(name))


@pytest.mark.parametrize("name", BUNDLED)
def test_load_by_path_str_and_pathlib(name, tmp_path):
    """load_profile(path) (str or Path) of a copy gives the same numbers as the TOML text."""
    text = (MACHINES / f"{name}.toml").read_text(encoding="utf-8")
    path = tmp_path / "copy.toml"
    path.write_text(text, encoding="utf-8")
    for arg in (path, str(path)):
        profile = load_profile(arg)
        assert profile.source == str(path)
        assert_matches_raw(profile, tomllib.loads(text))


def test_patent_spot_values():
    """A few numbers typed from the patent profile text (Table 1, 10 kHz, L1/L2) and max_jerk absent."""
    p = load_profile("patent-xy-stage")
    assert p.sample_rate_hz == 10000.0
    assert p.planner_acceleration_mm_s2 == 5000.0
    assert p.planner_square_corner_velocity_mm_s == 5.0
    for ax in "XY":
        assert p.axes[ax].max_velocity_mm_s == 100.0
        assert p.axes[ax].max_acceleration_mm_s2 == 8000.0
        assert p.axes[ax].max_jerk_mm_s3 is None
        assert len(p.axes[ax].modes) == 4
    assert [m.frequency_hz for m in p.axes["X"].modes] == [20.52, 34.94, 42.53, 42.60]
    assert [m.damping for m in p.axes["Y"].modes] == [0.120, 0.021, 0.440, 0.036]


def test_patent_raw_dc_gain_offsets():
    """Table 1 as typed is not exactly DC gain 1: about +4.9e-5 (X) and +2.85e-4 (Y); loading fixes it."""
    raw = raw_toml("patent-xy-stage")
    assert raw_dc_gain(raw["axes"]["X"]["modes"]) - 1 == pytest.approx(4.9e-5, abs=1e-5)
    assert raw_dc_gain(raw["axes"]["Y"]["modes"]) - 1 == pytest.approx(2.85e-4, abs=1e-5)
    p = load_profile("patent-xy-stage")
    for ax in "XY":
        ratio = [m.alpha / rm["alpha"] for m, rm in zip(p.axes[ax].modes, raw["axes"][ax]["modes"], strict=True)]
        assert ratio == pytest.approx([1 / raw_dc_gain(raw["axes"][ax]["modes"])] * 4, rel=1e-14)
        assert ratio[0] != 1.0  # the rescaling really happened


# ---------------------------------------------------------------------------------------------
# A valid baseline file and deliberately broken variants of it.

BASE = """\
name = "test-machine"
description = "for tests"

[motion]
sample_rate = 1000.0

[planner]
acceleration = 3000.0
square_corner_velocity = 5.0

[axes.X]
max_velocity = 300.0
max_acceleration = 10000.0
max_jerk = 1000000.0
modes = [
  { frequency = 48.0, damping = 0.08, alpha = 90000.0, beta = 0.0 },
  { frequency = 70.0, damping = 0.05, alpha = 50000.0, beta = 1.0 },
]

[axes.Y]
max_velocity = 200.0
max_acceleration = 8000.0
modes = [ { frequency = 36.0, damping = 0.06, alpha = 51164.0, beta = 2.0 } ]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "machine.toml"
    path.write_text(text, encoding="utf-8")
    return path


def edited(old: str, new: str) -> str:
    assert BASE.count(old) == 1, old  # the edit must hit exactly one place of the baseline
    return BASE.replace(old, new)


def test_baseline_is_valid(tmp_path):
    """The baseline loads and matches its own text, so each broken variant fails because of its edit."""
    profile = load_profile(write(tmp_path, BASE))
    assert_matches_raw(profile, tomllib.loads(BASE))
    assert profile.axes["X"].max_jerk_mm_s3 == 1e6
    assert profile.axes["Y"].max_jerk_mm_s3 is None


MODE1 = "frequency = 70.0, damping = 0.05, alpha = 50000.0, beta = 1.0"
BROKEN = [
    # (id, old, new, offending key)
    ("unknown-top-key", 'name = "test-machine"', 'name = "test-machine"\ncolour = "red"', "colour"),
    ("unknown-axis-key", "max_velocity = 300.0", "max_velocity = 300.0\nmax_speed = 3.0", "axes.X.max_speed"),
    ("unknown-mode-key", MODE1, MODE1.replace("frequency", "freq"), "axes.X.modes[1].freq"),
    ("missing-name", 'name = "test-machine"\n', "", "name"),
    ("empty-name", 'name = "test-machine"', 'name = "  "', "name"),
    ("missing-motion", "[motion]\nsample_rate = 1000.0\n", "", "motion"),
    ("missing-sample-rate", "sample_rate = 1000.0\n", "", "motion.sample_rate"),
    ("missing-planner-acc", "acceleration = 3000.0\n", "", "planner.acceleration"),
    ("missing-modes", "modes = [ { frequency = 36.0, damping = 0.06, alpha = 51164.0, beta = 2.0 } ]", "",
     "axes.Y.modes"),
    ("missing-alpha", MODE1, MODE1.replace("alpha = 50000.0, ", ""), "axes.X.modes[1].alpha"),
    ("frequency-zero", MODE1, MODE1.replace("frequency = 70.0", "frequency = 0"), "axes.X.modes[1].frequency"),
    ("frequency-negative", MODE1, MODE1.replace("frequency = 70.0", "frequency = -70.0"),
     "axes.X.modes[1].frequency"),
    ("frequency-above-nyquist", MODE1, MODE1.replace("frequency = 70.0", "frequency = 500.0"),
     "axes.X.modes[1].frequency"),
    ("damping-zero", MODE1, MODE1.replace("damping = 0.05", "damping = 0"), "axes.X.modes[1].damping"),
    ("damping-one", MODE1, MODE1.replace("damping = 0.05", "damping = 1"), "axes.X.modes[1].damping"),
    ("damping-negative", MODE1, MODE1.replace("damping = 0.05", "damping = -0.05"), "axes.X.modes[1].damping"),
    ("damping-1.5", MODE1, MODE1.replace("damping = 0.05", "damping = 1.5"), "axes.X.modes[1].damping"),
    ("max-velocity-zero", "max_velocity = 300.0", "max_velocity = 0.0", "axes.X.max_velocity"),
    ("max-velocity-negative", "max_velocity = 200.0", "max_velocity = -200.0", "axes.Y.max_velocity"),
    ("max-acceleration-negative", "max_acceleration = 10000.0", "max_acceleration = -1.0",
     "axes.X.max_acceleration"),
    ("max-jerk-zero", "max_jerk = 1000000.0", "max_jerk = 0", "axes.X.max_jerk"),
    ("string-alpha", MODE1, MODE1.replace("alpha = 50000.0", 'alpha = "50000"'), "axes.X.modes[1].alpha"),
    ("string-sample-rate", "sample_rate = 1000.0", 'sample_rate = "fast"', "motion.sample_rate"),
    ("bool-velocity", "max_velocity = 300.0", "max_velocity = true", "axes.X.max_velocity"),
    ("nan-beta", MODE1, MODE1.replace("beta = 1.0", "beta = nan"), "axes.X.modes[1].beta"),
    ("inf-velocity", "max_velocity = 300.0", "max_velocity = inf", "axes.X.max_velocity"),
    ("-inf-alpha", MODE1, MODE1.replace("alpha = 50000.0", "alpha = -inf"), "axes.X.modes[1].alpha"),
    ("nan-sample-rate", "sample_rate = 1000.0", "sample_rate = nan", "motion.sample_rate"),
    ("unknown-axis-Q", "[axes.Y]", "[axes.Q]", "axes.Q"),
    ("scv-negative", "square_corner_velocity = 5.0", "square_corner_velocity = -1.0",
     "planner.square_corner_velocity"),
    ("home-unknown-axis", "[motion]", "[home]\nE = 1.0\n\n[motion]", "home.E"),
    ("home-string", "[motion]", '[home]\nX = "max"\n\n[motion]', "home.X"),
    ("home-not-a-table", 'name = "test-machine"', 'name = "test-machine"\nhome = 3', "home"),
    ("travel-string", "max_velocity = 200.0", 'max_velocity = 200.0\nposition_min = "0"', "axes.Y.position_min"),
    ("travel-empty", "max_velocity = 200.0", "max_velocity = 200.0\nposition_min = 5.0\nposition_max = 5.0",
     "axes.Y.position_max"),
    ("travel-nan", "max_velocity = 200.0", "max_velocity = 200.0\nposition_max = nan", "axes.Y.position_max"),
]


def assert_one_line_naming(message: str, path, key: str | None) -> None:
    assert "\n" not in message.strip()
    assert str(path) in message
    if key is not None:
        # the dotted key as a whole word (e.g. "axes.X.modes" must not just be a prefix of "axes.X.modes[0]")
        assert re.search(re.escape(key) + r"(?![\w.\[])", message), (key, message)


@pytest.mark.parametrize("old,new,key", [c[1:] for c in BROKEN], ids=[c[0] for c in BROKEN])
def test_broken_profile_raises_profile_error(tmp_path, old, new, key):
    """Each broken variant raises ProfileError, one line, naming the file and the offending key."""
    path = write(tmp_path, edited(old, new))
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert_one_line_naming(str(info.value), path, key)


def test_home(tmp_path):
    """[home] gives where G28 leaves the homed axes (0 where not given, and without the table);
    format_profile writes it back."""
    from fbspost.profile import format_profile
    assert load_profile(write(tmp_path, BASE)).home_mm == (0.0, 0.0, 0.0)
    homed = load_profile(write(tmp_path, edited("[motion]", "[home]\nX = 235.0\nZ = -1\n\n[motion]")))
    assert homed.home_mm == (235.0, 0.0, -1.0)
    assert load_profile(write(tmp_path, format_profile(homed))).home_mm == (235.0, 0.0, -1.0)


def test_travel_and_the_firmwares_defaults(tmp_path):
    """position_min / position_max as given (format_profile writes them back); where none is given,
    Klipper's, Marlin's and RepRapFirmware's minimum 0 on X and Y (the home position where that is
    below), none for LinuxCNC (its INI has them) nor on the other axes."""
    from fbspost.profile import format_profile, with_travel
    given = load_profile(write(tmp_path, edited("max_velocity = 200.0", "max_velocity = 200.0\nposition_min = "
                                                "-5.5\nposition_max = 210")))
    assert (given.axes["Y"].position_min_mm, given.axes["Y"].position_max_mm) == (-5.5, 210.0)
    assert load_profile(write(tmp_path, format_profile(given))).axes["Y"] == given.axes["Y"]
    for flavor in ("klipper", "marlin", "reprap"):
        assert with_travel(given, flavor).travel_mm("XYZE") == ([0.0, -5.5, -math.inf, -math.inf],
                                                                [math.inf, 210.0, math.inf, math.inf])
    assert with_travel(given, "linuxcnc").travel_mm("XYZE") == ([-math.inf, -5.5, -math.inf, -math.inf],
                                                                [math.inf, 210.0, math.inf, math.inf])
    below = load_profile(write(tmp_path, edited("[motion]", "[home]\nX = -3.0\nY = 235.0\n\n[motion]")))
    assert with_travel(below, "klipper").travel_mm("XY")[0] == [-3.0, 0.0]


def test_profile_error_is_value_error():
    """ProfileError is a ValueError (callers may catch either)."""
    assert issubclass(ProfileError, ValueError)


def test_invalid_toml(tmp_path):
    """A file that is not TOML raises ProfileError naming the file, on one line."""
    path = write(tmp_path, BASE + "\nthis is = = not toml\n")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert_one_line_naming(str(info.value), path, None)


def test_missing_file(tmp_path):
    """A path that does not exist raises ProfileError naming it."""
    path = tmp_path / "nowhere" / "no-such-machine.toml"
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert_one_line_naming(str(info.value), path, None)
    with pytest.raises(ProfileError) as info:
        load_profile("no-such-bundled-profile")
    assert "no-such-bundled-profile" in str(info.value)


def test_empty_modes_is_valid(tmp_path):
    """modes = [] declares an uncompensated axis: it loads, with no modes and the limits of the text."""
    path = write(tmp_path, edited(
        "modes = [ { frequency = 36.0, damping = 0.06, alpha = 51164.0, beta = 2.0 } ]", "modes = []"))
    profile = load_profile(path)
    assert profile.axes["Y"].modes == ()
    assert profile.axes["Y"].max_velocity_mm_s == 200.0
    assert len(profile.axes["X"].modes) == 2


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(1.0, 400.0), st.floats(0.001, 0.999), st.floats(1.0, 1e7),
                          st.floats(-1e3, 1e3)), min_size=1, max_size=5))
def test_normalization_property(tmp_path_factory, modes):
    """For any modes with positive alphas written to a file: the loaded alphas/betas are the written ones
    times the single factor 1/sum(alpha/w^2) computed here, and the loaded DC gain is 1 to 1e-12."""
    rows = ",\n".join(f"  {{ frequency = {f!r}, damping = {z!r}, alpha = {a!r}, beta = {b!r} }}"
                      for f, z, a, b in modes)
    text = (BASE.split("[axes.X]")[0]
            + f"[axes.Z]\nmax_velocity = 10.0\nmax_acceleration = 100.0\nmodes = [\n{rows}\n]\n")
    path = tmp_path_factory.mktemp("prop") / "m.toml"
    path.write_text(text, encoding="utf-8")
    axis = load_profile(path).axes["Z"]
    dc = sum(a / (2 * math.pi * f) ** 2 for f, z, a, b in modes)
    for mode, (f, z, a, b) in zip(axis.modes, modes, strict=True):
        assert (mode.frequency_hz, mode.damping) == (f, z)
        assert mode.alpha == pytest.approx(a / dc, rel=1e-13)
        assert mode.beta == pytest.approx(b / dc, rel=1e-13, abs=1e-300)
    assert math.fsum(m.alpha / (2 * math.pi * m.frequency_hz) ** 2 for m in axis.modes) == pytest.approx(1, abs=1e-12)


def test_bundled_name_wins_over_a_directory_of_that_name(tmp_path, monkeypatch):
    """A folder called like a bundled profile in the working directory is not a profile file."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "patent-xy-stage").mkdir()
    assert load_profile("patent-xy-stage").name == "patent-xy-stage"


# ---------------------------------------------------------------------------------------------
# The [firmware] table

FIRMWARE = """
[firmware]
steps_per_mm = { X = 80.0, Y = 80.0, E = 415.0 }
block_buffer = 16
max_line_rate = 300.0
minimum_cruise_ratio = 0.5
instantaneous_corner_velocity = 1.0
filament_diameter = 1.75
nozzle_diameter = 0.4
"""
FIRMWARE_BROKEN = [
    ("unknown-key", "block_buffer = 16", "block_buffer = 16\nbuffer = 3", "firmware.buffer"),
    ("buffer-zero", "block_buffer = 16", "block_buffer = 0", "firmware.block_buffer"),
    ("buffer-float", "block_buffer = 16", "block_buffer = 16.5", "firmware.block_buffer"),
    ("rate-negative", "max_line_rate = 300.0", "max_line_rate = -1.0", "firmware.max_line_rate"),
    ("ratio-one", "minimum_cruise_ratio = 0.5", "minimum_cruise_ratio = 1.0", "firmware.minimum_cruise_ratio"),
    ("ratio-and-decel", "minimum_cruise_ratio = 0.5", "minimum_cruise_ratio = 0.5\nmax_accel_to_decel = 1500.0",
     "firmware.max_accel_to_decel"),
    ("steps-axis", "E = 415.0", "Q = 415.0", "firmware.steps_per_mm.Q"),
    ("steps-zero", "E = 415.0", "E = 0.0", "firmware.steps_per_mm.E"),
    ("steps-not-table", "steps_per_mm = { X = 80.0, Y = 80.0, E = 415.0 }", "steps_per_mm = 80.0",
     "firmware.steps_per_mm"),
    ("icv-negative", "instantaneous_corner_velocity = 1.0", "instantaneous_corner_velocity = -1.0",
     "firmware.instantaneous_corner_velocity"),
    ("filament-below-nozzle", "filament_diameter = 1.75", "filament_diameter = 0.3", "firmware.filament_diameter"),
    ("servo-period-zero", "block_buffer = 16", "block_buffer = 16\nservo_period = 0", "firmware.servo_period"),
    ("arc-blend-enable-number", "block_buffer = 16", "block_buffer = 16\narc_blend_enable = 1",
     "firmware.arc_blend_enable"),
    ("gap-cycles-fraction", "block_buffer = 16", "block_buffer = 16\narc_blend_gap_cycles = 2.5",
     "firmware.arc_blend_gap_cycles"),
    ("depth-negative", "block_buffer = 16", "block_buffer = 16\narc_blend_optimization_depth = -1",
     "firmware.arc_blend_optimization_depth"),
    ("kink-ratio-above-1", "block_buffer = 16", "block_buffer = 16\narc_blend_kink_ratio = 1.5",
     "firmware.arc_blend_kink_ratio"),
    ("g64-p-negative", "block_buffer = 16", "block_buffer = 16\ng64_p = -0.01", "firmware.g64_p"),
]


@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_firmware_matches_toml_text(name):
    """Every [firmware] value of a bundled profile is the number in its file."""
    raw = raw_toml(name)["firmware"]
    fw = load_profile(name).firmware
    assert fw.steps_per_mm == raw["steps_per_mm"]
    assert fw.block_buffer == raw["block_buffer"]
    assert fw.max_line_rate_hz == raw.get("max_line_rate")  # (None: no budget)
    assert fw.minimum_cruise_ratio == raw.get("minimum_cruise_ratio", 0.5)


def test_firmware_defaults_are_klippers(tmp_path):
    """Without [firmware]: Klipper's defaults (minimum_cruise_ratio 0.5, instantaneous_corner_velocity
    1, 1.75 mm filament, 0.4 mm nozzle) and its derived extrude-only limits, in closed form:
    max_accel * 4 nozzle^2 / (pi (filament / 2)^2) = 3000 * 0.64 / (pi 0.875^2) = 798.24 mm/s^2
    (the figure issue 14 read from klippy), max_velocity the slower of X (300) and Y (200)."""
    profile = load_profile(write(tmp_path, BASE))
    fw = profile.firmware
    assert (fw.minimum_cruise_ratio, fw.instantaneous_corner_velocity_mm_s, fw.block_buffer) == (0.5, 1.0, 16)
    assert fw.max_line_rate_hz is None and fw.steps_per_mm == {}
    ratio = 0.64 / (math.pi * 0.875**2)
    assert profile.extrude_only_accel_mm_s2 == pytest.approx(3000.0 * ratio, rel=1e-15)
    assert round(profile.extrude_only_accel_mm_s2, 2) == 798.24
    assert profile.toolhead_max_velocity_mm_s == 200.0
    assert profile.extrude_only_velocity_mm_s == pytest.approx(200.0 * ratio, rel=1e-15)


def test_firmware_explicit_limits(tmp_path):
    """Given extrude-only limits and max_velocity are used as written; max_accel_to_decel replaces the ratio."""
    text = BASE + FIRMWARE.replace("minimum_cruise_ratio = 0.5", "max_accel_to_decel = 1500.0") + (
        "max_velocity = 250.0\nmax_extrude_only_velocity = 40.0\nmax_extrude_only_accel = 1200.0\n")
    profile = load_profile(write(tmp_path, text))
    assert profile.firmware.max_accel_to_decel_mm_s2 == 1500.0
    assert profile.toolhead_max_velocity_mm_s == 250.0
    assert (profile.extrude_only_velocity_mm_s, profile.extrude_only_accel_mm_s2) == (40.0, 1200.0)
    assert profile.firmware.steps_per_mm == {"X": 80.0, "Y": 80.0, "E": 415.0}


@pytest.mark.parametrize("old,new,key", [c[1:] for c in FIRMWARE_BROKEN], ids=[c[0] for c in FIRMWARE_BROKEN])
def test_broken_firmware_raises_profile_error(tmp_path, old, new, key):
    """Each broken [firmware] variant raises ProfileError, one line, naming the file and the key."""
    assert FIRMWARE.count(old) == 1
    path = write(tmp_path, BASE + FIRMWARE.replace(old, new))
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert_one_line_naming(str(info.value), path, key)


def test_linuxcnc_settings_default_to_linuxcnc_s_and_round_trip(tmp_path):
    """Without them, LinuxCNC 2.9's defaults (its INI reading of [TRAJ]: ARC_BLEND_ENABLE 1,
    FALLBACK 0, OPTIMIZATION_DEPTH 50, GAP_CYCLES 4, RAMP_FREQ 100, KINK_RATIO 0.1; SERVO_PERIOD
    1 ms as the sample configurations; G64 without P or Q); given ones are read as written,
    reach the model of its planner and the restored blending mode, and format_profile writes
    them back."""
    from fbspost.firmware.linuxcnc_segments import LinuxCNCConfig
    from fbspost.firmware.transparency import FirmwareSettings
    from fbspost.profile import format_profile

    default = load_profile(write(tmp_path, BASE))
    lc = default.firmware.linuxcnc
    assert (lc.servo_period_s, lc.arc_blend_enable, lc.arc_blend_fallback_enable, lc.arc_blend_optimization_depth,
            lc.arc_blend_gap_cycles, lc.arc_blend_ramp_freq_hz, lc.arc_blend_kink_ratio, lc.g64_p_mm,
            lc.g64_q_mm) == (0.001, True, False, 50, 4, 100.0, 0.1, 0.0, 0.0)
    assert FirmwareSettings.from_profile(default).startup_blend_mm == (0.0, 0.0)
    text = BASE + FIRMWARE + ("servo_period = 0.00025\narc_blend_enable = false\narc_blend_optimization_depth = 20\n"
                              "arc_blend_gap_cycles = 2\narc_blend_ramp_freq = 50.0\ng64_p = 0.01\n")
    profile = load_profile(write(tmp_path, text))
    config = LinuxCNCConfig.from_profile(profile)
    assert (config.servo_period_s, config.arc_blends, config.optimization_depth, config.gap_cycles,
            config.ramp_frequency_hz, config.startup_tolerance_mm) == (0.00025, False, 20, 2.0, 50.0, 0.01)
    assert FirmwareSettings.from_profile(profile).startup_blend_mm == (0.01, 0.0)
    again = load_profile(write(tmp_path, format_profile(profile)))
    assert again.firmware.linuxcnc == profile.firmware.linuxcnc


def test_linuxcnc_parameter_file_gives_the_work_offsets(tmp_path):
    """``parameter_file`` (relative to the profile) is LinuxCNC's var file: G54..G59.3's X Y Z are
    its parameters 5221 + 20 k + axis, a parameter it leaves out 0 (as LinuxCNC reads it), a system
    rotated by its 5230 + 20 k unknown; format_profile writes it back; a missing file or a line
    that is no parameter is a one-line error naming the key."""
    from fbspost.profile import format_profile

    (tmp_path / "mill.var").write_text("5220\t2.000000\n5241\t10.500000\n5243\t-2.000000\n5261\t1.0\n"
                                       "5270\t30.0\n5381\t-7.25\n")
    profile = load_profile(write(tmp_path, BASE + FIRMWARE + 'parameter_file = "mill.var"\n'))
    offsets = profile.work_offsets_mm
    assert offsets[:3] == ((0.0, 0.0, 0.0), (10.5, 0.0, -2.0), None)
    assert offsets[3:] == ((0.0, 0.0, 0.0),) * 5 + ((-7.25, 0.0, 0.0),)
    assert load_profile(write(tmp_path, BASE)).work_offsets_mm == ()
    again = load_profile(write(tmp_path, format_profile(profile)))
    assert again.firmware.linuxcnc == profile.firmware.linuxcnc
    for var, key in (("missing.var", "firmware.parameter_file"), ("bad.var", "firmware.parameter_file")):
        (tmp_path / "bad.var").write_text("5221 zero\n")
        path = write(tmp_path, BASE + FIRMWARE + f'parameter_file = "{var}"\n')
        with pytest.raises(ProfileError) as info:
            load_profile(path)
        assert_one_line_naming(str(info.value), path, key)
