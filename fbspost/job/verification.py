"""The check beside the job (``CompensateOptions.verify``): both programs on the firmware's planner.

Takes the program read, the profile and the flavor; forks ``verify.measured_beside`` before the
axes' processes, tells it the output's temporary file and its length as it is written
(``Announced``), and gives ``atomic_write`` its check (``Verification``): the verdict, and the
original copied over the output where that is no better.
"""
from __future__ import annotations

import queue
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ..firmware.verify import Verdict, measured_beside
from ..plan.planner import PlanStream
from ..profile import MachineProfile
from .offload import NICENESS, Offloaded

_ANNOUNCE_BYTES = 1 << 20  # of the output written, told the check's process at once (a few hundred ms of writing)
# Chunks of the original the check (LinuxCNC: their line times) may be ahead of the feeds that
# need them: 64 chunks of 50,000 lines, at most about 26 MB held here
_CHECK_AHEAD = 64
# The check's priority: below the axes' processes (offload.NICENESS), which the writer waits for,
# so that where the cores are short it takes what they leave; its verdict is wanted only after the
# last line. Not for LinuxCNC, whose feeds wait for its plan of the original.
CHECK_NICENESS = 19


class Verification:
    """``atomic_write``'s check for ``CompensateOptions.verify`` (verify.py): the written file and
    the program read (``read_path``) re-planned on the firmware's planner, in a process of its own
    beside the compensation (``verify.measured_beside``: the original measured at once, the output
    as it is written); where the output is no better there, the input (``input_path``) copied over
    the written file. The wait for its verdict goes to ``stages["verify"]``."""

    def __init__(self, read_path, input_path, profile: MachineProfile, flavor: str, option: bool | None,
                 stages: dict[str, float]):
        self.read_path, self.input_path, self.profile, self.flavor = read_path, input_path, profile, flavor
        self.stages = stages
        self.plan: PlanStream | None = None  # (its margins: the time fbspost added)
        self.failed: Exception | None = None
        self.auto = option is None and flavor != "klipper"
        self.wanted = bool(option) or self.auto
        self.verdict: Verdict | None = None
        self.warnings: list[str] = []
        self.worker: Offloaded | None = None
        self.written: Announced | None = None
        if self.wanted:  # (forked here, before the axes' processes and any thread: see Offloaded.start)
            self.worker = Offloaded(measured_beside, read_path, profile, flavor, requests=queue.Queue(), start=False,
                                    ahead=_CHECK_AHEAD, niceness=NICENESS if flavor == "linuxcnc" else CHECK_NICENESS)

    @property
    def original_kept(self) -> bool:
        return self.verdict is not None and not self.verdict.better

    def start(self) -> None:
        if self.worker is not None:
            self.worker.start()

    def line_times(self) -> Iterator[np.ndarray]:
        """For LinuxCNC, the check's plan of the original (``verify.measure``'s items) as it comes;
        none once the check failed (it says so in its verdict's place)."""
        while self.worker is not None and self.failed is None:
            try:
                yield self.worker.get()
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 (as in __call__)
                self.failed = exc

    def opened(self, written: Path) -> None:
        """The output's temporary file, made: its name to the check's process."""
        self.written = Announced(written, None if self.worker is None else self.worker.send)

    def announced(self, f):
        """``f``, the output's temporary file, telling the check's process how much of it is written."""
        self.written.file = f
        return self.written if self.worker is not None else f

    def __call__(self, written: Path) -> None:
        started_s = time.perf_counter()
        self.worker.send((str(written), self.written.size, True))  # (written and closed)
        try:
            for _ in self.worker:  # (LinuxCNC: the plan of the original's chunks past what the feeds needed)
                pass
        except Exception as exc:  # noqa: BLE001 (a model's gap must not cost the user the output)
            self.failed = exc
        measured = self.worker.value
        if self.failed is not None:
            self.warnings.append(f"not verified on the firmware's planner: its model failed "
                                 f"({type(self.failed).__name__}: {' '.join(str(self.failed).split())})")
        elif measured is not None:
            self.verdict = Verdict(self.flavor, *measured, self.plan.added_s)
        if self.original_kept:
            shutil.copyfile(self.input_path, written)
            self.warnings.append("the original was written unchanged: on the firmware's planner "
                                 f"{'; '.join(self.verdict.shortfalls)} (the verified line)")
        self.stages["verify"] = time.perf_counter() - started_s

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()


class Announced:
    """The output's binary file, whose length written (flushed) is sent to the check's process
    (``send((path, bytes, False))``) every ``_ANNOUNCE_BYTES`` (its end: ``Verification``)."""

    def __init__(self, path: Path, send: Callable | None):
        self.path, self.send, self.file = str(path), send, None
        self.size = self._told = 0

    def write(self, data: bytes) -> int:
        n = self.file.write(data)
        self.size += n
        if self.size - self._told >= _ANNOUNCE_BYTES:
            self.file.flush()
            self.send((self.path, self.size, False))
            self._told = self.size
        return n
