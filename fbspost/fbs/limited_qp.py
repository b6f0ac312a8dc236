"""The QP of one window whose unconstrained optimum breaks a limit.

Takes a window (``windows.Window``: its Hessian ``H``, limit rows ``A_free``, end conditions ``E``
and factorization ``factor``), the window's target and limit offsets and the optimum without the
limits; gives the control points of the optimum within the limits (relative excess at most
``settings.LIMIT_TOLERANCE``), or None. DAQP (least-distance form) for a regular window, the dual
active-set method of Goldfarb and Idnani for a final one and where DAQP fails, OSQP where neither
finishes.
"""
from __future__ import annotations

import weakref

import daqp
import numpy as np
from scipy import linalg, sparse

from .settings import LIMIT_TOLERANCE

_QP_ROUNDS = 4
_ACTIVE_SET_STEPS = 400


class LimitedQP:
    """A window's QP under the command limits (``constrained``): DAQP for a regular window, our
    dual active-set method for a final one (and where DAQP fails), OSQP where neither finishes.
    Held by a ``windows.Window``, whose matrices and factorizations it reads (``window``); it keeps
    the solvers' set-up, built on first use."""

    def __init__(self, window):
        # A proxy: a reference would make a cycle with the window that holds this, which only the
        # cyclic collector frees, so evicted windows' matrices would pile up (1.5 GB on systems.ngc).
        self.window = weakref.proxy(window)
        self._qp = None  # OSQP's problem, with its matrix ``_A``
        self._ldp = self._hinv_at = None  # DAQP's least-distance problem; H^-1 A^T and the Gram matrix

    def reset(self) -> None:
        """Drop OSQP's state (its duals) from earlier windows: a reused window solves as a new one."""
        self._qp = None

    def constrained(self, target, p_fixed, offset, end_values, warm) -> np.ndarray | None:
        """The QP: min ||W (target - Nt_free p)||^2 s.t. every limit row, end conditions, from
        ``warm``, the optimum without the limits. None if unsolved.

        A dual active-set method first (DAQP for a regular window, ours, which takes the end
        conditions, for a final one); OSQP where that does not finish. For OSQP, limit rows
        are divided by their limit and the objective by its scale, so that its tolerances mean
        the same at any sample rate; its matrices are set up once per window shape and each
        window only changes vectors.
        """
        w = self.window
        m = w.m
        p = self.least_distance(warm, offset) if w.E is None else self.active_set(warm, offset)
        if p is not None:
            return p
        import osqp  # rarely needed: not loaded before

        lower, upper = -1.0 - offset, 1.0 - offset
        n_limit_rows = len(lower)
        if w.E is not None:
            scale = np.abs(w.E[:, m:]).max(axis=1)
            rhs = (end_values - w.E[:, :m] @ p_fixed) / scale
            lower, upper = np.concatenate([lower, rhs]), np.concatenate([upper, rhs])
        q = -w.gradient(target) * w.objective_scale
        if self._qp is None:
            A = w.A_free
            if w.E is not None:
                A = sparse.vstack([A, sparse.csr_matrix(w.E[:, m:] / scale[:, None])], format="csc")
            self._A = A
            self._qp = osqp.OSQP()
            self._qp.setup(sparse.triu(sparse.csc_matrix(w.H * w.objective_scale), format="csc"), q, A,
                           lower, upper, verbose=False, polishing=False, eps_abs=1e-6, eps_rel=1e-6,
                           max_iter=100000)
        else:
            self._qp.update(q=q, l=lower, u=upper)
        self._qp.warm_start(x=warm)
        # OSQP meets the limits to its tolerance; pull the bounds in by what it overshot and
        # solve again from there, until the limits hold to ``LIMIT_TOLERANCE`` (relative).
        margin = 0.0
        for _ in range(_QP_ROUNDS):
            result = self._qp.solve(raise_error=False)
            if result.info.status_val not in (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
                return None
            x = result.x
            if w.E is not None:
                x = x.copy()
                x[w.end_points] = 0.0
                x[w.end_points] = linalg.lu_solve(w.end_solve, rhs * scale - w.E[:, m:] @ x)
            row = self._A @ x
            excess = max(0.0, np.max(row[:n_limit_rows] - upper[:n_limit_rows]),
                         np.max(lower[:n_limit_rows] - row[:n_limit_rows]))
            if excess <= LIMIT_TOLERANCE:
                break
            margin += 2.0 * excess
            tightened_l, tightened_u = lower.copy(), upper.copy()
            tightened_l[:n_limit_rows] += margin
            tightened_u[:n_limit_rows] -= margin
            self._qp.update(l=tightened_l, u=tightened_u)
        return x

    def least_distance(self, p_free: np.ndarray, offset: np.ndarray) -> np.ndarray | None:
        """A regular window's QP by DAQP (Arnstrom, Bemporad, Axehill: a compiled dual active-set
        method for small dense QPs) in least-distance form: with H = R^T R and u = R p,
        min ||u - R p_free||^2 s.t. |A R^-1 u + offset| <= 1. R and A R^-1 are the window
        shape's, set up once; each window starts from no held row (the previous window's rows
        are other samples). Ours (exact) where DAQP fails or misses the limits: on these
        ill-conditioned windows (cond(H) to 1e12) it may call a barely feasible window infeasible."""
        w = self.window
        lower, upper = -1.0 - offset, 1.0 - offset
        if self._ldp is None:
            self._root = linalg.cholesky(w.H)  # (Fortran order, as LAPACK takes it)
            self._trtrs, = linalg.get_lapack_funcs(("trtrs",), (self._root,))
            rows = linalg.solve_triangular(self._root, w.A_free.toarray().T, trans="T").T
            self._ldp = daqp.Model()
            self._ldp.setup(np.eye(w.n_free), -(self._root @ p_free), rows, upper, lower)
            self._ldp.settings = {"primal_tol": 0.1 * LIMIT_TOLERANCE}
            self._cold = np.zeros(len(offset), dtype=np.int32)
        else:
            self._ldp.update(f=-(self._root @ p_free), bupper=upper, blower=lower, sense=self._cold)
        u, _, flag, _ = self._ldp.solve()
        if flag > 0:
            # R p = u: linalg.solve_triangular's own LAPACK call, less its checks (20 -> 2 us)
            p, singular = self._trtrs(self._root, u)
            if not singular and w.violation(p, offset) <= LIMIT_TOLERANCE:
                return p
        return self.active_set(p_free, offset)

    def active_set(self, p_free: np.ndarray, offset: np.ndarray) -> np.ndarray | None:
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
        w = self.window
        column, direction = self._gram_columns()
        start = w.A_free @ p_free + offset
        rows, lam = [], np.zeros(0)  # held rows; sign(lambda) says which bound
        held_columns = np.zeros((start.size, 0))  # their Gram columns
        value = start
        steps = 0
        while steps < _ACTIVE_SET_STEPS:
            q = int(np.argmax(np.abs(value)))
            if abs(value[q]) <= 1.0 + LIMIT_TOLERANCE:
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
        w = self.window
        if w.E is None:
            if self._hinv_at is None:
                dense = w.A_free.toarray()
                self._hinv_at = np.asfortranarray(linalg.cho_solve(w.factor, dense.T))  # H^-1 A^T
                self._gram = np.asfortranarray(dense @ self._hinv_at)
            return (lambda q: self._gram[:, q]), (lambda q: self._hinv_at[:, q])
        rows_of_a, n_eq, found = w.A_free.tocsr(), len(w.E), {}

        def solve(q):
            if q not in found:
                rhs = np.concatenate([rows_of_a[q].toarray().ravel(), np.zeros(n_eq)])
                k_col = linalg.lu_solve(w.factor, rhs)[:w.n_free]
                found[q] = (w.A_free @ k_col, k_col)
            return found[q]
        return (lambda q: solve(q)[0]), (lambda q: solve(q)[1])

