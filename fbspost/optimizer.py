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

import contextlib
import io
import math
from dataclasses import dataclass, field, replace

import numpy as np
import osqp
from scipy import linalg, sparse

from .dynamics import AxisDynamics
from .profile import AxisProfile
from .splines import basis_matrix, uniform_knots


@dataclass(frozen=True)
class AxisLimits:
    """Largest absolute r-th finite-difference derivative, by order r (1 velocity mm/s,
    2 acceleration mm/s^2, 3 jerk mm/s^3), of the command and of the modelled output."""

    command: dict[int, float] = field(default_factory=dict)
    output: dict[int, float] = field(default_factory=dict)

    @classmethod
    def from_profile(cls, axis: AxisProfile) -> AxisLimits:
        command = {1: axis.max_velocity_mm_s, 2: axis.max_acceleration_mm_s2}
        if axis.max_jerk_mm_s3 is not None:
            command[3] = axis.max_jerk_mm_s3
        return cls(command)

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

    def resolve(self, dynamics: AxisDynamics) -> FBSSettings:
        """Fill in every automatic size from the axis dynamics.

        Knots: 12 per period of the highest mode, so the spline can shape the command well above
        the band it must cancel. Overlap: the optimal command depends on what is coming only
        through the inverse's anticausal part, the right-half-plane zeros of G; look ahead until
        the slowest of them has decayed by 1e-6 (at least one period of the lowest mode, and
        m + 2 spans). Final
        window: the end conditions reach back through the slowest zero of all (the complete
        solution starts preparing the stop that early); cover its decay by a factor of 5, at
        most 1 s. Settle: two periods of the lowest mode after the end. Kept per window: the
        overlap, at least 0.1 s.
        """
        period_s = dynamics.sample_period_s
        f_max = max(m.frequency_hz for m in dynamics.modes)
        f_min = min(m.frequency_hz for m in dynamics.modes)
        k = self.knot_spacing_samples or max(1, int(1.0 / (12.0 * f_max * period_s)))
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
_QP_ROUNDS = 4


def _difference_matrix(order: int, n: int, sample_period_s: float) -> sparse.csr_matrix:
    """Rows (r-th backward difference) / T^r over n + order samples: the first ``order`` are
    the samples before the stretch."""
    coeffs = [(-1) ** (order - i) * math.comb(order, i) for i in range(order + 1)]
    return sparse.diags(coeffs, list(range(order + 1)), shape=(n, n + order), format="csr", dtype=float) / sample_period_s**order


class _Stretch:
    """Constant matrices of one window shape.

    Local control points: the first m are fixed (chosen before), the next ``n_free`` are solved.
    Rows: ``n_samples`` samples from the window's first knot; rows from ``hold_from`` on hold the
    command at its value at sample ``hold_from - 1`` (the settling stretch after the end).
    ``end_conditions``: rows of the command's derivatives 0..r at sample ``hold_from - 1``.
    """

    def __init__(self, dynamics: AxisDynamics, settings: FBSSettings, limits: AxisLimits,
                 n_samples: int, n_free: int, hold_from: int | None = None, end_conditions: bool = False):
        m, k, T = settings.degree, settings.knot_spacing_samples, dynamics.sample_period_s
        self.m, self.n_free, self.n_samples = m, n_free, n_samples
        hold_from = n_samples if hold_from is None else hold_from
        knots = uniform_knots(m + n_free, m, k * T, first_knot=-m)
        rows = np.minimum(np.arange(n_samples), hold_from - 1)
        self.N = basis_matrix(knots, m, rows * T).toarray()  # n_samples x (m + n_free)
        self.Nt = dynamics.filter(self.N)  # filtered basis, from the zero state
        self.Phi = dynamics.free_response_matrix(n_samples)

        # Objective ||W (x - y)||, W = [I; alpha_r D_r]; differences inside the stretch only.
        weights = np.ones(n_samples)
        weights[hold_from:] = settings.settle_weight
        w_rows = [sparse.diags(weights, format="csr")]
        for r, a in enumerate(settings.derivative_weights, start=1):
            if a:
                w_rows.append(a * _difference_matrix(r, n_samples - r, T))
        self.W = sparse.vstack(w_rows, format="csr")
        self.M = np.asarray(self.W @ self.Nt[:, m:])
        self.H = self.M.T @ self.M
        self._objective_scale = 1.0 / np.abs(self.H).max()
        if end_conditions:
            t_end = (hold_from - 1) * T
            self.E = np.vstack([basis_matrix(knots, m, [t_end], r).toarray()
                                for r in range(settings.end_rest_order + 1)])
            n_eq = len(self.E)
            self._factor = linalg.lu_factor(np.block([[self.H, self.E[:, m:].T],
                                                      [self.E[:, m:], np.zeros((n_eq, n_eq))]]))
        else:
            # The last m control points reach past the window, where nothing pins them: they make
            # H singular to working precision. A faint penalty on their third differences lets them
            # continue the spline's trend; the committed points, a whole overlap earlier, do not see it.
            self.E = None
            tail = sparse.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(n_free - 3, n_free), dtype=float).tocsr()[-m:]
            self.H = self.H + 1e-9 * np.trace(self.H) / n_free * (tail.T @ tail).toarray()
            self._factor = linalg.cho_factor(self.H)

        # Limits, one row per sample and limit, divided by the limit: |A_free p + offset| <= 1 with
        # offset = A_fixed p_fixed + A_prev [previous command; previous output] + A_state state.
        r_max = limits.history
        free, fixed, prev, state, row_sample = [], [], [], [], []
        for kind, table in (("command", limits.command), ("output", limits.output)):
            basis = self.N if kind == "command" else self.Nt
            for r, value in sorted(table.items()):
                D = _difference_matrix(r, n_samples, T) / value
                rows = D[:, r:] @ basis
                free.append(sparse.csr_matrix(rows[:, m:]))
                fixed.append(rows[:, :m])
                before = np.zeros((n_samples, 2 * r_max))
                column = r_max if kind == "command" else 2 * r_max
                before[:, column - r:column] = D[:, :r].toarray()
                prev.append(before)
                state.append(D[:, r:] @ self.Phi if kind == "output" else np.zeros((n_samples, self.Phi.shape[1])))
                row_sample.append(np.arange(n_samples))
        self.has_limits = bool(free)
        if self.has_limits:
            self.A_free = sparse.vstack(free, format="csc")
            self.A_fixed, self.A_prev, self.A_state = np.vstack(fixed), np.vstack(prev), np.vstack(state)
            self.row_sample = np.concatenate(row_sample)
        self._qp = None

    # ---- the pieces every solve needs -------------------------------------------------------
    def target(self, desired: np.ndarray, state: np.ndarray, p_fixed: np.ndarray) -> np.ndarray:
        """What the free control points must make the output do: x - free response - fixed part."""
        return desired - self.Phi @ state - self.Nt[:, :self.m] @ p_fixed

    def gradient(self, target: np.ndarray) -> np.ndarray:
        return self.M.T @ (self.W @ target)

    def unconstrained(self, target: np.ndarray, p_fixed: np.ndarray, end_values: np.ndarray | None) -> np.ndarray:
        if self.E is None:
            return linalg.cho_solve(self._factor, self.gradient(target))
        rhs = np.concatenate([self.gradient(target), end_values - self.E[:, :self.m] @ p_fixed])
        return linalg.lu_solve(self._factor, rhs)[:self.n_free]

    def limit_offset(self, p_fixed, state, prev_command, prev_output) -> np.ndarray:
        return self.A_fixed @ p_fixed + self.A_prev @ np.concatenate([prev_command, prev_output]) + self.A_state @ state

    def check_rows(self, n_samples: int):
        """The limit rows of the first ``n_samples`` samples: (their rows of A_free, their indices)."""
        rows = np.flatnonzero(self.row_sample < n_samples)
        return self.A_free[rows].tocsr(), rows

    def violation(self, p: np.ndarray, offset: np.ndarray, check=None) -> float:
        """Largest relative excess over a limit (0 when within), on all rows or ``check_rows``."""
        values = self.A_free @ p + offset if check is None else check[0] @ p + offset[check[1]]
        return max(0.0, float(np.abs(values).max(initial=0.0)) - 1.0)

    def constrained(self, target, p_fixed, offset, end_values, warm) -> np.ndarray | None:
        """The QP: min ||W (target - Nt_free p)||^2 s.t. every limit row, end conditions. None if unsolved.

        Limit rows are divided by their limit and the objective by its scale, so that OSQP's
        tolerances mean the same at any sample rate. Its matrices are set up once per window
        shape; each window only changes vectors.
        """
        m = self.m
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
                           lower, upper, verbose=False, polishing=True, eps_abs=1e-5, eps_rel=1e-5,
                           max_iter=100000, polish_refine_iter=20)
        else:
            self._qp.update(q=q, l=lower, u=upper)
        self._qp.warm_start(x=warm)
        # OSQP meets the limits to its tolerance; pull the bounds in by what it overshot and
        # solve again from there, until the limits hold to ``_LIMIT_TOLERANCE`` (relative).
        margin = 0.0
        for _ in range(_QP_ROUNDS):
            # OSQP 1.x prints "Polishing not needed" (through sys.stdout) whatever ``verbose`` says
            # (osqp/osqp#785); a post-processor's stdout may be a pipe that must stay clean.
            with contextlib.redirect_stdout(io.StringIO()):
                result = self._qp.solve(raise_error=False)
            if result.info.status_val not in (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
                return None
            row = self._A @ result.x
            excess = max(0.0, np.max(row[:n_limit_rows] - upper[:n_limit_rows]),
                         np.max(lower[:n_limit_rows] - row[:n_limit_rows]))
            if excess <= _LIMIT_TOLERANCE:
                break
            margin += 2.0 * excess
            tightened_l, tightened_u = lower.copy(), upper.copy()
            tightened_l[:n_limit_rows] += margin
            tightened_u[:n_limit_rows] -= margin
            self._qp.update(l=tightened_l, u=tightened_u)
        return result.x


class _Carry:
    """What the next window needs from everything solved before it."""

    def __init__(self, dynamics: AxisDynamics, m: int, r_max: int, start_mm: float):
        self.state = dynamics.rest_state(start_mm)
        self.p_fixed = np.full(m, start_mm)
        self.prev_command = np.full(r_max, start_mm)
        self.prev_output = np.full(r_max, start_mm)


def compensate_axis(desired_mm: np.ndarray, dynamics: AxisDynamics, limits: AxisLimits,
                    settings: FBSSettings = FBSSettings(), lookahead: str = "limited") -> AxisResult:
    """The compensated command for ``desired_mm`` (sampled at the dynamics' sample period).

    ``lookahead``: "limited" (sliding windows) or "complete" (one solve over everything).
    """
    desired_mm = np.asarray(desired_mm, dtype=float)
    if desired_mm.ndim != 1 or desired_mm.size == 0 or not np.all(np.isfinite(desired_mm)):
        raise ValueError("the desired trajectory must be a non-empty 1-D array of finite positions")
    settings = settings.resolve(dynamics)
    result = AxisResult(desired_mm.copy(), settings)
    if np.ptp(desired_mm) == 0.0:
        return result  # nothing moves: the command is the desired position
    if desired_mm.size <= (settings.end_rest_order + 3) * settings.knot_spacing_samples:
        return result  # a few spans: too short to shape, the end conditions would fix every point

    m, k = settings.degree, settings.knot_spacing_samples
    r_max = limits.history
    carry = _Carry(dynamics, m, r_max, desired_mm[0])
    last = desired_mm.size - 1
    commit, window = settings.commit_spans, settings.commit_spans + settings.overlap_spans
    q0 = 0  # first span of the current window
    if lookahead == "limited":
        regular = None
        # Regular windows while what follows the committed spans is longer than the final window.
        while (q0 + commit + max(window, settings.final_spans)) * k <= last:
            if regular is None:
                regular = _Stretch(dynamics, settings, limits, window * k, window)
                commit_rows = commit * k
                to_state = dynamics.input_to_state_matrix(commit_rows) @ regular.N[:commit_rows]
                advance = np.linalg.matrix_power(dynamics.A, commit_rows)
                # The kept samples and the next m + 1 spans: those depend mostly on kept control
                # points, and the next window could not undo a limit broken there.
                check_rows = regular.check_rows(commit_rows + (m + 1) * k) if regular.has_limits else None
            k0 = q0 * k
            desired = desired_mm[k0:k0 + window * k]
            p_free = _solve_window(regular, desired, carry, None, result, check_rows, k0)
            p_all = np.concatenate([carry.p_fixed, p_free[:commit]])
            result.command_mm[k0:k0 + commit_rows] = regular.N[:commit_rows, :m + commit] @ p_all
            tail = slice(max(commit_rows - r_max, 0), commit_rows)  # only the carried samples of the output
            output = regular.Phi[tail] @ carry.state + regular.Nt[tail, :m + commit] @ p_all
            carry.state = advance @ carry.state + to_state[:, :m + commit] @ p_all
            carry.p_fixed = p_all[-m:]
            carry.prev_command = np.concatenate([carry.prev_command, result.command_mm[k0:k0 + commit_rows]])[-r_max:]
            carry.prev_output = np.concatenate([carry.prev_output, output])[-r_max:]
            q0 += commit
            result.windows += 1
    elif lookahead != "complete":
        raise ValueError(f"lookahead must be 'limited' or 'complete', not {lookahead!r}")

    # The final window: from span q0 to the end, the end conditions, and the settling stretch.
    k0 = q0 * k
    n_rows = last - k0 + 1
    # The spans up to the last sample; a point whose support starts at the last sample does nothing.
    final = _Stretch(dynamics, settings, limits, n_rows + settings.settle_samples, max(1, -(-(n_rows - 1) // k)),
                     hold_from=n_rows, end_conditions=True)
    desired = np.concatenate([desired_mm[k0:], np.full(settings.settle_samples, desired_mm[-1])])
    end_values = np.zeros(settings.end_rest_order + 1)
    end_values[0] = desired_mm[-1]
    p_free = _solve_window(final, desired, carry, end_values, result, None, k0)
    result.command_mm[k0:] = final.N[:n_rows] @ np.concatenate([carry.p_fixed, p_free])
    # Both ends are these positions in exact arithmetic; make them so in floating point too.
    result.command_mm[0], result.command_mm[-1] = desired_mm[0], desired_mm[-1]
    result.windows += 1
    return result


def _solve_window(stretch: _Stretch, desired, carry: _Carry, end_values, result: AxisResult, check,
                  first_sample: int) -> np.ndarray:
    """Free control points of one window: the unconstrained optimum, or the QP where it breaks a
    limit on the ``check`` rows (the samples whose command this window decides)."""
    target = stretch.target(desired, carry.state, carry.p_fixed)
    p = stretch.unconstrained(target, carry.p_fixed, end_values)
    if not stretch.has_limits:
        return p
    offset = stretch.limit_offset(carry.p_fixed, carry.state, carry.prev_command, carry.prev_output)
    if stretch.violation(p, offset, check) <= 0.0:
        return p
    result.qp_windows += 1
    p_qp = stretch.constrained(target, carry.p_fixed, offset, end_values, warm=p)
    best = p if p_qp is None else p_qp
    excess = stretch.violation(best, offset)
    if excess <= _LIMIT_TOLERANCE:
        return best
    result.warnings.append(f"window from sample {first_sample}: the limits could not be met; "
                           f"the command there exceeds them by up to {excess:.3g} (relative)")
    return best
