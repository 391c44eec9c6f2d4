"""DepthNoise's σ and variance per depth against its definition written plainly (numpy's median of
the last WINDOW |Δ²z| over even, short intervals; the deadband, the bound, the memo of a time seen
before): seeded series crossing the deadband and the bound, with gaps, uneven and repeated times,
out of order and not finite depths."""
from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest

from adaptnav.fusion.aiding.depth import DepthNoise
from adaptnav.fusion.config import DepthConfig


def _reference(ts: list, zs: list, cfg: DepthConfig) -> list:
    floor, bound = float(cfg.sigma_m), float(cfg.adaptive_max_sigma_m)
    enabled = bound > floor
    diffs: deque = deque(maxlen=DepthNoise.WINDOW)
    pts: list = []  # the two latest (t, z)
    memo: dict = {}
    sigma = floor
    out = []
    for t, z in zip(ts, zs):
        if pts and not t > pts[-1][0]:
            s = memo.get(t, sigma)
        elif not math.isfinite(z):
            s = sigma
        else:
            if len(pts) == 2:
                (t0, z0), (t1, z1) = pts
                dt1, dt2 = t1 - t0, t - t1
                if 0 < dt1 <= DepthNoise.MAX_GAP_S and 0 < dt2 <= DepthNoise.MAX_GAP_S \
                        and abs(dt2 - dt1) <= DepthNoise.MAX_UNEVEN * max(dt1, dt2):
                    diffs.append(abs(z - 2.0 * z1 + z0))
            pts = (pts + [(t, z)])[-2:]
            if len(diffs) >= DepthNoise.MIN_COUNT and enabled:
                measured = float(np.median(np.array(diffs))) / (0.6745 * math.sqrt(6.0))
                sigma = min(measured, bound) if measured > DepthNoise.DEADBAND * floor else floor
            s = memo[t] = sigma
        out.append(floor ** 2 if s == floor or not enabled else s * s)
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_variance_is_the_definitions(seed):
    rng = np.random.default_rng(seed)
    n = 6000
    # intervals of 0.1 s, ±40 % (the uneven test on both sides of its 25 %), some gaps
    dt = 0.1 * (1.0 + rng.uniform(-0.4, 0.4, n))
    dt[rng.integers(0, n, 30)] = 1.5
    ts = np.cumsum(dt).tolist()
    noise = np.repeat(rng.choice([0.005, 0.06, 0.1, 0.3, 1.5], size=n // 500), 500)
    zs = (20.0 + np.cumsum(rng.normal(size=n) * 0.01) + rng.normal(size=n) * noise).tolist()
    for k in rng.integers(0, n, 40):
        zs[k] = math.nan
    for k in rng.integers(1, n, 40):  # a time seen before (a re-fusion), or older (out of order)
        ts[k] = ts[k - 1] - (0.05 if k % 2 else 0.0)
    for cfg in (DepthConfig(), DepthConfig(sigma_m=0.2, adaptive_max_sigma_m=0.2)):  # (the second: off)
        noise_model = DepthNoise(cfg)
        got = [noise_model.variance_m2(t, z) for t, z in zip(ts, zs)]
        assert got == _reference(ts, zs, cfg)
        assert len(set(got)) > (100 if noise_model.enabled else 0)


def test_the_series_crosses_the_deadband_and_the_bound():
    rng = np.random.default_rng(1)
    cfg = DepthConfig()
    noise_model = DepthNoise(cfg)
    for k, s in enumerate(np.repeat([0.005, 0.1, 1.5], 1000)):
        noise_model.variance_m2(k * 0.1, 20.0 + rng.normal() * s)
        if k == 999:
            assert noise_model.sigma_m == cfg.sigma_m
        if k == 1999:
            assert cfg.sigma_m < noise_model.sigma_m < cfg.adaptive_max_sigma_m
    assert noise_model.sigma_m == cfg.adaptive_max_sigma_m and noise_model.samples_at_bound > 0
