"""The target's time law on LinuxCNC: each motion line's feed for fbspost's plan to take the time
LinuxCNC's trajectory planner takes to run the original there.

Takes the program (its path, read a chunk of lines at a time as ``verify`` reads it) and a
profile; gives ``retimed(blocks, ...)``: the program's blocks with the feed of each motion line
(a MOVE of finite feed that moves) set so that fbspost plans, and the output keeps, the time the
original takes on LinuxCNC (issue 31): the written feed, capped as LinuxCNC caps a segment (its
length over 1.02 servo periods), scaled by the time fbspost's planner takes over a stretch of
path around the line over the time the model of LinuxCNC's planner (``linuxcnc_tp``) takes
there. LinuxCNC does not run a program at its feeds: at 1 ms it caps 0.05 mm chords at 49 mm/s
(F6000 written), and at 0.25 ms it runs the butterflies up to 1.5% faster than fbspost's plan of
their feeds (it ramps and blends at the axes' acceleration). Every other block is given as it is.

The stretch is the path LinuxCNC covers from ``WINDOW_S / 2`` before the line starts to as long
after it ends, within its run of motion (rests and rapids end a run): LinuxCNC's speed ripples
from line to line at the servo period (split cycles; a line consumed into a blend arc takes no
time of its own). Measured on the model (docs/linuxcnc.md), LinuxCNC's speed as the feed:
windows of 5, 10 and 30 ms ran the output of the chords at scale 2 and 1 ms +2.1%, +1.4% and
+2.1% long. The written feed scaled rather than LinuxCNC's own speed written: where fbspost's
planner slows for its own limits (a corner, its ramps at the profile's planner acceleration) the
feed is raised, so that the two planners' limits do not both slow it (LinuxCNC's speed as the
feed: the chords' plan at 0.25 ms 4.6% longer than LinuxCNC's run, scaled 0.3% shorter). The
cap first: without it, at 1 ms the feeds were raised where fbspost's plan of F6000 slows at the
chords' corners though LinuxCNC's 49 mm/s does not, and the chords at scale 2 ran 3% faster than
on LinuxCNC at 34 um RMS contour error (15 um at LinuxCNC's speed).
Re-planning with the scaled feeds and scaling again did not converge (the plan of the chords at
scale 2 and 0.25 ms: +0.9%, +1.1%, +1.3% longer than LinuxCNC's run for 1, 2, 3 passes).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..plan.pieces import changes_known
from ..plan.planner import Plan, plan_blocks
from ..profile import MachineProfile
from ..read.blocks import AXES, EXTRA_AXES, Block, Kind
from . import verify
from .linuxcnc_queue import MIN_SEGMENT_CYCLES
from .linuxcnc_tp import run_linuxcnc

WINDOW_S = 0.01  # the progress is averaged over the line's time and half this either side
# a run is sped up to pay for its margins only if this share does it: a shorter run keeps them (the
# dense butterfly's first 40 lines sped up 5% lost their gain: --verify kept the original)
MAX_PAID = 0.05
# the share of a run's time its margins may add unpaid (a long run pays none): the dense butterfly at 1 ms,
# paid whole, +0.06% of time at 24.5 um, with this +0.32% at 24.3 um; the chords 19.6 -> 16.8 um, +0.86%
UNPAID_SHARE = 0.0025


def retimed(blocks: Iterator[Block], program: Path, profile: MachineProfile,
            line_times: Iterator[np.ndarray] | None = None, margins_s: float = 0.0) -> Iterator[Block]:
    """``blocks`` (the program at ``program``, read in the same order) with the feeds of
    ``linuxcnc_feeds``."""
    feeds = linuxcnc_feeds(program, profile, line_times, margins_s)
    for block in blocks:
        feed = next(feeds)
        yield block if feed is None else replace(block, feed_mm_s=feed)


def linuxcnc_feeds(program: Path, profile: MachineProfile, line_times: Iterator[np.ndarray] | None = None,
                   margins_s: float = 0.0) -> Iterator[float | None]:
    """Line by line, the feed (mm/s) at which fbspost's planner runs the original as the model of
    LinuxCNC's planner runs it (see the module docstring); None for a line that is not a motion line.
    ``line_times``: that model's times of each chunk's lines (``verify.measure``'s items, where the
    check plans the original: planned once), in order; the chunks past its end are planned here.
    ``margins_s``: the lead and settle margins of a run, paid for by running it faster (``_paid``)."""
    shortest_s = MIN_SEGMENT_CYCLES * profile.firmware.linuxcnc.servo_period_s
    planned = iter(()) if line_times is None else line_times
    for blocks, before, last in verify.program_chunks(program, profile, "linuxcnc", verify.CHUNK_LINES,
                                                      verify.OVERLAP_LINES):
        line_time_s = next(planned, None)
        if line_time_s is None:
            line_time_s = run_linuxcnc(blocks, profile).line_time_s
        lengths_mm, runs = _motion(blocks)
        capped = [block if length_mm <= 0 else replace(block, feed_mm_s=min(block.feed_mm_s, length_mm / shortest_s))
                  for block, length_mm in zip(blocks, lengths_mm, strict=True)]
        feeds = _chunk_feeds(capped, lengths_mm, runs, line_time_s, plan_blocks(capped, profile, firmware="linuxcnc"))
        feeds = _paid(feeds, blocks, capped, runs, line_time_s, margins_s)
        yield from feeds[(0 if before is None else before + 1):(len(blocks) if last is None else last + 1)]


def _motion(blocks: list[Block]) -> tuple[np.ndarray, np.ndarray]:
    """Each block's length (mm) if it is a motion line (a MOVE of finite feed) that fbspost
    compensates, else 0; and the run of motion it is in (a rest, a rapid or a straight move of A B C
    U V W, which the plan copies as written: ``plan.planner``, ends one)."""
    lengths_mm, runs = np.zeros(len(blocks)), np.zeros(len(blocks), dtype=int)
    position, run = np.full(len(AXES), np.nan), 0
    for i, block in enumerate(blocks):
        moves = block.kind is Kind.MOVE and block.points_mm is not None
        copied = moves and len(block.points_mm) == 1 and changes_known(block.points_mm[-1].tolist(),
                                                                       position.tolist(), EXTRA_AXES)
        if moves and not copied and np.isfinite(block.feed_mm_s):
            path = np.vstack([position[:3], block.points_mm[:, :3]])
            lengths_mm[i] = np.linalg.norm(np.nan_to_num(np.diff(path, axis=0)), axis=1).sum()
        if block.kind is Kind.STOP or moves and not lengths_mm[i] > 1e-12:
            run += 1
        runs[i] = run
        where = block.points_mm[-1] if moves else block.position_mm
        position = np.where(np.isnan(where), position, where)
    lengths_mm[lengths_mm <= 1e-12] = 0.0
    return lengths_mm, runs


def _chunk_feeds(blocks: list[Block], lengths_mm: np.ndarray, runs: np.ndarray, line_time_s: np.ndarray,
                 planned: Plan) -> list[float | None]:
    """The feeds of one chunk's ``blocks`` (``_motion``'s ``lengths_mm`` and ``runs``), which LinuxCNC
    runs at ``line_time_s`` (when each line's motion ends) and fbspost's planner as ``planned``."""
    feeds: list[float | None] = [None] * len(blocks)
    line = np.flatnonzero(lengths_mm)
    if not line.size:
        return feeds
    before_s = np.append(0.0, line_time_s[:-1])
    run_of, step_mm, start_s, end_s = runs[line], lengths_mm[line], before_s[line], line_time_s[line]
    plan_start_s, plan_end_s = planned.move_start_s[line], planned.line_time_s[line]
    new_run = np.diff(run_of, prepend=-1) != 0
    index = np.cumsum(new_run) - 1
    # the progress along the path against time, each line's length over its own time; each run's
    # apart (a run's end and the next's start are the same length: read there, the plan's time
    # jumped the rest between them, and the run's last line ran at its feed times the rest's time)
    s_mm = np.cumsum(step_mm) + index * (step_mm.sum() + 1.0)
    lengths = np.column_stack([s_mm - step_mm, s_mm]).ravel()
    times, plan_times = (np.column_stack(pair).ravel() for pair in ((start_s, end_s), (plan_start_s, plan_end_s)))
    first, last = np.flatnonzero(new_run), np.append(np.flatnonzero(new_run)[1:], len(line)) - 1
    from_s = np.maximum(start_s - WINDOW_S / 2, start_s[first][index])
    to_s = np.minimum(end_s + WINDOW_S / 2, end_s[last][index])
    from_mm, to_mm = np.interp(from_s, times, lengths), np.interp(to_s, times, lengths)
    # the same stretch of path in fbspost's plan of the capped feeds: the feed scaled by its
    # time there over LinuxCNC's (where the plan's own limits slow it, the feed is raised)
    planned_s = np.interp(to_mm, lengths, plan_times) - np.interp(from_mm, lengths, plan_times)
    written = np.array([blocks[int(k)].feed_mm_s for k in line])
    for k in np.flatnonzero((to_s > from_s) & (to_mm > from_mm) & (planned_s > 0)):
        feeds[int(line[k])] = float(written[k] * planned_s[k] / (to_s[k] - from_s[k]))
    return feeds


def _paid(feeds: list[float | None], blocks: list[Block], capped: list[Block], runs: np.ndarray,
          line_time_s: np.ndarray, margins_s: float) -> list[float | None]:
    """``feeds`` of each run raised by its LinuxCNC time T over that less ``margins_s`` beyond
    ``UNPAID_SHARE`` of T (if that is at most ``MAX_PAID``), none above its line's written F (``blocks``):
    only on the lines LinuxCNC's segment cap slows below their F (``capped``), where the output's
    margins are paid within the run, and not where the retiming already raised the feed above the
    cap (where fbspost's planner slows at a corner). Raised there too, the chords at 1 ms lost 15%
    of their gain; raised to F where LinuxCNC is not capped, rcone_demo's first 12 s at 0.25 ms
    lost 12% of its gain for 0.05% of time (the model)."""
    lines = np.array([i for i, feed in enumerate(feeds) if feed is not None], dtype=int)
    if not lines.size or margins_s <= 0.0:
        return feeds
    before_s = np.append(0.0, line_time_s[:-1])
    paid = list(feeds)
    by_run = lines[np.argsort(runs[lines], kind="stable")]  # (each run's lines in order: one pass, not one a run)
    for members in np.split(by_run, np.flatnonzero(np.diff(runs[by_run])) + 1):
        members = members.tolist()
        taken_s = line_time_s[members[-1]] - before_s[members[0]]
        owed_s = margins_s - UNPAID_SHARE * taken_s
        if owed_s <= 0.0 or taken_s - owed_s <= taken_s / (1.0 + MAX_PAID):
            continue  # nothing owed, or a run too short to pay it
        factor = taken_s / (taken_s - owed_s)
        for i in members:
            if capped[i].feed_mm_s < blocks[i].feed_mm_s and feeds[i] <= capped[i].feed_mm_s * (1.0 + 1e-3):
                paid[i] = max(feeds[i], min(feeds[i] * factor, blocks[i].feed_mm_s))
    return paid
