"""Real ArduSub telemetry (no usable IMU rate: RAW_IMU at 2 Hz): the attitude's increments drive
the strapdown, or (``attitude_driven.enabled = false``) the filter runs in AHRS mode."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

TLOG = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mavlink" / "ardusub-4.1.1-bluerov2-ugps.tlog"


@pytest.mark.realdata
@pytest.mark.parametrize("attitude_driven", [True, False])
def test_real_ardusub_log_gives_attitude_depth_and_a_position_only_where_fixes_measure_it(attitude_driven):
    if not TLOG.is_file():
        pytest.skip(f"real data absent: {TLOG}")
    from adaptnav.service.transport.tlog_source import TlogSource

    cfg = FilterConfig()
    cfg = replace(cfg, attitude_driven=replace(cfg.attitude_driven, enabled=attitude_driven))
    est = None
    attitudes, states, fixes = [], [], []
    for sample in TlogSource(TLOG):
        if est is None and sample.KIND == "usbl":
            est = Estimator(cfg, MotionParams(), RpmSpeedTable(), GeoOrigin(sample.lat_rad, sample.lon_rad))
        if est is not None and sample.KIND == "usbl":
            fixes.append(est.origin.to_ned(sample.lat_rad, sample.lon_rad)[:2])
        if est is None:
            continue
        est.process(sample)
        if sample.KIND == "attitude" and est.initialized:
            attitudes.append((sample.roll_rad, sample.pitch_rad, sample.yaw_rad))
            states.append(est.nav_state())
    assert est is not None and est.initialized and len(states) > 1000
    if attitude_driven:
        # THEN the UGPS fixes (936, ~4 Hz) measure the motion: valid from the first on; each
        # valid position within 3σ of where the fixes place the vehicle (all of them on one
        # spot: the vehicle held still, thrusters idle), with σ_h about a fix's (≤ 5 m)
        assert est.imu_model.grade == "attitude"
        valid = [s for s in states if s.valid]
        assert len(valid) >= 0.95 * len(states)
        spot = np.median(np.asarray(fixes), axis=0)
        for s in valid:
            sigma_h = float(np.sqrt(max(s.cov[0, 0], s.cov[1, 1])))
            assert sigma_h <= 5.0 and np.hypot(*(s.pos_n_m[:2] - spot)) <= 3.0 * sigma_h
    else:
        # THEN no state is valid (no dead reckoning)
        assert not any(s.valid for s in states)
    # every state finite, attitude follows the AHRS
    assert all(np.all(np.isfinite(s.cov)) and np.all(np.isfinite(s.pos_n_m)) for s in states)
    est_rpy = np.array([s.euler_rad() for s in states])
    err = np.asarray(attitudes) - est_rpy
    err = (err + np.pi) % (2 * np.pi) - np.pi
    assert np.percentile(np.abs(err), 95, axis=0).max() < np.radians(2.0)
    # AND the depth is the pressure sensor's: near the surface in this log
    depths = np.array([s.pos_n_m[2] for s in states])
    assert np.all(np.abs(depths) < 5.0)
