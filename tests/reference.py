"""Independent truths for the tests: nothing here calls fbspost's dynamics or optimizer."""
from __future__ import annotations

import numpy as np
from scipy import linalg, signal


def continuous_model(modes):
    """Block-diagonal continuous state space of sum_i (alpha + beta s)/(s^2 + 2 z w s + w^2)."""
    blocks, b, c = [], [], []
    for mode in modes:
        w = 2 * np.pi * mode.frequency_hz
        blocks.append(np.array([[0.0, 1.0], [-w * w, -2 * mode.damping * w]]))
        b += [0.0, 1.0]
        c += [mode.alpha, mode.beta]
    return linalg.block_diag(*blocks), np.array(b)[:, None], np.array(c)[None, :], np.zeros((1, 1))


def simulate_lsim(modes, period_s, command):
    """Actual position for a zero-order-hold command, from rest at command[0] (scipy.signal.lsim)."""
    command = np.asarray(command, dtype=float)
    t = np.arange(command.size) * period_s
    _, y, _ = signal.lsim(continuous_model(modes), command - command[0], t, interp=False)
    return np.asarray(y) + command[0]


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def finite_derivative_max(u, order, period_s):
    """Largest |r-th backward difference| / T^r of the sampled command, counting the rest before
    the first sample and the hold after the last (the machine sees both)."""
    padded = np.concatenate([np.full(order, u[0]), u, np.full(order, u[-1])])
    return float(np.abs(np.diff(padded, order)).max() / period_s**order)
