"""The plan shared with the axes' processes: planned once, here, and sent to each.

``PlanFeed`` (the writer's process) takes the ``PlanStream`` that the writer reads and answers
each axis process' request with what has settled since its last one: the samples of the columns
it uses, the runs that changed, the moves (for the fallback's warnings) and whether the plan is
done. It holds the planned samples (rows X Y Z E, machine mm) until the writer ``take``s them.

``PlanProxy`` (an axis' process) is what its compensation reads in place of a ``PlanStream``:
``runs``, ``frontier``, ``samples``, ``release``, ``wait``, ``moves``, ``done``, ``n_samples``. It
asks for the next batch as soon as one comes, so that the writer's process plans the next while
this one compensates; columns not sent are NaN.
"""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

from ..read.blocks import AXES

BATCH_SAMPLES = 1 << 14  # samples a request is answered with at least (fewer at the end)
# Samples planned ahead of the writer at most, unless it waits for the process asking: the writer's process
# holds their blocks (a CAM program's 5 samples a block: about 40 MB). A request is answered up
# to there, so that the processes can work that far ahead: with 2 batches, in step with the
# writer, they and it waited for each other (gear 6 h: 15% of two cores idle, 77 -> 67 s).
LEAD_SAMPLES = 1 << 16


class _Held:
    """Samples from ``base`` to ``end``, kept in the pieces they came in (never copied whole),
    until dropped."""

    def __init__(self, width: int):
        self.base = self.end = 0
        self._width = width
        self._pieces: deque[np.ndarray] = deque()

    def append(self, rows: np.ndarray) -> None:
        self._pieces.append(rows)
        self.end += len(rows)

    def rows(self, first: int, stop: int) -> np.ndarray:
        """Samples first .. stop - 1."""
        assert first >= self.base and stop <= self.end, "samples asked for that are not held"
        parts, at = [], self.base
        for piece in self._pieces:
            if at >= stop:
                break
            if at + len(piece) > first:
                parts.append(piece[max(first - at, 0):stop - at])
            at += len(piece)
        return parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.zeros((0, self._width))

    def drop_before(self, sample: int) -> None:
        """Let go of the pieces that end at or before ``sample``."""
        while self._pieces and self.base + len(self._pieces[0]) <= sample:
            self.base += len(self._pieces.popleft())


class PlanFeed:
    """``plan``'s settled samples, runs and moves for the axes' processes; ``columns``: by
    process key, the sample columns it uses."""

    def __init__(self, plan, columns: dict[int, list[int]]):
        self.plan, self.columns = plan, columns
        self._held = _Held(len(AXES))  # the samples evaluated (rows X Y Z E), until every one took them
        self.taken = 0  # samples the writer has taken
        self.sent = dict.fromkeys(columns, 0)  # samples sent to each process
        self.runs_from = dict.fromkeys(columns, 0)  # each process' first run not known closed
        self.moves: dict[int, list] = {key: [] for key in columns}
        self.time_s = 0.0  # spent evaluating and sending the plan (its planning is the plan's own time_s)

    @property
    def evaluated(self) -> int:
        return self._held.end

    def due(self, key: int) -> bool:
        """Whether process ``key``'s request is answered now: it has samples to come, or the
        plan is less than ``LEAD_SAMPLES`` ahead of the writer."""
        return self.sent[key] < self.evaluated or self.evaluated - self.taken < LEAD_SAMPLES

    def answer(self, key: int, send: Callable) -> None:
        """``send`` process ``key`` the next samples up to ``LEAD_SAMPLES`` ahead of the writer,
        at least ``BATCH_SAMPLES`` (fewer at the end: planned on as far as needed), the runs as
        far as they reach and the moves settled since."""
        plan = self.plan
        clock, planning_s = time.perf_counter(), plan.time_s
        stop = max(self.sent[key] + BATCH_SAMPLES, self.taken + LEAD_SAMPLES)
        while plan.frontier < stop and plan.advance():
            pass
        self._settle(min(stop, plan.frontier))
        first, last_sample = self.sent[key], self.evaluated - 1
        changed = [(i, run_first, run_last if run_last is not None and run_last <= last_sample else None)
                   for i, (run_first, run_last) in enumerate(plan.runs[self.runs_from[key]:], self.runs_from[key])
                   if run_first <= last_sample]
        send((first, self._held.rows(first, self.evaluated)[:, self.columns[key]], changed, self.moves[key],
              plan.done and self.evaluated == plan.n_samples, plan.n_samples))
        self.sent[key], self.moves[key] = self.evaluated, []
        self.runs_from[key] = next((i for i, _, last in changed if last is None), self.runs_from[key] + len(changed))
        self._drop()
        self.time_s += time.perf_counter() - clock - (plan.time_s - planning_s)

    def take(self, n: int) -> np.ndarray:
        """The writer's next ``n`` planned samples (sent to every process already)."""
        rows = self._held.rows(self.taken, self.taken + n)
        self.taken += n
        self._drop()
        return rows

    def _drop(self) -> None:
        """Let go of what every process has and the writer took."""
        self._held.drop_before(min(self.taken, *self.sent.values()))

    def _settle(self, stop: int) -> None:
        """Evaluate the plan's samples up to ``stop`` (settled) and let the plan drop them; take
        the moves settled."""
        plan = self.plan
        if stop > self.evaluated:
            self._held.append(plan.samples(self.evaluated, stop))
            plan.release(stop)
        for key in self.moves:
            self.moves[key].extend(plan.moves)
        plan.moves.clear()


class PlanProxy:
    """The plan as ``PlanFeed`` sends it over ``channel`` (offload.Channel), a batch per request."""

    def __init__(self, channel, sample_rate_hz: float, columns: list[int]):
        self._channel, self._columns = channel, columns
        self.sample_rate_hz = sample_rate_hz
        self.runs: list[list] = []
        self.done, self.n_samples = False, None
        self.moves: deque = deque()
        self.time_s = 0.0  # spent waiting for the plan
        self._held = _Held(len(columns))
        channel.request()

    @property
    def frontier(self) -> int:
        return self._held.end

    def wait(self, known: Callable[[], bool]) -> None:
        """Take batches until ``known()`` or the end."""
        clock = time.perf_counter()
        while not known() and not self.done:
            self._add(*self._channel.get())
            if not self.done:
                self._channel.request()  # (the next batch is planned while this one is used)
        self.time_s += time.perf_counter() - clock

    def samples(self, first: int, stop: int) -> np.ndarray:
        rows = np.full((stop - first, len(AXES)), np.nan)
        rows[:, self._columns] = self._held.rows(first, stop)
        return rows

    def release(self, sample: int) -> None:
        self._held.drop_before(sample)

    def _add(self, first: int, columns: np.ndarray, runs: list, moves: list, done: bool,
             n_samples: int | None) -> None:
        assert first == self.frontier, "a batch out of order"
        self._held.append(columns)
        for i, run_first, run_last in runs:
            if i < len(self.runs):
                self.runs[i][1] = run_last
            else:
                self.runs.append([run_first, run_last])
        self.moves.extend(moves)
        self.done, self.n_samples = done, n_samples
