"""The plan's timeline: piecewise-quadratic segments, and the samples they give.

Takes the segments of the settled motion (the three phases of every piece, the rests, each with
an order key); gives the positions at any samples (``Segments.evaluate``) and holds what is not
yet released, or everything for the whole plan (``Timeline``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..read.blocks import AXES

_NA = len(AXES)


@dataclass
class Segments:
    """The plan's piecewise-quadratic timeline: position = a0 + a1 tau + a2 tau^2, tau = t - ref,
    from t0 on (t0 never decreases; of equal starts the later one rules)."""

    t0: np.ndarray  # (s,) s
    ref: np.ndarray  # (s,) s
    a0: np.ndarray  # (s, len(AXES)) mm
    a1: np.ndarray  # (s, len(AXES)) mm/s
    a2: np.ndarray  # (s, len(AXES)) mm/s^2

    def evaluate(self, first: int, stop: int, fs: float) -> np.ndarray:
        """(stop - first, len(AXES)) positions at samples first .. stop - 1 (t = k / fs)."""
        t = np.arange(first, stop) / fs
        if not t.size:
            return np.zeros((0, _NA))
        # the segment of each sample (searchsorted right, minus 1) by merging the sorted sample
        # times with the segment starts in the stretch: cheaper than a search per sample
        lo, hi = np.searchsorted(self.t0, t[[0, -1]], side="right")
        entered = np.searchsorted(t, self.t0[lo:hi], side="left")  # sample where each later segment starts
        index = (lo - 1) + np.cumsum(np.bincount(entered, minlength=t.size))
        tau = (t - np.take(self.ref, index))[:, None]
        out = np.take(self.a2, index, axis=0)
        out *= tau
        out += np.take(self.a1, index, axis=0)
        out *= tau
        out += np.take(self.a0, index, axis=0)
        return out

    def __getitem__(self, rows) -> Segments:
        return Segments(self.t0[rows], self.ref[rows], self.a0[rows], self.a1[rows], self.a2[rows])

    @classmethod
    def joined(cls, parts: list[Segments]) -> Segments:
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t0", "ref", "a0", "a1", "a2")))



class Timeline:
    """The plan's samples. Takes the segments of the settled motion (``add``: pieces' phases,
    rests, each with an order key) and gives the samples below the frontier (``samples``), dropping
    what is ``release``d; with ``keep``, holds every segment for the whole plan (``kept``)."""

    def __init__(self, fs: float, keep: bool):
        self._fs, self._keep = fs, keep
        self._segments = Segments(np.zeros(0), np.zeros(0), np.zeros((0, _NA)), np.zeros((0, _NA)), np.zeros((0, _NA)))
        self._t0_max = -math.inf
        self.kept: list[Segments] = []

    def samples(self, first: int, stop: int) -> np.ndarray:
        return self._segments.evaluate(first, stop, self._fs)

    def release(self, sample: int) -> None:
        drop = int(np.searchsorted(self._segments.t0, sample / self._fs, side="right")) - 1
        if drop > len(self._segments.t0) // 2:  # copy seldom
            self._segments = self._segments[drop:]

    def add(self, parts: list) -> None:
        """The segments ``parts`` ((order keys, Segments) each), in the order of their keys."""
        keys = np.concatenate([np.ravel(k) for k, _ in parts])
        seg = Segments.joined([s for _, s in parts])[np.argsort(keys, kind="stable")]
        # Sums of rounded times can put a phase an ulp after the next one's start: they are in
        # time order, make their starts say so (of equal starts, the later rules)
        seg.t0 = np.maximum.accumulate(np.concatenate([[self._t0_max], seg.t0]))[1:]
        self._t0_max = seg.t0[-1]
        if self._keep:
            self.kept.append(seg)
        else:
            self._segments = Segments.joined([self._segments, seg])

    @staticmethod
    def held(key: int, t0: float, ref: float, position: np.ndarray) -> tuple:
        """A rest at ``position`` from ``t0`` on, with its order key."""
        t = np.array([t0])
        return np.array([key]), Segments(t, np.array([ref]), position[None], np.zeros((1, _NA)), np.zeros((1, _NA)))

    @staticmethod
    def phases(first_piece: int, piece_start, piece_end, t_accel, t_cruise, start, end, d_accel, length, accel,
               speeds) -> tuple:
        """The three phases of every piece (the braking phase measured from the piece's end, so
        pieces end exactly at their end point), with their order keys."""
        v0, vp, v1 = speeds
        unit_pos = (end - start) / length[:, None]  # position per mm of the piece
        half_a = (0.5 * accel)[:, None] * unit_pos
        n = len(piece_start)
        return (8 * (first_piece + np.arange(n))[:, None] + np.arange(3), Segments(
            np.stack([piece_start, piece_start + t_accel, piece_start + (t_accel + t_cruise)], axis=1).ravel(),
            np.stack([piece_start, piece_start + t_accel, piece_end], axis=1).ravel(),
            np.stack([start, start + d_accel[:, None] * unit_pos, end], axis=1).reshape(-1, _NA),
            np.stack([v0[:, None] * unit_pos, vp[:, None] * unit_pos, v1[:, None] * unit_pos], axis=1).reshape(-1, _NA),
            np.stack([half_a, np.zeros_like(half_a), -half_a], axis=1).reshape(-1, _NA)))

