"""The blocks' times: each block timed as its pieces are settled.

Takes the blocks read (``pieces.BlockReader.pending``) and the settled pieces' blocks and
times; gives each block's line time and whether it is a STOP, and the MOVE blocks' (line,
start s, end s) (``BlockClock``).
"""
from __future__ import annotations

from collections import deque

import numpy as np


class BlockClock:
    """The blocks' times. Takes the blocks read (``BlockReader.pending``) and, as their pieces are
    settled, the pieces' blocks and times (``settle``); gives each block timed with its line time
    and whether it is a STOP (``lines``) and the MOVE blocks' (line, start s, end s) (``moves``),
    or with ``keep`` the columns of the whole plan (``kept``). A block without pieces happens when
    the motion before it ends, after the dwells between."""

    def __init__(self, pending: deque, keep: bool):
        self._pending, self._keep = pending, keep
        self.first = 0  # the first block not yet timed
        self.latest_end, self.latest_dwell = 0.0, 0.0  # the last block with pieces: its end, dwells to it
        self.lines: deque = deque()  # (block, line time s, is_stop) settled and not yet taken
        self.moves: deque = deque()  # (line, start s, end s) of the MOVE blocks settled and not yet taken
        self.kept: list[tuple] = []

    def dwell_before(self, block: int) -> float:
        """The dwells of the blocks before ``block`` (a block not yet timed)."""
        return self._pending[block - self.first][3]

    def settle(self, stop: int, pieces: tuple) -> None:
        """Time the blocks before ``stop`` (the first with waypoints or pieces not settled), with
        the pieces settled since the last call: (block, start s, end s) each, and the (block,
        start s) of the block whose pieces the last call left going on."""
        block, piece_start, piece_end, trail = pieces
        count = stop - self.first
        if count <= 0:
            return
        taken = [self._pending.popleft() for _ in range(count)]
        idx = np.arange(self.first, stop)
        self.first = stop
        dwell_before = np.array([t[3] for t in taken])
        is_move = np.array([t[1] for t in taken], dtype=bool)
        is_stop = np.array([t[2] for t in taken], dtype=bool)
        last_piece = np.searchsorted(block, idx, side="right") - 1
        has = last_piece >= 0
        has[has] = block[last_piece[has]] == idx[has]
        if block.size:
            first_piece = np.minimum(np.searchsorted(block, idx, side="left"), block.size - 1)
            block_end = np.where(has, piece_end[np.maximum(last_piece, 0)], 0.0)
            block_start = np.where(has, np.where(idx == trail[0], trail[1], piece_start[first_piece]), 0.0)
        else:
            block_end = block_start = np.zeros(count)
        latest = np.maximum.accumulate(np.where(has, np.arange(count), -1))
        end_at = np.where(latest >= 0, block_end[np.maximum(latest, 0)], self.latest_end)
        # (a MOVE has no dwell)
        dwell_at = np.where(latest >= 0, dwell_before[np.maximum(latest, 0)], self.latest_dwell)
        clock_at = end_at + (dwell_before - dwell_at)
        line_time = np.where(has, block_end, clock_at)
        move_start = np.where(has, block_start, clock_at)
        if latest[-1] >= 0:
            self.latest_end, self.latest_dwell = float(end_at[-1]), float(dwell_at[-1])
        if self._keep:
            self.kept.append((line_time, move_start, is_move, is_stop))
        else:
            self.lines.extend(zip((t[0] for t in taken), line_time.tolist(), is_stop.tolist(), strict=True))
            moves = np.flatnonzero(is_move)
            self.moves.extend(zip((taken[i][0].line_no for i in moves), move_start[moves].tolist(),
                                  line_time[moves].tolist(), strict=True))

