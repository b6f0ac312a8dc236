"""The contour error's measure: the exact distance from points to a program's path.

Takes the path as straight pieces (start and end points in mm) and points in mm; gives each
point's distance to the path and the nearest point on it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

_PIECE_MM = 0.25  # the path is searched in straight pieces no longer than this
_PAIRS = 1 << 19  # (point, piece) pairs measured at once: about 100 MB of temporaries


class PathDistance:
    """Exact distance from points to a set of straight pieces, and the nearest point on them."""

    def __init__(self, start_mm: np.ndarray, end_mm: np.ndarray):
        count = np.maximum(1, np.ceil(np.linalg.norm(end_mm - start_mm, axis=1) / _PIECE_MM)).astype(int)
        piece = np.repeat(np.arange(len(start_mm)), count)
        step = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        d = (end_mm - start_mm)[piece] / count[piece, None]
        self.a = start_mm[piece] + step[:, None] * d
        self.d = d
        self.half_mm = 0.5 * float(np.linalg.norm(d, axis=1).max(initial=0.0))
        self.tree = cKDTree(self.a + 0.5 * d)

    def __call__(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        distance = np.full(len(points_mm), np.inf)
        nearest = np.zeros((len(points_mm), self.a.shape[1]))
        todo, k = np.arange(len(points_mm)), 4
        while todo.size:
            k = min(k, len(self.a))
            # Points a query at a time so that memory holds _PAIRS candidates, whatever k: on a path
            # smaller than its pieces (a LinuxCNC program at a 1e-4 scale) k grows to every piece.
            batch = max(1, _PAIRS // k)
            todo = np.concatenate([self._nearest(points_mm, rows, k, distance, nearest)
                                   for rows in np.split(todo, range(batch, todo.size, batch))])
            k *= 4
        return distance, nearest

    def _nearest(self, points_mm: np.ndarray, rows: np.ndarray, k: int, distance: np.ndarray,
                 nearest: np.ndarray) -> np.ndarray:
        """The nearest point to each of ``points_mm[rows]`` on its ``k`` pieces whose middles are
        nearest, into ``distance`` and ``nearest``; gives the rows whose search must go on."""
        reach, candidate = self.tree.query(points_mm[rows], k=k)
        reach, candidate = reach.reshape(rows.size, -1), candidate.reshape(rows.size, -1)
        p = points_mm[rows][:, None, :]
        a, d = self.a[candidate], self.d[candidate]
        length2 = np.einsum("ijk,ijk->ij", d, d)
        u = np.clip(np.einsum("ijk,ijk->ij", p - a, d) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        point = a + u[..., None] * d
        gap = np.sqrt(np.einsum("ijk,ijk->ij", p - point, p - point))
        best = gap.argmin(axis=1)
        within = np.arange(rows.size)
        distance[rows], nearest[rows] = gap[within, best], point[within, best]
        # A middle is on the path, so the nearest one bounds the distance: every piece holding a
        # nearer point has its middle within that bound plus half a piece. Those whose k
        # nearest middles may not include all such pieces are searched again with more.
        complete = (reach[:, -1] > reach[:, 0] + self.half_mm) | (k == len(self.a))
        return rows[~complete]
