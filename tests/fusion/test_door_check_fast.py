"""The plausibility door's per-sample shortcuts (fusion.plausibility): Door.check's in-window
test ahead of _time, and _over's three components written out — the verdicts, data clock,
counts, jumps and gaps of the full path on seeded streams, and any() of the magnitudes on
seeded and edge vectors."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest

from adaptnav.fusion import plausibility
from adaptnav.fusion.plausibility import Door, PlausibilityConfig
from adaptnav.fusion.samples import DepthSample, DvlSample, HeadingSample, ImuSample, RpmSample


def _vectors(rng: random.Random):
    special = [0.0, -0.0, 1.0, -1.0, 2.0, -2.0, 2.0000000001, math.nan, math.inf, -math.inf, 1e308, -1e-308]
    for _ in range(3000):
        n = rng.choice([0, 1, 2, 3, 3, 3, 4, 5])
        v = [rng.choice(special) if rng.random() < 0.3 else rng.uniform(-3.0, 3.0) for _ in range(n)]
        yield rng.choice([tuple, list, np.array])(v)


def test_over_is_any_magnitude_beyond_the_bound():
    rng = random.Random(5)
    seen = set()
    for vec in _vectors(rng):
        for bound in (2.0, 1e308, math.inf):
            want = any(abs(v) > bound for v in vec)
            assert bool(plausibility._over(vec, bound)) == want, (vec, bound)
            seen.add((len(vec), want))
    assert {(3, True), (3, False), (4, True), (2, False)} <= seen


def _stream(rng: random.Random) -> list:
    """Samples of five kinds around a data clock that steps and jumps: in the window, behind
    and ahead of it, runs of one stream from a new time (jumps, gaps), NaN stamps."""
    out, t = [], rng.uniform(0.0, 10.0)
    for _ in range(600):
        r = rng.random()
        if r < 0.02:
            t += rng.choice([20.0, 300.0, -50.0])  # the next samples come from a new time
        t += rng.uniform(0.0, 0.2)
        s = t + (rng.choice([-40.0, 8.0, -3.0]) if rng.random() < 0.05 else 0.0)
        if rng.random() < 0.02:
            s = math.nan
        kind = rng.randrange(5)
        if kind == 0:
            out.append(ImuSample(s, (0.0, 0.0, -9.8), (0.0, 0.0, rng.choice([0.0, 0.1, 1e3]))))
        elif kind == 1:
            out.append(DepthSample(s, rng.choice([150000.0, 1e12])))
        elif kind == 2:
            out.append(HeadingSample(s, rng.uniform(-4.0, 4.0)))
        elif kind == 3:
            out.append(RpmSample(s, rng.choice([1000.0, 1e6])))
        else:
            out.append(DvlSample(s, (rng.uniform(-1.0, 1.0), 0.0, rng.choice([0.0, 20.0])), True, 0.01))
    return out


def _judged(door: Door, stream: list) -> list:
    return [door.check(s) for s in stream] + [door.t_data_s, dict(door.rejected), door.jumps, door.gaps]


@pytest.mark.parametrize("seed", range(12))
def test_check_judges_as_the_full_time_test(seed):
    stream = _stream(random.Random(seed))
    cfg = PlausibilityConfig(jump_confirm_samples=3)
    gap = lambda a, b: b - a > 100.0  # noqa: E731
    fast, full = Door(cfg, forward_jump_is_gap=gap), Door(cfg, forward_jump_is_gap=gap)
    full._max_behind_s = math.nan  # the in-window shortcut never taken: _time judges every stamp
    assert _judged(fast, stream) == _judged(full, stream)
    assert fast.jumps and fast.gaps and fast.rejected["time_ahead"] and fast.rejected["time_behind"]
