"""A generator run in a second process, its items streamed back: the compensation of a long
program runs beside its writer on another core.

Takes a module-level generator function and its (picklable) arguments; gives its items in
order, and at the end the value it returns (``value``). An exception in the child is raised
here (as itself where it pickles, else as a RuntimeError with its traceback). The child runs
at most ``ahead`` items ahead of the reader, at a lower priority (``NICENESS``); it is ended if
the reader stops early. With ``requests`` (a queue) the two talk: the generator gets a
``Channel`` first, whose ``request()`` puts the worker's ``key`` in ``requests`` here, and whose
``get()`` gives what the parent ``send``s.

Python threads share one interpreter lock, so the axes' threads of one process overlap little
(CPU time equals wall time on the gear); a process has its own.
"""
from __future__ import annotations

import gc
import os
import pickle
import queue
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path

_AHEAD = 16  # items the child may be ahead: room to work on while the parent writes (4: it waited for the writer)
# The parent reads the items and is the slower (the writer): where both want a core, it gets it
# first, and the child takes what is left (gear 6 h: wall time 1.16 -> 1.11 x the writer's CPU time).
NICENESS = 10
# Pipes of 1 MB (Linux; else as they are): a batch of the plan (up to 0.5 MB) is sent without
# waiting for the child, at nice 10, to read it (64 kB pipes: 0.5 s a print hour of the writer's).
_PIPE_BYTES = 1 << 20
# (A child started as ``python -m``, not by multiprocessing: its spawn re-runs the parent's main
# script, which fails for a script read from stdin and re-runs the work of one without a main guard.)
_PACKAGE_ROOT = str(Path(__file__).resolve().parent.parent)  # this fbspost, not another installed one


class Offloaded:
    """``function(*args)``'s items, made in a child process (a context manager: leaving it ends
    the child if it still runs)."""

    def __init__(self, function: Callable[..., Iterator], *args, ahead: int = _AHEAD,
                 requests: queue.Queue | None = None, key=None):
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [_PACKAGE_ROOT, os.environ.get("PYTHONPATH")]))}
        self._process = subprocess.Popen([sys.executable, "-m", "fbspost.offload"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, env=env)
        for pipe in (self._process.stdin, self._process.stdout):
            _widen(pipe)
        self._requests, self._key = requests, key
        self.send((function, args, requests is not None))
        if requests is None:
            self._process.stdin.close()
        self._items: queue.Queue = queue.Queue(ahead)
        self._receiver = threading.Thread(target=self._receive, daemon=True)
        self._receiver.start()
        self._ended = False
        self.value = None

    def send(self, message) -> None:
        """``message`` to the child's ``Channel.get``. (A child that ended tells why through its
        items: a pipe it no longer reads is not an error here.)"""
        try:
            pickle.dump(message, self._process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._process.stdin.flush()
        except (BrokenPipeError, ValueError):  # (ValueError: closed by close())
            pass

    def _receive(self) -> None:
        """Move the child's messages to the queue as they come (the child sends only while the
        queue has room, so that it may compute the next items meanwhile), its requests to
        ``requests``."""
        try:
            while True:
                message = pickle.load(self._process.stdout)
                if message[0] == "request":
                    self._requests.put(self._key)
                    continue
                self._items.put(message)
                if message[0] != "item":
                    return
        except (EOFError, OSError, pickle.UnpicklingError):
            self._items.put(("error", RuntimeError("the compensation's process ended unexpectedly")))

    def get(self, timeout: float | None = None):
        """The next item: queue.Empty if none comes within ``timeout`` s, StopIteration after
        the last (``value`` set)."""
        if self._ended:
            raise StopIteration
        kind, payload = self._items.get(timeout=timeout)
        if kind == "item":
            return payload
        self._ended = True
        if kind == "done":
            self.value = payload
            raise StopIteration
        raise payload

    def __iter__(self) -> Iterator:
        while True:
            try:
                yield self.get()
            except StopIteration:
                return

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        self._process.stdout.close()
        if not self._process.stdin.closed:
            self._process.stdin.close()

    def __enter__(self) -> Offloaded:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _widen(pipe) -> None:
    try:
        import fcntl
        fcntl.fcntl(pipe.fileno(), fcntl.F_SETPIPE_SZ, _PIPE_BYTES)
    except (ImportError, AttributeError, OSError):  # not Linux, or over the system's pipe-max-size
        pass


class Channel:
    """The child's side of the talk: ``request()`` asks the parent for something, ``get()`` waits
    for what the parent sent next (read as it comes, so that the parent never waits to send)."""

    def __init__(self, source, send: Callable):
        self._send, self._inbox = send, queue.Queue()
        threading.Thread(target=self._read, args=(source,), daemon=True).start()

    def _read(self, source) -> None:
        try:
            while True:
                self._inbox.put(("message", pickle.load(source)))
        except (EOFError, OSError, pickle.UnpicklingError):
            self._inbox.put(("end", None))

    def request(self) -> None:
        self._send(("request", None))

    def get(self):
        kind, message = self._inbox.get()
        if kind == "end":
            raise EOFError("the parent stopped sending")
        return message


def _serve(source, sink) -> None:
    """The child: read the generator and its arguments, send each item, then its value or its
    exception."""
    def send(message):
        pickle.dump(message, sink, protocol=pickle.HIGHEST_PROTOCOL)
        sink.flush()

    try:
        function, args, talks = pickle.load(source)
        gc.freeze()  # (the imports' objects: see cli.compensate)
        generator = function(Channel(source, send), *args) if talks else function(*args)
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
    _code = 0
    try:
        _serve(sys.stdin.buffer, _sink)
    except (BrokenPipeError, KeyboardInterrupt):  # the parent ended first: nobody to tell
        _code = 1
    sys.stderr.flush()
    os._exit(_code)  # (no interpreter shutdown: a Channel's reader thread holds stdin's lock, which is fatal there)
