"""``fbspost compensate``: one program, or several (in place or into a folder, in processes of
their own with --jobs), each file's summary or one-line error on stderr.
"""
from __future__ import annotations

import gc
import json
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import TYPE_CHECKING

import click

from .. import __version__
from ..errors import InputError
from ..profile import FLAVORS, MachineProfile, ProfileError, load_profile
from ..write.atomicfile import atomic_write
from .group import ENDING_SIGNALS, describe, interrupt_status, machine_option, main, margin_options, one_line

# The command imports the stages it runs (scipy's signal, ndimage and optimize take seconds to
# load), so that --help and a failing argument answer at once.
if TYPE_CHECKING:
    from ..job.report import CompensateOptions, Report


@main.command()
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...",
                type=click.Path(dir_okay=False, path_type=Path))
@machine_option
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
@margin_options
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
    from ..job.report import CompensateOptions

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
    from ..job.pipeline import compensate_file

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
        click.get_current_context().exit(interrupt_status(exc))
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
    for signum in ENDING_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    sender.send(_compensate_one(source, target, profile, options))


def _compensate_one(source: Path, target: Path, profile: MachineProfile, options: CompensateOptions) -> Report | str:
    """One file of several, here or in a worker: its report, or its one-line error. Never raises
    but on an interrupt, so one bad file cannot stop the others."""
    from ..job.pipeline import compensate_file

    try:
        return compensate_file(source, target, profile, options)
    except InputError as exc:
        return one_line(str(exc))  # already FILE:LINE: message
    except OSError as exc:
        return describe(exc) if exc.filename is not None else one_line(f"{source}: {exc}")
    except ProfileError as exc:
        return one_line(f"{source}: {exc}")
    except Exception as exc:  # a bug, or out of memory: still only this file fails
        return one_line(f"{source}: internal error: {type(exc).__name__}: {exc}")


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

