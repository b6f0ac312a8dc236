"""Filtered B-spline (FBS) optimizer: the compensated command of one axis.

Takes one axis' desired trajectory (mm, on the uniform grid of its ``AxisDynamics``), its limits
and settings; gives the command (mm, same grid, same length) whose modelled response tracks the
desired trajectory best in the least-squares sense (patent Eq. 8/9), with derivative tracking
(Eq. 13), rest conditions at both ends (Eq. 11/12) and inequality limits on the command's and,
optionally, the modelled output's derivatives (a QP, solved with OSQP only where the
unconstrained solution breaks a limit).

The command is a degree-m B-spline on uniform knots, K samples apart, aligned with the first
sample. Control points before the start are the starting position, so the command starts at rest
with all its derivatives continuous. It ends at the last desired position with zero velocity and
acceleration at the last sample and is held there; the objective also covers a settling stretch
after the end, so the compensation does not buy accuracy with residual vibration.

Limited look-ahead solves windows of ``commit + overlap`` spans in sequence and keeps the first
``commit`` spans of each. Between windows it carries exactly what the future depends on: the
plant state, the last m control points and the last samples of command and output. With uniform
knots every window has the same matrices, so they are built and factored once. Complete
look-ahead solves the whole trajectory as a single final window.

Limits are on finite differences of the sampled command (and output), the motion a controller
running at the sample rate executes: velocity (u[k] - u[k-1]) / T, acceleration and jerk likewise.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import daqp
import numpy as np
from scipy import linalg, sparse

from ..profile import AxisProfile
from .dynamics import AxisDynamics, ModelSet
from .smoothing import RunSmoother
from .splines import basis_matrix, uniform_knots
from .varying import VaryingModes


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


_LIMIT_TOLERANCE = 1e-7  # relative excess over a limit accepted as meeting it
# Half the position rows' band where one end of the travel is open: wider than any window's motion
# and overshoot, narrow enough that _LIMIT_TOLERANCE of it (0.05 um) is nothing (fallback.py clips it).
_OPEN_HALF_MM = 500.0
_QP_ROUNDS = 4
_FINAL_CACHE_BYTES = 128 << 20  # per axis (printer-two-mode's X: the final windows of every long run's length, 63 MB)
_ACTIVE_SET_STEPS = 400


def _difference_matrix(order: int, n: int, sample_period_s: float) -> sparse.csr_matrix:
    """Rows (r-th backward difference) / T^r over n + order samples: the first ``order`` are
    the samples before the stretch."""
    coeffs = [(-1) ** (order - i) * math.comb(order, i) for i in range(order + 1)]
    return (
        sparse.diags(coeffs, list(range(order + 1)), shape=(n, n + order), format="csr", dtype=float)
        / sample_period_s**order
    )


class _LimitedQP:
    """A window's QP under the command limits (``constrained``): DAQP for a regular window, our
    dual active-set method for a final one (and where DAQP fails), OSQP where neither finishes.
    Part of ``_Stretch``, whose matrices and factorizations it uses and whose solvers it keeps."""

    def constrained(self, target, p_fixed, offset, end_values, warm) -> np.ndarray | None:
        """The QP: min ||W (target - Nt_free p)||^2 s.t. every limit row, end conditions, from
        ``warm``, the optimum without the limits. None if unsolved.

        A dual active-set method first (DAQP for a regular window, ours, which takes the end
        conditions, for a final one); OSQP where that does not finish. For OSQP, limit rows
        are divided by their limit and the objective by its scale, so that its tolerances mean
        the same at any sample rate; its matrices are set up once per window shape and each
        window only changes vectors.
        """
        m = self.m
        p = self._least_distance(warm, offset) if self.E is None else self._active_set(warm, offset)
        if p is not None:
            return p
        import osqp  # rarely needed: not loaded before

        lower, upper = -1.0 - offset, 1.0 - offset
        n_limit_rows = len(lower)
        if self.E is not None:
            scale = np.abs(self.E[:, m:]).max(axis=1)
            rhs = (end_values - self.E[:, :m] @ p_fixed) / scale
            lower, upper = np.concatenate([lower, rhs]), np.concatenate([upper, rhs])
        q = -self.gradient(target) * self._objective_scale
        if self._qp is None:
            A = self.A_free
            if self.E is not None:
                A = sparse.vstack([A, sparse.csr_matrix(self.E[:, m:] / scale[:, None])], format="csc")
            self._A = A
            self._qp = osqp.OSQP()
            self._qp.setup(sparse.triu(sparse.csc_matrix(self.H * self._objective_scale), format="csc"), q, A,
                           lower, upper, verbose=False, polishing=False, eps_abs=1e-6, eps_rel=1e-6,
                           max_iter=100000)
        else:
            self._qp.update(q=q, l=lower, u=upper)
        self._qp.warm_start(x=warm)
        # OSQP meets the limits to its tolerance; pull the bounds in by what it overshot and
        # solve again from there, until the limits hold to ``_LIMIT_TOLERANCE`` (relative).
        margin = 0.0
        for _ in range(_QP_ROUNDS):
            result = self._qp.solve(raise_error=False)
            if result.info.status_val not in (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
                return None
            x = result.x
            if self.E is not None:
                x = x.copy()
                x[self._end_points] = 0.0
                x[self._end_points] = linalg.lu_solve(self._end_solve, rhs * scale - self.E[:, m:] @ x)
            row = self._A @ x
            excess = max(0.0, np.max(row[:n_limit_rows] - upper[:n_limit_rows]),
                         np.max(lower[:n_limit_rows] - row[:n_limit_rows]))
            if excess <= _LIMIT_TOLERANCE:
                break
            margin += 2.0 * excess
            tightened_l, tightened_u = lower.copy(), upper.copy()
            tightened_l[:n_limit_rows] += margin
            tightened_u[:n_limit_rows] -= margin
            self._qp.update(l=tightened_l, u=tightened_u)
        return x

    def _least_distance(self, p_free: np.ndarray, offset: np.ndarray) -> np.ndarray | None:
        """A regular window's QP by DAQP (Arnstrom, Bemporad, Axehill: a compiled dual active-set
        method for small dense QPs) in least-distance form: with H = R^T R and u = R p,
        min ||u - R p_free||^2 s.t. |A R^-1 u + offset| <= 1. R and A R^-1 are the window
        shape's, set up once; each window starts from no held row (the previous window's rows
        are other samples). Ours (exact) where DAQP fails or misses the limits: on these
        ill-conditioned windows (cond(H) to 1e12) it may call a barely feasible window infeasible."""
        lower, upper = -1.0 - offset, 1.0 - offset
        if self._ldp is None:
            self._root = linalg.cholesky(self.H)  # (Fortran order, as LAPACK takes it)
            self._trtrs, = linalg.get_lapack_funcs(("trtrs",), (self._root,))
            rows = linalg.solve_triangular(self._root, self.A_free.toarray().T, trans="T").T
            self._ldp = daqp.Model()
            self._ldp.setup(np.eye(self.n_free), -(self._root @ p_free), rows, upper, lower)
            self._ldp.settings = {"primal_tol": 0.1 * _LIMIT_TOLERANCE}
            self._cold = np.zeros(len(offset), dtype=np.int32)
        else:
            self._ldp.update(f=-(self._root @ p_free), bupper=upper, blower=lower, sense=self._cold)
        u, _, flag, _ = self._ldp.solve()
        if flag > 0:
            # R p = u: linalg.solve_triangular's own LAPACK call, less its checks (20 -> 2 us)
            p, singular = self._trtrs(self._root, u)
            if not singular and self.violation(p, offset) <= _LIMIT_TOLERANCE:
                return p
        return self._active_set(p_free, offset)

    def _active_set(self, p_free: np.ndarray, offset: np.ndarray) -> np.ndarray | None:
        """The QP by the dual active-set method of Goldfarb and Idnani: from the optimum without
        the limits, take the most violated limit row and raise its multiplier until the row
        reaches its bound, releasing held rows whose multiplier reaches zero on the way; until
        every row holds. The dual objective rises at every step, so it cannot cycle, and the end
        point is the exact optimum (a KKT point of this convex QP). None if the limits cannot be
        met or it takes over ``_ACTIVE_SET_STEPS`` steps (OSQP then decides).

        ``p_free``: the optimum without the limits; rows A p + offset, divided by their limit.
        With held rows W and multipliers lambda, p = p_free - K A_W^T lambda, K the inverse of H
        on the points the end conditions leave free; so every row's value follows from the
        columns of the Gram matrix A K A^T of the rows held.
        """
        column, direction = self._gram_columns()
        start = self.A_free @ p_free + offset
        rows, lam = [], np.zeros(0)  # held rows; sign(lambda) says which bound
        held_columns = np.zeros((start.size, 0))  # their Gram columns
        value = start
        steps = 0
        while steps < _ACTIVE_SET_STEPS:
            q = int(np.argmax(np.abs(value)))
            if abs(value[q]) <= 1.0 + _LIMIT_TOLERANCE:
                return p_free - (np.column_stack([direction(r) for r in rows]) @ lam if rows else 0.0)
            side, lam_q = (1.0 if value[q] > 0 else -1.0), 0.0
            col_q = column(q)
            while steps < _ACTIVE_SET_STEPS:
                steps += 1
                # Raising lambda_q by side * t keeps the held rows at their bounds if lambda_W
                # moves by d t; row q then approaches its bound at rate ``rate``.
                cross = col_q[rows]  # = S[q, rows]
                try:
                    d = -side * np.linalg.solve(held_columns[rows], cross) if rows else lam
                except np.linalg.LinAlgError:
                    return None
                rate = col_q[q] + side * (cross @ d)
                gap = side * (start[q] - cross @ lam - col_q[q] * lam_q) - 1.0
                full = gap / rate if rate > 1e-12 * col_q[q] else np.inf
                to_zero = np.divide(-lam, d, out=np.full(len(rows), np.inf), where=lam * d < 0.0)
                block = int(np.argmin(to_zero)) if rows else -1
                partial = to_zero[block] if rows else np.inf
                if not np.isfinite(min(full, partial)):
                    return None  # row q cannot be brought within its limit
                t = min(full, partial)
                lam, lam_q = lam + d * t, lam_q + side * t
                if full <= partial:
                    rows.append(q)
                    lam = np.append(lam, lam_q)
                    held_columns = np.column_stack([held_columns, col_q])
                    break
                del rows[block]
                lam = np.delete(lam, block)
                held_columns = np.delete(held_columns, block, axis=1)
            value = start - held_columns @ lam
        return None

    def _gram_columns(self):
        """(column(q), direction(q)): the Gram matrix's column A K A_q^T and K A_q^T. A regular
        window has them all computed once; a final window (one solve per run, rows at every
        sample) computes those it needs through its KKT factorization."""
        if self.E is None:
            if self._hinv_at is None:
                dense = self.A_free.toarray()
                self._hinv_at = np.asfortranarray(linalg.cho_solve(self._factor, dense.T))  # H^-1 A^T
                self._gram = np.asfortranarray(dense @ self._hinv_at)
            return (lambda q: self._gram[:, q]), (lambda q: self._hinv_at[:, q])
        rows_of_a, n_eq, found = self.A_free.tocsr(), len(self.E), {}

        def solve(q):
            if q not in found:
                rhs = np.concatenate([rows_of_a[q].toarray().ravel(), np.zeros(n_eq)])
                k_col = linalg.lu_solve(self._factor, rhs)[:self.n_free]
                found[q] = (self.A_free @ k_col, k_col)
            return found[q]
        return (lambda q: solve(q)[0]), (lambda q: solve(q)[1])


class _Stretch(_LimitedQP):
    """Constant matrices of one window shape.

    Local control points: the first m are fixed (chosen before), the next ``n_free`` are solved.
    Rows: ``n_samples`` samples from the window's first knot; rows from ``hold_from`` on hold the
    command at its value at sample ``hold_from - 1`` (the settling stretch after the end).
    ``end_conditions``: rows of the command's derivatives 0..r at sample ``hold_from - 1``.
    """

    def __init__(self, models: ModelSet, settings: FBSSettings, limits: AxisLimits,
                 n_samples: int, n_free: int, hold_from: int | None = None, end_conditions: bool = False):
        m, k, T = settings.degree, settings.knot_spacing_samples, models.sample_period_s
        self.m, self.n_free, self.n_samples = m, n_free, n_samples
        hold_from = n_samples if hold_from is None else hold_from
        knots = uniform_knots(m + n_free, m, k * T, first_knot=-m)
        rows = np.minimum(np.arange(n_samples), hold_from - 1)
        # Times on the knots' own scale, (r / K) (K T): a sample on a knot is that knot's time to
        # the bit (r T can round past the spline's last knot, outside its base interval).
        self.N = basis_matrix(knots, m, rows / k * (k * T)).toarray()  # n_samples x (m + n_free)
        # Filtered basis from the zero state and free response, every model's stacked (the nominal's first).
        self.Nt = models.filter(self.N)
        self.Phi = models.free_response_matrix(n_samples)
        self.n_models = len(models.models)

        # Objective ||W (x - y)||, W = [I; alpha_r D_r]; differences inside the stretch only.
        weights = np.ones(n_samples)
        weights[hold_from:] = settings.settle_weight
        w_rows = [sparse.diags(weights, format="csr")]
        for r, a in enumerate(settings.derivative_weights, start=1):
            if a:
                w_rows.append(a * _difference_matrix(r, n_samples - r, T))
        self.W = sparse.vstack(w_rows, format="csr")
        if self.n_models > 1:  # sum over the models of weight x error^2
            self.W = sparse.block_diag([math.sqrt(w) * self.W for w in models.weights], format="csr")
        self.M = np.asarray(self.W @ self.Nt[:, m:])
        self.H = self.M.T @ self.M
        self._objective_scale = 1.0 / np.abs(self.H).max()
        if end_conditions:
            t_end = (hold_from - 1) / k * (k * T)
            self.E = np.vstack([basis_matrix(knots, m, [t_end], r).toarray()
                                for r in range(settings.end_rest_order + 1)])
            n_eq = len(self.E)
            self._factor = linalg.lu_factor(np.block([[self.H, self.E[:, m:].T],
                                                      [self.E[:, m:], np.zeros((n_eq, n_eq))]]))
            # OSQP meets equality rows only to its tolerance; the end conditions are then solved
            # exactly for the n_eq best-conditioned points they involve (pivoted QR) from the rest.
            pivots = linalg.qr(self.E[:, m:], pivoting=True, mode="r")[1][:n_eq]
            self._end_points = pivots
            self._end_solve = linalg.lu_factor(self.E[:, m:][:, pivots])
        else:
            # The last m control points reach past the window, where nothing pins them: they make
            # H singular to working precision. A faint penalty on their third differences lets them
            # continue the spline's trend; the committed points, a whole overlap earlier, do not see it.
            self.E = None
            third = sparse.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(n_free - 3, n_free), dtype=float)
            tail = third.tocsr()[-m:]
            self.H = self.H + 1e-9 * np.trace(self.H) / n_free * (tail.T @ tail).toarray()
            # The solve for every right-hand side at once: p_free = G target.
            self._factor = linalg.cho_factor(self.H)
            self.G = linalg.cho_solve(self._factor, np.asarray(self.W.T @ self.M).T)

        self._limit_rows(limits, n_samples, T)
        self._qp = None
        self._ldp = self._hinv_at = None

    def _limit_rows(self, limits: AxisLimits, n_samples: int, T: float) -> None:
        """The rows of ``limits``, one per sample and limit, divided by the limit: |A_free p + offset|
        <= 1 with offset = A_fixed p_fixed + A_prev [previous command; previous output] + A_state
        state + A_center center (``has_limits``: are there any)."""
        m = self.m
        r_max = limits.history
        free, fixed, prev, state, row_sample = [], [], [], [], []
        for kind, table in (("command", limits.command), ("output", limits.output)):
            basis = self.N if kind == "command" else self.Nt[:n_samples]
            for r, value in sorted(table.items()):
                D = _difference_matrix(r, n_samples, T) / value
                rows = D[:, r:] @ basis
                free.append(sparse.csr_matrix(rows[:, m:]))
                fixed.append(rows[:, :m])
                before = np.zeros((n_samples, 2 * r_max))
                column = r_max if kind == "command" else 2 * r_max
                before[:, column - r:column] = D[:, :r].toarray()
                prev.append(before)
                state.append(
                    D[:, r:] @ self.Phi[:n_samples] if kind == "output" else np.zeros((n_samples, self.Phi.shape[1]))
                )
                row_sample.append(np.arange(n_samples))
        # The travel: |(N p - center) / half| <= 1 at every sample, the center set per window.
        half = limits.position_half_mm
        center = [np.zeros(len(rows)) for rows in fixed]
        if half is not None:
            rows = self.N / half
            free.append(sparse.csr_matrix(rows[:, m:]))
            fixed.append(rows[:, :m])
            prev.append(np.zeros((n_samples, 2 * r_max)))
            state.append(np.zeros((n_samples, self.Phi.shape[1])))
            row_sample.append(np.arange(n_samples))
            center.append(np.full(n_samples, -1.0 / half))
        self.has_limits = bool(free)
        self.position_center = limits.position_center
        if self.has_limits:
            self.A_free = sparse.vstack(free, format="csc")
            self.A_fixed, self.A_prev, self.A_state = np.vstack(fixed), np.vstack(prev), np.vstack(state)
            self.A_center = np.concatenate(center)
            self.row_sample = np.concatenate(row_sample)

    @property
    def nbytes(self) -> int:
        """Memory held by its matrices (and factorizations)."""
        held = [x for v in vars(self).values() for x in (v if isinstance(v, tuple) else (v,))]
        return sum(v.nbytes if isinstance(v, np.ndarray) else v.data.nbytes + v.indices.nbytes + v.indptr.nbytes
                   for v in held if isinstance(v, np.ndarray) or sparse.issparse(v))

    def reset(self) -> None:
        """Drop OSQP's state (its duals) from earlier windows: a reused window solves as a new one."""
        self._qp = None

    # ---- the pieces every solve needs -------------------------------------------------------
    def target(self, desired: np.ndarray, state: np.ndarray, p_fixed: np.ndarray) -> np.ndarray:
        """What the free control points must make the outputs do: x - free response - fixed part."""
        return np.tile(desired, self.n_models) - self.Phi @ state - self.Nt[:, :self.m] @ p_fixed

    def gradient(self, target: np.ndarray) -> np.ndarray:
        return self.M.T @ (self.W @ target)

    def unconstrained(self, target: np.ndarray, p_fixed: np.ndarray, end_values: np.ndarray | None) -> np.ndarray:
        if self.E is None:
            return self.G @ target
        rhs = np.concatenate([self.gradient(target), end_values - self.E[:, :self.m] @ p_fixed])
        return linalg.lu_solve(self._factor, rhs)[:self.n_free]

    def limit_offset(self, p_fixed, state, previous, desired) -> np.ndarray:
        """``previous``: the last commands, then the last outputs, before the window; ``desired``:
        the window's desired trajectory (where the travel's rows center)."""
        return (self.A_fixed @ p_fixed + self.A_prev @ previous + self.A_state @ state
                + self.A_center * self.position_center(desired))

    def check_rows(self, n_samples: int):
        """The limit rows of the first ``n_samples`` samples: (their rows of A_free, their indices)."""
        rows = np.flatnonzero(self.row_sample < n_samples)
        return self.A_free[rows].tocsr(), rows

    def violation(self, p: np.ndarray, offset: np.ndarray) -> float:
        """Largest relative excess over a limit (0 when within)."""
        return max(0.0, float(np.abs(self.A_free @ p + offset).max(initial=0.0)) - 1.0)


class _Carry:
    """What the next window needs from everything solved before it, as one vector
    z = [plant state, last m control points, last r commands, last r outputs]."""

    def __init__(self, n_states: int, m: int, r_max: int):
        self.n_states, self.m, self.r_max = n_states, m, r_max
        self.size = n_states + m + 2 * r_max

    def state(self, z):
        return z[:self.n_states]

    def p_fixed(self, z):
        return z[self.n_states:self.n_states + self.m]

    def previous(self, z):
        """[previous commands; previous outputs], oldest first."""
        return z[self.n_states + self.m:]


class _Sweep:
    """The regular window folded into linear maps of the carry z, for the windows whose
    unconstrained optimum meets the limits (most of them): the first control points
    p = Gd desired - Gz z, the limit rows of the samples the window decides (divided by the
    limit) A p + Az z, and the next carry z' = L [z; kept points]. Everything here is built
    once per axis."""

    def __init__(self, stretch: _Stretch, models: ModelSet, carry: _Carry, commit: int, k: int):
        m, ns, r = stretch.m, carry.n_states, carry.r_max
        self.commit, self.commit_rows = commit, commit * k
        rows = self.commit_rows
        used = commit
        if stretch.has_limits:
            # The kept samples and the next m + 1 spans: those depend mostly on kept control
            # points, and the next window could not undo a limit broken there.
            check, index = stretch.check_rows(rows + (m + 1) * k)
            used = max(commit, int(check.indices.max(initial=-1)) + 1)  # points the checked rows see
            self.A = check[:, :used].toarray()
            self.Az = np.hstack([stretch.A_state, stretch.A_fixed, stretch.A_prev])[index]
            self.A_center = stretch.A_center[index]
        G = stretch.G[:used]  # of the stacked target; every model's desired trajectory is the same
        self.Gd = G.reshape(used, stretch.n_models, -1).sum(axis=1) if stretch.n_models > 1 else G
        self.Gz = np.hstack([G @ stretch.Phi, G @ stretch.Nt[:, :m], np.zeros((used, 2 * r))])
        # z' from x = [z; kept points]: the kept command is N p_all with p_all = [p_fixed; kept points].
        n_x = carry.size + commit
        p_all = np.zeros((m + commit, n_x))
        p_all[:m, ns:ns + m] = np.eye(m)
        p_all[m:, carry.size:] = np.eye(commit)
        state = np.zeros((ns, n_x))
        state[:, :ns] = np.eye(ns)
        to_state = models.input_to_state_matrix(rows) @ stretch.N[:rows, :m + commit]
        tail = slice(rows - r, rows)
        self.L = np.vstack([np.linalg.matrix_power(models.A, rows) @ state + to_state @ p_all,
                            p_all[-m:],
                            stretch.N[tail, :m + commit] @ p_all,
                            stretch.Phi[tail] @ state + stretch.Nt[tail, :m + commit] @ p_all])
        self.N_kept = stretch.N[:rows, :m + commit]


class AxisCompensator:
    """The compensation of one axis: ``compensator(desired_mm)`` gives an ``AxisResult``, and
    ``compensator.stream()`` an ``AxisStream`` for a run that arrives in pieces.

    Everything that does not depend on the trajectory (the regular window's matrices, their
    factorization, the folded maps and the QP set-up) is built on first use and reused for
    every motion run of a program.

    ``models``: the set whose mean squared error is minimized (robust compensation), the
    nominal ``dynamics`` first; by default ``dynamics`` alone. The carry holds every model's state.
    ``varying``: modes that move with the machine's state (``stream().push``'s ``state``: the
    filament printed, or an axis' position): each window uses the level in force at its start
    (level 0 is ``models``), the carry mapped to it; every level's matrices are built on its first use.
    """

    def __init__(self, dynamics: AxisDynamics, limits: AxisLimits, settings: FBSSettings = FBSSettings(),
                 lookahead: str = "limited", models: ModelSet | None = None,
                 varying: VaryingModes | None = None):
        if lookahead not in ("limited", "complete"):
            raise ValueError(f"lookahead must be 'limited' or 'complete', not {lookahead!r}")
        self.dynamics, self.limits, self.lookahead = dynamics, limits, lookahead
        self.models, self.varying = models or ModelSet([dynamics]), varying
        self.settings = settings.resolve(dynamics)
        self.carry = _Carry(self.models.n_states, self.settings.degree, limits.history)
        self.state_from = None  # the first state pushed, for ``varying`` that counts from it (mm)
        self._sets = {0: self.models}
        self._rest_units, self._regulars, self._remaps = {}, {}, {}
        self._finals: OrderedDict[tuple[int, int], _Stretch] = OrderedDict()
        self._finals_bytes = 0

    def __call__(self, desired_mm: np.ndarray) -> AxisResult:
        stream = self.stream()
        head = stream.push(desired_mm)
        result = stream.finish()
        result.command_mm = np.concatenate([head, result.command_mm])
        return result

    def stream(self) -> AxisStream:
        return AxisStream(self)

    def model_set(self, level: int = 0) -> ModelSet:
        if level not in self._sets:
            self._sets[level] = self.varying.models(level)
        return self._sets[level]

    def rest_unit(self, level: int = 0) -> np.ndarray:
        """The carry at rest at 1 mm (the carry at rest at x mm is x times it)."""
        if level not in self._rest_units:
            models = self.model_set(level)
            self._rest_units[level] = np.concatenate(
                [models.rest_state(1.0), np.ones(self.carry.size - models.n_states)]
            )
        return self._rest_units[level]

    def remap(self, z: np.ndarray, old: int, new: int) -> np.ndarray:
        """The carry ``z`` of level ``old`` as level ``new``'s (``varying.remap``)."""
        if (old, new) not in self._remaps:
            self._remaps[old, new] = self.varying.remap(old, new)
        to_new, from_command = self._remaps[old, new]
        z = z.copy()
        z[: self.carry.n_states] = (
            to_new @ z[: self.carry.n_states] + from_command * self.carry.previous(z)[self.carry.r_max - 1]
        )
        return z

    def regular(self, level: int = 0) -> tuple[_Stretch, _Sweep]:
        if level not in self._regulars:
            k = self.settings.knot_spacing_samples
            window = self.settings.commit_spans + self.settings.overlap_spans
            models = self.model_set(level)
            stretch = _Stretch(models, self.settings, self.limits, window * k, window)
            self._regulars[level] = stretch, _Sweep(stretch, models, self.carry, self.settings.commit_spans, k)
        return self._regulars[level]

    def final(self, n_rows: int, level: int = 0) -> _Stretch:
        """The final window of a run whose last ``n_rows`` samples it solves. Every run has one;
        its length is at most the samples a regular window needs ahead, so runs share them: the
        most recently used are kept, up to ``_FINAL_CACHE_BYTES`` (a few hundred per axis)."""
        key = level, n_rows
        final = self._finals.pop(key, None)
        if final is None:
            settings = self.settings
            # The spans up to the last sample; a point whose support starts at the last sample does nothing.
            final = _Stretch(self.model_set(level), settings, self.limits, n_rows + settings.settle_samples,
                             max(1, -(-(n_rows - 1) // settings.knot_spacing_samples)), hold_from=n_rows,
                             end_conditions=True)
            self._finals_bytes += final.nbytes
        final.reset()
        self._finals[key] = final
        while self._finals_bytes > _FINAL_CACHE_BYTES:
            self._finals_bytes -= self._finals.popitem(last=False)[1].nbytes
        return final


class AxisStream:
    """One run of one axis, fed in pieces: ``push(desired_mm)`` gives the command samples that
    nothing later can change, ``finish()`` an ``AxisResult`` with the rest. The samples are the
    same, bit for bit, however the run is cut into pieces: every window is computed alike.

    A window runs as a regular one once the samples after its kept spans are known to outlast
    the final window; the buffer holds the samples from the current window's start (and, with
    varying modes, the state they follow there).
    """

    def __init__(self, compensator: AxisCompensator):
        self.owner = compensator
        self.result = AxisResult(np.empty(0), compensator.settings)
        self.buffer = self.state = np.empty(0)
        self.first_sample = 0  # run sample at buffer[0]
        self.z = None  # the carry, once the first sample is known
        self.level = 0  # of the model in force (AxisCompensator.varying)
        half_width = compensator.settings.smoothing_half_width
        self.smoother = RunSmoother(half_width) if half_width else None

    def push(self, desired_mm: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """``state``: what varying modes follow (``varying.column`` of the plan: the filament
        position, an axis' position), at the same samples (unknown: NaN)."""
        desired_mm = np.asarray(desired_mm, dtype=float)
        if desired_mm.ndim != 1 or not np.all(np.isfinite(desired_mm)):
            raise ValueError("the desired trajectory must be a 1-D array of finite positions")
        if self.owner.varying is not None:
            self._note_state(desired_mm.size, state)  # (ahead of the buffer while the smoother holds samples)
        self._take(desired_mm if self.smoother is None else self.smoother.push(desired_mm))
        if self.owner.lookahead == "complete":
            return np.empty(0)
        return self._regular_windows()

    def finish(self) -> AxisResult:
        """The rest of the run: regular windows while they are still regular, then the final one."""
        owner, result = self.owner, self.result
        settings = owner.settings
        if self.smoother is not None:
            self._take(self.smoother.finish())
        if self.first_sample + self.buffer.size == 0:
            raise ValueError("the desired trajectory must be a non-empty 1-D array of finite positions")
        head = self._regular_windows() if owner.lookahead == "limited" else np.empty(0)
        if self.first_sample == 0 and self.buffer.size <= (settings.end_rest_order + 3) * settings.knot_spacing_samples:
            # a few spans: too short to shape, the end conditions would fix every point
            result.command_mm = self.buffer.copy()
            return result
        tail = self._final()
        tail[-1] = self.buffer[-1]  # the last position in exact arithmetic; make it so in floating point too
        result.command_mm = np.concatenate([head, tail])
        return result

    def _take(self, desired_mm: np.ndarray) -> None:
        self.buffer = np.concatenate([self.buffer, desired_mm])
        if self.z is None and self.buffer.size:
            self.level = self._level_at(0)
            self.z = self.owner.rest_unit(self.level) * self.buffer[0]

    def _note_state(self, n: int, state: np.ndarray | None) -> None:
        """Keep the state, counted from the compensator's first known one where ``varying`` says so
        (the filament extruded since then)."""
        owner = self.owner
        state = np.full(n, np.nan) if state is None else np.asarray(state, dtype=float)
        if owner.varying.since_first:
            known = state[np.isfinite(state)]
            if owner.state_from is None and known.size:
                owner.state_from = float(known[0])
            state = state - (owner.state_from or 0.0)
        self.state = np.concatenate([self.state, state])

    def _level_at(self, sample: int) -> int:
        """The level in force at buffer sample ``sample``."""
        return 0 if self.owner.varying is None else self.owner.varying.level(float(self.state[sample]))

    def _regular_windows(self) -> np.ndarray:
        """Run every window known to be regular: followed by more than the final window needs
        in the samples known so far (so whatever comes later)."""
        owner = self.owner
        settings, carry = owner.settings, owner.carry
        k, commit = settings.knot_spacing_samples, settings.commit_spans
        window = commit + settings.overlap_spans
        ahead = (commit + max(window, settings.final_spans)) * k  # samples a regular window needs after its start
        rows = commit * k
        out, start = [], 0
        while start + ahead < self.buffer.size:
            level = self._level_at(start)
            if level != self.level:
                self.z, self.level = owner.remap(self.z, self.level, level), level
            stretch, sweep = owner.regular(level)
            desired = self.buffer[start:start + window * k]
            z = self.z
            at_rest = desired[0] == desired[-1] and np.ptp(desired) == 0.0
            if at_rest and np.array_equal(z, owner.rest_unit(level) * desired[0]):
                command = desired[:rows].copy()  # at rest and staying there: exactly the optimum
            else:
                p = sweep.Gd @ desired - sweep.Gz @ z
                if stretch.has_limits and np.abs(sweep.A @ p + sweep.Az @ z
                                                 + sweep.A_center * stretch.position_center(desired)).max() > 1.0:
                    p = _solve_window(stretch, desired, carry, z, None, self.result, self.first_sample + start,
                                      breaks_limit=True)
                kept = np.concatenate([carry.p_fixed(z), p[:commit]])
                command = sweep.N_kept @ kept
                self.z = sweep.L @ np.concatenate([z, p[:commit]])
            if self.first_sample + start == 0:
                command[0] = desired[0]  # the first position in exact arithmetic; so in floating point
            out.append(command)
            start += rows
            self.result.windows += 1
        self.buffer = self.buffer[start:]
        self.state = self.state[start:]
        self.first_sample += start
        return np.concatenate(out) if out else np.empty(0)

    def _final(self) -> np.ndarray:
        """The final window: from the buffer's start to the end, the end conditions, the settling stretch."""
        owner, desired_mm, z = self.owner, self.buffer, self.z
        settings, carry = owner.settings, owner.carry
        self.result.windows += 1
        if np.ptp(desired_mm) == 0.0 and np.array_equal(z, owner.rest_unit(self.level) * desired_mm[0]):
            return desired_mm.copy()  # at rest and staying there
        n_rows = desired_mm.size
        final = owner.final(n_rows, self.level)
        desired = np.concatenate([desired_mm, np.full(settings.settle_samples, desired_mm[-1])])
        end_values = np.zeros(settings.end_rest_order + 1)
        end_values[0] = desired_mm[-1]
        p_free = _solve_window(final, desired, carry, z, end_values, self.result, self.first_sample)
        command = final.N[:n_rows] @ np.concatenate([carry.p_fixed(z), p_free])
        if self.first_sample == 0:
            command[0] = desired_mm[0]
        return command


def compensate_axis(desired_mm: np.ndarray, dynamics: AxisDynamics, limits: AxisLimits,
                    settings: FBSSettings = FBSSettings(), lookahead: str = "limited") -> AxisResult:
    """The compensated command for ``desired_mm`` (sampled at the dynamics' sample period).

    ``lookahead``: "limited" (sliding windows) or "complete" (one solve over everything).
    For several trajectories of one axis, an ``AxisCompensator`` reuses its set-up.
    """
    return AxisCompensator(dynamics, limits, settings, lookahead)(desired_mm)


def _solve_window(stretch: _Stretch, desired, carry: _Carry, z: np.ndarray, end_values, result: AxisResult,
                  first_sample: int, breaks_limit: bool = False) -> np.ndarray:
    """Free control points of one window after carry ``z``: the unconstrained optimum, or the QP
    where that breaks a limit (``breaks_limit``: the caller found it does, on the samples whose
    command the window decides)."""
    p_fixed, state = carry.p_fixed(z), carry.state(z)
    target = stretch.target(desired, state, p_fixed)
    p = stretch.unconstrained(target, p_fixed, end_values)
    if not stretch.has_limits:
        return p
    offset = stretch.limit_offset(p_fixed, state, carry.previous(z), desired)
    if not breaks_limit and stretch.violation(p, offset) <= 0.0:
        return p
    result.qp_windows += 1
    p_qp = stretch.constrained(target, p_fixed, offset, end_values, warm=p)
    best = p if p_qp is None else p_qp
    excess = stretch.violation(best, offset)
    if excess <= _LIMIT_TOLERANCE:
        return best
    result.warnings.append(f"window from sample {first_sample}: the limits could not be met; "
                           f"the command there exceeds them by up to {excess:.3g} (relative)")
    return best
