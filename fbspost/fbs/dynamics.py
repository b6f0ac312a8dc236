"""Axis dynamics: each mode of an axis discretized exactly (zero-order hold), in parallel form.

Takes an axis' modes (``profile.Mode``) and the sample period; gives the discrete state-space
model x[k+1] = A x[k] + B u[k], y[k] = C x[k] from commanded position u to actual position y
(two states per mode, block diagonal), simulation from rest, the continuous frequency
response, poles and zeros. The command u[k] is held over [k T, (k+1) T), so y[k] is exactly the
continuous response at t = k T.

A single high-order transfer function at 10 kHz is numerically useless (its poles crowd at z = 1),
so nothing here ever multiplies modes together in discrete time.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import linalg, signal

from ..profile import Mode


class AxisDynamics:
    """Discrete exact model of one axis at ``sample_period_s``."""

    def __init__(self, modes: tuple[Mode, ...] | list[Mode], sample_period_s: float):
        if not modes:
            raise ValueError("an axis without modes has no dynamics to model")
        if not sample_period_s > 0:
            raise ValueError(f"the sample period must be > 0 s, got {sample_period_s!r}")
        self.modes = tuple(modes)
        self.sample_period_s = float(sample_period_s)
        blocks_a, blocks_b, blocks_c = [], [], []
        self.mode_filters = []  # (b, a) per mode, for lfilter (b[0] = 0: no feedthrough)
        for mode in self.modes:
            w, z = mode.omega_rad_s, mode.damping
            a_c = np.array([[0.0, 1.0], [-w * w, -2.0 * z * w]])
            b_c = np.array([[0.0], [1.0]])
            c_c = np.array([[mode.alpha, mode.beta]])
            a_d, b_d, c_d, d_d, _ = signal.cont2discrete(
                (a_c, b_c, c_c, np.zeros((1, 1))), self.sample_period_s, method="zoh"
            )
            blocks_a.append(a_d)
            blocks_b.append(b_d[:, 0])
            blocks_c.append(c_d[0])
            num, den = signal.ss2tf(a_d, b_d, c_d, d_d)
            self.mode_filters.append((num[0], den))
        self.A = linalg.block_diag(*blocks_a)
        self.B = np.concatenate(blocks_b)
        self.C = np.concatenate(blocks_c)

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def dc_gain(self) -> float:
        """Continuous DC gain sum(alpha / w^2); exactly 1 for a normalized profile."""
        return float(sum(m.alpha / m.omega_rad_s**2 for m in self.modes))

    def rest_state(self, position_mm: float) -> np.ndarray:
        """The state of the axis at rest under a constant command ``position_mm``."""
        return np.linalg.solve(np.eye(self.n_states) - self.A, self.B * position_mm)

    def filter(self, u: np.ndarray, axis: int = 0) -> np.ndarray:
        """Response to ``u`` from the zero state (u taken as zero before its first sample)."""
        u = np.asarray(u, dtype=float)
        return sum(signal.lfilter(b, a, u, axis=axis) for b, a in self.mode_filters)

    def simulate(self, command_mm: np.ndarray) -> np.ndarray:
        """Actual position for ``command_mm``, starting at rest at the first commanded position."""
        command_mm = np.asarray(command_mm, dtype=float)
        if command_mm.size == 0:
            return command_mm.copy()
        return self.response(command_mm[0])(command_mm)

    def response(self, start_mm: float):
        """``simulate`` for a command given in pieces, from rest at ``start_mm``: a function
        taking each next piece of the command (mm) and giving that piece of the actual position."""
        states = [np.zeros(len(a) - 1) for _, a in self.mode_filters]

        def step(command_mm: np.ndarray) -> np.ndarray:
            u = np.asarray(command_mm, dtype=float) - start_mm
            if not u.size:
                return u  # (lfilter gives a garbage final state for an empty input)
            total = 0.0
            for i, (b, a) in enumerate(self.mode_filters):
                y, states[i] = signal.lfilter(b, a, u, zi=states[i])
                total = total + y
            return start_mm + total

        return step

    def markov(self, n_samples: int) -> np.ndarray:
        """Impulse response h[k] = C A^(k-1) B (h[0] = 0): y = h * u."""
        impulse = np.zeros(n_samples)
        impulse[:1] = 1.0
        return self.filter(impulse)

    def free_response_matrix(self, n_samples: int) -> np.ndarray:
        """Rows C A^k, k = 0..n_samples-1: the output caused by the state at sample 0."""
        out = np.empty((n_samples, self.n_states))
        row = self.C.copy()
        for k in range(n_samples):
            out[k] = row
            row = row @ self.A
        return out

    def input_to_state_matrix(self, n_samples: int) -> np.ndarray:
        """Columns A^(n-1-i) B: the state after ``n_samples`` inputs u[0..n-1] from the zero state."""
        out = np.empty((self.n_states, n_samples))
        col = self.B.copy()
        for i in range(n_samples - 1, -1, -1):
            out[:, i] = col
            col = self.A @ col
        return out

    def frequency_response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Continuous G(j 2 pi f), commanded to actual position."""
        return modal_response(self.modes, frequency_hz)

    def poles(self) -> np.ndarray:
        """Continuous poles, rad/s."""
        return np.concatenate([np.roots([1.0, 2 * m.damping * m.omega_rad_s, m.omega_rad_s**2]) for m in self.modes])

    def zeros(self) -> np.ndarray:
        """Continuous zeros of G(s), rad/s (roots of the numerator of the summed modes)."""
        dens = [np.array([1.0, 2 * m.damping * m.omega_rad_s, m.omega_rad_s**2]) for m in self.modes]
        terms = []
        for i, m in enumerate(self.modes):
            term = np.array([m.beta, m.alpha])
            for j, den in enumerate(dens):
                if j != i:
                    term = np.convolve(term, den)  # (not np.polymul: it drops a leading 0, a mode without beta)
            terms.append(term)
        terms = np.array(terms)
        numerator = terms.sum(axis=0)
        # A leading coefficient that is only the rounding left of cancelling terms (betas summing
        # to zero) is zero: kept, it would put a spurious zero near infinity.
        cancelled = np.abs(numerator) <= 1e-12 * np.abs(terms).sum(axis=0)
        leading = np.argmin(cancelled) if not cancelled.all() else numerator.size
        return np.roots(numerator[leading:])


def scaled_mode(mode: Mode, frequency_scale: float = 1.0, damping_scale: float = 1.0) -> Mode:
    """``mode`` with its frequency and damping scaled; the residues follow the frequency (alpha as
    w^2, beta as w) so the mode keeps its DC gain and its shape in time."""
    return replace(mode, frequency_hz=mode.frequency_hz * frequency_scale, damping=mode.damping * damping_scale,
                   alpha=mode.alpha * frequency_scale**2, beta=mode.beta * frequency_scale)


# The machine below the profiled frequency, and below the profiled damping, weighs this much more in
# the set (by frequency: True, damping: False): it rings with more amplitude and for longer, and an
# equal weight left FBS above the best input shaper there (docs/robust.md: measured on the gear print).
LOW_END_WEIGHTS = {True: 1.5, False: 3.0}


class ModelSet:
    """Several models of one axis side by side, the nominal first: the states of all stacked
    (block-diagonal A, B stacked), and every output stacked in the same order (``filter``,
    ``free_response_matrix``). The optimizer minimizes the sum of their squared errors, each
    times its weight; its limits and carried outputs are the nominal's."""

    def __init__(self, models: list[AxisDynamics], weights: list[float] | None = None):
        self.models = tuple(models)
        self.nominal = self.models[0]
        self.weights = tuple(weights) if weights is not None else (1.0,) * len(self.models)
        self.sample_period_s = self.nominal.sample_period_s
        self.A = linalg.block_diag(*(d.A for d in self.models))
        self.B = np.concatenate([d.B for d in self.models])
        self.n_states = self.A.shape[0]

    @classmethod
    def spread(cls, modes, sample_period_s: float) -> ModelSet:
        """The nominal ``modes`` and the machines with every mode's frequency, then every mode's
        damping, at the low and at the high end of its tolerance (``Mode.frequency_tolerance``,
        ``damping_tolerance``): the modes drift together, as a load or a temperature moves them.
        The weighted mean squared error over the set, the low ends weighing more
        (``LOW_END_WEIGHTS``). Just the nominal without tolerances."""
        modes = tuple(modes)
        variants, weights = [modes], [1.0]
        for sign in (-1.0, 1.0):
            for frequency in (True, False):
                variant = tuple(scaled_mode(m, 1.0 + sign * m.frequency_tolerance) if frequency
                                else scaled_mode(m, 1.0, 1.0 + sign * m.damping_tolerance) for m in modes)
                if variant != modes:
                    variants.append(variant)
                    weights.append(LOW_END_WEIGHTS[frequency] if sign < 0 else 1.0)
        return cls([AxisDynamics(v, sample_period_s) for v in variants], weights)

    def rest_state(self, position_mm: float) -> np.ndarray:
        return np.concatenate([d.rest_state(position_mm) for d in self.models])

    def filter(self, u: np.ndarray) -> np.ndarray:
        """Every model's response to ``u`` (along axis 0) from the zero state, stacked."""
        return np.concatenate([d.filter(u) for d in self.models])

    def free_response_matrix(self, n_samples: int) -> np.ndarray:
        """Each model's rows C A^k on its own states: (models x n_samples, n_states)."""
        return linalg.block_diag(*(d.free_response_matrix(n_samples) for d in self.models))

    def input_to_state_matrix(self, n_samples: int) -> np.ndarray:
        return np.vstack([d.input_to_state_matrix(n_samples) for d in self.models])


def modal_response(modes, frequency_hz: np.ndarray) -> np.ndarray:
    """sum_i (alpha_i + beta_i s) / (s^2 + 2 zeta_i w_i s + w_i^2) at s = j 2 pi f: the continuous
    frequency response of ``modes`` (profile.Mode), commanded to actual position."""
    s = 2j * np.pi * np.asarray(frequency_hz, dtype=float)
    return sum((m.alpha + m.beta * s) / (s * s + 2 * m.damping * m.omega_rad_s * s + m.omega_rad_s**2)
               for m in modes) + np.zeros_like(s)
