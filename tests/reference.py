"""Independent truths for the tests: nothing here calls fbspost's dynamics or optimizer."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import linalg, signal


def continuous_model(modes):
    """Block-diagonal continuous state space of sum_i (alpha + beta s)/(s^2 + 2 z w s + w^2)."""
    blocks, b, c = [], [], []
    for mode in modes:
        w = 2 * np.pi * mode.frequency_hz
        blocks.append(np.array([[0.0, 1.0], [-w * w, -2 * mode.damping * w]]))
        b += [0.0, 1.0]
        c += [mode.alpha, mode.beta]
    return linalg.block_diag(*blocks), np.array(b)[:, None], np.array(c)[None, :], np.zeros((1, 1))


def slow_swing(t):
    """A slow line with a swing (mm at ``t`` s): X 20 mm/s with a 0.5 mm 3 Hz swing, Y 6 mm/s
    with 0.3 mm at 2 Hz."""
    return np.column_stack([20.0 * t + 0.5 * np.sin(2 * np.pi * 3.0 * t),
                            6.0 * t + 0.3 * np.sin(2 * np.pi * 2.0 * t + 1.0)])


def swing_ends(axes: int, n: int = 1000, period_s: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """(times s, (n, ``axes``) targets): ``slow_swing`` from its start, an end every ``period_s``."""
    t_s = np.arange(1, n + 1) * period_s
    targets = np.zeros((n, axes))
    targets[:, :2] = slow_swing(t_s) - slow_swing(np.zeros(1))
    return t_s, targets


def felt_um(profile, wanted, knots_s, knots_mm) -> np.ndarray:
    """RMS (um) per axis of the modes' response (``profile``'s X and Y, continuous, scipy's lsim)
    to the error of a motion linear between ``knots_mm`` (X Y) at ``knots_s`` from ``wanted(t)``,
    on a 20 us grid over the knots."""
    t = np.arange(knots_s[0], knots_s[-1], 2e-5)
    error_mm = np.column_stack([np.interp(t, knots_s, knots_mm[:, c]) for c in range(2)]) - wanted(t)
    felt = [signal.lsim(continuous_model(profile.axes[a].modes), error_mm[:, c], t - t[0])[1]
            for c, a in enumerate("XY")]
    return 1e3 * np.sqrt(np.mean(np.square(felt), axis=1))


def simulate_lsim(modes, period_s, command):
    """Actual position for a zero-order-hold command, from rest at command[0]: each mode's state
    space discretized exactly by scipy (``cont2discrete``, zero-order hold) and run by ``lfilter``,
    the modes summed (equal to ``scipy.signal.lsim`` with ``interp=False`` to 1e-12, whose
    per-sample Python loop took minutes on a whole print)."""
    command = np.asarray(command, dtype=float)
    u = command - command[0]
    y = np.zeros_like(u)
    for mode in modes:
        a, b, c, d = continuous_model([mode])
        ad, bd, cd, dd, _ = signal.cont2discrete((a, b, c, d), period_s, method="zoh")
        numerator, denominator = signal.ss2tf(ad, bd, cd, dd)
        y += signal.lfilter(numerator[0], denominator, u)
    return y + command[0]


def modelled_xy(profile, commands_xy, period_s):
    """X Y through the profile's modes (``simulate_lsim``) of commanded X Y every ``period_s``."""
    return np.column_stack(
        [simulate_lsim(profile.axes[a].modes, period_s, commands_xy[:, i]) for i, a in enumerate("XY")]
    )


def simulate_varying(modes, period_s, command, scale):
    """Actual position for a zero-order-hold command, from rest at command[0], of modes (beta = 0)
    whose every frequency is ``scale[k]`` times its own over sample k, the DC gain kept: per mode
    y'' + 2 z w_k y' + w_k^2 y = alpha_k u, alpha_k = alpha scale_k^2, in the coordinates a change
    of mass leaves continuous (y, y'). Exact per sample (matrix exponential), scales rounded to 1e-9."""
    command = np.asarray(command, dtype=float)
    u = command - command[0]
    rounded = np.round(np.asarray(scale, dtype=float), 9)
    total = np.zeros(command.size)
    for mode in modes:
        assert mode.beta == 0.0
        scales, index = np.unique(rounded, return_inverse=True)
        w = 2 * np.pi * mode.frequency_hz * scales
        augmented = np.zeros((scales.size, 3, 3))
        augmented[:, 0, 1] = 1.0
        augmented[:, 1, 0], augmented[:, 1, 1] = -w * w, -2 * mode.damping * w
        augmented[:, 1, 2] = mode.alpha * scales**2
        steps = linalg.expm(augmented * period_s)[:, :2]  # all the scales' [A_d | B_d] at once
        x = np.zeros(2)
        for k in range(command.size):
            total[k] += x[0]
            step = steps[index[k]]
            x = step[:, :2] @ x + step[:, 2] * u[k]
    return total + command[0]


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def finite_derivative_max(u, order, period_s):
    """Largest |r-th backward difference| / T^r of the sampled command, counting the rest before
    the first sample and the hold after the last (the machine sees both)."""
    padded = np.concatenate([np.full(order, u[0]), u, np.full(order, u[-1])])
    return float(np.abs(np.diff(padded, order)).max() / period_s**order)


# ---- an independent G-code executor ------------------------------------------------------------
import re  # noqa: E402

_WORD = re.compile(rb"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_COMMENT = re.compile(rb"\([^)]*\)")
_MOTION = {b"G0", b"G1", b"G5"}
_ARCS = {b"G2", b"G3"}
_ARC_STEPS = 4096  # chords per G5 curve for its arc length (their sum is within ~1e-8 of it)


def split_code(raw: bytes) -> list[tuple[bytes, float]]:
    code = raw.split(b";", 1)[0]
    code = _COMMENT.sub(b"", code)
    return [(letter.upper(), float(value)) for letter, value in _WORD.findall(code)]


def is_motion_line(raw: bytes) -> bool:
    """A G0/G1/G5 line that names an axis (X Y Z E), or any G2/G3 (a full circle names none):
    what a post-processor may rewrite."""
    return is_motion(split_code(raw))


def is_motion(words: list[tuple[bytes, float]]) -> bool:
    """``is_motion_line`` of a line's ``split_code`` words."""
    g = {f"G{v:g}".encode() for k, v in words if k == b"G"}
    return bool(g & _ARCS) or (bool(g & _MOTION) and any(k in (b"X", b"Y", b"Z", b"E") for k, _ in words))


def arc_length(start, end, offset_ij, radius, clockwise):
    """Length of a G2/G3 arc in the XY plane with its helical rise ``end[2] - start[2]``, from
    the start, the end and either the centre's offset (I, J) or the radius R (negative: the
    long way round), the way RS274NGC defines them. The same end as the start is a full circle."""
    (x0, y0, z0), (x1, y1, z1) = start, end
    if radius is None:
        cx, cy = x0 + offset_ij[0], y0 + offset_ij[1]
    else:  # the centre on the chord's bisector, to the right of the chord going clockwise
        half = np.hypot(x1 - x0, y1 - y0) / 2
        rise = np.sqrt(max(radius**2 - half**2, 0.0)) * (1 if (radius > 0) != clockwise else -1)
        cx = (x0 + x1) / 2 - rise * (y1 - y0) / (2 * half)
        cy = (y0 + y1) / 2 + rise * (x1 - x0) / (2 * half)
    r = np.hypot(x0 - cx, y0 - cy)
    turn = (np.arctan2(y1 - cy, x1 - cx) - np.arctan2(y0 - cy, x0 - cx)) % (2 * np.pi)  # counterclockwise
    if clockwise:
        turn = (2 * np.pi - turn) % (2 * np.pi)
    if turn < 1e-12:
        turn = 2 * np.pi
    return float(np.hypot(r * turn, z1 - z0))


class Executed:
    """Blocks run one after another at their feed, each at constant speed (no acceleration)."""

    def __init__(self):
        self.ends = []  # (time_s, x, y, z, e) at the end of every block, machine coordinates
        self.path = []  # the same, and inside G5 blocks at every multiple of the sample period
        self.g5_blocks = 0  # how many of the blocks were G5
        self.e_at_lines = []  # E (program coordinate) at every line that is not a motion line
        self.at_lines = []  # (x, y, z, e) there, machine coordinates (NaN: not yet known)
        self.nonmotion = []  # those lines' bytes, in order
        self.nonmotion_s = []  # when each runs
        self.extruded = 0.0  # sum of positive and negative E moves
        self.dwells = []  # when each G4 ends
        self.duration_s = 0.0  # when the last line ends


def bezier_points(p0, p1, p2, p3, u):
    """Points of the cubic Bezier at parameters ``u`` (Bernstein form), rows of XY."""
    u = np.asarray(u, dtype=float)[:, None]
    w = 1.0 - u
    return w**3 * p0 + 3 * w * w * u * p1 + 3 * w * u * u * p2 + u**3 * p3


def arc_lengths(p0, p1, p2, p3):
    """The curve's parameters on _ARC_STEPS equal steps and its XY length up to each, as sums of
    chords: inverted by interpolation, the parameter at an arc length (how Marlin and LinuxCNC move
    along a G5 at constant feed)."""
    grid = np.linspace(0.0, 1.0, _ARC_STEPS + 1)
    chords = np.hypot(*np.diff(bezier_points(p0, p1, p2, p3, grid), axis=0).T)
    return grid, np.concatenate([[0.0], np.cumsum(chords)])


def execute(path, sample_rate_hz: float = 10000.0, dwell_p_seconds: bool = False,
            rests: dict[str, tuple[float, float]] | None = None) -> Executed:
    """G0/G1 with X Y Z E F, G2/G3 with I J or R in G17 (timed by their helical length; their
    end points only), G5 with I J P Q X Y Z E F (timed by the curve's XY length; Z and E
    linear in its parameter, as Marlin moves them; only in G17), G4 (P milliseconds, or seconds
    with ``dwell_p_seconds`` as in LinuxCNC; S seconds), G90/G91, M82/M83, G92, G20/G21,
    G17/G18/G19, G28 (the homed axes at 0); other lines are recorded as non-motion. ``path`` gets the points inside G5
    blocks at every multiple of 1 / ``sample_rate_hz``. The first position of an axis is where it
    is first set (a move from an unknown place is instant). With ``rests`` (axis:
    (max velocity, acceleration)), a line that moves Z or E but not X and Y runs from rest to
    rest at the slowest limits of the axes it moves (the controller's plan of a line fbspost
    copies at rest) instead."""
    run = Executed()
    pos = {a: None for a in "XYZE"}
    pos["E"] = 0.0
    offset = {a: 0.0 for a in "XYZE"}
    abs_xyz, abs_e, scale, feed, t, plane = True, True, 1.0, None, 0.0, 17
    for raw in open(path, "rb").read().splitlines(keepends=True):
        words = split_code(raw)
        codes = [(k, v) for k, v in words if k in (b"G", b"M")]
        if is_motion(words):
            target = dict(pos)
            curve = {}
            for k, v in words:
                a = k.decode()
                if a in "XYZE":
                    rel = not (abs_e if a == "E" else abs_xyz)
                    value = v * scale
                    target[a] = (pos[a] or 0.0) + value if rel else value + offset[a]
                elif a in "IJPQR":
                    curve[a] = v * scale
                elif a == "F":
                    feed = v * scale / 60.0
            known = [a for a in "XYZ" if pos[a] is not None and target[a] is not None]
            unknown = any(pos[a] is None and target[a] is not None for a in "XYZ")
            if (b"G", 5.0) in codes:
                assert plane == 17, f"G5 outside the XY plane: {raw!r}"
                assert not unknown and sorted(curve) == list("IJPQ"), f"G5 needs a known start and I J P Q: {raw!r}"
                p0, p3 = np.array([pos["X"], pos["Y"]]), np.array([target["X"], target["Y"]])
                p1, p2 = p0 + [curve["I"], curve["J"]], p3 + [curve["P"], curve["Q"]]
                grid, arc = arc_lengths(p0, p1, p2, p3)
                t0, t = t, t + arc[-1] / feed
                inside = np.arange(np.floor(t0 * sample_rate_hz) + 1, np.ceil(t * sample_rate_hz)) / sample_rate_hz
                u = np.interp((inside - t0) / (t - t0) * arc[-1], arc, grid)
                xy = bezier_points(p0, p1, p2, p3, u)
                z0, z3 = pos["Z"] or 0.0, target["Z"] or 0.0
                run.path += [(ti, x, y, z0 + (z3 - z0) * ui, pos["E"] + (target["E"] - pos["E"]) * ui)
                             for ti, (x, y), ui in zip(inside, xy, u, strict=True)]
                run.g5_blocks += 1
            elif codes and codes[0][0] == b"G" and codes[0][1] in (2.0, 3.0):
                assert plane == 17 and not unknown, f"an arc outside G17 or from an unknown start: {raw!r}"
                xyz0, xyz1 = ([p[a] or 0.0 for a in "XYZ"] for p in (pos, target))
                t += arc_length(xyz0, xyz1, (curve.get("I", 0.0), curve.get("J", 0.0)), curve.get("R"),
                                codes[0][1] == 2.0) / feed
            else:
                d_xyz = math.sqrt(sum((target[a] - pos[a]) ** 2 for a in known)) if known else 0.0
                d_e = abs(target["E"] - pos["E"])
                length = d_xyz if d_xyz > 0 else d_e
                moved = [a for a in "XYZE" if pos[a] is not None and target[a] != pos[a]]
                if not unknown and length > 0 and rests and not {"X", "Y"} & set(moved):
                    v = min([feed] + [rests[a][0] for a in moved])
                    accel = min(rests[a][1] for a in moved)
                    t += length / v + v / accel if length >= v * v / accel else 2.0 * math.sqrt(length / accel)
                elif not unknown and length > 0:
                    t += length / feed
            run.extruded += target["E"] - pos["E"]
            pos = target
            if all(pos[a] is not None for a in "XY"):
                run.ends.append((t, pos["X"], pos["Y"], pos["Z"] or 0.0, pos["E"]))
                run.path.append(run.ends[-1])
            continue
        for k, v in codes:
            code = (k + (b"%g" % v)).upper()
            if code == b"G90":
                abs_xyz = abs_e = True
            elif code == b"G91":
                abs_xyz = abs_e = False
            elif code == b"M82":
                abs_e = True
            elif code == b"M83":
                abs_e = False
            elif code == b"G20":
                scale = 25.4
            elif code == b"G21":
                scale = 1.0
            elif code in (b"G17", b"G18", b"G19"):
                plane = int(code[1:])
            elif code == b"G4":
                seconds = dict(words)
                t += seconds.get(b"S", seconds.get(b"P", 0.0) / (1.0 if dwell_p_seconds else 1000.0))
                run.dwells.append(t)
            elif code == b"G28":  # homing: the named axes (all without a name) at 0
                named = [kk.decode() for kk, _ in words if kk.decode() in "XYZ"] or list("XYZ")
                pos.update({a: 0.0 for a in named})
            elif code == b"G92":
                for kk, vv in words:
                    a = kk.decode()
                    if a in "XYZE" and pos[a] is not None:
                        offset[a] = pos[a] - vv * scale
        sets_feed = all(k == b"G" and v in (0.0, 1.0) for k, v in codes)  # F alone, "G1 F1800"
        for k, v in words:
            if k == b"F" and sets_feed:
                feed = v * scale / 60.0
        run.nonmotion.append(raw)
        run.nonmotion_s.append(t)
        run.e_at_lines.append(pos["E"] - offset["E"])
        run.at_lines.append(tuple(np.nan if pos[a] is None else pos[a] for a in "XYZE"))
    run.duration_s = t
    return run


def rest_limits(profile) -> dict[str, tuple[float, float]]:
    """``execute``'s ``rests``: Z's and E's max velocity and acceleration, each at most the
    planner's acceleration (the profile's)."""
    return {a: (profile.axes[a].max_velocity_mm_s, min(profile.axes[a].max_acceleration_mm_s2,
                                                       profile.planner_acceleration_mm_s2))
            for a in "ZE" if a in profile.axes}


def serial(profile, lines_per_s: float = 300.0):
    """``profile`` fed by a host over a serial line: at most ``lines_per_s`` lines a second."""
    return dataclasses.replace(profile, firmware=dataclasses.replace(profile.firmware, max_line_rate_hz=lines_per_s))


def unbudgeted(profile):
    """``profile`` without the firmware's line rate and steps: the writer's blocks then keep to
    the tolerance everywhere (the budget's cost is tested apart)."""
    firmware = dataclasses.replace(profile.firmware, max_line_rate_hz=None, steps_per_mm={})
    return dataclasses.replace(profile, firmware=firmware)


def fine_servo(profile):
    """``profile`` with LinuxCNC's servo period under half a sample: its shortest block (two
    periods) no longer binds, so the blocks keep to the tolerance (the writer's own tests; what
    the firmware's minimum costs is measured on LinuxCNC itself: docs/linuxcnc.md)."""
    linuxcnc = dataclasses.replace(profile.firmware.linuxcnc, servo_period_s=0.4 / profile.sample_rate_hz)
    return dataclasses.replace(profile, firmware=dataclasses.replace(profile.firmware, linuxcnc=linuxcnc))


# What fbspost adds to a program: its header, the firmware's settings (transparency), dwells (a run's
# unused settle margin), mode lines, the program's feed.
INSERTED = (
    b"; fbspost",
    b"(fbspost",
    b"M201",
    b"M204",
    b"M205",
    b"M566",
    b"M203 I",
    b"M593",
    b"SET_VELOCITY_LIMIT",
    b"SET_INPUT_SHAPER",
    b"G4 P",
    b"G64",
    b"G61",
    b"G90",
    b"G91",
    b"M82",
    b"M83",
    b"G20",
    b"G21",
    b"G17",
    b"G18",
    b"G19",
    b"G1 F",  # the program's feed back before a copied move without its own
    b"F",
)


def kept_lines(original: list[bytes], output: list[bytes]) -> list[int]:
    """Where each of the ``original`` lines is among the ``output`` lines, asserting that they are
    all there, byte-exact and in order (a last line without a line ending may have gained one,
    when fbspost writes after it) and that every other output line is one fbspost adds."""
    where, i = [], 0
    for j, line in enumerate(output):
        if i < len(original) and (line == original[i] or (
                i == len(original) - 1 and not original[i].endswith(b"\n") and line.rstrip(b"\r\n") == original[i])):
            where.append(j)
            i += 1
        else:
            assert line.startswith(INSERTED), (
                f"output line {j}: {line!r} is not the original's {i}: {original[i : i + 1]!r}"
            )
    assert i == len(original), f"original line {original[i]!r} missing from the output"
    return where


def positions_at(points, t):
    """X Y Z E of executed points (rows time_s, x, y, z, e), linear between them, at the times t."""
    points = np.array(points)
    # Several points at one time (instant moves): keep the last, so interpolation is well defined.
    points = points[np.append(np.diff(points[:, 0]) > 0, True)]
    return np.column_stack([np.interp(t, points[:, 0], points[:, i]) for i in (1, 2, 3, 4)])


def sample_blocks(ends, sample_rate_hz):
    """The piecewise-linear command of executed blocks on a uniform grid: (times, [x y z e])."""
    t = np.arange(0.0, ends[-1][0] + 0.5 / sample_rate_hz, 1.0 / sample_rate_hz)
    return t, positions_at(ends, t)


def contour_error(path_xy, points_xy, piece_mm=0.5, candidates=16):
    """Distance from every point to the polyline ``path_xy``: the exact distance to the nearest of
    the ``candidates`` path pieces (pieces no longer than ``piece_mm``) whose middles are closest."""
    path_xy = np.asarray(path_xy, dtype=float)
    return segments_distance(path_xy[:-1], path_xy[1:], points_xy, piece_mm, candidates)


def segments_distance(seg_starts, seg_ends, points, piece_mm=0.5, candidates=16):
    """``contour_error`` for separate straight segments (rows of starts and ends, any dimension)."""
    from scipy.spatial import cKDTree

    starts, ends = [], []
    for a, b in zip(np.asarray(seg_starts, dtype=float), np.asarray(seg_ends, dtype=float), strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / piece_mm)))
        f = np.linspace(0.0, 1.0, n + 1)[:, None]
        pts = a + f * (b - a)
        starts.append(pts[:-1])
        ends.append(pts[1:])
    starts, ends = np.concatenate(starts), np.concatenate(ends)
    points_xy = np.asarray(points)
    tree = cKDTree((starts + ends) / 2)
    _, idx = tree.query(points_xy, k=min(candidates, len(starts)))
    idx = idx.reshape(len(points_xy), -1)
    a, d = starts[idx], (ends - starts)[idx]
    p = np.asarray(points_xy)[:, None, :]
    length2 = np.sum(d * d, axis=2)
    u = np.clip(np.divide(np.sum((p - a) * d, axis=2), length2, out=np.zeros_like(length2), where=length2 > 0), 0, 1)
    return np.sqrt(np.sum((p - a - u[..., None] * d) ** 2, axis=2)).min(axis=1)
