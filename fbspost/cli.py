"""The ``fbspost`` command line.

Takes arguments and files; gives exit status 0 on success, 1 on bad input (one line
``error: FILE:LINE: message`` on stderr, no traceback, no output file), 130 on interrupt.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click
import numpy as np

from . import __version__
from .dynamics import AxisDynamics
from .gcode import FLAVORS
from .optimizer import AxisLimits, FBSSettings, compensate_axis
from .pipeline import AxisReport, CompensateOptions, compensate_file
from .profile import ProfileError, bundled_profiles, load_profile
from .trajectory import InputError, read_trajectory_csv, write_trajectory_csv


class _FriendlyGroup(click.Group):
    """Bad input ends in one line on stderr and exit status 1, never a traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (ProfileError, InputError, OSError) as exc:
            click.echo(f"error: {exc}", err=True)
            ctx.exit(1)
        except KeyboardInterrupt:
            click.echo("error: interrupted; no output written", err=True)
            ctx.exit(130)


_machine_option = click.option("--machine", "-m", required=True,
                               help="Bundled profile name (see `fbspost machines`) or path to a profile .toml.")


@click.group(cls=_FriendlyGroup)
@click.version_option(__version__, prog_name="fbspost")
def main():
    """Compensate servo- and vibration-induced motion errors before the program reaches the machine."""


@main.command()
def machines():
    """List the bundled machine profiles, one per line."""
    for name, path in bundled_profiles().items():
        profile = load_profile(path)
        axes = ", ".join(f"{a} ({len(p.modes)} modes)" for a, p in profile.axes.items())
        click.echo(f"{name:24s} {profile.description}  [{axes}; {profile.sample_rate_hz:g} Hz]")


@main.command()
@click.argument("input_gcode", type=click.Path(dir_okay=False, path_type=Path))
@_machine_option
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path),
              help="Output file (default: replace INPUT in place, atomically, as slicers expect).")
@click.option("--format", "output_format", type=click.Choice(["dense"]), default="dense", show_default=True,
              help="dense: G1 blocks on the compensated command.")
@click.option("--tolerance", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True,
              help="Largest distance (mm) between the written blocks and the compensated command.")
@click.option("--min-segment-time", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True,
              help="Shortest block (s).")
@click.option("--flavor", type=click.Choice(FLAVORS), help="Firmware dialect (default: detected from the file).")
@click.option("--lookahead", type=click.Choice(["limited", "complete"]), default="limited", show_default=True)
@click.option("--report", "report_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the summary as JSON to this file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar and no summary on stderr.")
def compensate(input_gcode, machine, output, output_format, tolerance, min_segment_time, flavor, lookahead,
               report_path, quiet):
    """Compensate a G-code program for the machine's dynamics.

    Plans the program as the controller would, compensates every axis that has modes in the
    profile, and writes a program that makes the machine follow the original path with the
    original timing. Every other line is copied byte-exact, in order.
    """
    profile = load_profile(machine)
    options = CompensateOptions(flavor=flavor, tolerance_mm=tolerance, min_segment_time_s=min_segment_time,
                                lookahead=lookahead)
    output = output or input_gcode
    show_progress = not quiet and sys.stderr.isatty()
    with click.progressbar(length=1000, label="compensating", file=sys.stderr, hidden=not show_progress) as bar:
        report = compensate_file(input_gcode, output, profile, options,
                                 progress=lambda fraction: bar.update(int(fraction * 1000) - bar.pos))
    if report_path:
        report_path.write_text(json.dumps(report.as_dict(), indent=2) + "\n")
    if not quiet:
        lines = [f"fbspost {__version__}: {input_gcode} -> {output} on {profile.name} ({report.flavor}): "
                 f"{report.lines_in} lines in, {report.lines_out} out; print time {report.print_time_s:.1f} s, "
                 f"computed in {report.compute_time_s:.2f} s"]
        for name, axis in report.axes.items():
            lines.append(f"axis {name}: predicted RMS error {axis.rms_error_before_um:.4g} -> {axis.rms_error_after_um:.4g} um, "
                         f"max {axis.max_error_before_um:.4g} -> {axis.max_error_after_um:.4g} um")
        lines.extend(f"warning: {w}" for w in report.warnings)
        click.echo("\n".join(lines), err=True)


@main.command()
@click.argument("input_csv", type=click.Path(dir_okay=False, path_type=Path))
@_machine_option
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


if __name__ == "__main__":
    main()
