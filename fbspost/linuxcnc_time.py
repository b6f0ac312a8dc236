"""The target's time law on LinuxCNC: each motion line's feed as LinuxCNC's planner runs the original.

Takes the program (its path, read as ``verify`` reads it, a chunk of lines at a time) and a
profile; gives ``retimed(blocks, ...)``: the program's blocks with the feed of each motion line
(a MOVE of finite feed that moves) replaced by the speed at which the model of LinuxCNC's
trajectory planner (``linuxcnc_tp``) runs the original there, so that fbspost plans, and the
output keeps, the time the original takes on LinuxCNC (issue 31). LinuxCNC does not run a program
at its feeds: at 1 ms it caps 0.05 mm chords at 49 mm/s (F6000 written), and at 0.25 ms it ran
the dense butterfly 3% faster than fbspost's plan of its feeds (it ramps at the axes'
acceleration). Every other block is given as it is.

The speed is the planner's progress along the path averaged over the line's own time and
``WINDOW_S / 2`` either side, within its run of motion (rests and rapids end a run): LinuxCNC's
speed ripples from line to line at the servo period (split cycles; a line consumed into a blend
arc takes no time of its own), and fbspost's planner, ramping between such feeds, ran the chords
5.6% longer than LinuxCNC (docs/linuxcnc.md).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import verify
from .gcode import Block, Kind
from .linuxcnc_tp import run_linuxcnc
from .planner import Plan, plan_blocks
from .profile import MachineProfile

WINDOW_S = 0.01  # the progress is averaged over the line's time and half this either side


def retimed(blocks: Iterator[Block], program: Path, profile: MachineProfile) -> Iterator[Block]:
    """``blocks`` (the program at ``program``, read in the same order) with the feeds of
    ``linuxcnc_feeds``."""
    feeds = linuxcnc_feeds(program, profile)
    for block in blocks:
        feed = next(feeds)
        yield block if feed is None else replace(block, feed_mm_s=feed)


def linuxcnc_feeds(program: Path, profile: MachineProfile) -> Iterator[float | None]:
    """Line by line, the feed (mm/s) at which fbspost's planner runs the original as the model of
    LinuxCNC's planner runs it (see the module docstring); None for a line that is not a motion line."""
    for blocks, before, last in verify.program_chunks(program, profile, "linuxcnc", verify.CHUNK_LINES,
                                                      verify.OVERLAP_LINES):
        planned = plan_blocks(blocks, profile, firmware="linuxcnc")
        feeds = _chunk_feeds(blocks, run_linuxcnc(blocks, profile).line_time_s, planned)
        yield from feeds[(0 if before is None else before + 1):(len(blocks) if last is None else last + 1)]


def _chunk_feeds(blocks: list[Block], line_time_s: np.ndarray, planned: Plan) -> list[float | None]:
    """The feeds of one chunk's ``blocks``, which LinuxCNC runs at ``line_time_s`` (when each line's
    motion ends) and fbspost's planner as ``planned``."""
    feeds: list[float | None] = [None] * len(blocks)
    position = np.full(3, np.nan)
    rows = []  # (line, its run of motion, its length, its start and end s on LinuxCNC, in the plan)
    run, before_s = 0, 0.0
    for i, block in enumerate(blocks):
        moves = block.kind is Kind.MOVE and block.points_mm is not None
        if moves and np.isfinite(block.feed_mm_s):
            path = np.vstack([position, block.points_mm[:, :3]])
            step_mm = float(np.linalg.norm(np.nan_to_num(np.diff(path, axis=0)), axis=1).sum())
            if step_mm > 1e-12:
                rows.append((i, run, step_mm, before_s, float(line_time_s[i]), planned.move_start_s[i],
                             planned.line_time_s[i]))
        elif block.kind is Kind.STOP or moves:  # a rest, a rapid: the run of motion ends
            run += 1
        where = block.points_mm[-1, :3] if moves else block.position_mm[:3]
        position = np.where(np.isnan(where), position, where)
        before_s = float(line_time_s[i])
    if not rows:
        return feeds
    line, run_of, step_mm, start_s, end_s, plan_start_s, plan_end_s = (np.array(c) for c in zip(*rows, strict=True))
    # the progress along the path against time: flat at rest, each line's length over its own time
    s_mm = np.cumsum(step_mm)
    lengths = np.column_stack([s_mm - step_mm, s_mm]).ravel()
    times, plan_times = (np.column_stack(pair).ravel() for pair in ((start_s, end_s), (plan_start_s, plan_end_s)))
    new_run = np.diff(run_of, prepend=-1) != 0
    index = np.cumsum(new_run) - 1
    first, last = np.flatnonzero(new_run), np.append(np.flatnonzero(new_run)[1:], len(rows)) - 1
    from_s = np.maximum(start_s - WINDOW_S / 2, start_s[first][index])
    to_s = np.minimum(end_s + WINDOW_S / 2, end_s[last][index])
    from_mm, to_mm = np.interp(from_s, times, lengths), np.interp(to_s, times, lengths)
    # the same stretch of path in fbspost's plan of the written feeds: the feed scaled by its
    # time there over LinuxCNC's (where the plan's own limits slow it, the feed is raised)
    planned_s = np.interp(to_mm, lengths, plan_times) - np.interp(from_mm, lengths, plan_times)
    written = np.array([blocks[int(k)].feed_mm_s for k in line])
    for k in np.flatnonzero((to_s > from_s) & (to_mm > from_mm) & (planned_s > 0)):
        feeds[int(line[k])] = float(written[k] * planned_s[k] / (to_s[k] - from_s[k]))
    return feeds
