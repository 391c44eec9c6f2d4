"""No usable IMU, but the autopilot's attitude (ArduSub's telemetry at its default stream rates:
RAW_IMU at 2 Hz, ATTITUDE at 10–20 Hz): the attitude's increments drive the strapdown
(``[filter.attitude_driven]``), velocity comes from the motion model, position from fixes, and
the solution is valid only while something measures the motion."""
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.integrity import chi2_quantile
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import AttitudeSample, DepthSample, ImuBatch, ImuSample, RpmSample, UsblSample
from adaptnav.fusion.state import KS

from .mission import ATM_PA, ORIGIN, RHO, make_mission

CHI2_2_99 = chi2_quantile(0.99, 2)


def _cfg(model_measures_motion: bool = True) -> FilterConfig:
    cfg = FilterConfig()
    return replace(cfg, attitude_driven=replace(cfg.attitude_driven, model_measures_motion=model_measures_motion))


def _without_imu(m, attitude_rate_hz: float = 10.0) -> list:
    """The mission's aids (no heading: ATTITUDE carries the yaw) and ATTITUDE samples of the
    true attitude (level, the mission's yaw) at ``attitude_rate_hz``; no IMU."""
    step = int(round(1.0 / attitude_rate_hz / (m.t_imu[1] - m.t_imu[0])))
    att = [AttitudeSample(float(m.t_imu[k]), 0.0, 0.0, float(m.yaw[k])) for k in range(0, m.t_imu.size, step)]
    aids = [a for a in m.aids if a.KIND != "heading"]
    return sorted(att + aids, key=lambda s: (s.t_s, s.KIND != "attitude"))


def _run(est: Estimator, m, samples) -> list[tuple[float, bool, float]]:
    """Feed ``samples``; per attitude sample after the start: (t, valid, horizontal NEES)."""
    out = []
    for s in samples:
        est.process(s)
        if s.KIND == "attitude" and est.initialized:
            ns = est.nav_state()
            err = ns.pos_n_m[:2] - m.truth_at(s.t_s)["pos"][:2]
            out.append((s.t_s, ns.valid, float(err @ np.linalg.solve(ns.cov[:2, :2], err)), float(np.hypot(*err))))
    return out


def test_the_attitude_drives_the_strapdown_and_the_solution_is_as_good_as_it_says():
    # GIVEN a 10-min mission with turns, ATTITUDE at 10 Hz, thrust, depth, a USBL fix every 10 s, no IMU
    m = make_mission(np.random.default_rng(11), 600.0, yaw_rate0=0.01, usbl_period_s=10.0, usbl_sigma_m=2.0)
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    rows = _run(est, m, _without_imu(m))
    # THEN the filter runs as an INS on the attitude's virtual IMU, valid once it has started
    assert est.imu_model.grade == "attitude" and "10.0 Hz" in est.imu_model.why
    t, valid, nees, err = map(np.array, zip(*rows))
    assert valid[t > 15.0].all()
    # AND where it says valid the truth lies inside its 99 % ellipse as a consistent filter's does
    assert np.mean(nees[valid] > CHI2_2_99) <= 0.02, np.mean(nees[valid] > CHI2_2_99)
    assert err.max() < 6.0 and np.sqrt(np.mean(err ** 2)) < 2.5


def test_without_a_measurement_of_the_motion_the_track_is_kept_but_not_valid():
    # GIVEN fixes for the first 200 s only, and a motion model nobody calibrated for this vehicle
    m = make_mission(np.random.default_rng(12), 400.0, usbl_period_s=5.0, usbl_until_s=200.0)
    est = Estimator(_cfg(model_measures_motion=False), MotionParams(), RpmSpeedTable(), ORIGIN)
    rows = _run(est, m, _without_imu(m))
    t, valid, nees, err = map(np.array, zip(*rows))
    max_age = est.config.attitude_driven.motion_aid_max_age_s
    # THEN valid while the fixes come, not after the last one's age passed the bound ...
    assert valid[(t > 15.0) & (t < 195.0)].all()
    assert not valid[t > 200.0 + max_age].any()
    assert "no_motion_measurement" in est.invalid_reasons()
    # ... and the track goes on (the model's velocity, finite, not frozen)
    assert np.all(np.isfinite(err)) and err[-1] < 50.0
    # AND a calibrated model's velocity is a measurement: the same mission stays valid
    est = Estimator(_cfg(model_measures_motion=True), MotionParams(), RpmSpeedTable(), ORIGIN)
    t, valid, nees, err = map(np.array, zip(*_run(est, m, _without_imu(m))))
    assert valid[t > 15.0].all() and np.mean(nees[valid] > CHI2_2_99) <= 0.02


def test_fixes_that_calibrated_the_speed_scale_carry_the_model_through_their_outage():
    # GIVEN an uncalibrated model, and fixes (σ 0.5 m, every 2 s) for 300 s that measure its scale
    m = make_mission(np.random.default_rng(13), 500.0, yaw_rate0=0.01, usbl_period_s=2.0, usbl_sigma_m=0.5,
                     usbl_until_s=300.0)
    est = Estimator(_cfg(model_measures_motion=False), MotionParams(), RpmSpeedTable(), ORIGIN)
    t, valid, nees, err = map(np.array, zip(*_run(est, m, _without_imu(m))))
    # THEN k_speed's σ is below attitude_driven.calibrated_sigma_k_speed (measured 0.025) and the
    # learned velocity keeps the solution valid for the 200 s without fixes, as good as it says
    assert float(np.sqrt(est.nav_state().cov[KS, KS][0, 0])) <= est.config.attitude_driven.calibrated_sigma_k_speed
    assert valid[t > 15.0].all() and np.mean(nees[valid] > CHI2_2_99) <= 0.01
    assert err[t > 300.0].max() < 5.0
    # AND with that bound at 0 (only fixes and DVL count) it is not valid after the fixes end
    cfg = _cfg(model_measures_motion=False)
    cfg = replace(cfg, attitude_driven=replace(cfg.attitude_driven, calibrated_sigma_k_speed=0.0))
    est = Estimator(cfg, MotionParams(), RpmSpeedTable(), ORIGIN)
    t, valid, nees, err = map(np.array, zip(*_run(est, m, _without_imu(m))))
    assert not valid[t > 300.0 + cfg.attitude_driven.motion_aid_max_age_s].any()


def _at_rest(est: Estimator, t0: float, t1: float, yaw: float = 0.7) -> None:
    for t in np.arange(t0, t1, 0.1):
        est.process(AttitudeSample(float(t), 0.0, 0.0, yaw))
        if round(t * 10) % 5 == 0:
            est.process(DepthSample(float(t), ATM_PA + RHO * GRAVITY_M_S2 * 4.0))
            est.process(RpmSample(float(t), 0.0))


def test_slow_imu_samples_beside_the_attitude_are_not_integrated():
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    lat, lon, _ = ORIGIN.to_geodetic(np.array([20.0, -5.0, 0.0]))
    est.process(UsblSample(0.05, float(lat), float(lon), 4.0, 1.0))
    _at_rest(est, 0.0, 5.0)
    assert est.imu_model.grade == "attitude"
    # WHEN the autopilot's RAW_IMU comes at 2 Hz, reading a 3 m/s² surge (vibration, a bump)
    for k in range(20):
        t = 5.0 + 0.5 * k
        est.process(ImuSample(t + 0.01, (3.0, 0.0, -GRAVITY_M_S2), (0.0, 0.0, 0.2)))
        _at_rest(est, t, t + 0.5)
    # THEN nothing of it is integrated: the vehicle is where the fix put it, the heading the attitude's
    s = est.nav_state()
    assert est.rejected["attitude_driven"] == 20 and est.imu_model.grade == "attitude"
    np.testing.assert_allclose(s.pos_n_m[:2], [20.0, -5.0], atol=0.05)
    assert s.euler_rad()[2] == pytest.approx(0.7, abs=1e-3)


def test_a_fast_imu_appearing_re_aligns_into_an_ins_on_it_keeping_the_position():
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    lat, lon, _ = ORIGIN.to_geodetic(np.array([20.0, -5.0, 0.0]))
    est.process(UsblSample(0.05, float(lat), float(lon), 4.0, 1.0))
    _at_rest(est, 0.0, 10.0)
    before = est.nav_state()
    assert est.imu_model.grade == "attitude" and before.valid
    # WHEN the requested 100 Hz IMU arrives (the vehicle at rest), in time order with the rest
    for k in range(30):
        t = np.arange(1, 11) / 100.0 + 10.0 + 0.1 * k
        est.process(ImuBatch(t, np.tile([0.0, 0.0, -GRAVITY_M_S2], (10, 1)), np.zeros((10, 3))))
        _at_rest(est, float(t[-1]), float(t[-1]) + 0.05)
    # THEN the filter is an INS on it, where the attitude-driven one was, with its heading
    s = est.nav_state()
    assert est.imu_model.grade != "attitude" and est.imu_model.source != "attitude"
    np.testing.assert_allclose(s.pos_n_m[:2], [20.0, -5.0], atol=0.1)
    assert s.euler_rad()[2] == pytest.approx(0.7, abs=1e-3)
    assert s.reset_counter > before.reset_counter  # a new start: the autopilot is told


@pytest.mark.parametrize("imu_rate_hz, integrated", [(10.0, False), (50.0, True)])
def test_one_imu_rate_rule_decides_whether_the_imu_or_the_attitude_drives(imu_rate_hz, integrated):
    # GIVEN an autopilot at rest streaming its IMU at imu_rate_hz from the start, ATTITUDE at 10 Hz
    # (the live daemon gets whatever rate the autopilot keeps; the tlog reader withholds a
    # stream below the same alignment.min_imu_rate_hz)
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    lat, lon, _ = ORIGIN.to_geodetic(np.array([20.0, -5.0, 0.0]))
    est.process(UsblSample(0.05, float(lat), float(lon), 4.0, 1.0))
    period = 1.0 / imu_rate_hz
    for k in range(int(20.0 / 0.1)):
        t0 = 0.1 * k
        t = t0 + period * np.arange(1, int(round(0.1 / period)) + 1)
        est.process(ImuBatch(t, np.tile([0.0, 0.0, -GRAVITY_M_S2], (t.size, 1)), np.zeros((t.size, 3))))
        _at_rest(est, float(t[-1]), float(t[-1]) + 0.05)
    # THEN a 10 Hz IMU's instants are not integrated (the attitude drives), a 50 Hz one's are
    assert est.initialized
    assert (est.imu_model.grade != "attitude") == integrated, est.imu_model
    assert (est.rejected["attitude_driven"] > 0) == (not integrated)


def test_with_the_attitude_drive_off_the_filter_is_an_ahrs_and_never_valid():
    cfg = FilterConfig()
    cfg = replace(cfg, attitude_driven=replace(cfg.attitude_driven, enabled=False))
    m = make_mission(np.random.default_rng(13), 120.0, usbl_period_s=5.0)
    est = Estimator(cfg, MotionParams(), RpmSpeedTable(), ORIGIN)
    t, valid, nees, err = map(np.array, zip(*_run(est, m, _without_imu(m))))
    assert est.initialized and not valid.any() and est.invalid_reasons() == ["ahrs_only"]


def test_dropped_attitude_messages_are_a_longer_step_not_a_reset():
    # GIVEN an attitude-driven filter turning at 6°/s, ATTITUDE at 10 Hz over a lossy radio
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    yaw_rate = np.radians(6.0)
    times = [t for t in np.arange(0.0, 30.0, 0.1) if not (10.0 < t < 10.55 or 20.0 < t < 20.75)]
    counter = None
    for t in times:
        est.process(AttitudeSample(float(t), 0.0, 0.0, float(yaw_rate * t)))
        if counter is None and est.initialized:
            counter = est.nav_state().reset_counter
    s = est.nav_state()
    # THEN the drops of 0.6 and 0.8 s are steps: no gap, no reset told to the autopilot, and the
    # heading is the attitude's (the rotation over a drop is exact, whatever its length)
    assert est.rejected["imu_gap"] == 0 and s.reset_counter == counter
    assert s.euler_rad()[2] == pytest.approx(yaw_rate * times[-1], abs=1e-3)
    # AND a drop longer than attitude_driven.max_step_s is a gap
    t_last = times[-1] + est.config.attitude_driven.max_step_s + 0.5
    est.process(AttitudeSample(float(t_last), 0.0, 0.0, float(yaw_rate * t_last)))
    assert est.rejected["imu_gap"] == 1 and est.nav_state().reset_counter == counter + 1


def test_an_attitude_stream_too_sparse_to_drive_the_strapdown_leaves_the_ahrs():
    # GIVEN ATTITUDE at 1 Hz only (each step would be a gap): AHRS, never valid
    m = make_mission(np.random.default_rng(14), 120.0, usbl_period_s=5.0)
    est = Estimator(_cfg(), MotionParams(), RpmSpeedTable(), ORIGIN)
    t, valid, nees, err = map(np.array, zip(*_run(est, m, _without_imu(m, attitude_rate_hz=1.0))))
    assert est.initialized and not valid.any() and est.invalid_reasons() == ["ahrs_only"]
    assert est.imu_model.grade != "attitude" and est.rejected["imu_gap"] == 0  # no gap after gap
