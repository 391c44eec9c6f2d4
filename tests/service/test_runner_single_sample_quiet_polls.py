"""The runner's single-sample path tests a calibrator's ``quiet_until_s`` and updates the
summary's first/last data times itself (not through ``releases_due`` / ``_reached`` calls):
the polls (when and with which data time), the data time kept and the summary's times and
progress must be those of the plain rules, for stamps out of order, repeated, NaN, ±inf, and
quiet bounds below, at, above the data time or NaN."""
from __future__ import annotations

import math
import random

from adaptnav.service.runtime.clock import LogClock
from adaptnav.service.runtime.runner import Runner


class _Sample:
    def __init__(self, t_s, kind):
        self.t_s = t_s
        self.KIND = kind


class _Estimator:
    initialized = False  # no nav states: the test is about polls and times
    rejected: dict = {}

    def process(self, sample):
        return []


class _QuietCalibrator:
    """Sets a random quiet bound around the data time of each poll; records the polls."""

    def __init__(self, rng):
        self.rng = rng
        self.quiet_until_s = -math.inf
        self.polls = []

    def observe(self, sample):
        pass

    def poll(self, data_time_s):
        self.polls.append(data_time_s)
        self.quiet_until_s = self.rng.choice([data_time_s - 1.0, data_time_s, data_time_s + 0.25,
                                              data_time_s + 3.0, math.nan, -math.inf, math.inf])
        return []


def _stamps(rng, n):
    out = []
    t = 0.0
    for _ in range(n):
        r = rng.random()
        if r < 0.05:
            out.append(math.nan)
        elif r < 0.07:
            out.append(math.inf if rng.random() < 0.5 else -math.inf)
        elif r < 0.2:
            out.append(t - rng.uniform(0.0, 2.0))  # late
        elif r < 0.3:
            out.append(t)  # repeated
        else:
            t += rng.uniform(0.0, 0.7)
            out.append(t)
    return out


def test_polls_data_time_and_summary_times_follow_the_plain_rules():
    for seed in range(20):
        rng = random.Random(seed)
        stamps = _stamps(rng, 300)
        kinds = [rng.choice(["depth", "dvl", "truth", "sonar"]) for _ in stamps]
        progress = []
        cal = _QuietCalibrator(random.Random(seed + 1000))
        runner = Runner(_Estimator(), [], LogClock(), cal, progress=progress.append)
        loop = runner.loop

        # the plain rules, item by item (releases_due, then _reached, as methods)
        exp_polls, exp_progress = [], []
        data_t, first, last = -math.inf, math.nan, math.nan
        model_quiet = random.Random(seed + 1000)
        quiet = -math.inf
        for t, kind in zip(stamps, kinds):
            runner.feed(_Sample(t, kind))
            if kind != "truth":
                if t > data_t:
                    data_t = t
                if not data_t < quiet:
                    exp_polls.append(data_t)
                    quiet = model_quiet.choice([data_t - 1.0, data_t, data_t + 0.25, data_t + 3.0,
                                                math.nan, -math.inf, math.inf])
            if math.isfinite(t):
                if not first <= t:
                    first = t
                if not last >= t:
                    last = t
                exp_progress.append(t)
            assert loop.data_t == data_t or (math.isnan(loop.data_t) and math.isnan(data_t))
            assert cal.polls == exp_polls
        s = runner.summary
        assert s.errors == {}
        assert (s.first_t_s, s.last_t_s) == (first, last) or (math.isnan(first) and math.isnan(s.first_t_s))
        assert progress == exp_progress


def test_a_calibrator_without_a_quiet_bound_is_polled_after_every_sample_but_truth():
    class _Plain:
        def __init__(self):
            self.polls = []

        def observe(self, sample):
            pass

        def poll(self, data_time_s):
            self.polls.append(data_time_s)
            return []

    cal = _Plain()
    runner = Runner(_Estimator(), [], LogClock(), cal)
    for t, kind in [(1.0, "depth"), (0.5, "dvl"), (2.0, "truth"), (math.nan, "depth"), (3.0, "sonar")]:
        runner.feed(_Sample(t, kind))
    assert cal.polls == [1.0, 1.0, 1.0, 3.0]
    assert (runner.summary.first_t_s, runner.summary.last_t_s) == (0.5, 3.0)
