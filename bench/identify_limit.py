"""How well can any fit to a noisy FRF compensate the patent's butterfly? The Cramer-Rao spread.

Run from the repository root:  python bench/identify_limit.py [--noise 0.01] [--dc-known]

The tests identify the patent's axes from their FRF (1..150 Hz every 0.05 Hz) with complex
Gaussian noise of ``--noise`` times |G|, and compensate the butterfly with the result. An
identified model G^ (scaled to DC gain 1) adds the error (1 - G / G^) x_d to the true model's
residual. Linearized about the true parameters (frequency, damping, alpha, beta of each mode),
a maximum-likelihood fit's parameter error is Gaussian with the inverse Fisher information as
covariance (the Cramer-Rao bound: no unbiased fit does better); sampled, that gives the
distribution of the butterfly RMS with the identified model over noise draws, as a ratio to the
RMS with the true model (the two errors are uncorrelated: measured). ``--dc-known``: the DC gain
is taken as exactly known (one constraint fewer to estimate).
"""
from __future__ import annotations

import argparse

import numpy as np

from fbspost.fbs.dynamics import AxisDynamics, modal_response
from fbspost.fbs.optimizer import compensate_axis
from fbspost.fbs.settings import AxisLimits
from fbspost.profile import Mode, load_profile
from fbspost.tools.examples import butterfly


def log_response_derivatives(modes, frequency_hz):
    """d log G / d (f, zeta, alpha, beta of each mode), central differences; one column each."""
    params = np.array([[m.frequency_hz, m.damping, m.alpha, m.beta] for m in modes])
    columns = []
    for i, j in np.ndindex(params.shape):
        step = 1e-6 * abs(params[i, j])
        logs = []
        for sign in (1, -1):
            p = params.copy()
            p[i, j] += sign * step
            logs.append(np.log(modal_response([Mode(*row) for row in p], frequency_hz)))
        columns.append((logs[0] - logs[1]) / (2 * step))
    return np.stack(columns, axis=1)


def main(noise: float, dc_known: bool, draws: int = 20000) -> None:
    profile = load_profile("patent-xy-stage")
    period_s = 1.0 / profile.sample_rate_hz
    _, x, y = butterfly(sample_rate_hz=profile.sample_rate_hz, size_mm=0.8)
    skip = int(0.05 / period_s)  # as the tests
    f = np.arange(1.0, 150.0 + 1e-9, 0.05)
    for axis_name, desired in (("X", x), ("Y", y)):
        axis = profile.axes[axis_name]
        dynamics = AxisDynamics(axis.modes, period_s)
        command = compensate_axis(desired, dynamics, AxisLimits.from_profile(axis)).command_mm
        rms_true = np.sqrt(np.mean((desired - dynamics.simulate(command))[skip:] ** 2))
        # Fisher information of the relative residual (G_theta - h) / |G|: noise variance
        # noise^2 / 2 in each of its real and imaginary parts.
        j = log_response_derivatives(axis.modes, f)
        covariance = np.linalg.inv(np.real(j.conj().T @ j) / (noise**2 / 2))
        if dc_known:  # projected onto the parameters that keep sum(alpha / w^2)
            w = np.array([m.omega_rad_s for m in axis.modes])
            c = np.zeros(covariance.shape[0])
            c[0::4] = -2 * np.array([m.alpha for m in axis.modes]) / w**2 * (2 * np.pi) / w  # d / d frequency
            c[2::4] = 1 / w**2
            covariance -= np.outer(covariance @ c, c @ covariance) / (c @ covariance @ c)
        # the butterfly error added per parameter error: (d log G - d log G(0)) x_d, G^ at DC gain 1
        n = len(desired)
        spectrum = np.fft.rfft(desired - desired[0])
        fz = np.fft.rfftfreq(n, period_s)
        d_log = log_response_derivatives(axis.modes, fz[1:]) - log_response_derivatives(axis.modes, [1e-6]).real
        d_log = np.vstack([np.zeros(d_log.shape[1]), d_log])  # none at DC
        s = np.stack([np.fft.irfft(d_log[:, k] * spectrum, n)[skip:] for k in range(d_log.shape[1])], axis=1)
        gram = s.T @ s / s.shape[0]
        rng = np.random.default_rng(0)
        dtheta = rng.multivariate_normal(np.zeros(len(covariance)), covariance, size=draws)
        added = np.sqrt(np.einsum("ij,jk,ik->i", dtheta, gram, dtheta))
        ratio = np.sqrt(rms_true**2 + added**2) / rms_true
        p = np.mean(ratio <= 1.10)
        print(f"{axis_name}: true model {1e3 * rms_true:.4f} um; "
              f"added by the fit: median {1e3 * np.median(added):.4f} um; "
              f"ratio to the true model 10/50/90%: "
              f"{' / '.join(f'{q:.3f}' for q in np.quantile(ratio, [0.1, 0.5, 0.9]))}; "
              f"P(<= 1.10) {p:.3f}, all of 5 seeds {p**5:.3g}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=0.01, help="complex noise, relative to |G| (default 0.01)")
    parser.add_argument("--dc-known", action="store_true", help="the DC gain known exactly")
    args = parser.parse_args()
    main(args.noise, args.dc_known)
