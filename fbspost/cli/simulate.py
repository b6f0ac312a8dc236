"""The commands that model rather than write a program: ``trajectory`` (a sampled CSV through the
optimizer alone) and ``simulate`` (a program compensated or shaped, each through the axes'
models, side by side).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from .. import __version__
from ..firmware.shapers import MAX_DAMPING, SHAPERS
from ..plan.margins import RunMargins
from ..profile import FLAVORS, load_profile
from ..read.flavors import detect_flavor
from ..tools.trajectory import read_trajectory_csv, write_trajectory_csv
from .group import machine_option, main, margin_options


@main.command()
@click.argument("input_csv", type=click.Path(dir_okay=False, path_type=Path))
@machine_option
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path),
              help="Output CSV (default: INPUT-compensated.csv beside the input).")
@click.option("--lookahead", type=click.Choice(["limited", "complete"]), default="limited", show_default=True,
              help="Sliding windows, or one solve over the whole trajectory.")
@click.option("--knot-spacing", type=click.IntRange(min=1), help="Samples between knots (default: from the dynamics).")
@click.option("--commit-spans", type=click.IntRange(min=1), help="Knot spans kept from each window.")
@click.option("--overlap-spans", type=click.IntRange(min=1), help="Look-ahead knot spans beyond the kept ones.")
@click.option("--quiet", "-q", is_flag=True, help="No summary on stderr.")
def trajectory(input_csv, machine, output, lookahead, knot_spacing, commit_spans, overlap_spans, quiet):
    """Compensate a sampled trajectory (CSV: time_s,X,Y,... at the profile's sample rate).

    Every axis with modes in the profile gets the command whose modelled motion tracks the input
    within the axis' limits; other columns are copied. The output has the same samples.
    """
    from ..fbs.dynamics import AxisDynamics
    from ..fbs.optimizer import compensate_axis
    from ..fbs.settings import AxisLimits, FBSSettings
    from ..job.report import AxisReport

    started = time.perf_counter()
    profile = load_profile(machine)
    data = read_trajectory_csv(input_csv, profile.sample_rate_hz)
    settings = FBSSettings(knot_spacing_samples=knot_spacing, commit_spans=commit_spans, overlap_spans=overlap_spans)
    period_s = 1.0 / profile.sample_rate_hz
    n = len(next(iter(data.axes.values())))
    lines = [f"fbspost {__version__}: {input_csv} on {profile.name}, {n} samples at {profile.sample_rate_hz:g} Hz "
             f"({(n - 1) * period_s:.3f} s), {lookahead} look-ahead"]
    for name, desired in data.axes.items():
        axis = profile.axes.get(name)
        if axis is None or not axis.modes:
            lines.append(f"axis {name}: no modes in the profile, copied")
            continue
        dynamics = AxisDynamics(axis.modes, period_s)
        limits = AxisLimits.from_profile(axis)
        result = compensate_axis(desired, dynamics, limits, settings, lookahead)
        error = AxisReport.from_errors(desired - dynamics.simulate(desired),
                                       desired - dynamics.simulate(result.command_mm))
        data.axes[name] = result.command_mm
        v = np.abs(np.diff(result.command_mm)).max(initial=0.0) / period_s
        a = np.abs(np.diff(result.command_mm, 2)).max(initial=0.0) / period_s**2
        lines.append(f"axis {name}: RMS error {error.rms_error_before_um:.4g} -> {error.rms_error_after_um:.4g} um, "
                     f"max {error.max_error_before_um:.4g} -> {error.max_error_after_um:.4g} um; "
                     f"command |v| {v:.4g}/{limits.command[1]:g} mm/s, "
                     f"|a| {a:.5g}/{limits.command[2]:g} mm/s^2; {result.windows} windows, {result.qp_windows} with QP")
        lines.extend(f"warning: axis {name}: {w}" for w in result.warnings)
    output = output or input_csv.with_name(f"{input_csv.stem}-compensated.csv")
    write_trajectory_csv(output, data)
    lines.append(f"wrote {output} in {time.perf_counter() - started:.2f} s")
    if not quiet:
        click.echo("\n".join(lines), err=True)



def _shaper_names(ctx, param, value: str) -> tuple[str, ...]:
    names = tuple(n.strip().lower() for n in value.split(",") if n.strip())
    if names == ("none",):
        return ()
    for name in names:
        if name not in SHAPERS:
            raise click.BadParameter(f"unknown shaper {name!r}: expected some of {','.join(SHAPERS)}, or none")
    return names


def _per_axis(low: float, high: float | None):
    """A click callback reading AXIS=VALUE,... with low < value (< high)."""

    def parse(ctx, param, value: str | None) -> dict[str, float]:
        out = {}
        for item in (value or "").split(","):
            if not item.strip():
                continue
            axis, _, number = item.partition("=")
            try:
                out[axis.strip().upper()] = float(number)
            except ValueError:
                raise click.BadParameter(f"{item.strip()!r}: expected AXIS=VALUE, e.g. X=48") from None
            if not (low < out[axis.strip().upper()] and (high is None or out[axis.strip().upper()] < high)):
                raise click.BadParameter(f"{item.strip()!r}: must be > {low:g}" + (f" and < {high:g}" if high else ""))
        return out

    return parse


@main.command()
@click.argument("input_path", metavar="INPUT", type=click.Path(dir_okay=False, path_type=Path))
@machine_option
@click.option("--compensated", type=click.Path(dir_okay=False, path_type=Path), metavar="OUT.gcode",
              help="Run this compensated program (from `fbspost compensate`) block by block at its feed as the "
                   "FBS row, instead of compensating now.")
@click.option("--shapers", default=",".join(SHAPERS), show_default=True, callback=_shaper_names,
              help="Klipper input shapers to compare, comma-separated, or none.")
@click.option("--shaper-freq", "shaper_freq", callback=_per_axis(0.0, None), metavar="AXIS=HZ,...",
              help="Shaper frequency per axis, e.g. X=48,Y=36 (default: the axis' dominant mode).")
@click.option("--shaper-damping", "shaper_damping", callback=_per_axis(0.0, 1.0), metavar="AXIS=RATIO,...",
              help="Shaper damping ratio per axis, e.g. X=0.1,Y=0.1 (default: the dominant mode's).")
@click.option("--flavor", type=click.Choice(FLAVORS), help="Firmware dialect (default: detected from INPUT).")
@margin_options
@click.option("--json", "as_json", is_flag=True,
              help="Print the figures as JSON (keys in docs/simulate.md) instead of tables.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), metavar="FILE",
              help="Also write plots: FILE.png (one page) or FILE.pdf (one panel per page).")
@click.option("--model-error", "model_error", is_flag=True,
              help="Also run every method's command on machines whose modes are off the profile's (every frequency "
                   "x0.9 to x1.1 in steps of 2.5%, every damping x0.8 and x1.25): RMS contour error per method.")
def simulate(input_path, machine, compensated, shapers, shaper_freq, shaper_damping, flavor, lead_time_s, settle_time_s,
             as_json, plot_path, model_error):
    """Compare the original, FBS and Klipper's input shapers on INPUT, through the profile's model.

    Plans INPUT as the controller would and runs every axis with modes through its model: the
    original plan; FBS (compensated now, or the --compensated program run block by block at its
    feed); each input shaper applied to the plan (Klipper's definitions and time shift; its
    frequency and damping from the axis' dominant mode unless given). Per method, for the path
    and each axis: tracking error RMS/max, contour error RMS/max (on extruding moves if the
    program extrudes, else on feed moves), the command's own distance from the path (a shaper's
    smoothing), residual vibration after the last move, duration and how much earlier/later the
    motion starts/ends than the plan, largest command velocity and acceleration. Units: um, s,
    mm/s, mm/s^2.
    """
    from ..tools.plots import FORMATS as PLOT_FORMATS  # matplotlib is imported when plotting
    from ..tools.plots import write_plot
    from ..tools.simulate import model_error as run_on_perturbed
    from ..tools.simulate import shaper_settings, simulate_program

    if plot_path and plot_path.suffix.lower() not in PLOT_FORMATS:
        raise click.BadParameter(f"{plot_path}: expected a .png or .pdf file", param_hint="--plot")
    profile = load_profile(machine)
    try:
        settings = shaper_settings(profile, shaper_freq, shaper_damping)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    for name in shapers:
        for axis, (_, damping) in settings.items():
            if damping > MAX_DAMPING[name]:
                raise click.UsageError(f"{name} is defined for damping ratios up to {MAX_DAMPING[name]:g}, axis {axis} "
                                       f"has {damping:g}: give --shaper-damping or leave {name} out of --shapers")
    flavor = flavor or detect_flavor(input_path)
    margins = RunMargins.for_profile(profile, lead_time_s, settle_time_s, flavor)
    sim = simulate_program(input_path, profile, shapers, settings, compensated, flavor, margins)
    if plot_path:
        write_plot(sim, plot_path)
    perturbed = run_on_perturbed(sim) if model_error else None
    if as_json:
        document = sim.as_dict()
        if perturbed:
            document["model_error"] = [{"frequency_scale": f, "damping_scale": d, "rms_contour_error_um": errors}
                                       for f, d, errors in perturbed]
        click.echo(json.dumps(document, indent=2))
    else:
        click.echo(_simulate_tables(sim) + (_model_error_table(perturbed) if perturbed else ""))


def _model_error_table(perturbed) -> str:
    """``simulate --model-error``'s table: a row per perturbed machine, RMS contour error per method."""
    names = list(perturbed[0][2])
    shapers = [n for n in names if n not in ("original", "fbs")]
    lines = ["", "model error: each command as made for the profile, run on a machine with every mode's frequency "
                 "and damping scaled; RMS contour error, um",
             "frequency damping  " + "".join(f"{n:9s}" for n in names) + ("best shaper" if shapers else "")]
    for frequency_scale, damping_scale, errors in perturbed:
        best = min(shapers, key=errors.get) if shapers else None
        lines.append(
            (
                f"x{frequency_scale:<8.3f} x{damping_scale:<7.2f} "
                + "".join(_g(errors[n], 8) + " " for n in names)
                + (f"{best} {_g(errors[best], 0)}" if best else "")
            ).rstrip()
        )
    return "\n" + "\n".join(lines)


def _simulate_tables(sim) -> str:
    """The human-readable figures: one row per method, the path first, then each axis."""
    p = sim.profile
    moves = "extruding moves (the program extrudes)" if sim.printer else "feed moves (the program does not extrude)"
    lines = [f"fbspost simulate: {sim.program} on {p.name} ({sim.flavor}, {p.sample_rate_hz:g} Hz); "
             f"contour error on {moves}; residual vibration over {sim.settle_s:.3g} s after the last motion"]
    lines += [f"  {m.label}" for m in sim.methods]
    lines += [
        "",
        "path      contour um        tracking um       residual  command off path  duration   starts    ends     "
        "|v| max  |a| max",
        "          RMS       max     RMS       max     max um    RMS um    max um  s          early s   late s   "
        "mm/s     mm/s^2",
    ]
    for m in sim.methods:
        q = m.path
        lines.append(
            f"{m.name:9s} {_g(q.rms_contour_error_um, 9)} {_g(q.max_contour_error_um, 7)} "
            f"{_g(q.rms_tracking_error_um, 9)} {_g(q.max_tracking_error_um, 7)} {_g(q.residual_vibration_um, 9)} "
            f"{_g(q.rms_command_contour_error_um, 9)} {_g(q.max_command_contour_error_um, 7)} "
            f"{q.duration_s:<10.4f} {q.start_advance_s:<9.4f} {q.end_delay_s:<8.4f} "
            f"{_g(q.max_velocity_mm_s, 8)} {q.max_acceleration_mm_s2:.0f}"
        )
    for axis in sim.modelled:
        lines += ["", f"axis {axis}    tracking um       residual  |v| max  |a| max",
                  "          RMS       max     max um    mm/s     mm/s^2"]
        for m in sim.methods:
            q = m.axes[axis]
            lines.append(
                f"{m.name:9s} {_g(q.rms_tracking_error_um, 9)} {_g(q.max_tracking_error_um, 7)} "
                f"{_g(q.residual_vibration_um, 9)} {_g(q.max_velocity_mm_s, 8)} {q.max_acceleration_mm_s2:.0f}"
            )
    lines += [f"warning: {w}" for w in sim.warnings]
    return "\n".join(lines)


def _g(value: float, width: int) -> str:
    """4 significant digits, left-aligned; below 1e-6 (rounding of a zero) as 0."""
    return f"{value if abs(value) >= 1e-6 else 0.0:<{width}.4g}"

