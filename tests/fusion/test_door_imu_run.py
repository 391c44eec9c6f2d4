"""The door's IMU-run test is one compiled call (strapdown.imu_run_in_bounds): it must say what
the numpy expression it replaced says — every value in range, the first stamp in the window of
the data clock (none before the first sample), every step positive and short, NaN failing —
and Door.check_batch must keep its verdicts (the fast path, and the per-sample path otherwise)."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.fusion.plausibility import Door, PlausibilityConfig
from adaptnav.fusion.strapdown import imu_run_in_bounds


def _numpy_verdict(t, f, w, c: PlausibilityConfig, d: float) -> bool:
    """The expression Door.check_batch used before the kernel."""
    steps = t[1:] - t[:-1]
    return bool(np.abs(f).max() <= c.max_specific_force_m_s2 and np.abs(w).max() <= c.max_rate_rad_s
                and (d == -math.inf or d - c.max_behind_s <= t[0] <= d + c.max_ahead_s)
                and (steps.size == 0 or (steps.min() > 0 and steps.max() <= c.max_ahead_s)))


def _kernel_verdict(t, f, w, c: PlausibilityConfig, d: float) -> bool:
    lo, hi = (-math.inf, math.inf) if d == -math.inf else (d - c.max_behind_s, d + c.max_ahead_s)
    return bool(imu_run_in_bounds(t, f, w, c.max_specific_force_m_s2, c.max_rate_rad_s, lo, hi, c.max_ahead_s))


def test_kernel_agrees_with_the_numpy_expression():
    c = PlausibilityConfig()
    rng = np.random.default_rng(7)
    cases = 0
    for trial in range(400):
        n = int(rng.integers(1, 12))
        t = 100.0 + np.cumsum(rng.uniform(0.001, 0.02, n))
        f = rng.normal(0.0, 3.0, (n, 3))
        w = rng.normal(0.0, 0.5, (n, 3))
        d = [-math.inf, 100.0, 50.0, 200.0, float(t[0]) - c.max_ahead_s][trial % 5]
        k = int(rng.integers(0, n))
        bad = trial % 9
        if bad == 1:
            f[k, trial % 3] = math.nan
        elif bad == 2:
            w[k, trial % 3] = math.nan
        elif bad == 3:
            t[k] = math.nan
        elif bad == 4:
            f[k, 0] = 2.0 * c.max_specific_force_m_s2 * (1 if trial % 2 else -1)
        elif bad == 5:
            w[k, 2] = -2.0 * c.max_rate_rad_s
        elif bad == 6 and n > 1:
            t[k] = t[k - 1] if k else t[1]  # a repeated stamp
        elif bad == 7 and n > 1:
            t[-1] = t[-2] + 2.0 * c.max_ahead_s  # a long step
        elif bad == 8:
            f[k, 1] = c.max_specific_force_m_s2  # on the bound: in range
        assert _kernel_verdict(t, f, w, c, d) == _numpy_verdict(t, f, w, c, d), (trial, t, d)
        cases += 1
    assert cases == 400


def test_check_batch_verdicts():
    door = Door(PlausibilityConfig())
    t = np.arange(1, 11) * 0.01
    f = np.tile([0.0, 0.0, -9.8], (10, 1))
    w = np.zeros((10, 3))
    assert door.check_batch(t, f, w) == (None, 0.0)  # the first run: no data clock yet
    assert door.t_data_s == t[-1]
    f2 = f.copy()
    f2[3, 0] = 1e6  # one absurd sample: refused, the rest kept
    keep, jump = door.check_batch(t + 0.1, f2, w)
    assert keep.tolist() == [True] * 3 + [False] + [True] * 6 and jump == 0.0
    assert door.rejected["imu_acc_range"] == 1
