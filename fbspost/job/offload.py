"""A generator run in a second process, its items streamed back: the compensation of a long
program runs beside its writer on another core.

Takes a module-level generator function and its (picklable) arguments; gives its items in
order, and at the end the value it returns (``value``). An exception in the child is raised
here (as itself where it pickles, else as a RuntimeError with its traceback). The child runs
at most ``ahead`` items ahead of the reader, at a lower priority (``niceness``); it is ended if
the reader stops early. With ``requests`` (a queue) the two talk: the generator gets a
``Channel`` first, whose ``request()`` puts the worker's ``key`` in ``requests`` here, and whose
``get()`` gives what the parent ``send``s.

Python threads share one interpreter lock, so the axes' threads of one process overlap little
(CPU time equals wall time on the gear); a process has its own.

On Linux the child is forked, so it starts with this process' imports done (about 1 s of CPU
each otherwise, while the writer waits for its first samples: gear 1 h, 9.8-10.3 -> 8.6-9.6 s);
it keeps only its own pipes. Elsewhere it is started as ``python -m fbspost.job.offload``.
"""
from __future__ import annotations

import gc
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import time
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
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])  # this fbspost, not another installed one
# (Not on macOS, where a forked child may not use the system's frameworks, Accelerate's BLAS among them.)
FORK = sys.platform.startswith("linux")
_SINK_FD = 3  # the forked child's pipe to the parent


class Offloaded:
    """``function(*args)``'s items, made in a child process (a context manager: leaving it ends
    the child if it still runs)."""

    def __init__(self, function: Callable[..., Iterator], *args, ahead: int = _AHEAD,
                 requests: queue.Queue | None = None, key=None, start: bool = True, niceness: int = NICENESS):
        if FORK:
            self._process = _Forked()
        else:
            path = os.pathsep.join(filter(None, [_PACKAGE_ROOT, os.environ.get("PYTHONPATH")]))
            env = {**os.environ, "PYTHONPATH": path}
            self._process = subprocess.Popen([sys.executable, "-m", "fbspost.job.offload"], stdin=subprocess.PIPE,
                                             stdout=subprocess.PIPE, env=env)
        for pipe in (self._process.stdin, self._process.stdout):
            _widen(pipe)
        self._requests, self._key = requests, key
        self.send((function, args, requests is not None, niceness))
        if requests is None:
            self._process.stdin.close()
        self._items: queue.Queue = queue.Queue(ahead)
        self._receiver = threading.Thread(target=self._receive, daemon=True)
        if start:
            self.start()
        self._ended = False
        self.value = None

    def start(self) -> None:
        """Start reading the child's messages (``start=False``: so that several children are
        forked before any thread starts here: a fork copies only the thread that forks, and a
        lock another thread holds stays held in the child)."""
        self._receiver.start()

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
        except (EOFError, OSError, ValueError, pickle.UnpicklingError):  # (ValueError: closed by close())
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
            try:
                self._process.stdin.close()
            except BrokenPipeError:  # (what was sent after the child ended, unread: send's to drop)
                pass

    def __enter__(self) -> Offloaded:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Forked:
    """A forked child running ``_serve``, with the part of ``subprocess.Popen`` used here: its
    ``stdin`` and ``stdout`` pipes (its input and its messages), ``poll``, ``kill``, ``wait``."""

    def __init__(self):
        child_in, parent_out = os.pipe()
        parent_in, child_out = os.pipe()
        # (Else the child's copy of their buffers is written twice; None: started without them.)
        for stream in filter(None, (sys.stdout, sys.stderr)):
            stream.flush()
        pid = os.fork()
        if pid == 0:
            try:
                os.dup2(child_in, 0)
                os.dup2(child_out, _SINK_FD)
                # Every other descriptor is the parent's: an axis' child holding the other's
                # input open would keep that one from ever seeing its end.
                os.closerange(_SINK_FD + 1, os.sysconf("SC_OPEN_MAX"))
                # As a started child: Ctrl-C unwinds, the other signals end it (not the command's handlers).
                signal.signal(signal.SIGINT, signal.default_int_handler)
                for other in (signal.SIGTERM, signal.SIGHUP):
                    signal.signal(other, signal.SIG_DFL)
                _child(_SINK_FD)
            finally:
                os._exit(1)  # (the set-up failed: _child never returns)
        os.close(child_in)
        os.close(child_out)
        self.pid, self.returncode = pid, None
        self.stdin, self.stdout = os.fdopen(parent_out, "wb"), os.fdopen(parent_in, "rb")

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def kill(self) -> None:
        os.kill(self.pid, signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        """(``timeout`` as Popen's: polled; subprocess.TimeoutExpired after it.)"""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is None:
                self.returncode = os.waitstatus_to_exitcode(os.waitpid(self.pid, 0)[1])
            elif time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"process {self.pid}", timeout)
            else:
                time.sleep(0.01)
        return self.returncode


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
        function, args, talks, niceness = pickle.load(source)
        if hasattr(os, "nice"):  # (POSIX)
            os.nice(niceness)
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


def _child(sink_fd: int) -> None:
    """The child's life: the parent's messages on stdin, its own on ``sink_fd``; anything
    printed goes to stderr. It never returns."""
    code = 0
    try:
        os.dup2(2, 1)
        _serve(open(0, "rb", closefd=False), open(sink_fd, "wb"))
    except (BrokenPipeError, KeyboardInterrupt):  # the parent ended first: nobody to tell
        code = 1
    finally:
        sys.stderr.flush()
        # (No interpreter shutdown: a Channel's reader thread holds stdin's lock, which is fatal
        # there; and a forked child must not unwind into its parent's code.)
        os._exit(code)


if __name__ == "__main__":
    _child(os.dup(1))  # (the messages go to the parent on what was stdout)
