"""The compensated axes of a long program, each in a process of its own beside the writer.

Takes the program's size and the options (``in_second_process``: whether to), the writer's plan
sent through a ``PlanFeed``; gives, in each axis' process, its command chunk by chunk
(``proxied_chunks``, run by ``offload.Offloaded``), and in the writer's, the planned samples and
every axis' command joined (``received``), answering the processes' requests for more of the plan
meanwhile.
"""
from __future__ import annotations

import queue
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..fbs.optimizer import AxisCompensator
from ..profile import MachineProfile
from .axes import axis_compensators, compensation_chunks
from .offload import Offloaded
from .planfeed import PlanFeed, PlanProxy
from .report import CompensateOptions, Outcome

_SECOND_PROCESS_BYTES = 256_000  # (a second process starts in about 0.5 s: a program this long takes 5 s)
_POLL_S = 0.002  # how often the writer, waiting for an axis' process, answers the others' requests


def in_second_process(read_path, options: CompensateOptions) -> bool:
    """Whether each compensated axis runs in a process of its own (``second_process``; None:
    for a program long enough that the processes' start pays)."""
    if options.second_process is not None:
        return options.second_process
    return options.parallel_axes and Path(read_path).stat().st_size >= _SECOND_PROCESS_BYTES


def plan_columns(c: int, compensator: AxisCompensator) -> list[int]:
    """The planned samples' columns that compensating column ``c`` uses: its own, and the one its
    varying modes follow."""
    varying = compensator.varying
    return [c] if varying is None or varying.column == c else [c, varying.column]


def proxied_chunks(channel, profile: MachineProfile, options: CompensateOptions, axis: int,
                    columns: list[int]) -> Iterator[np.ndarray]:
    """In a process of its own (offload.py): the command of ``axis`` (a column), the only one
    compensated, in ``compensation_chunks``' chunks of the plan that the writer's process sends
    (``PlanFeed``, the samples of ``columns``). Returns the ``Outcome``."""
    plan = PlanProxy(channel, profile.sample_rate_hz, columns)
    compensators = {axis: axis_compensators(profile, options)[axis]}
    outcome = Outcome.of(compensators)
    # (one axis: threads would only hand the interpreter lock back and forth)
    for _, command in compensation_chunks(plan, compensators, replace(options, parallel_axes=False), outcome):
        yield command[:, axis].copy()
    return outcome


def received(workers: dict[int, Offloaded], feed: PlanFeed,
              requests: queue.Queue) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The planned samples and the axes' processes' commands (``workers``: by column) joined,
    as far as every one has given them; the processes' ``requests`` for more of the plan are
    answered meanwhile (``PlanFeed.due``: not far ahead of the writer, unless it waits for that
    process: the other may not run on ahead meanwhile, or the plan held here would grow with the
    program)."""
    held = {c: np.zeros(0) for c in workers}  # each axis' command
    asked: list[int] = []  # requests not yet answered

    def command_of(c: int) -> np.ndarray:
        waiting = False
        while True:
            while not requests.empty():
                asked.append(requests.get())
            for key in [key for key in asked if (waiting and key == c) or feed.due(key)]:
                asked.remove(key)
                feed.answer(key, workers[key].send)
            try:
                return workers[c].get(timeout=_POLL_S if waiting else 0.0)
            except queue.Empty:
                waiting = True
            except StopIteration:
                return np.zeros(0)

    while True:
        for c in workers:
            if not len(held[c]):
                held[c] = command_of(c)
        n = min(len(column) for column in held.values())
        if not n:
            if any(len(column) for column in held.values()):
                raise RuntimeError("the axes' processes gave different samples")
            return
        planned = feed.take(n)
        command = planned.copy()
        for c, column in held.items():
            command[:, c], held[c] = column[:n], column[n:]
        yield planned, command
