"""The optimizer's settings and limits: what ``AxisCompensator`` takes and gives.

Takes an axis' profile (``AxisLimits.from_profile``) or explicit limits and settings; gives
``AxisLimits`` (the largest derivatives of command and output, the travel), ``FBSSettings`` (the
spline and its windows, sized from the dynamics by ``resolve``) and ``AxisResult`` (a run's command,
its windows and warnings). ``LIMIT_TOLERANCE``: the relative excess over a limit that meets it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..profile import AxisProfile
from .dynamics import AxisDynamics


@dataclass(frozen=True)
class AxisLimits:
    """Largest absolute r-th finite-difference derivative, by order r (1 velocity mm/s,
    2 acceleration mm/s^2, 3 jerk mm/s^3), of the command and of the modelled output."""

    command: dict[int, float] = field(default_factory=dict)
    output: dict[int, float] = field(default_factory=dict)
    position_mm: tuple[float, float] = (-math.inf, math.inf)  # the machine's travel: the command stays within

    @classmethod
    def from_profile(cls, axis: AxisProfile) -> AxisLimits:
        command = {1: axis.max_velocity_mm_s, 2: axis.max_acceleration_mm_s2}
        if axis.max_jerk_mm_s3 is not None:
            command[3] = axis.max_jerk_mm_s3
        travel = tuple(math.copysign(math.inf, sign) if value is None else value
                       for value, sign in ((axis.position_min_mm, -1.0), (axis.position_max_mm, 1.0)))
        return cls(command, position_mm=travel)

    @property
    def position_half_mm(self) -> float | None:
        """Half the band |command - center| <= half of the position rows (None: no travel given).
        With one end of the travel open, a fixed ``_OPEN_HALF_MM``: the center follows the window."""
        low, high = self.position_mm
        if math.isinf(low) and math.isinf(high):
            return None
        return 0.5 * (high - low) if math.isfinite(low + high) else _OPEN_HALF_MM

    def position_center(self, desired_mm: np.ndarray) -> float:
        """The center of the position rows' band for a window tracking ``desired_mm``: the middle of
        the travel; with one end open, the band's far side half a band beyond the window's motion,
        its near side at the travel's end wherever the window comes within a band of it."""
        low, high = self.position_mm
        half = self.position_half_mm
        if half is None:  # no rows
            return 0.0
        if math.isfinite(low + high):
            return 0.5 * (low + high)
        if math.isfinite(low):
            return max(low + half, float(desired_mm.max()) - 0.5 * half)
        return min(high - half, float(desired_mm.min()) + 0.5 * half)

    @property
    def history(self) -> int:
        """Samples before a window that its limit rows need (the highest order, at least 1)."""
        return max([*self.command, *self.output, 1])


@dataclass(frozen=True)
class FBSSettings:
    """Spline and look-ahead settings; ``None`` sizes are chosen from the dynamics (``resolve``)."""

    degree: int = 5
    knot_spacing_samples: int | None = None  # K
    commit_spans: int | None = None  # spans kept from each window
    overlap_spans: int | None = None  # look-ahead spans solved but not kept
    final_spans: int | None = None  # the last window reaches back at least this far
    settle_samples: int | None = None  # objective horizon after the end
    settle_weight: float = 0.5  # weight of the error after the end (residual vibration)
    derivative_weights: tuple[float, ...] = ()  # alpha_1, alpha_2, ... in s, s^2, ... (Eq. 13)
    end_rest_order: int = 2  # derivatives 1..r of the command are zero at the end
    smoothing_half_width: int = 0  # samples: track the desired trajectory Hann-smoothed (smoothing.RunSmoother)

    def resolve(self, dynamics: AxisDynamics) -> FBSSettings:
        """Fill in every automatic size from the axis dynamics.

        Knots: 6 per period of the highest mode, so the spline can shape the command up to about
        three times the band it must cancel (12 per period, half the spacing, leave under 3% less
        residual error on the patent butterfly for twice the work); at least 2 samples apart: with
        a knot on every sample the command wiggles at half the sample rate (two modes at 52 and
        96 Hz sampled at 1 kHz), which the firmware runs as a speed step at every block (a sliced
        print's first 8000 lines through klippy's planner: 9.5 times lower RMS contour error than
        the original with a knot every sample, 69 times with one every 2). Overlap: the optimal command
        depends on what is coming only through the inverse's anticausal part, the right-half-plane
        zeros of G; look ahead until the slowest of them has decayed by 1e-6 (at least one period
        of the lowest mode, and m + 2 spans). Final window: the end conditions reach back through
        the slowest zero of all (the complete solution starts preparing the stop that early);
        cover its decay by a factor of 5, at most 1 s. Settle: two periods of the lowest mode
        after the end. Kept per window: the overlap, at least 0.1 s.
        """
        period_s = dynamics.sample_period_s
        f_max = max(m.frequency_hz for m in dynamics.modes)
        f_min = min(m.frequency_hz for m in dynamics.modes)
        k = self.knot_spacing_samples or max(2, int(1.0 / (6.0 * f_max * period_s)))
        span_s = k * period_s
        zeros = dynamics.zeros()
        rhp = zeros.real[zeros.real > 0]
        lookahead_s = max(1.0 / f_min, math.log(1e6) / rhp.min() if rhp.size else 0.0)
        overlap = self.overlap_spans or max(math.ceil(lookahead_s / span_s), self.degree + 2)
        slowest = np.abs(zeros.real).min(initial=np.inf)
        final_s = min(1.0, math.log(5.0) / slowest) if slowest > 0 else 1.0
        final = self.final_spans or math.ceil(final_s / span_s)
        settle = self.settle_samples if self.settle_samples is not None else math.ceil(2.0 / (f_min * period_s))
        # Keep at least 0.1 s per window: the work per sample does not grow, the overhead per window shrinks.
        commit = self.commit_spans or max(overlap, math.ceil(0.1 / span_s))
        if not 1 <= self.end_rest_order < self.degree or commit + overlap < self.degree + 4 or settle < 0:
            raise ValueError(f"FBS settings need 1 <= end_rest_order < degree and windows of at least degree + 4 "
                             f"spans, got degree {self.degree}, end_rest_order {self.end_rest_order}, "
                             f"{commit} + {overlap} spans")
        return replace(self, knot_spacing_samples=k, commit_spans=commit,
                       overlap_spans=overlap, final_spans=final, settle_samples=settle)


@dataclass
class AxisResult:
    command_mm: np.ndarray
    settings: FBSSettings
    windows: int = 0
    qp_windows: int = 0
    warnings: list[str] = field(default_factory=list)


LIMIT_TOLERANCE = 1e-7  # relative excess over a limit accepted as meeting it
# Half the position rows' band where one end of the travel is open: wider than any window's motion
# and overshoot, narrow enough that LIMIT_TOLERANCE of it (0.05 um) is nothing (fallback.py clips it).
_OPEN_HALF_MM = 500.0
