"""Benchmark the FBS engine: complete vs limited look-ahead on the patent's butterfly, and the
optimizer's throughput on a long trajectory.

Run from the repository root:  python bench/engine.py [--long-seconds 60]
"""
from __future__ import annotations

import argparse
import functools
import time

import numpy as np

from fbspost.fbs.dynamics import AxisDynamics
from fbspost.fbs.optimizer import AxisCompensator, compensate_axis
from fbspost.fbs.settings import AxisLimits
from fbspost.profile import load_profile
from fbspost.tools.examples import butterfly


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def butterfly_table(profile):
    period_s = 1.0 / profile.sample_rate_hz
    _, x, y = butterfly(profile.sample_rate_hz, size_mm=0.8)
    skip = int(0.05 / period_s)
    print(f"Butterfly on {profile.name}: {x.size} samples ({(x.size - 1) * period_s:.3f} s) at "
          f"{profile.sample_rate_hz:g} Hz, profile limits, RMS tracking error after the first 50 ms")
    print(f"{'axis':4} {'look-ahead':10} {'time s':>8} {'windows':>7} {'QP':>3} {'RMS um':>9} "
          f"{'max um':>8} {'% of uncomp.':>12} {'max |v|':>8} {'max |a|':>8}")
    for name, desired in (("X", x), ("Y", y)):
        axis = profile.axes[name]
        dynamics = AxisDynamics(axis.modes, period_s)
        limits = AxisLimits.from_profile(axis)
        base = rms((desired - dynamics.simulate(desired))[skip:])
        print(f"{name:4} {'none':10} {'':>8} {'':>7} {'':>3} {base * 1e3:9.3f} "
              f"{np.abs(desired - dynamics.simulate(desired))[skip:].max() * 1e3:8.2f} {100:12.3f}")
        times = {}
        for mode in ("complete", "limited"):
            result, times[mode] = timed(functools.partial(compensate_axis, desired, dynamics, limits, lookahead=mode))
            u = result.command_mm
            err = (desired - dynamics.simulate(u))[skip:]
            print(f"{name:4} {mode:10} {times[mode]:8.2f} {result.windows:7d} {result.qp_windows:3d} "
                  f"{rms(err) * 1e3:9.4f} {np.abs(err).max() * 1e3:8.3f} {100 * rms(err) / base:12.4f} "
                  f"{np.abs(np.diff(u)).max() / period_s:8.2f} {np.abs(np.diff(u, 2)).max() / period_s**2:8.1f}")
        print(f"{name:4} limited look-ahead is {times['complete'] / times['limited']:.1f}x faster than complete "
              f"({100 * (1 - times['limited'] / times['complete']):.1f}% of the computation saved)")


def throughput(profile, seconds):
    """A long smooth random trajectory (band-limited, within the planner's limits): samples/s."""
    period_s = 1.0 / profile.sample_rate_hz
    n = int(seconds * profile.sample_rate_hz)
    rng = np.random.default_rng(1)
    t = np.arange(n) * period_s
    desired = np.zeros(n)
    for f in rng.uniform(0.2, 3.0, 12):
        desired += rng.uniform(0.2, 1.0) / f * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    desired *= np.minimum(1.0, np.minimum(t, t[-1] - t) / 0.5) ** 3  # start and end at rest
    print(f"\nThroughput: {seconds:g} s of smooth motion ({n} samples), limited look-ahead, one process; the set-up "
          f"(once per axis in a program) excluded; the regular windows, then the final one (once per run)")
    print(f"{'axis':4} {'limits':8} {'time s':>8} {'samples/s':>12} {'final s':>8} {'windows':>7} {'QP':>4}")
    for name, axis in profile.axes.items():
        dynamics = AxisDynamics(axis.modes, period_s)
        for label, limits in (("none", AxisLimits()), ("profile", AxisLimits.from_profile(axis))):
            compensate = AxisCompensator(dynamics, limits)
            compensate(desired[:n // 10])
            stream = compensate.stream()
            regular, elapsed = timed(functools.partial(stream.push, desired))
            result, final_s = timed(stream.finish)
            print(f"{name:4} {label:8} {elapsed:8.2f} {regular.size / elapsed:12.0f} {final_s:8.2f} "
                  f"{result.windows:7d} {result.qp_windows:4d}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--long-seconds", type=float, default=60.0, help="length of the throughput trajectory")
    args = parser.parse_args()
    profile = load_profile("patent-xy-stage")
    butterfly_table(profile)
    throughput(profile, args.long_seconds)


if __name__ == "__main__":
    main()
