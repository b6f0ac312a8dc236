"""The firmware settings around the compensated motion, line by line per flavor; copied moves run
under the program's own settings (read back from the output by a small interpreter of the lines);
the written time of the blocks against the exact sum of their durations."""
import dataclasses
import re
from fractions import Fraction

import numpy as np
import pytest

from fbspost.firmware.transparency import FirmwareSettings, Transparency
from fbspost.job.pipeline import SHAPING_LEFT_OFF, compensate_file
from fbspost.job.report import CompensateOptions
from fbspost.profile import ProfileError, format_profile, load_profile, parse_profile, tomllib
from fbspost.read.blocks import AXES, Block, Kind, Modal, PlannerLimits
from fbspost.write.emitter import Emitter

PRINTER = load_profile("printer-two-mode")

TRANSPARENT = {
    "klipper": ["SET_VELOCITY_LIMIT ACCEL=100000000 ACCEL_TO_DECEL=100000000 MINIMUM_CRUISE_RATIO=0 "
                "SQUARE_CORNER_VELOCITY=10000"],
    "marlin": ["M201 X1000000 Y1000000 E1000000", "M204 P1000000 T1000000", "M205 B0 J0.3 X1000 Y1000"],
    "reprap": ["M201 X100000 Y100000 E100000", "M204 P100000 T100000", "M566 X60000 Y60000", "M203 I0.6"],
    "linuxcnc": ["G64 P0.001 Q0"],
}
SHAPING_OFF = {"klipper": ["SET_INPUT_SHAPER SHAPER_FREQ_X=0 SHAPER_FREQ_Y=0"], "marlin": ["M593 F0"],
               "reprap": ['M593 P"none"'], "linuxcnc": []}


def limits_line(limits: PlannerLimits, raw: bytes = b"") -> Block:
    return Block(1, raw, Kind.PASS, Modal(), np.zeros(4), limits=limits)


@pytest.mark.parametrize("flavor", ["klipper", "marlin", "reprap", "linuxcnc"])
def test_lines_per_flavor(flavor):
    """Transparent limits before the first block, shaping off only at rest; a program line that
    sets a limit undoes the limits (set again), not the shaping; restore gives the program's
    values as they stand, the profile's where the program set none."""
    program = FirmwareSettings(3000.0, square_corner_velocity_mm_s=5.0, minimum_cruise_ratio=0.4,
                               shaper_frequency_hz={"X": 52.0, "Y": 34.5})
    t = Transparency(flavor, program, 1e-3)
    assert t.apply(True, Modal()) == TRANSPARENT[flavor] + SHAPING_OFF[flavor]
    assert t.apply(True, Modal()) == []  # in force
    t.note(limits_line(PlannerLimits(1500.0, 2500.0, junction_deviation_mm=0.02,
                                     axis_max_acceleration_mm_s2={"X": 4000.0}), b"G61\n"))
    assert t.apply(False, Modal()) == TRANSPARENT[flavor]
    restored = {
        "klipper": [
            "SET_VELOCITY_LIMIT ACCEL=1500 ACCEL_TO_DECEL=900 MINIMUM_CRUISE_RATIO=0.4 SQUARE_CORNER_VELOCITY=5",
            "SET_INPUT_SHAPER SHAPER_FREQ_X=52 SHAPER_FREQ_Y=34.5",
        ],
        "marlin": ["M201 X4000", "M204 P1500 T2500", "M205 B20000 J0.02 X5 Y5", "M593 X F52", "M593 Y F34.5"],
        # (its shaper type is not known; M203 I: RRF's default 0.5 mm/s, the program set none)
        "reprap": ["M201 X4000", "M204 P1500 T2500", "M566 X300 Y300", "M203 I30"],
        "linuxcnc": ["G61"],
    }[flavor]
    assert t.restore() == restored
    assert t.restore() == []  # restored already
    t = Transparency("klipper", program, 1e-3)
    t.apply(True, Modal())
    t.note(limits_line(PlannerLimits(2000.0, 2000.0, accel_to_decel_mm_s2=500.0)))  # (Klipper 2024 reads it as a ratio)
    t.apply(False, Modal())
    assert t.restore()[0] == ("SET_VELOCITY_LIMIT ACCEL=2000 ACCEL_TO_DECEL=500 MINIMUM_CRUISE_RATIO=0.75 "
                              "SQUARE_CORNER_VELOCITY=5")
    old_klippy = Transparency("klipper", FirmwareSettings(3000.0, max_accel_to_decel_mm_s2=1500.0), 1e-3)
    old_klippy.apply(True, Modal())
    assert old_klippy.restore()[0] == "SET_VELOCITY_LIMIT ACCEL=3000 ACCEL_TO_DECEL=1500 MINIMUM_CRUISE_RATIO=0.5"
    inches = Modal(inches=True)
    assert Transparency("linuxcnc", program, 0.0254).apply(True, inches) == ["G64 P0.001 Q0"]


def test_linuxcnc_startup_blending_restored_in_the_programs_units():
    """The startup code's G64 P0.0254 Q0.0127 (mm, the profile's) given back where the program is
    in G20: P0.001 Q0.0005 inches (P 25.4 times too loose else); in G21, as given; no P Q: G64."""
    startup = FirmwareSettings(3000.0, startup_blend_mm=(0.0254, 0.0127))
    for modal, expected in ((Modal(inches=True), "G64 P0.001 Q0.0005"), (Modal(), "G64 P0.0254 Q0.0127")):
        t = Transparency("linuxcnc", startup, 0.0254)
        t.apply(True, modal)
        assert t.restore() == [expected]
    t = Transparency("linuxcnc", startup, 0.0254)
    t.apply(True, Modal())
    t.note(Block(1, b"G20\n", Kind.PASS, Modal(inches=True), np.zeros(4)))  # units changed mid-run
    assert t.restore() == ["G64 P0.001 Q0.0005"]
    none = Transparency("linuxcnc", FirmwareSettings(3000.0), 1e-3)
    none.apply(True, Modal())
    assert none.restore() == ["G64"]


@pytest.mark.parametrize("flavor, raised, restored", [
    ("klipper", "SQUARE_CORNER_VELOCITY=10000 VELOCITY=360.555", "SQUARE_CORNER_VELOCITY=5 VELOCITY=150"),
    ("marlin", "M203 X300", "M203 X150"),
    ("reprap", "M203 X18000 I0.6", "M203 X9000 I30")])
def test_velocity_limits_raised_where_known_to_be_lower(flavor, raised, restored):
    """Klipper's max_velocity (along the path) 150 mm/s, the program's M203 X 150 mm/s (Marlin, RRF:
    per axis) below the command's X 300 and Y 200 mm/s: raised around the compensated motion to
    what the axes allow (Klipper: sqrt(300^2 + 200^2) = 360.555 along the path; M203 X to 300, RRF
    in mm/min), the program's given back after. Not known (Klipper: the profile gives no
    max_velocity; M203 not set), or not lower: not raised."""
    command = {"X": 300.0, "Y": 200.0}
    program = FirmwareSettings(3000.0, square_corner_velocity_mm_s=5.0, max_velocity_mm_s=150.0,
                               command_velocity_mm_s=command)
    t = Transparency(flavor, program, 1e-3)
    t.note(limits_line(PlannerLimits(axis_max_velocity_mm_s={"X": 150.0, "Y": 250.0})))
    assert raised in " ".join(t.apply(False, Modal()))
    assert restored in " ".join(t.restore())
    for settings in (FirmwareSettings(3000.0, command_velocity_mm_s=command),
                     FirmwareSettings(3000.0, max_velocity_mm_s=400.0, axis_max_velocity_mm_s={"X": 300.0},
                                      command_velocity_mm_s=command)):
        t = Transparency(flavor, settings, 1e-3)
        assert t.apply(False, Modal()) == TRANSPARENT[flavor] and "VELOCITY=" not in t.restore()[-1]
    assert FirmwareSettings.from_profile(PRINTER).command_velocity_mm_s == {"X": 300.0, "Y": 300.0, "Z": 12.0}


def test_header_names_what_cannot_be_restored():
    marlin = Transparency("marlin", FirmwareSettings(3000.0), 1e-3).header()[-1]
    assert "input shaping on X, input shaping on Y, M201 X, M201 Y, M201 E, M205 J" in marlin
    known = FirmwareSettings(3000.0, shaper_frequency_hz={"X": 50.0, "Y": 40.0})
    assert len(Transparency("klipper", known, 1e-3).header()) == 1  # nothing left unrestored


_SETTING = re.compile(r"(SET_VELOCITY_LIMIT|SET_INPUT_SHAPER|M201|M204|M205)\b(.*)")


def settings_at_lines(path) -> list[tuple[str, dict]]:
    """Every line of a Klipper program with the firmware's settings when it runs (ACCEL, MINIMUM_CRUISE_RATIO,
    SQUARE_CORNER_VELOCITY, shaper frequencies), as Klipper reads them: an interpreter of the
    setting lines, starting at Klipper's config values given by the profile."""
    state = {"ACCEL": 3000.0, "MINIMUM_CRUISE_RATIO": 0.5, "SQUARE_CORNER_VELOCITY": 5.0,
             "SHAPER_FREQ_X": 52.0, "SHAPER_FREQ_Y": 34.5}
    out = []
    for line in path.read_text().splitlines():
        match = _SETTING.match(line)
        if match and match.group(1) == "M204":
            state["ACCEL"] = float(re.search(r"S([\d.]+)", line).group(1))
        elif match:
            state.update({k: float(v) for k, v in re.findall(r"([A-Z_]+)=([\d.]+)", match.group(2))})
        out.append((line, dict(state)))
    return out


def test_copied_moves_run_under_the_programs_own_settings(tmp_path):
    """Homing mid-program, a retraction, a macro and a move from the unknown place after it, an M204
    mid-motion: every copied move runs with what the program set (or Klipper's config where it set nothing),
    every written block with the transparent settings, and the program ends with its own."""
    source = tmp_path / "in.gcode"
    source.write_text("\n".join([
        "G21", "G90", "M83", "G28", "G1 X10 Y10 Z0.2 F6000", "G1 X30 Y10 E1 F3000", "G1 X30 Y30 E1",
        "M204 S2000", "G1 X10 Y30 E1", "G1 E-0.8 F2400", "G28 X", "G1 X10 F6000", "G1 X30 Y10 E1 F3000",
        "SET_VELOCITY_LIMIT SQUARE_CORNER_VELOCITY=8", "G1 X30 Y20 E1", "PARK_MACRO", "G1 X20 Y20 F6000",
        "G1 X10 Y10 E1", "M107", ""]))
    target = tmp_path / "out.gcode"
    compensate_file(source, target, PRINTER, CompensateOptions(flavor="klipper"))
    transparent = {"ACCEL": 1e8, "MINIMUM_CRUISE_RATIO": 0.0, "SQUARE_CORNER_VELOCITY": 1e4}
    # (the moves after a G28 start from the home position: planned and written, not copied)
    own = {"G28": 3000.0, "G1 E-0.8 F2400": 2000.0, "G28 X": 2000.0, "PARK_MACRO": 2000.0, "G1 X20 Y20 F6000": 2000.0}
    lines = settings_at_lines(target)
    copied = {line: state for line, state in lines if line in own}
    assert len(copied) == len(own)
    for line, state in copied.items():
        scv = 8.0 if line in ("PARK_MACRO", "G1 X20 Y20 F6000") else 5.0
        assert state["ACCEL"] == own[line] and state["MINIMUM_CRUISE_RATIO"] == 0.5, line
        assert state["SQUARE_CORNER_VELOCITY"] == scv, line
    written = [state for line, state in lines if line.startswith("G1 ") and line not in own]
    assert len(written) > 50
    for state in written:
        assert {k: state[k] for k in transparent} == transparent
        assert state["SHAPER_FREQ_X"] == state["SHAPER_FREQ_Y"] == 0.0
    assert {k: lines[-1][1][k] for k in transparent} == {"ACCEL": 2000.0, "MINIMUM_CRUISE_RATIO": 0.5,
                                                          "SQUARE_CORNER_VELOCITY": 8.0}


def written_blocks(text: bytes) -> tuple[list[Fraction], list[Fraction]]:
    """Each G1 block's time as the controller computes it, exactly (its XYZ length, E's when XYZ
    do not move, over its F, from the decimal text; the length to double precision), and its F
    (mm/min)."""
    position, feed, times, feeds = [Fraction(0)] * 4, None, [], []
    for line in text.decode().splitlines():
        words = {w[0]: Fraction(w[1:]) for w in line.split()[1:]}
        feed = words.get("F", feed)
        target = [words.get(a, p) for a, p in zip("XYZE", position, strict=True)]
        d = [b - a for a, b in zip(position, target, strict=True)]
        squared = sum(x * x for x in d[:3]) or d[3] * d[3]
        times.append(Fraction(float(np.sqrt(float(squared)))) * 60 / feed)
        feeds.append(feed)
        position = target
    return times, feeds


def test_written_time_carries_the_feed_rounding():
    """Slow, long and tiny blocks whose F rounding alone loses up to milliseconds each: the written
    time after every block is the exact sum of the durations up to it within that block's own
    rounding (half a unit of F, 0.0005 mm/min), never drifting; blocks that round to no motion
    give their time to the next. Per-block rounding without the carry drifts far more."""
    rng = np.random.default_rng(7)
    n = 3000
    durations = rng.uniform(1e-3, 0.5, n)
    speeds = 10 ** rng.uniform(-2.5, 1.5, n)  # 0.003 to 30 mm/s: F 0.2 to 1800 mm/min
    steps = rng.normal(size=(n, 4)) * (speeds * durations)[:, None] / 2
    steps[::97] = 0.0  # no motion
    targets = np.cumsum(steps, axis=0)
    emitter = Emitter(np.zeros(len(AXES)), b"\n")
    still = np.zeros((n, len(AXES) - 4))  # LinuxCNC's other axes
    text = b"".join(emitter.blocks(np.column_stack([targets, still])[a:a + 500], durations[a:a + 500])[0]
                    for a in range(0, n, 500))
    times, feeds = written_blocks(text)
    units = np.rint(np.vstack([np.zeros(4), targets]) * [1e4, 1e4, 1e4, 1e5])
    moving = np.flatnonzero(np.abs(np.diff(units, axis=0)).sum(axis=1) > 0)
    assert len(times) == len(moving) > 0.95 * n
    exact = np.cumsum([Fraction(float(d)) for d in durations])[moving]  # up to each written block
    drift_s = np.array([float(w - e) for w, e in zip(np.cumsum(times), exact, strict=True)])
    # |L/F - L/F*| <= (L/F) (half a unit) / F*, F* >= F - half a unit: the ideal F
    half = Fraction(1, 2000)
    own_rounding_s = (
        np.array([float(t * half / (f - half)) for t, f in zip(times, feeds, strict=True)]) * (1 + 1e-9) + 1e-15
    )
    assert np.all(np.abs(drift_s) <= own_rounding_s)
    assert np.abs(drift_s[own_rounding_s < 1e-6]).max() < 1e-6  # (F rounds to 0.001 mm/min: a block of
    # 0.1 um in 0.3 s at F0.02 is off by 7 ms, given on to the next)
    # each block's F rounded on its own, no carry: the drift adds up
    lengths = np.array([float(t * f / 60) for t, f in zip(times, feeds, strict=True)])  # mm
    owed_s = np.diff(np.array([0.0] + [float(e) for e in exact]))
    alone_s = lengths * 60000 / np.maximum(np.rint(lengths * 60000 / owed_s), 1)
    assert abs(np.sum(alone_s - owed_s)) > 100 * abs(drift_s[-1])


def test_profile_shaper_frequencies_reach_the_restore(tmp_path):
    """[firmware] shaper_frequency: read, written back by format_profile, restored after the motion."""
    text = format_profile(PRINTER).replace("[firmware]", "[firmware]\nshaper_frequency = { X = 51.5, Y = 33.0 }")
    profile = parse_profile(tomllib.loads(text), "p.toml")
    assert profile.firmware.shaper_frequency_hz == {"X": 51.5, "Y": 33.0}
    assert parse_profile(tomllib.loads(format_profile(profile)), "q.toml") == dataclasses.replace(
        profile, source="q.toml"
    )
    t = Transparency("klipper", FirmwareSettings.from_profile(profile), 1e-3)
    t.apply(True, Modal())
    assert t.restore()[-1] == "SET_INPUT_SHAPER SHAPER_FREQ_X=51.5 SHAPER_FREQ_Y=33"
    with pytest.raises(ProfileError, match="firmware.shaper_frequency.Q"):
        parse_profile(tomllib.loads(text.replace("X = 51.5", "Q = 51.5")), "p.toml")


HEAD = "G28\nG90\nM83\nG1 X20 Y20 Z0.2 F6000\n{}G1 X40 Y20 E1 F3000\nG1 X40 Y40 E1\nG1 X20 Y40 E1\nG4 P100\n"


def compensated(tmp_path, text: str, flavor: str | None, profile=PRINTER):
    source, target = tmp_path / "part.gcode", tmp_path / "out.gcode"
    source.write_text(text)
    report = compensate_file(source, target, profile, CompensateOptions(flavor=flavor, verify=False))
    return report, target.read_text().splitlines()


@pytest.mark.parametrize("flavor, line, restored", [
    ("klipper", "SET_INPUT_SHAPER SHAPER_FREQ_X=52 SHAPER_FREQ_Y=34.5 DAMPING_RATIO_X=0.1\n",
     "SET_INPUT_SHAPER SHAPER_FREQ_X=52 SHAPER_FREQ_Y=34.5"),
    ("marlin", "M593 X F52 D0.07\nM593 Y F34.5\n", "M593 Y F34.5"),
    ("marlin", "M593 F40 ; both axes\n", "M593 Y F40"),
])
def test_the_programs_own_shaping_is_restored(tmp_path, flavor, line, restored):
    """Shaping the program sets itself is switched off again before the next compensated motion
    and is what the output turns back on after it (the profile gives none); nothing is said."""
    report, lines = compensated(tmp_path, HEAD.format(line), flavor)
    shaping = [i for i, x in enumerate(lines) if x.startswith(("SET_INPUT_SHAPER", "M593"))]
    copied = [lines.index(x) for x in line.splitlines()]  # (the restore may repeat them)
    after = [lines[i] for i in shaping if i > copied[-1]]
    assert after[0] == SHAPING_OFF[flavor][0], after  # (else the motion after it is shaped twice)
    assert lines[shaping[-1]] == restored, after
    last_move = max(i for i, x in enumerate(lines) if x.startswith("G1 X"))
    assert shaping[-1] > last_move
    assert not any("input shaping" in w for w in report.warnings), report.warnings


@pytest.mark.parametrize("flavor", ["klipper", "marlin", "reprap"])
def test_shaping_left_off_is_said_on_stderr(tmp_path, flavor):
    """Neither profile nor program says what the shaping was: the output leaves it off, and the
    summary says so in one warning that names the way to state it."""
    report, lines = compensated(tmp_path, HEAD.format(""), flavor)
    shaping = [x for x in lines if x.startswith(("SET_INPUT_SHAPER", "M593"))]
    assert shaping == SHAPING_OFF[flavor]
    left = [w for w in report.warnings if w.startswith(f"{SHAPING_LEFT_OFF} on X and Y: ")]
    assert len(left) == 1 and "[firmware] shaper_frequency" in left[0], report.warnings


def test_the_profiles_firmware_wins_over_the_files_hints(tmp_path):
    """A Klipper printer's file sliced as Marlin: with [firmware] flavor = "klipper" it is written for
    Klipper (SET_VELOCITY_LIMIT, SET_INPUT_SHAPER; no M201, M204, M205, M593, which Klipper ignores),
    and one warning says the two disagree; --flavor still chooses."""
    profile = dataclasses.replace(PRINTER, firmware=dataclasses.replace(PRINTER.firmware, flavor="klipper"))
    assert parse_profile(tomllib.loads(format_profile(profile)), "p.toml").firmware.flavor == "klipper"
    text = "; generated by PrusaSlicer\n; gcode_flavor = marlin2\n" + HEAD.format("")
    report, lines = compensated(tmp_path, text, None, profile)
    assert report.flavor == "klipper"
    assert any(x.startswith("SET_VELOCITY_LIMIT") for x in lines)
    assert not any(x.startswith(("M201", "M204", "M205", "M593")) for x in lines)
    said = [w for w in report.warnings if "the profile's [firmware] flavor" in w]
    assert len(said) == 1 and "the file's hints say marlin" in said[0]
    report, lines = compensated(tmp_path, text, "marlin", profile)
    assert report.flavor == "marlin" and any(x.startswith("M205") for x in lines)
    assert not any("[firmware] flavor" in w for w in report.warnings)
    with pytest.raises(ProfileError, match="firmware.flavor"):
        parse_profile(tomllib.loads(format_profile(profile).replace('"klipper"', '"grbl"')), "p.toml")
