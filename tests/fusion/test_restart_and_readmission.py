"""Recovery the live ArduSub run needs: a learned velocity that is re-admitted after its reset
instead of rejected again, a restart seeded from the persisted position with an honest σ, and
no radio fix under water taken as the initial position."""
import math

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig, ImuConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import AttitudeSample, DepthSample, GnssSample, ImuBatch, RpmSample

from .mission import ATM_PA, ORIGIN, RHO

RATE_HZ = 50.0
TABLE = RpmSpeedTable()


def _est(cfg=None):
    cfg = cfg or FilterConfig(imu=ImuConfig(grade="tactical"))
    return Estimator(cfg, MotionParams(), TABLE, ORIGIN)


def _drive(est, t0, t1, speed_true, model_scale=1.0, depth_m=None, rng=None):
    """Straight north at ``speed_true(t)`` (m/s): a level IMU sensing the accelerations, the
    autopilot's attitude at 10 Hz, thrust (as RPM for ``model_scale`` × the true speed) at
    10 Hz, pressure at ``depth_m``. Returns the statuses and the true north position gained."""
    out, north = [], 0.0
    n = int(round((t1 - t0) * RATE_HZ))
    for k in range(n):
        t = t0 + (k + 1) / RATE_HZ
        v0, v1 = speed_true(t - 1 / RATE_HZ), speed_true(t)
        north += 0.5 * (v0 + v1) / RATE_HZ
        acc = (v1 - v0) * RATE_HZ
        if k % 5 == 0:
            out += est.process(AttitudeSample(t - 0.001, 0.0, 0.0, 0.0))
            rpm = float(TABLE.rpm_for_speed(model_scale * v1)) if v1 > 0 else 0.0
            out += est.process(RpmSample(t - 0.002, rpm))
            if depth_m is not None:
                out += est.process(DepthSample(t - 0.003, ATM_PA + RHO * GRAVITY_M_S2 * depth_m))
        f = np.array([[acc, 0.0, -GRAVITY_M_S2]])
        w = np.zeros((1, 3))
        if rng is not None:
            f = f + 1e-3 * rng.standard_normal((1, 3))
        out += est.process(ImuBatch(np.array([t]), f, w))
    return out, north


def _steps(t):
    """True speed: still, then 20 s legs at changing speeds (1 s ramps)."""
    legs = [(5.0, 0.0), (6.0, 0.5), (26.0, 0.25), (46.0, 0.75), (66.0, 0.4), (86.0, 0.6)]
    v = 0.0
    for t_start, speed in legs:
        if t >= t_start:
            v_prev, v = v, speed
            if t < t_start + 1.0:
                return v_prev + (speed - v_prev) * (t - t_start)
    return v


def _shock(t):
    """At rest, then for 0.5 s the IMU says 20 m/s² forward (a shock; the thrusters idle)."""
    return 10.0 * min(max(t - 5.0, 0.0), 0.5) / 0.5


def test_after_a_velocity_reset_the_learned_velocity_is_measured_again_and_fused():
    # GIVEN a velocity 10 m/s off after a shock, the thrusters idle: the learned velocity is gated
    est = _est()
    statuses, _ = _drive(est, 0.0, 25.0, _shock, model_scale=0.0, depth_m=3.0)
    lv = [a for a in statuses if a.source == "learned_velocity"]
    gated = [a for a in lv if a.reason == "gate"]
    assert gated
    # THEN after reset.velocity_after_s the velocity is reset onto it once, and the attempt of
    # that epoch is measured again after the reset (innovation ≈ 0, fused) — not the stale
    # pre-reset innovation, which would be gated again (or, fused, applied twice)
    assert est.resets == {"velocity:learned_velocity": 1}
    after_s = FilterConfig().reset.velocity_after_s
    assert gated[-1].t_s - gated[0].t_s < after_s - 0.5  # the reset epoch's own attempt is not gated
    k = lv.index(gated[-1]) + 1
    assert lv[k].t_s - gated[0].t_s == pytest.approx(after_s, abs=0.1)
    assert lv[k].fused and max(abs(y) for y in lv[k].innovation) < 0.05, lv[k]
    assert all(a.fused for a in lv[k:])
    assert np.linalg.norm(est.nav_state().vel_n_m_s) < 0.2


def test_a_restart_is_seeded_from_the_persisted_position_with_sigma_grown_by_the_time_down():
    cfg = FilterConfig(imu=ImuConfig(grade="tactical"))
    est = _est(cfg)
    _, north = _drive(est, 0.0, 40.0, _steps, depth_m=4.0)
    saved = est.slow_states()
    s = est.nav_state()
    assert saved["pos_n_m"][0] == pytest.approx(s.pos_n_m[0]) and saved["pos_t_s"] == pytest.approx(s.t_s)
    # WHEN the daemon restarts 20 s later (the vehicle drifted on at 0.25 m/s meanwhile: 5 m)
    fresh = _est(cfg)
    fresh.restore_slow_states(saved)
    _drive(fresh, 60.0, 64.0, lambda t: 0.0, depth_m=4.0)
    assert fresh.initialized
    r = fresh.nav_state()
    # THEN it starts where the last run was, σ_h grown by the vehicle's top speed over the time
    # down (as a 3σ bound), so the truth is within 3σ; depth from the pressure
    sigma_h = math.sqrt(max(r.cov[0, 0], r.cov[1, 1]))
    down_s = r.t_s - saved["pos_t_s"]
    assert down_s > 20.0
    assert sigma_h >= cfg.position_reset_max_speed_m_s * down_s / 3.0
    truth_n = north + 0.25 * 20.0
    assert abs(r.pos_n_m[0] - truth_n) <= 3.0 * sigma_h
    assert r.pos_n_m[0] == pytest.approx(saved["pos_n_m"][0], abs=1.0)
    assert r.pos_n_m[2] == pytest.approx(4.0, abs=0.2)
    # AND when more time is known to have passed than the data clock says (the daemon's wall
    # clock: the autopilot may have rebooted meanwhile), σ grows with that
    longer = _est(cfg)
    longer.restore_slow_states({**saved, "pos_min_elapsed_s": 300.0})
    _drive(longer, 60.0, 64.0, lambda t: 0.0, depth_m=4.0)
    g = longer.nav_state()
    assert math.sqrt(max(g.cov[0, 0], g.cov[1, 1])) >= cfg.position_reset_max_speed_m_s * 300.0 / 3.0
    # AND a persisted state from another clock (the autopilot rebooted: time went back) is
    # not used: the position starts at the origin with the initial σ
    other = _est(cfg)
    other.restore_slow_states(saved)
    _drive(other, 0.0, 4.0, lambda t: 0.0, depth_m=4.0)
    o = other.nav_state()
    assert np.hypot(*o.pos_n_m[:2]) < 0.01 and math.sqrt(o.cov[0, 0]) == pytest.approx(cfg.initial.sigma_pos_m, rel=0.05)
    with pytest.raises(ValueError):
        _est(cfg).restore_slow_states({**saved, "var_pos_n_m2": [-1.0, 1.0, 1.0]})


@pytest.mark.parametrize("gnss_first", [False, True])
def test_a_radio_fix_under_water_does_not_seed_the_position(gnss_first):
    # GIVEN a vehicle at 5 m whose GNSS (a simulator's) still reports a fix 30 m off the
    # origin, before the filter has aligned — before or after the first depth sample
    est = _est()
    lat = ORIGIN.lat_rad + 30.0 / 6_378_137.0
    fix = GnssSample(0.001, lat, ORIGIN.lon_rad, 0.5)
    depth = DepthSample(0.002, ATM_PA + RHO * GRAVITY_M_S2 * 5.0)
    for s in ((fix, depth) if gnss_first else (depth, fix)):
        est.process(s)
    _drive(est, 0.0, 4.0, lambda t: 0.0, depth_m=5.0)
    # THEN the position does not start at the fix
    r = est.nav_state()
    assert est.initialized and abs(r.pos_n_m[0]) < 1.0 and r.pos_n_m[2] == pytest.approx(5.0, abs=0.2)
