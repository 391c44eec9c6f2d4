"""Real ArduSub telemetry (no usable IMU rate): the filter runs in AHRS mode."""
from pathlib import Path

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

TLOG = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mavlink" / "ardusub-4.1.1-bluerov2-ugps.tlog"


@pytest.mark.realdata
def test_real_ardusub_log_gives_ahrs_attitude_depth_and_invalid_position():
    if not TLOG.is_file():
        pytest.skip(f"real data absent: {TLOG}")
    from adaptnav.service.transport.tlog_source import TlogSource

    est = None
    attitudes, states = [], []
    for sample in TlogSource(TLOG):
        if est is None and sample.KIND == "usbl":
            est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(),
                            GeoOrigin(sample.lat_rad, sample.lon_rad))
        if est is None:
            continue
        est.process(sample)
        if sample.KIND == "attitude" and est.initialized:
            attitudes.append((sample.roll_rad, sample.pitch_rad, sample.yaw_rad))
            states.append(est.nav_state())
    assert est is not None and est.initialized and len(states) > 1000
    # THEN no state is valid (no dead reckoning), every one finite, attitude follows the AHRS
    assert not any(s.valid for s in states)
    assert all(np.all(np.isfinite(s.cov)) and np.all(np.isfinite(s.pos_n_m)) for s in states)
    est_rpy = np.array([s.euler_rad() for s in states])
    err = np.asarray(attitudes) - est_rpy
    err = (err + np.pi) % (2 * np.pi) - np.pi
    assert np.percentile(np.abs(err), 95, axis=0).max() < np.radians(2.0)
    # AND the depth is the pressure sensor's: near the surface in this log
    depths = np.array([s.pos_n_m[2] for s in states])
    assert np.all(np.abs(depths) < 5.0)
