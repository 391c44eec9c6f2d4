"""Estimator behaviour: alignment, bad input, late measurements, AHRS-only mode, persistence."""
import copy
import math
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import (AttitudeSample, DepthSample, HeadingSample, ImuBatch, ImuSample, TruthSample,
                            UsblSample)
from adaptnav.fusion.state import KS

from .mission import ATM_PA, ORIGIN, RHO, make_mission, run


def _est(cfg=None):
    return Estimator(cfg or FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)


def _static_batch(t0, n, rate=100.0):
    t = t0 + np.arange(1, n + 1) / rate
    f = np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    return ImuBatch(t, f, np.zeros((n, 3)))


def _aligned():
    est = _est()
    est.process(_static_batch(0.0, 100))
    est.process(HeadingSample(1.0, 0.5))
    assert est.initialized
    return est


def test_aids_before_alignment_are_reported_not_initialized():
    est = _est()
    out = est.process(HeadingSample(0.1, 0.3))
    assert [a.reason for a in out] == ["not_initialized"] and not est.initialized
    est.process(_static_batch(0.0, 100))
    assert est.initialized  # levelled from the accelerometers, heading from the held sample
    roll, pitch, yaw = est.nav_state().euler_rad()
    assert abs(roll) < 1e-9 and abs(pitch) < 1e-9 and yaw == pytest.approx(0.3)


def test_first_position_fix_before_alignment_sets_the_initial_position():
    est = _est()
    lat, lon, _ = ORIGIN.to_geodetic(np.array([100.0, -50.0, 0.0]))
    est.process(UsblSample(0.5, float(lat), float(lon), 5.0, 2.0))
    est.process(_static_batch(0.0, 100))
    est.process(HeadingSample(1.0, 0.0))
    s = est.nav_state()
    np.testing.assert_allclose(s.pos_n_m[:2], [100.0, -50.0], atol=1e-6)
    assert s.cov[0, 0] == pytest.approx(4.0)


def test_first_fix_after_the_start_places_the_position_a_later_one_is_fused():
    # GIVEN a start with no fix (at the origin, σ initial.sigma_pos_m = 10 m), at rest
    est = _aligned()
    counter = est.nav_state().reset_counter
    est.process(_static_batch(1.0, 100))
    lat, lon, _ = ORIGIN.to_geodetic(np.array([30.0, -20.0, 0.0]))
    # WHEN the first fix comes: THEN the position is the fix's, its covariance the fix's,
    # uncorrelated (fused as an update, the arbitrary start would keep 2 %: 0.8 m here)
    (st,) = est.process(UsblSample(2.0, float(lat), float(lon), 5.0, 1.5))
    s = est.nav_state()
    assert st.fused and st.innovation[:2] == pytest.approx((30.0, -20.0), abs=1e-6)
    np.testing.assert_allclose(s.pos_n_m[:2], [30.0, -20.0], atol=1e-9)
    np.testing.assert_allclose(s.cov[:2, :2], np.eye(2) * 1.5**2, atol=1e-9)
    assert not np.any(s.cov[:2, 2:]) and s.reset_counter == counter + 1  # a jump, told to the autopilot
    # a second fix is an update: the position moves part of the way, σ shrinks
    est.process(_static_batch(2.0, 100))
    lat, lon, _ = ORIGIN.to_geodetic(np.array([31.5, -20.0, 0.0]))
    (st,) = est.process(UsblSample(3.0, float(lat), float(lon), 5.0, 1.5))
    s = est.nav_state()
    assert st.fused and 30.5 < s.pos_n_m[0] < 31.0 and s.cov[0, 0] < 0.6 * 1.5**2
    assert s.reset_counter == counter + 1


def test_unused_sample_types_are_ignored():
    est = _aligned()
    assert est.process(TruthSample(1.0, (0, 0, 0), (0, 0, 0), (1, 0, 0, 0), (0, 0, 0), 1.0)) == []


def test_non_finite_imu_samples_are_rejected_counted_and_the_state_stays_finite():
    est = _aligned()
    b = _static_batch(1.0, 200)
    f = b.specific_force_b_m_s2.copy()
    f[50, 1] = np.nan
    f[120, 2] = np.inf
    est.process(ImuBatch(b.t_s, f, b.omega_b_rad_s))
    est.process(ImuSample(4.0, (math.nan, 0.0, -9.8), (0.0, 0.0, 0.0)))
    assert est.rejected["non_finite"] == 3
    s = est.nav_state()
    assert np.all(np.isfinite(s.pos_n_m)) and np.all(np.isfinite(s.cov))
    assert s.t_s == pytest.approx(3.0)
    np.testing.assert_allclose(s.vel_n_m_s, 0.0, atol=1e-6)


def test_out_of_order_and_duplicate_imu_timestamps_are_rejected_and_counted():
    est = _aligned()
    est.process(_static_batch(1.0, 100))          # up to t = 2.0
    est.process(ImuSample(2.0, (0, 0, -GRAVITY_M_S2), (0, 0, 0)))   # duplicate
    est.process(ImuSample(1.5, (0, 0, -GRAVITY_M_S2), (0, 0, 0)))   # out of order
    t = np.array([2.01, 2.02, 2.02, 2.015, 2.03])
    est.process(ImuBatch(t, np.tile([0, 0, -GRAVITY_M_S2], (5, 1)), np.zeros((5, 3))))
    assert est.rejected["duplicate"] == 2
    assert est.rejected["out_of_order"] == 2
    assert est.nav_state().t_s == pytest.approx(2.03)


def test_a_10_s_imu_gap_is_counted_reset_and_the_filter_keeps_fusing():
    m = make_mission(np.random.default_rng(5), 120.0, usbl_period_s=5.0)
    keep = (m.t_imu < 50.0) | (m.t_imu >= 60.0)
    m.t_imu, m.f_b, m.w_b, m.pos_n = m.t_imu[keep], m.f_b[keep], m.w_b[keep], m.pos_n[keep]
    est = _est()
    states, statuses = run(est, m, probe_times=[49.0, 61.0, 119.0])
    assert est.rejected["imu_gap"] == 1
    (s0, s1, s2) = [s for _, s in states]
    assert s1.reset_counter == s0.reset_counter + 1
    for s in (s1, s2):
        assert np.all(np.isfinite(s.cov)) and np.all(np.isfinite(s.pos_n_m))
    # the gap inflated the uncertainty, later fixes bring it back
    assert s1.cov[0, 0] > s0.cov[0, 0] and s2.cov[0, 0] < s1.cov[0, 0]
    assert all(a.fused for a in statuses if a.source == "usbl" and a.t_s > 70)
    k = int(np.searchsorted(m.t_imu, 119.0)) - 1
    assert np.linalg.norm(s2.pos_n_m[:2] - m.pos_n[k, :2]) < 3 * math.sqrt(s2.cov[0, 0] + s2.cov[1, 1])


def test_non_finite_aid_is_rejected_with_its_reason():
    est = _aligned()
    out = est.process(DepthSample(1.0, math.nan))
    assert out[0].reason == "non_finite" and not out[0].fused
    assert est.rejected["non_finite"] == 1


def test_an_outlier_is_gated():
    est = _aligned()
    out = est.process(HeadingSample(1.0, 0.5 + 1.0))  # 1 rad off with σ 0.05 prior + 0.5° aid
    assert out[0].reason == "gate" and out[0].test_ratio > 1.0


@pytest.mark.parametrize("delay_s, max_batch", [(0.6, None), (0.95, 1)])
def test_a_late_measurement_is_fused_at_its_time_of_validity(delay_s, max_batch):
    # GIVEN the same mission fed in order, and with one USBL fix arriving late — also just
    # inside max_delay_s (1 s) with the IMU sample by sample, as live (a hundred inputs a
    # second: the history is trimmed and holds snapshot-less IMU runs, yet still starts
    # before the fix)
    m = make_mission(np.random.default_rng(11), 60.0, usbl_period_s=20.0)
    fix = next(a for a in m.aids if a.KIND == "usbl" and a.t_s == 40.0)
    on_time = _est()
    run(on_time, m, max_batch=max_batch)
    late = _est()
    late_m = copy.copy(m)
    # deliver it when the IMU has reached 40 s + the delay
    late_m.aids = sorted([a for a in m.aids if a is not fix] + [_Delayed(fix, 40.0 + delay_s)], key=lambda a: a.t_s)
    run(late, late_m, max_batch=max_batch)
    # THEN the result equals the in-order run
    a, b = on_time.nav_state(), late.nav_state()
    np.testing.assert_allclose(b.pos_n_m, a.pos_n_m, atol=1e-6)
    np.testing.assert_allclose(b.cov, a.cov, atol=1e-9)
    assert late.late_fused == 1


class _Delayed:
    """Stands in for the transport: hands over ``sample`` when the stream reaches ``t_s``."""

    KIND = "delayed"

    def __init__(self, sample, t_s):
        self.sample, self.t_s = sample, t_s


class _Release:
    """A calibrator release applied when the stream reaches ``t_s``."""

    KIND = "release"

    def __init__(self, params, t_s):
        self.params, self.t_s = params, t_s


def test_a_release_between_a_late_measurement_and_its_time_is_reapplied_in_place():
    # GIVEN a release (k_V 1 → 0.9) at 40.3 s, and a USBL fix of 40.0 s that arrives at 40.6 s
    m = make_mission(np.random.default_rng(12), 60.0, usbl_period_s=20.0, k_v_true=0.9)
    fix = next(a for a in m.aids if a.KIND == "usbl" and a.t_s == 40.0)
    release = _Release(replace(MotionParams(), k_v=0.9, var_vv=0.1**2), 40.3)
    on_time = _est()
    m_on = copy.copy(m)
    m_on.aids = sorted(m.aids + [release], key=lambda a: a.t_s)
    run(on_time, m_on)
    late = _est()
    late_m = copy.copy(m)
    late_m.aids = sorted([a for a in m.aids if a is not fix] + [_Delayed(fix, 40.6), release],
                         key=lambda a: a.t_s)
    run(late, late_m)
    # THEN re-fusing the fix before the release gives the in-order result, k_speed included
    a, b = on_time.nav_state(), late.nav_state()
    assert late.late_fused == 1 and late.motion_params.k_v == 0.9
    assert b.k_speed == pytest.approx(a.k_speed, abs=1e-9)
    np.testing.assert_allclose(b.pos_n_m, a.pos_n_m, atol=1e-6)


def _surge_variances(statuses, t0, t1):
    return [s.innovation_variance[0] for s in statuses
            if s.source == "learned_velocity" and s.fused and t0 <= s.t_s < t1]


def test_the_adaptive_surge_scale_is_suspended_after_a_release_and_resumes_without_releases():
    # GIVEN water 4x noisier in surge than the filter's model, which the adaptive scale follows
    noisy = replace(MotionParams(), var_vv=0.2**2)
    cfg = replace(FilterConfig(), learned_velocity=replace(FilterConfig().learned_velocity,
                                                           adaptive_suspend_after_release_s=100.0))
    model_var = 1.5**2 * MotionParams().var_vv
    medians = {}
    for label, releases in (("none", []), ("release", [_Release(MotionParams(), 300.0)])):
        m = make_mission(np.random.default_rng(13), 600.0, params=noisy, usbl_period_s=10.0)
        m.aids = sorted(m.aids + releases, key=lambda a: a.t_s)
        _, statuses = run(_est(cfg), m)
        medians[label] = [np.median(_surge_variances(statuses, t0, t0 + 100.0)) for t0 in (300.0, 450.0)]
    # THEN without a release the scale is up after 300 s; with a release at 300 s (keeping
    # the too-tight model) it is off for the 100 s after it, and back once releases stop
    assert medians["none"][0] > 5 * model_var
    assert medians["release"][0] < 2 * model_var
    assert medians["release"][1] > 5 * model_var


def test_too_late_measurement_is_rejected():
    est = _aligned()
    est.process(_static_batch(1.0, 300))  # t = 4
    out = est.process(DepthSample(2.5, ATM_PA))
    assert out[0].reason == "too_late" and est.rejected["too_late"] == 1


def test_ahrs_only_log_gives_attitude_and_depth_and_says_position_invalid():
    # GIVEN real-ArduSub-like telemetry: ATTITUDE at 20 Hz, pressure at 2 Hz, IMU at 2 Hz
    est = _est()
    for k in range(400):
        t = k * 0.05
        if k % 10 == 0:
            est.process(ImuSample(t + 0.001, (0.0, 0.0, -GRAVITY_M_S2), (0.0, 0.0, 0.0)))
            est.process(DepthSample(t, ATM_PA + RHO * GRAVITY_M_S2 * 3.0))
        est.process(AttitudeSample(t, 0.05, -0.1, 1.2 + 0.01 * t))
    s = est.nav_state()
    # THEN attitude follows the AHRS, depth the pressure, and the horizontal position is invalid
    assert est.initialized and not s.valid
    roll, pitch, yaw = s.euler_rad()
    assert roll == pytest.approx(0.05, abs=0.01) and pitch == pytest.approx(-0.1, abs=0.01)
    assert yaw == pytest.approx(1.2 + 0.01 * 19.95, abs=0.02)
    assert s.pos_n_m[2] == pytest.approx(3.0, abs=0.05)
    assert np.all(np.isfinite(s.cov))


def test_slow_states_survive_a_restart():
    m = make_mission(np.random.default_rng(3), 120.0, current_n=(0.2, 0.1))
    est = _est()
    run(est, m)
    saved = est.slow_states()
    fresh = _est()
    fresh.restore_slow_states(saved)
    fresh.process(_static_batch(0.0, 100))
    fresh.process(HeadingSample(1.0, 0.0))
    s = fresh.nav_state()
    np.testing.assert_allclose(s.current_n_m_s, saved["current_n_m_s"])
    assert float(s.sigma(KS)[0]) ** 2 == pytest.approx(saved["var_k_speed"])
    with pytest.raises(ValueError):
        fresh.restore_slow_states({**saved, "k_speed": -1.0})


def test_no_slow_states_to_keep_before_alignment_unless_restored():
    """A filter that never aligned has only its defaults, with zero variances: kept, they were
    refused at the next start ("persisted slow states not usable"), so there are none to keep;
    restored ones are kept through the alignment, and an aligned filter's are its own."""
    m = make_mission(np.random.default_rng(3), 120.0, current_n=(0.2, 0.1))
    est = _est()
    run(est, m)
    saved = est.slow_states()
    assert saved and all(v > 0 for key in ("var_bias_acc", "var_bias_gyro", "var_current") for v in saved[key])
    fresh = _est()
    assert fresh.slow_states() == {}
    fresh.process(HeadingSample(0.5, 0.0))  # not aligned by a heading alone
    assert not fresh.initialized and fresh.slow_states() == {}
    fresh.restore_slow_states(saved)
    kept = fresh.slow_states()
    np.testing.assert_allclose(kept["current_n_m_s"], saved["current_n_m_s"])
    assert kept["var_k_speed"] == pytest.approx(saved["var_k_speed"])
    _est().restore_slow_states(saved)  # (what was kept is what a restart takes)


def test_a_calibrator_release_keeps_the_modelled_speed_continuous():
    est = _aligned()
    before = est.nav_state().k_speed * est.motion_params.k_v
    est.set_motion_params(replace(MotionParams(), k_v=1.1))
    assert est.nav_state().k_speed * 1.1 == pytest.approx(before)


def test_a_k_v_the_dvl_measured_becomes_the_speed_scale():
    # GIVEN a filter whose own k_speed has wandered to 1.03
    est = _aligned()
    from adaptnav.fusion.state import X_KS
    est._x[X_KS] = 1.03
    # WHEN a release whose k_V the DVL measured arrives
    est.set_motion_params(replace(MotionParams(), k_v=0.95), adopt_k_v=True)
    # THEN the modelled speed scale is the release's, not the filter's product 1.03 × 1.0
    assert est.nav_state().k_speed * est.motion_params.k_v == pytest.approx(0.95)


def test_a_filter_that_gated_the_fixes_repeatedly_trusts_them_again():
    # GIVEN an aligned filter that believes it is at the origin within 1.5 m
    est = _aligned()
    assert est.nav_state().cov[0, 0] < 150.0
    lat, lon, _ = ORIGIN.to_geodetic(np.array([200.0, 0.0, 0.0]))
    fixes = []
    # WHEN consecutive fixes, all 200 m away, arrive
    for k in range(4):
        est.process(_static_batch(1.0 + k, 100))
        fixes += est.process(UsblSample(2.0 + k, float(lat), float(lon), 0.0, 2.0))
    # THEN the first ones are gated, then the filter resets onto them
    assert [f.reason for f in fixes[:2]] == ["gate", "gate"]
    assert fixes[2].fused and est.rejected["position_reset"] == 1
    assert est.nav_state().pos_n_m[0] == pytest.approx(200.0, abs=5.0)


def test_k_speed_is_learned_from_position_fixes():
    # GIVEN water where the vehicle makes 8 % less speed per RPM than the model says
    m = make_mission(np.random.default_rng(21), 600.0, k_v_true=0.92, usbl_period_s=10.0)
    est = _est()
    states, _ = run(est, m, probe_times=[590.0])
    s = states[0][1]
    # THEN k_speed converges to the ratio within its 3σ, and that σ is small
    sigma = float(s.sigma(KS)[0])
    assert abs(s.k_speed - 0.92) < 3 * sigma and sigma < 0.03
