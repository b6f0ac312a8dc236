"""One window shape of the optimizer: its constant matrices, and what windows carry between them.

Takes the model set, the resolved ``FBSSettings``, the ``AxisLimits`` and a window's size; gives
``Window`` (the basis and filtered basis, the objective and its factorization, the limit rows, and
its ``LimitedQP`` for the windows whose optimum breaks a limit), ``Carry`` (the layout of the vector
one window passes to the next) and ``Sweep`` (the regular window folded into linear maps of that
carry, for the windows within the limits).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import linalg, sparse

from .dynamics import ModelSet
from .limited_qp import LimitedQP
from .settings import AxisLimits, FBSSettings
from .splines import basis_matrix, uniform_knots


def difference_matrix(order: int, n: int, sample_period_s: float) -> sparse.csr_matrix:
    """Rows (r-th backward difference) / T^r over n + order samples: the first ``order`` are
    the samples before the stretch."""
    coeffs = [(-1) ** (order - i) * math.comb(order, i) for i in range(order + 1)]
    return (
        sparse.diags(coeffs, list(range(order + 1)), shape=(n, n + order), format="csr", dtype=float)
        / sample_period_s**order
    )



class Window:
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
                w_rows.append(a * difference_matrix(r, n_samples - r, T))
        self.W = sparse.vstack(w_rows, format="csr")
        if self.n_models > 1:  # sum over the models of weight x error^2
            self.W = sparse.block_diag([math.sqrt(w) * self.W for w in models.weights], format="csr")
        self.M = np.asarray(self.W @ self.Nt[:, m:])
        self.H = self.M.T @ self.M
        self.objective_scale = 1.0 / np.abs(self.H).max()
        if end_conditions:
            t_end = (hold_from - 1) / k * (k * T)
            self.E = np.vstack([basis_matrix(knots, m, [t_end], r).toarray()
                                for r in range(settings.end_rest_order + 1)])
            n_eq = len(self.E)
            self.factor = linalg.lu_factor(np.block([[self.H, self.E[:, m:].T],
                                                      [self.E[:, m:], np.zeros((n_eq, n_eq))]]))
            # OSQP meets equality rows only to its tolerance; the end conditions are then solved
            # exactly for the n_eq best-conditioned points they involve (pivoted QR) from the rest.
            pivots = linalg.qr(self.E[:, m:], pivoting=True, mode="r")[1][:n_eq]
            self.end_points = pivots
            self.end_solve = linalg.lu_factor(self.E[:, m:][:, pivots])
        else:
            # The last m control points reach past the window, where nothing pins them: they make
            # H singular to working precision. A faint penalty on their third differences lets them
            # continue the spline's trend; the committed points, a whole overlap earlier, do not see it.
            self.E = None
            third = sparse.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(n_free - 3, n_free), dtype=float)
            tail = third.tocsr()[-m:]
            self.H = self.H + 1e-9 * np.trace(self.H) / n_free * (tail.T @ tail).toarray()
            # The solve for every right-hand side at once: p_free = G target.
            self.factor = linalg.cho_factor(self.H)
            self.G = linalg.cho_solve(self.factor, np.asarray(self.W.T @ self.M).T)

        self._limit_rows(limits, n_samples, T)
        self.qp = LimitedQP(self)

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
                D = difference_matrix(r, n_samples, T) / value
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
        held = [x for v in (*vars(self).values(), *vars(self.qp).values())
                for x in (v if isinstance(v, tuple) else (v,))]
        return sum(v.nbytes if isinstance(v, np.ndarray) else v.data.nbytes + v.indices.nbytes + v.indptr.nbytes
                   for v in held if isinstance(v, np.ndarray) or sparse.issparse(v))

    def reset(self) -> None:
        """Drop OSQP's state (its duals) from earlier windows: a reused window solves as a new one."""
        self.qp.reset()

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
        return linalg.lu_solve(self.factor, rhs)[:self.n_free]

    def limit_offset(self, p_fixed, state, previous, desired) -> np.ndarray:
        """``previous``: the last commands, then the last outputs, before the window; ``desired``:
        the window's desired trajectory (where the travel's rows center)."""
        return (self.A_fixed @ p_fixed + self.A_prev @ previous + self.A_state @ state
                + self.A_center * self.position_center(desired))

    def constrained(self, target, p_fixed, offset, end_values, warm) -> np.ndarray | None:
        """The QP within the limits (``LimitedQP.constrained``); None if unsolved."""
        return self.qp.constrained(target, p_fixed, offset, end_values, warm)

    def check_rows(self, n_samples: int):
        """The limit rows of the first ``n_samples`` samples: (their rows of A_free, their indices)."""
        rows = np.flatnonzero(self.row_sample < n_samples)
        return self.A_free[rows].tocsr(), rows

    def violation(self, p: np.ndarray, offset: np.ndarray) -> float:
        """Largest relative excess over a limit (0 when within)."""
        return max(0.0, float(np.abs(self.A_free @ p + offset).max(initial=0.0)) - 1.0)


class Carry:
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


class Sweep:
    """The regular window folded into linear maps of the carry z, for the windows whose
    unconstrained optimum meets the limits (most of them): the first control points
    p = Gd desired - Gz z, the limit rows of the samples the window decides (divided by the
    limit) A p + Az z, and the next carry z' = L [z; kept points]. Everything here is built
    once per axis."""

    def __init__(self, stretch: Window, models: ModelSet, carry: Carry, commit: int, k: int):
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

