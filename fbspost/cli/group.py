"""The ``fbspost`` command group and what its commands share: bad input, an OSError or an
interrupt ends in one line on stderr and an exit status (never a traceback); the options more
than one command takes.
"""
from __future__ import annotations

import signal
import threading

import click

from .. import __version__
from ..errors import InputError
from ..profile import ProfileError


class _FriendlyGroup(click.Group):
    """Bad input ends in one line on stderr and exit status 1, never a traceback; an interrupt
    unwinds (removing temporary files) and ends in one line and 128 + the signal's number."""

    def invoke(self, ctx):
        previous = _catch_signals()
        try:
            return super().invoke(ctx)
        except (ProfileError, InputError, OSError) as exc:
            click.echo(f"error: {describe(exc)}", err=True)
            ctx.exit(1)
        except KeyboardInterrupt as exc:
            click.echo("error: interrupted; no output written", err=True)
            ctx.exit(interrupt_status(exc))
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)


# Signals that end a run as Ctrl-C does. Their default action would kill the process at once and
# leave the temporary file of an output being written.
ENDING_SIGNALS = (signal.SIGINT, signal.SIGTERM, *((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ()))


class _Interrupted(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGINT, raised where the program is, so that it unwinds."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.status = 128 + signum


def _interrupted(signum, frame):
    # Further signals must not cut short the clean-up this one starts.
    for other in ENDING_SIGNALS:
        signal.signal(other, signal.SIG_IGN)
    raise _Interrupted(signum)


def _catch_signals() -> dict:
    """Installs the handler (on the main thread only, where Python runs handlers); gives the
    handlers it replaced."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {signum: signal.signal(signum, _interrupted) for signum in ENDING_SIGNALS}


def interrupt_status(exc: KeyboardInterrupt) -> int:
    return getattr(exc, "status", 128 + signal.SIGINT)


def one_line(message: str) -> str:
    """Messages of unexpected exceptions may span lines; stderr gets one line per failed file."""
    return " ".join(message.split())


def describe(exc: Exception) -> str:
    """One line: an OSError as ``FILE: what failed`` when it names its file."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return one_line(f"{exc.filename}: {exc.strerror}")
    return one_line(str(exc))


positive = click.FloatRange(min=0, min_open=True)



machine_option = click.option("--machine", "-m", required=True,
                               help="Bundled profile name (see `fbspost machines`) or path to a profile .toml.")


def margin_options(command):
    """--lead-time and --settle-time (margins.RunMargins; None: from the dynamics)."""
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

