"""NisMonitor.add keeps the failing set by each window's verdict and touches the set only when
that changes: after every attempt, failing() is the sources whose full window's sum exceeds its
bound, the sum the attempts' capped NIS added and dropped in order — on seeded streams of
several sources with dof changes (a new window) and clear() calls in between."""
from __future__ import annotations

import random

import pytest

from adaptnav.fusion.integrity import NisMonitor


@pytest.mark.parametrize("seed", range(8))
def test_failing_is_every_full_window_above_its_bound(seed):
    rng = random.Random(seed)
    window = rng.choice([1, 3, 5, 20])
    mon = NisMonitor(window, 0.99)
    ref: dict = {}  # source -> (dof, capped values, running sum)
    flips = 0
    before = []
    for k in range(4000):
        r = rng.random()
        if r < 0.005:
            source = rng.choice(["depth", "dvl", None])
            mon.clear(source)
            for s in ([source] if source else list(ref)):
                ref.pop(s, None)
            continue
        source = rng.choice(["depth", "heading", "dvl", "usbl"])
        dof = rng.choice([1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 3]) if source != "dvl" else 3
        # phases of a good and a too-small covariance: the windows' verdicts change often
        scale = 1.0 if (k // 150) % 2 == 0 else rng.choice([3.0, 8.0])
        nis = rng.expovariate(1.0 / (scale * dof)) if rng.random() > 0.01 else 1e9  # an outlier: capped
        mon.add(source, nis, dof)
        d, vals, total = ref.get(source, (None, [], 0.0))
        if d != dof:
            vals, total = [], 0.0
        v = min(nis, mon.cap(dof))
        vals.append(v)
        total = total + v
        if len(vals) > window:
            total = total - vals.pop(0)
        ref[source] = (dof, vals, total)
        want = sorted(s for s, (d, vals, total) in ref.items() if len(vals) >= window and total > mon.bound(d))
        got = mon.failing()
        assert got == want, (k, source)
        flips += got != before
        before = got
        assert mon._source[source].total == total
    assert flips > 20
