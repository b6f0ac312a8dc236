"""The plan sent to the axes' processes (planfeed.py) is the plan: an axis process' proxy gives
the very samples, runs and moves that planning the program itself gives, batch after batch."""
from pathlib import Path

import numpy as np
import pytest

from fbspost.job import planfeed
from fbspost.plan.margins import RunMargins
from fbspost.plan.planner import PlanStream
from fbspost.profile import load_profile
from fbspost.read.gcode import read_gcode

DATA = Path(__file__).parent / "data"


class _Wire:
    """The channel of one axis' process, here: a request is answered at once."""

    def __init__(self, feed: planfeed.PlanFeed, key: int):
        self.feed, self.key, self.inbox = feed, key, []

    def request(self):
        self.feed.answer(self.key, self.inbox.append)

    def get(self):
        return self.inbox.pop(0)


def _plan(source: Path, profile):
    return PlanStream(read_gcode(source, "marlin", profile.home_mm), profile,
                      margins=RunMargins.for_profile(profile, flavor="marlin"), firmware="marlin")


@pytest.mark.parametrize("batch_samples", [700, planfeed.BATCH_SAMPLES])
def test_the_proxy_gives_the_plan_itself(tmp_path, monkeypatch, batch_samples):
    """The gear's head (22 runs, rests between) planned twice: once as the axes'
    processes are sent it (X alone, and Y with E, a varying mode's column), once by itself."""
    monkeypatch.setattr(planfeed, "BATCH_SAMPLES", batch_samples)
    source = tmp_path / "gear.gcode"
    with open(DATA / "gear-marlin2.gcode", "rb") as f:
        source.write_bytes(b"".join(f.readline() for _ in range(900)))
    profile = load_profile("printer-two-mode")
    truth = _plan(source, profile)
    truth.wait(lambda: False)
    feed = planfeed.PlanFeed(_plan(source, profile), {0: [0], 1: [1, 3]})
    proxies = {key: planfeed.PlanProxy(_Wire(feed, key), profile.sample_rate_hz, columns)
               for key, columns in feed.columns.items()}
    open_at_a_batch_end = 0
    while not all(proxy.done for proxy in proxies.values()):
        for proxy in proxies.values():
            frontier = proxy.frontier
            proxy.wait(lambda p=proxy, f=frontier: p.frontier > f)
            # what a process is told is settled is: runs start below the frontier, and end below it
            assert all(first < proxy.frontier and (last is None or last < proxy.frontier)
                       for first, last in proxy.runs)
            assert all(known[0] == run[0] and known[1] in (None, run[1])
                       for known, run in zip(proxy.runs, truth.runs, strict=False))
            open_at_a_batch_end += bool(proxy.runs) and proxy.runs[-1][1] is None and not proxy.done
    assert open_at_a_batch_end > (20 if batch_samples < 1000 else 0)
    samples = truth.samples(0, truth.n_samples)
    for key, proxy in proxies.items():
        columns = feed.columns[key]
        got = proxy.samples(0, proxy.n_samples)
        assert proxy.n_samples == truth.n_samples and len(truth.runs) > 10
        assert np.array_equal(got[:, columns], samples[:, columns])  # bit for bit
        assert np.isnan(np.delete(got, columns, axis=1)).all()
        assert proxy.runs == truth.runs
        assert list(proxy.moves) == list(truth.moves)
    assert np.array_equal(feed.take(truth.n_samples), samples)  # the writer's, all columns
