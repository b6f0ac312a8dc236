"""The commands that make and list machine profiles: ``machines``, ``identify`` (a profile from a
measurement or from Klipper's own figures) and ``excite`` (the sweep program to measure with).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click
import numpy as np

from .. import __version__
from ..errors import InputError
from ..profile import AXIS_NAMES, FLAVORS, ProfileError, bundled_profiles, load_profile
from ..write.atomicfile import atomic_write
from .group import machine_option, main, positive


@main.command()
def machines():
    """List the bundled machine profiles, one per line."""
    for name, path in bundled_profiles().items():
        profile = load_profile(path)
        axes = ", ".join(f"{a} ({len(p.modes)} modes)" for a, p in profile.axes.items())
        click.echo(f"{name:24s} {profile.description}  [{axes}; {profile.sample_rate_hz:g} Hz]")




@main.command()
@click.argument("frf_csv", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--axis", type=click.Choice(list(AXIS_NAMES), case_sensitive=False),
              help="The axis measured (optional with --klipper-cfg: then X and Y as found).")
@click.option("--modes", "n_modes", type=click.IntRange(1, 12), help="Modes to fit (default: chosen automatically).")
@click.option("--max-modes", type=click.IntRange(1, 12), default=8, show_default=True,
              help="Most modes the automatic choice tries.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The profile to write.")
@click.option("--merge", type=click.Path(dir_okay=False, path_type=Path),
              help="Start from this profile (its other axes, limits and settings kept; comments not).")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write a PNG of measured and fitted magnitude and phase.")
@click.option("--klipper-csv", type=click.Path(dir_okay=False, path_type=Path),
              help="Coarse: one mode from Klipper calibrate_shaper's CSV (psd_<axis> peak, half-power damping).")
@click.option("--klipper-cfg", type=click.Path(dir_okay=False, path_type=Path),
              help="Coarse: one mode per axis from printer.cfg's [input_shaper] (also in the #*# block).")
@click.option("--accel-log", type=click.Path(dir_okay=False, path_type=Path),
              help="Accelerometer CSV recorded while the --program sweep ran (time_s or #time, accel_x, ...).")
@click.option("--program", type=click.Path(dir_okay=False, path_type=Path),
              help="The sweep program of `fbspost excite` that was recorded.")
@click.option("--accel-column", help="Column of --accel-log along the axis (default accel_<axis>).")
@click.option("--force", is_flag=True, help="Write a fit that fails the checks (docs/identify.md), with a warning.")
@click.option("--coarse-form", type=click.Choice(["base", "mass"]), default="base", show_default=True,
              help="Coarse estimates' mode: base-excited (a belt or screw drive: a zero) or a mass pushed by a force.")
@click.option("--machine", help="With --accel-log: the profile --program was written for, to plan it as its firmware "
                                "runs it (default: the bundled profile its header names, else printer-two-mode).")
@click.option("--name", help="Name of a new profile (default: the output file's name).")
@click.option("--sample-rate", type=positive, help="Hz, new profile (default 1000).")
@click.option("--planner-acceleration", type=positive, help="mm/s^2, new profile (default 3000).")
@click.option("--square-corner-velocity", type=click.FloatRange(min=0), help="mm/s, new profile (default 5).")
@click.option("--max-velocity", type=positive, help="mm/s, the axis (default: kept with --merge, else 300).")
@click.option("--max-acceleration", type=positive, help="mm/s^2, the axis (default: kept with --merge, else 10000).")
@click.option("--max-jerk", type=positive, help="mm/s^3, the axis (default: kept with --merge, else none).")
def identify(frf_csv, axis, n_modes, max_modes, output, merge, plot, klipper_csv, klipper_cfg, accel_log, program,
             accel_column, force, coarse_form, machine, name, sample_rate, planner_acceleration,
             square_corner_velocity, max_velocity, max_acceleration, max_jerk):
    """Build a profile's axis model from measurements.

    From a measured frequency response FRF_CSV (header frequency_hz,real,imag or
    frequency_hz,magnitude,phase_deg; commanded to actual position, or commanded to measured
    acceleration, the same ratio), from an accelerometer recording of `fbspost excite`'s sweep
    (--accel-log with --program; the sweep as its firmware runs it on --machine's profile is the
    commanded motion), or, as coarse estimates, from Klipper's calibrate_shaper CSV
    (--klipper-csv) or printer.cfg (--klipper-cfg). Fits the modes, prints each, the fit error
    and the tolerances written, and writes a new profile (limits from the options or their
    defaults) or merges the axis into --merge (comments there are not kept). A fit too far from
    the measurement, or too uncertain, is refused (exit status 1) unless --force.
    """
    from ..tools import identify as ident
    from ..tools import measurements

    sources = [s for s in (frf_csv, klipper_csv, klipper_cfg, accel_log) if s]
    if len(sources) != 1:
        raise click.UsageError("give exactly one of FRF_CSV, --klipper-csv, --klipper-cfg, --accel-log")
    if bool(accel_log) != bool(program):
        raise click.UsageError("--accel-log and --program go together")
    if not axis and not klipper_cfg:
        raise click.UsageError("--axis is required")
    if plot and (klipper_csv or klipper_cfg):
        raise click.UsageError("--plot needs a frequency response (FRF_CSV or --accel-log)")
    axis = axis.upper() if axis else None
    base = load_profile(merge) if merge else None
    lines = [f"fbspost {__version__}: identify from {sources[0]}"]
    if klipper_csv or klipper_cfg:
        axes_modes, note = _klipper_estimate(klipper_csv, klipper_cfg, axis, coarse_form, lines)
        picture = None
    else:
        axes_modes, note, picture = _fitted(frf_csv, accel_log, program, accel_column, axis, n_modes, max_modes,
                                            plot, force, lines, machine)
    options = dict(sample_rate=sample_rate, planner_acceleration=planner_acceleration,
                   square_corner_velocity=square_corner_velocity, max_velocity=max_velocity,
                   max_acceleration=max_acceleration, max_jerk=max_jerk)
    start = base
    if klipper_cfg:  # the firmware's settings too: the output restores its shaping, plans with its limits
        new = ident.profile_with_axes(None, {}, "", {}, name or output.stem)
        start = measurements.klipper_cfg_machine(klipper_cfg, base or new)
        lines.append(f"[firmware] from {klipper_cfg.name}: flavor klipper, input shaping "
                     + (", ".join(f"{a} {f:g} Hz" for a, f in start.firmware.shaper_frequency_hz.items()) or "none")
                     + f" (restored after the compensated motion), planner acceleration "
                     f"{start.planner_acceleration_mm_s2:g} mm/s^2")
    profile = ident.profile_with_axes(start, axes_modes, note, options, name or output.stem)
    text = ident.profile_text(profile, output)
    if not base:
        lines.append("new profile: limits and rates not given are defaults (see --help): check them")
    atomic_write(output, lambda f: f.write(text.encode()))
    lines.append(f"wrote {output}")
    if picture:
        atomic_write(plot, lambda f: f.write(picture))
        lines.append(f"wrote {plot}")
    click.echo("\n".join(lines), err=True)


def _klipper_estimate(klipper_csv, klipper_cfg, axis, form, lines: list[str]) -> tuple[dict, str]:
    """identify's coarse estimate from Klipper's files: the modes (of ``form``, with the tolerances
    of a machine not measured) per axis and the profile's note."""
    from ..tools import fit_trust, measurements

    if klipper_csv:
        mode, f1, f2 = measurements.klipper_psd_mode(klipper_csv, axis, form)
        found = {axis: mode}
        lines.append(f"axis {axis}: PSD peak {mode.frequency_hz:.4g} Hz, half power {f1:.4g}..{f2:.4g} Hz")
        note = f"axis {axis}: COARSE ESTIMATE from Klipper calibrate_shaper data {klipper_csv.name}"
    else:
        found = measurements.klipper_cfg_modes(klipper_cfg, form)
        if axis:
            if axis not in found:
                raise InputError(klipper_cfg, None, f"[input_shaper] has no shaper_freq_{axis.lower()}")
            found = {axis: found[axis]}
        note = f"axes {', '.join(found)}: COARSE ESTIMATE from Klipper [input_shaper] of {klipper_cfg.name}"
    found = {k: replace(m, frequency_tolerance=fit_trust.COARSE_FREQUENCY_TOLERANCE,
                        damping_tolerance=fit_trust.COARSE_DAMPING_TOLERANCE) for k, m in found.items()}
    for name_, mode in found.items():
        lines.append(f"axis {name_}: 1 mode ({form}-excited) {mode.frequency_hz:.4g} Hz, damping {mode.damping:.4g}, "
                     f"alpha {mode.alpha:.6g}, beta {mode.beta:.6g}; tolerances written: frequency "
                     f"{mode.frequency_tolerance:g}, damping {mode.damping_tolerance:g} (a machine not measured)")
    limit = ("one mode per axis, worse than your own input shaper (measured through Klipper's planner: 1.07 to "
             "1.5 times its error; where the shaper is poor, worse than no compensation); measure a response with "
             "fbspost excite to beat it")
    lines.append(f"warning: a coarse estimate gives {limit}")
    return {k: (v,) for k, v in found.items()}, f"{note}: {limit}"


def _fitted(frf_csv, accel_log, program, accel_column, axis, n_modes, max_modes, plot, force,
            lines: list[str], machine=None) -> tuple:
    """identify's fit of a measured frequency response (a CSV, or an accelerometer recording of
    the sweep ``program``, run as its firmware runs it on the profile ``machine``): the modes
    (with the fit's tolerances), the profile's note and the plot (PNG bytes, or None). A fit
    that fails ``fit_trust.assess_fit``'s checks raises ``InputError`` unless ``force`` (then it
    is a warning)."""
    from ..tools import excite as excite_module
    from ..tools import fit_trust, measurements, modal_fit, sweep_response
    from ..tools import identify as ident

    if accel_log:
        sweep = excite_module.commanded_sweep(program, axis, machine, lines)
        times_s, accel = measurements.read_accel_log(accel_log, accel_column or f"accel_{axis.lower()}")
        rec, fit, mark_rate = sweep_response.fit_recording(times_s, accel, sweep, n_modes, max_modes)
        frequency_hz, coherence = rec.frequency_hz, rec.coherence
        late_s = fit.delay_s + fit.clock_error * rec.excited_at_s
        measured = rec.response * np.exp(2j * np.pi * rec.frequency_hz * late_s)
        lines.append(f"recording: {len(times_s)} samples at {rec.sample_rate_hz:.1f} Hz, its clock "
                     f"{1e6 * (rec.clock_rate * (1 + fit.clock_error) - 1):+.1f} ppm from the machine's (its clock "
                     f"mark's: {1e6 * (mark_rate - 1):+.1f}; the phase over the band tells better); "
                     f"the sweep starts at "
                     f"{rec.offset_s + fit.delay_s:.6f} s of its time base"
                     + ("; accelerometer axis reversed: sign flipped" if rec.inverted else ""))
        note = f"axis {axis}: identified from the recording {accel_log.name} of {program.name}"
        advice = ("check that the firmware ran the sweep as written (its acceleration limit at least the "
                  "program's, input shaping off) and the accelerometer is fixed to the moving part, and record again")
    else:
        frequency_hz, measured = measurements.read_frf_csv(frf_csv)
        fit = modal_fit.fit_frf(frequency_hz, measured, n_modes, max_modes)
        coherence = None
        note = f"axis {axis}: identified from {frf_csv.name}"
        advice = "check the measurement and the fit (--plot, --modes)"
    lines.append(f"axis {axis}: {len(frequency_hz)} frequencies {frequency_hz[0]:.4g}..{frequency_hz[-1]:.4g} Hz, "
                 f"{len(fit.modes)} modes" + ("" if n_modes else " (chosen automatically)"))
    for i, m in enumerate(fit.modes, start=1):
        lines.append(f"  mode {i}: {m.frequency_hz:.5g} Hz, damping {m.damping:.4g}, alpha {m.alpha:.6g}, "
                     f"beta {m.beta:.6g}")
    lines.append(f"fit error: RMS {100 * fit.rms_error:.3g}%, max {100 * fit.max_error:.3g}% of the peak |G| "
                 f"{np.abs(measured).max():.4g}; RMS by mode count: "
                 + ", ".join(f"{n}: {100 * e:.3g}%" for n, e in fit.errors_by_count.items()))
    dc_gain = sum(m.alpha / m.omega_rad_s**2 for m in fit.modes)
    lines.append(f"DC gain of the fit {dc_gain:.4f} (scaled to 1 in the profile)")
    trust = fit_trust.assess_fit(fit, frequency_hz, coherence)
    source = accel_log or frf_csv
    if trust.refusals and not force:
        raise InputError(source, None, f"the fit is not usable: {'; '.join(trust.refusals + trust.warnings)}: "
                                       f"{advice}; --force writes it anyway")
    if trust.refusals or trust.warnings:
        what = "not usable, written as --force asks" if trust.refusals else "doubtful"
        lines.append(f"warning: {source}: the fit is {what}: {'; '.join(trust.refusals + trust.warnings)}: {advice}")
    lines.append(f"tolerances written: frequency {trust.frequency_tolerance:.3g}, damping "
                 f"{trust.damping_tolerance:.3g} (the fit's {fit_trust.COVERAGE:g} standard deviations "
                 f"{trust.frequency_spread:.2g} and {trust.damping_spread:.2g}; at least "
                 f"{fit_trust.MIN_FREQUENCY_TOLERANCE:g} and {fit_trust.MIN_DAMPING_TOLERANCE:g}, "
                 f"at most {fit_trust.MAX_TOLERANCE:g})")
    modes = tuple(replace(m, frequency_tolerance=trust.frequency_tolerance, damping_tolerance=trust.damping_tolerance)
                  for m in fit.modes)
    picture = ident.plot_png(frequency_hz, measured, fit.response(frequency_hz), note) if plot else None
    return {axis: modes}, note, picture



@main.command()
@machine_option
@click.option("--axis", required=True, type=click.Choice(list(AXIS_NAMES), case_sensitive=False))
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--center", "centre_mm", required=True, type=float, help="Position (mm) the sweep is about.")
@click.option("--start-hz", type=positive, default=5.0, show_default=True)
@click.option("--end-hz", type=positive, default=120.0, show_default=True)
@click.option("--duration", "duration_s", type=positive, default=30.0, show_default=True,
              help="Seconds from --start-hz to --end-hz (plus 0.5 s ramps at both ends).")
@click.option("--amplitude", "amplitude_mm", type=positive, default=1.0, show_default=True,
              help="Largest amplitude (mm); smaller where the axis' limits require.")
@click.option("--block-time", "block_s", type=positive,
              help="Time of each G1 block (s). Default: 1 ms, or the shortest the firmware runs as written "
                   "(the profile's max_line_rate). Not for LinuxCNC: one block per half period.")
@click.option("--flavor", type=click.Choice(FLAVORS), default="klipper", show_default=True,
              help="The firmware the program is written for: its settings around the sweep, its dwells, "
                   "its rounding.")
def excite(machine, axis, output, centre_mm, start_hz, end_hz, duration_s, amplitude_mm, block_s, flavor):
    """Write a sine-sweep program of one axis, to record with an accelerometer.

    The axis' position sweeps from --start-hz to --end-hz (exponentially) about --center, in G1
    blocks of --block-time, with the amplitude the axis' velocity, acceleration and jerk limits
    allow; it starts and ends at rest. Written for --flavor's firmware as `compensate` writes its
    blocks: its limits raised and input shaping off around the sweep (the profile's settings
    restored after it), each block's F carrying the time the firmware loses (LinuxCNC: one block
    per half period from rest to rest at the INI's acceleration, in whole servo periods). Record the whole
    run, then `fbspost identify --accel-log LOG.csv --program PROGRAM --axis AXIS --machine PROFILE`.
    """
    from ..tools import excite as excite_module
    from ..write.options import shortest_block_s

    profile = load_profile(machine)
    axis = axis.upper()
    if axis not in profile.axes:
        raise ProfileError(f"{profile.source}: axes.{axis}: the profile has no axis {axis}")
    shortest_s = shortest_block_s(profile, flavor)
    if flavor == "linuxcnc" and block_s is not None:
        raise click.UsageError("--block-time does not apply to --flavor linuxcnc: one block per half period")
    if block_s is None:
        block_s = max(1e-3, shortest_s)
    elif block_s < shortest_s * (1 - 1e-9):
        raise click.UsageError(f"--block-time {block_s:g} s is shorter than {flavor} runs as written on "
                               f"{profile.name}: at least {shortest_s:g} s (its line budget)")
    if not start_hz < end_hz <= 0.25 / block_s:
        raise click.UsageError(f"need --start-hz < --end-hz <= {0.25 / block_s:g} Hz (4 blocks of "
                               f"{block_s:g} s per period)")
    if flavor == "linuxcnc":
        period_s = profile.firmware.linuxcnc.servo_period_s
        positions, *linuxcnc = excite_module.linuxcnc_sweep(profile.axes[axis], centre_mm, start_hz, end_hz,
                                                             duration_s, amplitude_mm, period_s)
        text, warnings = excite_module.sweep_program(profile, axis, positions, period_s, start_hz, end_hz, flavor,
                                                     tuple(linuxcnc))
    else:
        positions = excite_module.sweep_samples(profile.axes[axis], centre_mm, start_hz, end_hz, duration_s,
                                                amplitude_mm, block_s)
        text, warnings = excite_module.sweep_program(profile, axis, positions, block_s, start_hz, end_hz, flavor)
    atomic_write(output, lambda f: f.write(text.encode()))
    blocks = "one block per half period from rest to rest" if flavor == "linuxcnc" else \
        f"{(len(positions) - 1) * block_s:g} s in {block_s * 1e3:g} ms blocks"
    click.echo("\n".join([f"fbspost {__version__}: wrote {output}: axis {axis} {start_hz:g}..{end_hz:g} Hz about "
                          f"{centre_mm:g} mm, {blocks} for {flavor}, largest amplitude "
                          f"{np.abs(positions - centre_mm).max():.4g} mm", *warnings]), err=True)


