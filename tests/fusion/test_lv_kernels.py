"""The learned velocity's compiled epoch (kalman.lv_epoch: measurement, surge-variance adaptation,
update) against the numpy model and the estimator's general path (Estimator._lv_measure, _fuse),
on seeded random states and parameters: the same operations in the same order, so the same
numbers — except where numpy sums through BLAS (the yaw rate's dot, ``Rᵀ v``, ``Rᵀ [v]×``,
``h P hᵀ``: fused multiply-adds, another order), there to the last bits (1e-12 relative)."""
import dataclasses
import math
from collections import Counter

import numpy as np
import pytest

from adaptnav.fusion import eskf, kalman
from adaptnav.fusion.aiding import learned_velocity as aid_lv
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import euler_to_quat
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import RpmSample
from adaptnav.fusion.state import ACC_OMEGA, ACC_RF, ACC_R, ACC_T, X_CUR, X_KS, initial_nominal

from .mission import ORIGIN, make_mission, run

# to the last bits: speeds and Jacobian entries (O(1), a near-cancelling sum may lose its relative
# digits: a few ulps of its terms), variances (down to 1e-5 m²/s²)
LAST_BITS = dict(rtol=1e-12, atol=1e-14)
VARIANCES = dict(rtol=1e-12, atol=1e-18)

# the estimator's additions off, each on, all on
CONFIGS = {
    "plain": {},
    "transient": dict(transient_time_s=3.0),
    "skid": dict(skid_sigma_s=0.5),
    "heave": dict(heave_sigma_per_vertical_speed=0.3),
    "all": dict(transient_time_s=3.0, skid_sigma_s=0.5, heave_sigma_per_vertical_speed=0.3, variance_scale=1.7,
                sigma_heave_m_s=0.07, coast_mean_fraction=0.3, coast_sigma_per_gap=1.5, skid_max_fraction=0.1),
}


def _estimator(**lv):
    config = FilterConfig()
    config = dataclasses.replace(config, learned_velocity=dataclasses.replace(config.learned_velocity, **lv))
    return Estimator(config, MotionParams(), RpmSpeedTable(), ORIGIN)


def _random_epoch(est, rng):
    """A random state, rate, covariance (with a covariance step pending), motion model and thrust."""
    roll, pitch, yaw = rng.uniform(-0.4, 0.4), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
    x = initial_nominal(rng.normal(size=3) * 100, rng.normal(size=3), euler_to_quat(roll, pitch, yaw))
    x[X_CUR] = rng.normal(size=2) * 0.3
    x[X_KS] = 1.0 + rng.normal() * 0.05
    est._x[:] = x
    est._acc[:] = 0.0
    est._acc[ACC_OMEGA] = rng.normal(size=3) * 0.2
    A = rng.normal(size=(18, 18))
    est._P[:, :] = A @ A.T * 0.01
    if rng.uniform() < 0.5:  # a covariance step pending: the adaptation's P is the flushed one
        est._acc[ACC_RF] = rng.normal(size=3) * 0.01
        est._acc[ACC_R] = np.eye(3).ravel() * 0.02
        est._acc[ACC_T] = 0.02
    est.motion_params = MotionParams(
        k_v=1.0 + rng.normal() * 0.1, turn_speed_loss=abs(rng.normal()), sway_per_turn=rng.normal() * 0.3,
        sway_per_surge=rng.normal() * 0.05, heave_per_surge=rng.normal() * 0.1, var_vv=rng.uniform(1e-4, 1e-2),
        var_vw=rng.uniform(1e-5, 1e-2), var_v1=rng.uniform(1e-5, 1e-3), var_s=rng.uniform(1e-5, 1e-3))
    surge, slow = rng.uniform(0.0, 2.0), rng.uniform(0.0, 2.0)
    sway, slow_sway = (rng.normal() * 0.2, rng.normal() * 0.2) if rng.uniform() < 0.5 else (0.0, 0.0)
    if rng.uniform() < 0.2:  # a settled thrust: no transient
        slow, slow_sway = surge, sway
    est._rpm = (0.0, surge, sway, surge, sway, slow, slow_sway)


def _epoch(est, gate, since_release_s=math.inf):
    """kalman.lv_epoch on the estimator's arrays as Estimator._lv_fast calls it: (buf, dx, its returns)."""
    buf, dx = np.full(kalman.LV_BUF_SIZE, np.nan), np.full(18, np.nan)
    r, r_hat = est._rpm, est._surge.r_hat_m2_s2
    out = kalman.lv_epoch(est._core, est._qdiag, aid_lv.kernel_params(est.motion_params, est.config.learned_velocity),
                          buf, dx, r[1], r[2], r[5], r[6], 0.0 if r_hat is None else r_hat, r_hat is not None,
                          since_release_s, gate, True)
    return buf, dx, out


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_the_compiled_lv_measurement_is_the_numpy_models(name):
    """The measurement in the scratch (gate −1: nothing fused) against the numpy model and the
    estimator's additions (Estimator._lv_measure), the surge variance not adapted (no estimate yet)."""
    rng = np.random.default_rng(29)
    est = _estimator(**CONFIGS[name])
    cfg = est.config.learned_velocity
    coasts = 0
    for _ in range(300):
        _random_epoch(est, rng)
        est._surge.r_hat_m2_s2 = None
        core = est._core.copy()
        want = est._lv_measure(0.0, adapt=False)  # the numpy model and the additions, not adapted
        kalman.flush_core(est._core, est._qdiag)
        flushed = est._core.copy()
        est._core[:] = core
        buf, dx, out = _epoch(est, -1.0, since_release_s=-math.inf)  # gated; the estimate not used
        assert est._core.tobytes() == flushed.tobytes()  # flushed as kalman.flush_core, nothing else
        assert not out[1] and np.all(dx == 0.0)
        np.testing.assert_allclose(buf[kalman.LV_Z], want.z, **LAST_BITS)
        np.testing.assert_allclose(buf[kalman.LV_H], want.h, **LAST_BITS)
        H = buf[kalman.LV_JAC].reshape(3, 18)
        np.testing.assert_allclose(H, want.H, **LAST_BITS)
        assert np.all(H[:, [0, 1, 2, 9, 10, 11, 12, 13, 14]] == 0.0) and H[2, 17] == 0.0
        np.testing.assert_allclose(buf[kalman.LV_R].reshape(3, 3), want.R, **VARIANCES)
        assert np.count_nonzero(buf[kalman.LV_R]) == 3
        y = buf[kalman.LV_Z] - buf[kalman.LV_H]
        assert out[2:8] == (*buf[kalman.LV_Z].tolist(), *y.tolist())
        coasts += cfg.transient_time_s > 0 and abs(est._rpm[5]) > abs(est._rpm[1])
    assert cfg.transient_time_s == 0 or coasts > 50  # both branches of a coast


def test_the_compiled_lv_squares_are_pythons_to_the_bit():
    """Squares of numbers the state does not enter (the model's variances, the heave's) are
    Python's ``x ** 2`` exactly: libm's pow, not ``x * x`` (they differ in ~1 case in 1000)."""
    rng = np.random.default_rng(3)
    est = _estimator(heave_sigma_per_vertical_speed=0.37, adaptive_window_s=0.0)
    differ = 0
    for _ in range(3000):
        _random_epoch(est, rng)
        est._acc[ACC_OMEGA] = 0.0  # no yaw rate: the dot that BLAS sums leaves the variances
        want = est._lv_measure(0.0, adapt=False)
        buf, _, _ = _epoch(est, -1.0)
        assert buf[kalman.LV_R].tobytes() == want.R.ravel().tobytes()
        assert buf[kalman.LV_Z].tobytes() == want.z.tobytes()
        vd = float(est._x[5])
        differ += (0.37 * vd) ** 2 != (0.37 * vd) * (0.37 * vd)
    assert differ > 0  # the case the exact pow is for happened


@pytest.mark.parametrize("name", ["plain", "all"])
def test_the_compiled_lv_epoch_is_the_general_paths(name):
    """State, covariance, correction, estimate and status numbers of one epoch against
    Estimator._lv_measure(adapt=True) and _fuse: estimates none or some, releases old and young,
    innovations fused and gated, surge variances scaled and not."""
    rng = np.random.default_rng(37)
    est = _estimator(**CONFIGS[name])
    gate = est._gate[3]
    seen = Counter()
    for _ in range(400):
        _random_epoch(est, rng)
        est._P[:, :] *= 10.0 ** rng.uniform(-4, 0)  # some gated, some fused
        est._surge.r_hat_m2_s2 = None if rng.uniform() < 0.2 else 10.0 ** rng.uniform(-5, -1)
        est._t_release = rng.choice([-math.inf, -rng.uniform(0.0, 2.0) * est.config.learned_velocity.adaptive_suspend_after_release_s])
        core, r_hat = est._core.copy(), est._surge.r_hat_m2_s2
        est._surge.r_hat_m2_s2 = None
        released = est._lv_measure(0.0, adapt=False).R[0, 0]  # the surge variance not adapted
        est._surge.r_hat_m2_s2 = r_hat
        want = est._lv_measure(0.0, adapt=True)
        status = est._fuse(want, 0.0, "learned_velocity")
        want_core, want_dx, want_r_hat = est._core.copy(), est._dx.copy(), est._surge.r_hat_m2_s2
        est._core[:] = core
        est._surge.r_hat_m2_s2 = r_hat
        buf, dx, out = _epoch(est, gate, since_release_s=0.0 - est._t_release)
        nis, fused = out[:2]
        assert fused == status.fused and out[12]
        np.testing.assert_allclose(nis / gate, status.test_ratio, rtol=1e-10)
        np.testing.assert_allclose(out[2:5], status.observation, **LAST_BITS)
        np.testing.assert_allclose(out[5:8], status.innovation, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(out[8:11], status.innovation_variance, **VARIANCES)
        np.testing.assert_allclose(buf[kalman.LV_R].reshape(3, 3), want.R, **VARIANCES)  # adapted as numpy
        assert out[11] == pytest.approx(want_r_hat, rel=1e-12, abs=1e-15)
        np.testing.assert_allclose(dx, want_dx, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(est._core, want_core, rtol=1e-9, atol=1e-13)
        seen["fused" if fused else "gated"] += 1
        seen["scaled" if want.R[0, 0] != released else "as released"] += 1
    assert min(seen["fused"], seen["gated"], seen["scaled"], seen["as released"]) > 20, seen


def _lv_mission():
    """No DVL: the learned velocity holds the speed; the adaptation, transient, skid and heave on;
    thrust changes (transients, coasts); the RPM 60 % high for 40 s: gated, then a velocity reset."""
    m = make_mission(np.random.default_rng(41), 240.0, heading_period_s=0.5, depth_period_s=0.5,
                     usbl_period_s=20.0, lv_rate_hz=1.0)
    aids = []
    for s in m.aids:
        if isinstance(s, RpmSample):
            f = 1.0 + 0.2 * math.sin(s.t_s / 7.0)
            if 150.0 <= s.t_s < 190.0:
                f = 1.6
            s = dataclasses.replace(s, rpm=s.rpm * f)
        aids.append(s)
    m.aids = aids
    return m


def _lv_run(m, compiled: bool):
    est = _estimator(transient_time_s=2.0, skid_sigma_s=0.5, heave_sigma_per_vertical_speed=0.3)
    est._lv_compiled = compiled
    _, statuses = run(est, m)
    return est, statuses


def test_the_compiled_lv_path_gives_the_general_paths_numbers(monkeypatch):
    m = _lv_mission()
    slow, slow_statuses = _lv_run(m, compiled=False)
    calls = []
    kernel = eskf.kalman.lv_epoch
    monkeypatch.setattr(eskf.kalman, "lv_epoch", lambda *a: calls.append(1) or kernel(*a))
    fast, fast_statuses = _lv_run(m, compiled=True)
    lv = [s for s in fast_statuses if s.source == "learned_velocity"]
    assert len(calls) > 200 and len(lv) == len(calls)  # every epoch (a reset: the status of its re-fusion)
    assert fast.resets["velocity:learned_velocity"] >= 1 and any(s.reason == "gate" for s in lv)
    assert slow.resets == fast.resets
    assert fast._surge.r_hat_m2_s2 is not None
    # the same decisions; the numbers to the last bits (BLAS's sums in the general path)
    slow_lv = [s for s in slow_statuses if s.source == "learned_velocity"]
    assert [(s.t_s, s.fused, s.reason) for s in lv] == [(s.t_s, s.fused, s.reason) for s in slow_lv]
    for a, b in zip(lv, slow_lv):  # (seen: 2e-13 relative at most)
        np.testing.assert_allclose(a.observation, b.observation, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(a.innovation, b.innovation, rtol=0.0, atol=1e-11)
        np.testing.assert_allclose(a.innovation_variance, b.innovation_variance, rtol=1e-11)
    np.testing.assert_allclose(fast._x, slow._x, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(fast._P, slow._P, rtol=0.0, atol=1e-12 * np.abs(slow._P).max())
    np.testing.assert_allclose(fast._surge.r_hat_m2_s2, slow._surge.r_hat_m2_s2, rtol=1e-12)
