"""A generator run in a second process, its items streamed back: the compensation of a long
program runs beside its writer on another core.

Takes a module-level generator function and its (picklable) arguments; gives its items in
order, and at the end the value it returns (``value``). An exception in the child is raised
here (as itself where it pickles, else as a RuntimeError with its traceback). The child runs
at most ``ahead`` items ahead of the reader, at a lower priority (``NICENESS``); it is ended if
the reader stops early.

Python threads share one interpreter lock, so the axes' threads of one process overlap little
(CPU time equals wall time on the gear); a process has its own.
"""
from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path

_AHEAD = 8  # items the child may be ahead
# The parent reads the items and is the slower (the writer): where both want a core, it gets it
# first, and the child takes what is left (gear 6 h: wall time 1.16 -> 1.11 x the writer's CPU time).
NICENESS = 10
# (A child started as ``python -m``, not by multiprocessing: its spawn re-runs the parent's main
# script, which fails for a script read from stdin and re-runs the work of one without a main guard.)
_PACKAGE_ROOT = str(Path(__file__).resolve().parent.parent)  # this fbspost, not another installed one


class Offloaded:
    """``function(*args)``'s items, made in a child process (a context manager: leaving it ends
    the child if it still runs)."""

    def __init__(self, function: Callable[..., Iterator], *args, ahead: int = _AHEAD):
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [_PACKAGE_ROOT, os.environ.get("PYTHONPATH")]))}
        self._process = subprocess.Popen([sys.executable, "-m", "fbspost.offload"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, env=env)
        pickle.dump((function, args), self._process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._process.stdin.close()
        self._items: queue.Queue = queue.Queue(ahead)
        self._receiver = threading.Thread(target=self._receive, daemon=True)
        self._receiver.start()
        self.value = None

    def _receive(self) -> None:
        """Move the child's messages to the queue as they come (the child sends only while the
        queue has room, so that it may compute the next items meanwhile)."""
        try:
            while True:
                message = pickle.load(self._process.stdout)
                self._items.put(message)
                if message[0] != "item":
                    return
        except (EOFError, OSError, pickle.UnpicklingError):
            self._items.put(("error", RuntimeError("the compensation's process ended unexpectedly")))

    def __iter__(self) -> Iterator:
        while True:
            kind, payload = self._items.get()
            if kind == "item":
                yield payload
            elif kind == "done":
                self.value = payload
                return
            else:
                raise payload

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        self._process.stdout.close()

    def __enter__(self) -> Offloaded:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve(source, sink) -> None:
    """The child: read the generator and its arguments, send each item, then its value or its
    exception."""
    def send(message):
        pickle.dump(message, sink, protocol=pickle.HIGHEST_PROTOCOL)
        sink.flush()

    try:
        function, args = pickle.load(source)
        generator = function(*args)
        while True:
            try:
                item = next(generator)
            except StopIteration as stop:
                send(("done", stop.value))
                return
            send(("item", item))
    except BaseException as error:  # noqa: BLE001  (every failure is the parent's to report)
        send(("error", _portable(error)))


def _portable(error: BaseException) -> BaseException:
    """``error`` if it survives pickling, else a RuntimeError that tells what and where."""
    try:
        return pickle.loads(pickle.dumps(error))
    except Exception:  # noqa: BLE001
        return RuntimeError("".join(traceback.format_exception(error)).strip())


if __name__ == "__main__":
    if hasattr(os, "nice"):  # (POSIX)
        os.nice(NICENESS)
    # The messages go to the parent on what was stdout; anything printed goes to stderr.
    _sink = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    try:
        _serve(sys.stdin.buffer, _sink)
    except (BrokenPipeError, KeyboardInterrupt):  # the parent ended first: nobody to tell
        sys.exit(1)
