"""OnlineCalibrator._heading (the nearest heading per pose, brought to the pose time, made once)
against the generic observation path it left (_add_obs with a HeadingObservation)."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.calibration.online import CalibratorConfig, OnlineCalibrator
from adaptnav.calibration.sensors import HeadingObservation, PositionFix
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import HeadingSample, ImuSample, RpmSample, UsblSample


class _GenericPath(OnlineCalibrator):
    """The reference: the heading observation made, then brought to the pose by _add_obs."""

    def _heading(self, t, yaw):
        if self._take_heading(t, yaw):
            self._add_obs(t, HeadingObservation(yaw, math.radians(self.config.heading_sigma_deg)))

    def _add_obs(self, t, ob):
        if not isinstance(ob, HeadingObservation):
            return super()._add_obs(t, ob)
        if self._t0 is None:
            return
        k = round((t - self._t0) / self.config.step_s)
        if k <= self._closed:
            return self._reject("late observation")
        lag = t - (self._t0 + k * self.config.step_s)
        ob = HeadingObservation(ob.yaw_rad - self._last_yaw_rate * lag, ob.sigma_rad)
        best = self._heading_at.get(k)
        if best is not None and abs(best[0]) <= abs(lag):
            return
        if best is not None:
            self._obs[k].remove(best[1])
        self._heading_at[k] = (lag, ob)
        self._obs.setdefault(k, []).append(ob)


def test_headings_reach_the_poses_as_by_the_generic_path():
    cfg = CalibratorConfig(window_steps=40, step_s=2.0, period_steps=1000, min_window_steps=24, n_particles=30,
                           n_smoothed=5, origin_lat_deg=43.0, origin_lon_deg=5.0, model_step_s=2.0)
    rng = np.random.default_rng(23)
    stream = [HeadingSample(-1.0, 0.1)]  # before the grid exists
    t = 0.0
    stream.append(UsblSample(0.0, math.radians(43.0), math.radians(5.0), 10.0, 2.0))
    for j in range(900):
        t += float(rng.exponential(0.35))
        u = rng.random()
        yaw = float(rng.uniform(-math.pi, math.pi))
        if j % 50 == 0:  # two headings equally far from their pose (the first kept)
            k = math.floor(t / 2.0) + 2
            stream += [HeadingSample(2.0 * k - 0.5, yaw), HeadingSample(2.0 * k + 0.5, yaw + 0.5)]
            t = 2.0 * k + 0.5
        elif u < 0.05:
            stream.append(HeadingSample(t - float(rng.uniform(1.0, 6.0)), yaw))  # late: its pose closed
        elif u < 0.08:
            stream.append(HeadingSample(t, math.nan))
        elif u < 0.5:
            stream.append(HeadingSample(t, yaw))
        elif u < 0.75:
            stream.append(ImuSample(t, (0.0, 0.0, -9.81), (0.0, 0.0, float(rng.normal(0.0, 0.05)))))
        elif u < 0.98:
            stream.append(RpmSample(t, 900.0))
        else:
            stream.append(UsblSample(t, math.radians(43.0) + 1e-6, math.radians(5.0), 10.0, 2.0))
    new, ref = (cls(cfg, MotionParams(), RpmSpeedTable(), np.random.default_rng(5)) for cls in (OnlineCalibrator,
                                                                                                 _GenericPath))
    for s in stream:
        new.observe(s)
        ref.observe(s)
        assert new._obs.keys() == ref._obs.keys()
        assert new._heading_at == ref._heading_at
    assert new._obs == ref._obs and list(new._win_obs) == list(ref._win_obs)
    assert new.rejected == ref.rejected and new.rejected["late observation"] > 10
    assert new.rejected["non-finite heading"] > 10
    n_heading = sum(isinstance(o, HeadingObservation) for obs in new._win_obs for o in obs)
    assert n_heading > 20
    assert any(isinstance(o, PositionFix) for obs in new._win_obs for o in obs)
    assert new._poses.tobytes() == ref._poses.tobytes()
