"""OnlineCalibrator._advance's skip (no pose can close before the time _close_time gives) against
the computation of the newest closed pose at every sample it replaced."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.calibration.online import CalibratorConfig, OnlineCalibrator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import HeadingSample, RpmSample, UsblSample


class _EverySample(OnlineCalibrator):
    """The reference: the newest closed pose computed at every sample."""

    def _advance(self, t):
        if t < self._last_t:
            self._reject("out-of-order timestamp")
        self._last_t = max(self._last_t, t)
        if self._t0 is None:
            return
        newest = math.floor((self._last_t - self._lag_s - self._t0) / self.config.step_s - 0.5)
        while self._closed < newest:
            self._close_pose(self._closed + 1)


@pytest.mark.parametrize("t0_s, step_s", [(0.0, 5.0), (1.7e9 + 0.123, 0.7), (12345.678, 1.0 / 3.0), (-50.0, 2.5)])
def test_poses_close_at_the_same_samples_as_computed_every_time(t0_s, step_s):
    cfg = CalibratorConfig(window_steps=40, step_s=step_s, period_steps=1000, min_window_steps=24, n_particles=30,
                           n_smoothed=5, origin_lat_deg=43.0, origin_lon_deg=5.0, model_step_s=step_s)
    rng = np.random.default_rng(int(abs(t0_s)) % 1000 + 7)
    cals = [cls(cfg, MotionParams(), RpmSpeedTable(), np.random.default_rng(5)) for cls in (OnlineCalibrator, _EverySample)]
    times = [t0_s - 0.4]
    # samples at random gaps, some exactly on the closing times (pose k at t0 + (k + 0.5) step),
    # some a few ulps either side, out of order now and then
    for _ in range(600):
        u = rng.random()
        if u < 0.15:
            k = math.floor((times[-1] - t0_s) / step_s - 0.5) + 1
            t = t0_s + (k + 0.5) * step_s
            t = t + int(rng.integers(-3, 4)) * math.ulp(t)
        elif u < 0.2:
            t = times[-1] - float(rng.uniform(0.0, step_s))
        else:
            t = times[-1] + float(rng.exponential(0.3 * step_s))
        times.append(t)
    for cal in cals:
        cal.observe(HeadingSample(times[0], 0.3))
        cal.observe(UsblSample(t0_s, math.radians(43.0), math.radians(5.0), 10.0, 2.0))
    assert cals[0]._t0 == cals[1]._t0 == t0_s
    for j, t in enumerate(times[1:]):
        for cal in cals:
            cal.observe(RpmSample(t, 900.0) if j % 2 else HeadingSample(t, 0.3 + 0.001 * j))
        assert cals[0]._closed == cals[1]._closed, (j, t)
    assert cals[0]._closed > 100
    assert cals[0].rejected == cals[1].rejected and cals[0].rejected.get("out-of-order timestamp", 0) > 5
    assert cals[0]._poses.tobytes() == cals[1]._poses.tobytes()


def test_close_time_is_the_first_time_that_closes_the_pose():
    cfg = CalibratorConfig(window_steps=40, step_s=0.7, n_particles=30, origin_lat_deg=43.0, origin_lon_deg=5.0,
                           model_step_s=0.7)
    cal = OnlineCalibrator(cfg, MotionParams(), RpmSpeedTable(), np.random.default_rng(5))
    cal.observe(UsblSample(1.7e9 + 0.1, math.radians(43.0), math.radians(5.0), 10.0, 2.0))
    for k in range(0, 5000, 37):
        t = cal._close_time(k)
        assert math.isfinite(t)  # (found: the skip is taken)
        assert cal._newest_closed(t) >= k > cal._newest_closed(math.nextafter(t, -math.inf))
