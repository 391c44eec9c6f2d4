"""Unit tests of the runner's parts that need no estimator: clocks, health, metrics,
the ordering/batching source core."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adaptnav.fusion.samples import DepthSample, ImuBatch, ImuSample, RpmSample, TruthSample
from adaptnav.service.runtime.clock import LiveClock, LogClock, RealtimeClock
from adaptnav.service.runtime.health import Health
from adaptnav.service.tools.metrics import (TrackArrays, TruthArrays, compute_metrics, dvl_outage_metrics,
                                            horizontal_path_length_m, nees)
from adaptnav.service.runtime.sources import SourceCounters, order_and_batch


# -- clocks ----------------------------------------------------------------------------
def test_realtime_clock_paces_data_time_against_wall_time():
    clock = RealtimeClock(speed=20.0)
    t0 = time.monotonic()
    clock.wait_until(100.0)
    clock.wait_until(101.0)  # 1 data second at 20x = 50 ms of wall time
    assert time.monotonic() - t0 >= 0.045


def test_realtime_clock_wakes_on_stop():
    clock = RealtimeClock(speed=1.0)
    stop = threading.Event()
    clock.wait_until(0.0, stop)
    stop.set()
    t0 = time.monotonic()
    clock.wait_until(3600.0, stop)
    assert time.monotonic() - t0 < 60.0  # returned on stop, not after the hour


def test_log_clock_tracks_newest_data_time_and_never_goes_back():
    clock = LogClock()
    assert math.isnan(clock.now_data_s())
    clock.wait_until(5.0)
    clock.wait_until(3.0)
    assert clock.now_data_s() == 5.0


def test_live_clock_now_advances_without_data():
    clock = LiveClock()
    clock.wait_until(1000.0)
    time.sleep(0.02)
    assert clock.now_data_s() >= 1000.015


def test_realtime_clock_rejects_bad_speed():
    with pytest.raises(ValueError, match="speed"):
        RealtimeClock(speed=0.0)


# -- health ----------------------------------------------------------------------------
def test_health_rates_silence_and_rejections():
    h = Health(silent_after_s=10.0, rate_window_s=5)
    for i in range(300):  # 30 s of depth at 10 Hz
        h.on_sample("depth", 100.0 + i * 0.1)
    for i in range(5):   # heading only in the first 5 s
        h.on_sample("heading", 100.0 + i)
    h.on_rejected("corrupt_frame", 3)
    h.estimator_rejected = {"non_finite": 2, "corrupt_frame": 1}
    rep = h.report()
    assert rep["sensors"]["depth"]["count"] == 300
    assert rep["sensors"]["depth"]["rate_hz"] == pytest.approx(10.0, rel=0.05)
    assert not rep["sensors"]["depth"]["silent"]
    assert rep["sensors"]["heading"]["silent"]
    assert rep["silent"] == ["heading"]
    assert rep["rejected"] == {"corrupt_frame": 4, "non_finite": 2}
    # a later "now" makes the depth sensor silent too
    assert h.report(now_s=140.0)["sensors"]["depth"]["silent"]


# -- metrics ---------------------------------------------------------------------------
def _straight_truth(n=601, speed=1.5):
    t = np.linspace(0.0, 600.0, n)
    pos = np.stack([speed * t, np.zeros(n), np.full(n, 10.0)], axis=1)
    vel = np.tile([speed, 0.0, 0.0], (n, 1))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    cur = np.tile([0.1, 0.0], (n, 1))
    return TruthArrays(t, pos, vel, q, cur)


def test_metrics_of_a_known_offset_track():
    truth = _straight_truth()
    t = np.arange(0.0, 600.0 + 1e-9, 0.1)
    n = len(t)
    # estimate: 3 m east of the truth everywhere, current off by (0, 0.05)
    pos = np.stack([1.5 * t, np.full(n, 3.0), np.full(n, 10.0)], axis=1)
    cov = np.tile(np.eye(9), (n, 1, 1))
    track = TrackArrays(t, pos, np.tile([1.5, 0.0, 0.0], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                        cov, np.tile([0.1, 0.05], (n, 1)))
    m = compute_metrics(track, truth, last_fix_t_s=400.0)
    assert m["final_horizontal_error_m"] == pytest.approx(3.0)
    assert m["rms_horizontal_error_m"] == pytest.approx(3.0)
    assert m["distance_travelled_m"] == pytest.approx(900.0)
    assert m["distance_since_fix_m"] == pytest.approx(300.0)
    assert m["drift_percent_since_fix"] == pytest.approx(1.0)
    assert m["current_error_m_s"] == pytest.approx(0.05)
    assert m["nees_mean"] == pytest.approx(9.0)  # only the 3 m east error, unit covariance

    # a log that ends with fixes: a few cm of path since the last one is no base for a percentage
    m = compute_metrics(track, truth, last_fix_t_s=float(t[-1]) - 0.01)
    assert m["distance_since_fix_m"] == pytest.approx(0.015)
    assert m["drift_percent_since_fix"] is None
    assert m["percent_distance_travelled"] == pytest.approx(100.0 * 3.0 / 900.0)


def test_nees_of_consistent_errors_matches_chi_square():
    rng = np.random.default_rng(7)
    truth = _straight_truth()
    t = np.arange(0.0, 600.0, 0.1)
    n = len(t)
    A = rng.normal(size=(9, 9))
    P = A @ A.T / 9 + np.eye(9) * 0.1
    err = rng.multivariate_normal(np.zeros(9), P, size=n)
    pos = np.stack([1.5 * t, np.zeros(n), np.full(n, 10.0)], axis=1) + err[:, :3]
    vel = np.tile([1.5, 0.0, 0.0], (n, 1)) + err[:, 3:6]
    # q_true = q(δθ) ⊗ q_est  ⇒  q_est = q(δθ)⁻¹ ⊗ q_true, with q_true = identity
    q_est_xyzw = Rotation.from_rotvec(err[:, 6:9]).inv().as_quat()
    q_est = q_est_xyzw[:, [3, 0, 1, 2]]
    track = TrackArrays(t, pos, vel, q_est, np.tile(P, (n, 1, 1)), np.tile([0.1, 0.0], (n, 1)))
    m = compute_metrics(track, truth, last_fix_t_s=None)
    assert m["nees_dim"] == 9
    # mean of 6000 χ²(9) draws: σ of the mean ≈ sqrt(18/6000) ≈ 0.055
    assert abs(m["nees_mean"] - 9.0) < 0.3
    assert abs(m["nees_fraction_in_95"] - 0.95) < 0.02


def test_outage_metrics_split_the_error_left_before_from_what_the_outage_added():
    truth = _straight_truth()
    t = np.arange(0.0, 600.0 + 1e-9, 0.1)
    n = len(t)
    # 2 m north of the truth up to the outage (t 200-400 s), then also drifting east at 1 cm/s
    off = np.zeros((n, 3))
    off[:, 1] = 2.0
    off[:, 0] = np.clip(t - 200.0, 0.0, 200.0) * 0.01
    pos = np.stack([1.5 * t, np.zeros(n), np.full(n, 10.0)], axis=1) + off[:, [1, 0, 2]]
    track = TrackArrays(t, pos, np.tile([1.5, 0.0, 0.0], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                        np.tile(np.eye(9), (n, 1, 1)), np.tile([0.1, 0.0], (n, 1)))
    dvl_t = np.arange(0.0, 600.0, 0.2)
    m = dvl_outage_metrics(track, truth, dvl_t, (dvl_t <= 200.0) | (dvl_t >= 400.0))
    assert m["outage_start_s"] == pytest.approx(200.0) and m["outage_end_s"] == pytest.approx(400.0)
    assert m["outage_start_error_m"] == pytest.approx(2.0)
    assert m["outage_growth_m"] == pytest.approx(2.0, abs=0.002)  # 1 cm/s for 200 s, east
    assert m["outage_error_m"] == pytest.approx(np.hypot(2.0, 2.0), abs=0.002)
    assert m["outage_drift_percent"] == pytest.approx(100.0 * m["outage_error_m"] / 300.0)


def test_nees_skips_singular_covariances():
    err = np.ones((3, 2))
    cov = np.stack([np.eye(2), np.zeros((2, 2)), np.eye(2) * 4.0])
    out = nees(err, cov)
    assert out[0] == pytest.approx(2.0) and math.isnan(out[1]) and out[2] == pytest.approx(0.5)


def test_path_length_is_horizontal():
    pos = np.array([[0, 0, 0], [3, 4, 100], [3, 4, 0]], dtype=float)
    assert horizontal_path_length_m(pos).tolist() == [0.0, 5.0, 5.0]


# -- ordering and batching --------------------------------------------------------------
def _imu(t, f=(0.0, 0.0, -9.81)):
    return ImuSample(t, f, (0.0, 0.0, 0.0))


def test_order_and_batch_sorts_groups_and_isolates_bad_imu():
    samples = [_imu(0.00), _imu(0.01), RpmSample(0.015, 900.0), _imu(0.03), _imu(0.02),
               _imu(0.03),                      # duplicate
               _imu(0.04, (math.nan, 0.0, -9.81)),  # NaN
               _imu(0.05), DepthSample(math.nan, 2e5),  # unusable timestamp
               _imu(0.06), TruthSample(0.06, (0, 0, 0), (0, 0, 0), (1, 0, 0, 0), (0, 0, 0), 1.0)]
    c = SourceCounters()
    out = list(order_and_batch(samples, c, horizon_s=1.0))
    kinds = [o.KIND for o in out]
    assert kinds == ["imu_batch", "rpm", "imu_batch", "imu", "imu", "imu_batch", "truth"]
    assert out[0].t_s.tolist() == [0.0, 0.01]
    assert out[2].t_s.tolist() == [0.02, 0.03]
    assert out[3].t_s == 0.03                      # the duplicate, alone
    assert math.isnan(out[4].specific_force_b_m_s2[0])
    assert out[5].t_s.tolist() == [0.05, 0.06]
    assert c.bad_timestamp == 1
    assert c.samples == len(samples) - 1
    # nothing lost: every usable sample comes out exactly once
    n_out = sum(len(o) if isinstance(o, ImuBatch) else 1 for o in out)
    assert n_out == len(samples) - 1


def test_order_and_batch_counts_samples_later_than_the_horizon():
    samples = [_imu(float(t)) for t in range(10)] + [RpmSample(1.0, 100.0)]
    c = SourceCounters()
    out = list(order_and_batch(samples, c, horizon_s=2.0))
    assert c.late_samples == 1
    assert sum(len(o) if isinstance(o, ImuBatch) else 1 for o in out) == 11


def test_closed_form_euler_matches_scipy():
    from scipy.spatial.transform import Rotation

    from adaptnav.fusion.frames import euler_to_quat, quat_to_euler

    rng = np.random.default_rng(3)
    for _ in range(500):
        rpy = (rng.uniform(-3.1, 3.1), rng.uniform(-1.5, 1.5), rng.uniform(-3.14, 3.14))
        q = euler_to_quat(*rpy)
        yaw, pitch, roll = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_euler("ZYX")
        assert np.allclose(quat_to_euler(q), (roll, pitch, yaw), atol=1e-9)
        assert np.allclose(quat_to_euler(q), rpy, atol=1e-9)
