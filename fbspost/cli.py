"""The ``fbspost`` command line.

Takes arguments and files; gives exit status 0 on success, 1 on bad input (one line
``error: FILE:LINE: message`` on stderr, no traceback, no output file; with several programs,
one such line per failed file and the others still written), 2 on bad usage, 128 + the signal's
number when interrupted (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP), leaving no output or
temporary file behind.
"""
from __future__ import annotations

import gc
import json
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np

from . import __version__
from .errors import InputError
from .firmware.shapers import MAX_DAMPING, SHAPERS
from .plan.planner import RunMargins
from .profile import AXIS_NAMES, MachineProfile, ProfileError, bundled_profiles, load_profile
from .read.gcode import FLAVORS, detect_flavor
from .tools.trajectory import read_trajectory_csv, write_trajectory_csv
from .write.atomicfile import atomic_write

# Each command imports the stages it runs (scipy's signal, ndimage and optimize take seconds to
# load), so that --help, `machines` and a failing argument answer at once.
if TYPE_CHECKING:
    from .job.report import CompensateOptions, Report


class _FriendlyGroup(click.Group):
    """Bad input ends in one line on stderr and exit status 1, never a traceback; an interrupt
    unwinds (removing temporary files) and ends in one line and 128 + the signal's number."""

    def invoke(self, ctx):
        previous = _catch_signals()
        try:
            return super().invoke(ctx)
        except (ProfileError, InputError, OSError) as exc:
            click.echo(f"error: {_describe(exc)}", err=True)
            ctx.exit(1)
        except KeyboardInterrupt as exc:
            click.echo("error: interrupted; no output written", err=True)
            ctx.exit(_interrupt_status(exc))
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)


# Signals that end a run as Ctrl-C does. Their default action would kill the process at once and
# leave the temporary file of an output being written.
_ENDING_SIGNALS = (signal.SIGINT, signal.SIGTERM, *((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ()))


class _Interrupted(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGINT, raised where the program is, so that it unwinds."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.status = 128 + signum


def _interrupted(signum, frame):
    # Further signals must not cut short the clean-up this one starts.
    for other in _ENDING_SIGNALS:
        signal.signal(other, signal.SIG_IGN)
    raise _Interrupted(signum)


def _catch_signals() -> dict:
    """Installs the handler (on the main thread only, where Python runs handlers); gives the
    handlers it replaced."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {signum: signal.signal(signum, _interrupted) for signum in _ENDING_SIGNALS}


def _interrupt_status(exc: KeyboardInterrupt) -> int:
    return getattr(exc, "status", 128 + signal.SIGINT)


def _describe(exc: Exception) -> str:
    """One line: an OSError as ``FILE: what failed`` when it names its file."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return _one_line(f"{exc.filename}: {exc.strerror}")
    return _one_line(str(exc))


_machine_option = click.option("--machine", "-m", required=True,
                               help="Bundled profile name (see `fbspost machines`) or path to a profile .toml.")


def _margin_options(command):
    """--lead-time and --settle-time (planner.RunMargins; None: from the dynamics)."""
    command = click.option("--settle-time", "settle_time_s", type=click.FloatRange(min=0),
                           help="Seconds the command may go on after each run of motion ends, the machine "
                                "otherwise at rest (default: half the lowest mode's damped period; for Klipper, "
                                "once the program prints, by each run's end: docs/compensate.md).")(command)
    return click.option("--lead-time", "lead_time_s", type=click.FloatRange(min=0),
                        help="Seconds the command may move before each run of motion starts (default: half "
                             "the lowest mode's damped period; for Klipper, once the program prints, by each "
                             "run's end: docs/compensate.md).")(command)


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
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...",
                type=click.Path(dir_okay=False, path_type=Path))
@_machine_option
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path),
              help="Output file, one INPUT only (default: replace INPUT in place, atomically, as slicers expect).")
@click.option("--output-dir", type=click.Path(file_okay=False, path_type=Path), metavar="DIR",
              help="Write each output to DIR/<input name> instead (DIR is created if needed).")
@click.option("--jobs", "-j", type=click.IntRange(min=0), default=1, show_default=True, metavar="N",
              help="Files compensated at once, each in its own process (0: one per CPU).")
@click.option("--format", "output_format", type=click.Choice(["dense", "g5"]), default="dense", show_default=True,
              help="dense: G1 blocks on the compensated command; g5: cubic Bezier G5 blocks fitted to it within "
                   "the tolerance (Marlin with BEZIER_CURVE_SUPPORT, LinuxCNC XY; G1 where none fits).")
@click.option("--tolerance", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True,
              help="Largest distance (mm) between the written blocks and the compensated command.")
@click.option("--min-segment-time", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True,
              help="Shortest block (s); LinuxCNC: at least 2 servo periods (the profile's servo_period).")
@click.option("--flavor", type=click.Choice(FLAVORS), help="Firmware dialect (default: detected from the file).")
@click.option("--lookahead", type=click.Choice(["limited", "complete"]), default="limited", show_default=True)
@_margin_options
@click.option("--fallback/--no-fallback", default=True, show_default=True,
              help="Blend to the planned original where compensating would do harm (off: compensate everywhere).")
@click.option("--expand/--no-expand", default=None,
              help="LinuxCNC: run the program through LinuxCNC's interpreter rs274 first and compensate the "
                   "expanded program (default: when it uses parameters, O-words, canned cycles, ...).")
@click.option("--tool-table", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --expand: the machine's LinuxCNC tool table (tool lengths and diameters).")
@click.option("--ini", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="With --expand: the machine's LinuxCNC INI file (subroutine paths, remaps; rs274 runs in its "
                   "directory, as LinuxCNC does).")
@click.option("--verify/--no-verify", default=None,
              help="Before committing, run the original and the output through the model of the firmware's planner "
                   "and the machine's modes; where the output is not more accurate there (a lower RMS contour "
                   "error, a largest at most 10% above the original's) or lasts longer than its margins, 2% "
                   "and 50 ms more, write the original unchanged. Default: on for Marlin, RepRapFirmware and LinuxCNC "
                   "at any length (it streams), off for Klipper (which runs the blocks as written).")
@click.option("--report", "report_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the summary as JSON to this file (one INPUT only).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar and no summary on stderr.")
def compensate(inputs, machine, output, output_dir, jobs, output_format, tolerance, min_segment_time, flavor,
               lookahead, lead_time_s, settle_time_s, fallback, expand, tool_table, ini, verify, report_path, quiet):
    """Compensate G-code programs for the machine's dynamics.

    Plans each program as the controller would, compensates every axis that has modes in the
    profile, and writes a program that makes the machine follow the original path with the
    original timing. Every other line is copied byte-exact, in order.

    Several INPUT files (for print farms) are each replaced in place, or written to
    --output-dir; --jobs N compensates N of them at once in separate processes. A file that
    fails gets one line `error: FILE:LINE: message` and
    is left unchanged; the others are still compensated. Exit status 0 if every file
    succeeded, otherwise 1 with a last line naming the failed files.
    """
    from .job.report import CompensateOptions

    targets = _targets(inputs, output, output_dir, report_path)
    profile = load_profile(machine)
    # What the imports made lives to the end: the collector need not walk it every time the
    # blocks' objects trigger a full collection (a tenth of a CAM program's time).
    gc.freeze()
    options = CompensateOptions(flavor=flavor, output_format=output_format, tolerance_mm=tolerance,
                                min_segment_time_s=min_segment_time, lookahead=lookahead, lead_time_s=lead_time_s,
                                settle_time_s=settle_time_s, fallback=fallback, expand=expand,
                                tool_table=tool_table, ini=ini, verify=verify)
    if len(inputs) == 1:
        _compensate_single(inputs[0], targets[0], profile, options, report_path, quiet)
        return
    failed = _compensate_many(
        list(zip(inputs, targets, strict=True)), profile, options, jobs or os.cpu_count() or 1, quiet
    )
    if failed:
        click.echo(f"error: {len(failed)} of {len(inputs)} files failed: {', '.join(map(str, failed))}", err=True)
        click.get_current_context().exit(1)


def _targets(inputs: tuple[Path, ...], output: Path | None, output_dir: Path | None,
             report_path: Path | None) -> list[Path]:
    """Each input's output path; refuses the combinations that would write one file twice."""
    if output and (output_dir or len(inputs) > 1):
        raise click.UsageError("-o/--output takes one INPUT and no --output-dir; use --output-dir DIR for several")
    if report_path and len(inputs) > 1:
        raise click.UsageError("--report takes one INPUT")
    targets = [output_dir / source.name if output_dir else output or source for source in inputs]
    resolved = [target.resolve() for target in targets]
    for i, target in enumerate(resolved):
        if target in resolved[:i]:
            # Two jobs writing one file would race, and an input compensated twice is wrong.
            raise click.UsageError(
                f"{inputs[resolved.index(target)]} and {inputs[i]} would both be written to {target}"
            )
    if output_dir:
        output_dir.mkdir(parents=True, exist_ok=True)
    return targets


def _compensate_single(source: Path, target: Path, profile: MachineProfile, options: CompensateOptions,
                       report_path: Path | None, quiet: bool) -> None:
    """One file: errors propagate to the group's one-line handler; a progress bar on a terminal."""
    from .job.pipeline import compensate_file

    show_progress = not quiet and sys.stderr.isatty()
    with click.progressbar(length=1000, label="compensating", file=sys.stderr, hidden=not show_progress) as bar:
        report = compensate_file(source, target, profile, options,
                                 progress=lambda fraction: bar.update(int(fraction * 1000) - bar.pos))
    if report_path:
        text = json.dumps(report.as_dict(), indent=2) + "\n"
        atomic_write(report_path, lambda f: f.write(text.encode()))
    if not quiet:
        click.echo(_summary(source, target, profile, report), err=True)


_Finish = Callable[[Path, Path, "Report | str"], None]  # reports one file's outcome: (input, output, outcome)


def _compensate_many(pairs: list[tuple[Path, Path]], profile: MachineProfile, options: CompensateOptions,
                     jobs: int, quiet: bool) -> list[Path]:
    """Compensates every (input, output) pair, each in a process of its own when jobs > 1, printing each
    file's summary or error as it finishes; gives the failed inputs in input order."""
    outcomes = {}

    def finish(source: Path, target: Path, outcome: Report | str) -> None:
        outcomes[source] = outcome
        if isinstance(outcome, str):
            click.echo(f"error: {outcome}", err=True)
        elif not quiet:
            click.echo(_summary(source, target, profile, outcome), err=True)

    workers = min(jobs, len(pairs))
    try:
        if workers == 1:
            for source, target in pairs:
                finish(source, target, _compensate_one(source, target, profile, options))
        else:
            # (every core busy with a file: no second processes for the axes)
            _compensate_in_processes(pairs, profile, replace(options, second_process=False), workers, finish)
    except KeyboardInterrupt as exc:
        done = sum(not isinstance(o, str) for o in outcomes.values())
        click.echo(f"error: interrupted; {done} of {len(pairs)} files compensated, the others unchanged", err=True)
        click.get_current_context().exit(_interrupt_status(exc))
    return [source for source, _ in pairs if isinstance(outcomes[source], str)]


def _compensate_in_processes(pairs: list[tuple[Path, Path]], profile: MachineProfile,
                             options: CompensateOptions, workers: int, finish: _Finish) -> None:
    """Each file in a process of its own, at most ``workers`` at once, calling ``finish(input,
    output, outcome)`` as each ends. A process that dies (killed, out of memory) fails only its own
    file; a pool's would take the results of the files its other workers had just finished with
    it. On an interrupt no other file is started, the files finished meanwhile are still
    reported, and the running ones are ended (without temporary files) before it propagates."""
    waiting = list(reversed(pairs))
    running: dict[Connection, tuple[multiprocessing.Process, Path, Path]] = {}
    try:
        while waiting or running:
            while waiting and len(running) < workers:
                source, target = waiting.pop()
                receiver, sender = multiprocessing.Pipe(duplex=False)
                process = multiprocessing.Process(target=_compensate_in_child,
                                                  args=(sender, source, target, profile, options))
                process.start()
                sender.close()  # the child's end closes with the child: a death reads as end of file
                running[receiver] = (process, source, target)
            for receiver in wait(list(running)):
                finish(*_outcome(receiver, *running.pop(receiver)))
    except KeyboardInterrupt:
        for receiver in wait(list(running), timeout=0):
            finish(*_outcome(receiver, *running.pop(receiver)))
        for process, _, _ in running.values():
            process.terminate()
        for process, _, _ in running.values():
            process.join()
        raise


def _outcome(receiver: Connection, process: multiprocessing.Process, source: Path,
             target: Path) -> tuple[Path, Path, Report | str]:
    """A finished child's (input, output, outcome)."""
    try:
        outcome = receiver.recv()
    except EOFError:
        outcome = f"{source}: its worker process died (killed, or out of memory?)"
    receiver.close()
    process.join()
    return source, target, outcome


def _compensate_in_child(sender: Connection, source: Path, target: Path, profile: MachineProfile,
                         options: CompensateOptions) -> None:
    """A file's own process: sends its outcome. Ending is the parent's to decide: it ignores
    Ctrl-C and hangups, and SIGTERM (the parent's) unwinds the running file, so that
    atomic_write removes its temporary file."""
    for signum in _ENDING_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    sender.send(_compensate_one(source, target, profile, options))


def _compensate_one(source: Path, target: Path, profile: MachineProfile, options: CompensateOptions) -> Report | str:
    """One file of several, here or in a worker: its report, or its one-line error. Never raises
    but on an interrupt, so one bad file cannot stop the others."""
    from .job.pipeline import compensate_file

    try:
        return compensate_file(source, target, profile, options)
    except InputError as exc:
        return _one_line(str(exc))  # already FILE:LINE: message
    except OSError as exc:
        return _describe(exc) if exc.filename is not None else _one_line(f"{source}: {exc}")
    except ProfileError as exc:
        return _one_line(f"{source}: {exc}")
    except Exception as exc:  # a bug, or out of memory: still only this file fails
        return _one_line(f"{source}: internal error: {type(exc).__name__}: {exc}")


def _one_line(message: str) -> str:
    """Messages of unexpected exceptions may span lines; stderr gets one line per failed file."""
    return " ".join(message.split())


def _summary(source: Path, target: Path, profile: MachineProfile, report: Report) -> str:
    """The per-file summary on stderr: first the one result to go by (the firmware's, where the
    output was verified on a model of its planner, else fbspost's prediction), then the sizes,
    then the other figures, each saying what it is."""
    kept = "the original written unchanged" if report.original_kept else "the output written"
    lines = [f"fbspost {__version__}: {source} -> {target} on {profile.name} ({report.flavor}): {kept}"]
    axes = ", ".join(f"{name} {a.rms_error_before_um:.4g} -> {a.rms_error_after_um:.4g} um"
                     for name, a in report.axes.items())
    if report.verified is not None:
        lines.append(f"result, verified {report.verified.summary()}")
    elif axes:
        why = ("Klipper runs the written blocks as written, proven on its own planner code"
               if report.flavor == "klipper" else "not verified on the firmware's planner")
        lines.append(f"result, predicted by fbspost's model of the machine ({why}): RMS tracking error {axes}; "
                     f"print time {report.print_time_s:.1f} s")
    budget = "" if report.line_rate_budget_hz is None else f" (budget {report.line_rate_budget_hz:g})"
    lines.append(f"size: {report.lines_in} lines, {_size(report.bytes_in)} in; {report.lines_out} lines, "
                 f"{_size(report.bytes_out)} out; at most {report.max_line_rate_hz:g} lines/s{budget}; "
                 f"computed in {report.compute_time_s:.2f} s")
    if report.axes:
        lines.append("predictions, fbspost's model of the machine running the written blocks exactly (the tracking "
                     "error: the distance from the planned position at each moment, along the path too, where the "
                     "contour error does not count it):")
    for name, axis in report.axes.items():
        # (after: the written blocks as the firmware runs them, straight between their ends)
        command = (
            "" if axis.rms_error_command_um is None else f" (the command itself: {axis.rms_error_command_um:.4g} um)"
        )
        lines.append(
            f"  axis {name}: predicted RMS error {axis.rms_error_before_um:.4g} -> {axis.rms_error_after_um:.4g} um "
            f"as the firmware runs the output{command}, "
            f"max {axis.max_error_before_um:.4g} -> {axis.max_error_after_um:.4g} um"
        )
    lines.append(f"  the written blocks: at most {report.tolerance_used_mm * 1e3:.3g} um from the command (at "
                 f"{report.tolerance_used_at_s:.3f} s; RMS {report.rms_deviation_mm * 1e3:.3g} um), "
                 f"{report.loosened_s:.3f} s of them beyond the tolerance; print time {report.print_time_s:.1f} s, "
                 f"{report.added_time_s:.2f} s of it lead and settle margins ({report.lead_time_s * 1e3:.3g} + "
                 f"{report.settle_time_s * 1e3:.3g} ms per run of motion at most), less about "
                 f"{report.travel_saved_s:.2f} s in the travels (planned faster)")
    lines.extend(f"warning: {w}" for w in report.warnings)
    return "\n".join(lines)


def _size(n_bytes: int) -> str:
    return f"{n_bytes / 1e6:.3g} MB" if n_bytes >= 1e6 else f"{n_bytes / 1e3:.3g} kB"


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
    from .fbs.dynamics import AxisDynamics
    from .fbs.optimizer import compensate_axis
    from .fbs.settings import AxisLimits, FBSSettings
    from .job.report import AxisReport

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


_positive = click.FloatRange(min=0, min_open=True)


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
@click.option("--sample-rate", type=_positive, help="Hz, new profile (default 1000).")
@click.option("--planner-acceleration", type=_positive, help="mm/s^2, new profile (default 3000).")
@click.option("--square-corner-velocity", type=click.FloatRange(min=0), help="mm/s, new profile (default 5).")
@click.option("--max-velocity", type=_positive, help="mm/s, the axis (default: kept with --merge, else 300).")
@click.option("--max-acceleration", type=_positive, help="mm/s^2, the axis (default: kept with --merge, else 10000).")
@click.option("--max-jerk", type=_positive, help="mm/s^3, the axis (default: kept with --merge, else none).")
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
    from .tools import identify as ident
    from .tools import measurements

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
    from .tools import fit_trust, measurements

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
    limit = ("one mode per axis, at best level with your own input shaper (measured on Klipper: 1.9x worse "
             "than it, with the mass form); measure a response with fbspost excite to beat it")
    lines.append(f"warning: a coarse estimate gives {limit}")
    return {k: (v,) for k, v in found.items()}, f"{note}: {limit}"


def _fitted(frf_csv, accel_log, program, accel_column, axis, n_modes, max_modes, plot, force,
            lines: list[str], machine=None) -> tuple:
    """identify's fit of a measured frequency response (a CSV, or an accelerometer recording of
    the sweep ``program``, run as its firmware runs it on the profile ``machine``): the modes
    (with the fit's tolerances), the profile's note and the plot (PNG bytes, or None). A fit
    that fails ``fit_trust.assess_fit``'s checks raises ``InputError`` unless ``force`` (then it
    is a warning)."""
    from .tools import excite as excite_module
    from .tools import fit_trust, measurements, modal_fit, sweep_response
    from .tools import identify as ident

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
@_machine_option
@click.option("--axis", required=True, type=click.Choice(list(AXIS_NAMES), case_sensitive=False))
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--center", "centre_mm", required=True, type=float, help="Position (mm) the sweep is about.")
@click.option("--start-hz", type=_positive, default=5.0, show_default=True)
@click.option("--end-hz", type=_positive, default=120.0, show_default=True)
@click.option("--duration", "duration_s", type=_positive, default=30.0, show_default=True,
              help="Seconds from --start-hz to --end-hz (plus 0.5 s ramps at both ends).")
@click.option("--amplitude", "amplitude_mm", type=_positive, default=1.0, show_default=True,
              help="Largest amplitude (mm); smaller where the axis' limits require.")
@click.option("--block-time", "block_s", type=_positive,
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
    from .tools import excite as excite_module
    from .write.writer import shortest_block_s

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
@_machine_option
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
@_margin_options
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
    from .tools.plots import FORMATS as PLOT_FORMATS  # matplotlib is imported when plotting
    from .tools.plots import write_plot
    from .tools.simulate import model_error as run_on_perturbed
    from .tools.simulate import shaper_settings, simulate_program

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


if __name__ == "__main__":
    main()
