"""Honest aids on autopilot telemetry (issue #11): a noisier depth sensor than the default σ gives
a consistent, valid filter while a sensor that goes bad is still caught."""
import math

import numpy as np
import pytest

from adaptnav.fusion.aiding.depth import DepthNoise
from adaptnav.fusion.config import DepthConfig, FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import AttitudeSample, DepthSample, ImuBatch

from .mission import ATM_PA, ORIGIN, RHO

IMU_HZ = 50.0
DEPTH_M = 5.0


def _pressure(depth_m: float) -> float:
    return ATM_PA + RHO * GRAVITY_M_S2 * depth_m


def _run(est, t0, t1, depth_of=None, att_hz=IMU_HZ, att_yaw_rad=0.0):
    """A level vehicle at rest under water: IMU at 50 Hz, ATTITUDE (yaw ``att_yaw_rad``) at
    ``att_hz``, depth at 10 Hz from ``depth_of(t)``; returns (t, valid, invalid reasons) at each depth."""
    out = []
    k0 = int(round(t0 * IMU_HZ))
    every = int(round(IMU_HZ / att_hz))
    for k in range(k0, int(round(t1 * IMU_HZ))):
        t = k / IMU_HZ
        if k % every == 0:
            est.process(AttitudeSample(t + 0.001, 0.0, 0.0, att_yaw_rad))
        if depth_of is not None and k % 5 == 0:
            est.process(DepthSample(t + 0.002, _pressure(depth_of(t))))
            s = est.nav_state()
            out.append((t, s.valid, tuple(est.invalid_reasons())))
        est.process(ImuBatch(np.array([t + 1.0 / IMU_HZ]), np.array([[0.0, 0.0, -GRAVITY_M_S2]]),
                             np.zeros((1, 3))))
    return out


def _noisy_depth(sigma_m, seed=1, step_at_s=math.inf, step_m=0.0):
    rng = np.random.default_rng(seed)
    return lambda t: DEPTH_M + sigma_m * rng.standard_normal() + (step_m if t >= step_at_s else 0.0)


def _est(cfg=None):
    return Estimator(cfg or FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)


# ArduSub SITL's pressure sensor: 0.115 m per sample, white (BARO[1] against SIM in
# tests/data/ardusub-4.7-sitl-drive.BIN), against the default σ of 5 cm
SITL_DEPTH_NOISE_M = 0.115


def test_a_noisier_depth_sensor_than_the_default_sigma_gives_a_valid_solution():
    est = _est()
    rows = _run(est, 0.0, 60.0, _noisy_depth(SITL_DEPTH_NOISE_M))
    late = [r for r in rows if r[0] >= 20.0]
    # THEN the filter is valid (with the fixed 5 cm, nis:depth made it invalid all along) ...
    assert sum(v for _, v, _ in late) / len(late) > 0.95, {r for _, _, r in late}
    assert not any("nis:depth" in r for _, _, r in late)
    # ... because it fuses the depth with the sensor's own noise, reported
    rep = est.depth_noise.report()
    assert rep["sigma_m"] == pytest.approx(SITL_DEPTH_NOISE_M, rel=0.2)
    assert rep["configured_sigma_m"] == 0.05 and rep["max_sigma_m"] == 0.5 and rep["fraction_at_bound"] == 0.0


def test_a_depth_sensor_that_steps_is_still_caught_by_the_integrity_test():
    est = _est()
    # WHEN the noisy sensor steps by 1 m at t = 40 s (the innovations' variance would absorb it)
    rows = _run(est, 0.0, 60.0, _noisy_depth(SITL_DEPTH_NOISE_M, step_at_s=40.0, step_m=1.0))
    before = [v for t, v, _ in rows if 20.0 <= t < 40.0]
    after = [r for t, _, r in rows if 40.0 <= t < 45.0]
    assert sum(before) / len(before) > 0.95
    # THEN the integrity test says so, and the measured noise did not take the step in
    assert any("nis:depth" in r for r in after)
    assert est.depth_noise.sigma_m < 1.3 * SITL_DEPTH_NOISE_M


def test_depth_noise_sees_noise_only_not_drift_steps_or_a_stuck_sensor():
    cfg = DepthConfig()
    t = np.arange(0.0, 30.0, 0.1)
    rng = np.random.default_rng(2)
    noise = 0.1 * rng.standard_normal(t.size)
    cases = {
        # a dive at 0.3 m/s and a drift of 1 m/min: no second difference, noise alone is measured
        "dive_and_drift": (2.0 + 0.3 * t + t / 60.0 + noise, 0.1),
        # steps of 2 m every 5 s: outliers of the median, noise alone is measured
        "steps": (2.0 + 2.0 * np.floor(t / 5.0) + noise, 0.1),
        # stuck: nothing measured, the configured σ (the strictest) is used
        "stuck": (np.full(t.size, 3.0), cfg.sigma_m),
        # noisier than the bound: fused at the bound (the integrity test judges the rest)
        "beyond_bound": (3.0 + 2.0 * rng.standard_normal(t.size), cfg.adaptive_max_sigma_m),
    }
    for name, (z, expected) in cases.items():
        dn = DepthNoise(cfg)
        for ti, zi in zip(t, z):
            dn.sigma_at(float(ti), float(zi))
        assert dn.sigma_m == pytest.approx(expected, rel=0.2), name
    # off (bound not above the configured σ): the configured σ whatever the data
    dn = DepthNoise(DepthConfig(adaptive_max_sigma_m=0.0))
    for ti, zi in zip(t, cases["beyond_bound"][0]):
        assert dn.sigma_at(float(ti), float(zi)) == cfg.sigma_m


def test_astern_thrust_is_a_speed_astern_not_a_stop():
    from adaptnav.fusion.samples import RpmSample

    # GIVEN a vehicle at rest, aligned, WHEN its thrusters run astern at the RPM that makes
    # 1.5 m/s ahead (the embedded table's 1200; an ROV backing out; the table starts at 0 RPM)
    rpm = 1200.0
    est = _est()
    _run(est, 0.0, 12.0, depth_of=lambda t: DEPTH_M)
    statuses = []
    for k in range(3):
        est.process(RpmSample(12.0 + k, -rpm))
        statuses += [s for s in est.process(ImuBatch(np.array([12.05 + k]), np.array([[0.0, 0.0, -GRAVITY_M_S2]]),
                                                     np.zeros((1, 3)))) if s.source == "learned_velocity"]
        statuses += [s for s in _noop(est, 12.05 + k, 13.0 + k) if s.source == "learned_velocity"]
    # THEN the learned velocity observes 1.5 m/s astern (it was "0": the vehicle stopped)
    assert statuses and all(s.observation[0] == pytest.approx(-1.5, abs=1e-6) for s in statuses)


def _noop(est, t0, t1):
    out = []
    for t in np.arange(t0, t1, 1.0 / IMU_HZ)[1:]:
        out += est.process(ImuBatch(np.array([t]), np.array([[0.0, 0.0, -GRAVITY_M_S2]]), np.zeros((1, 3))))
    return out


def _first_lv_status(seconds, **learned_velocity):
    """The learned velocity's status at its first epoch within the counted ``seconds`` — each
    ``(rpm, yaw_rate_rad_s, counted)``, from 12 s on, after an alignment at rest — with
    ``learned_velocity`` config changes."""
    from dataclasses import replace

    from adaptnav.fusion.samples import RpmSample

    cfg = FilterConfig()
    est = _est(replace(cfg, learned_velocity=replace(cfg.learned_velocity, **learned_velocity)))
    _run(est, 0.0, 12.0, depth_of=lambda t: DEPTH_M)
    statuses = []
    for k, (rpm, yaw_rate_rad_s, counted) in enumerate(seconds):
        est.process(RpmSample(12.0 + k, rpm))
        for t in np.arange(12.0 + k, 13.0 + k, 1.0 / IMU_HZ)[1:]:
            out = est.process(ImuBatch(np.array([t]), np.array([[0.0, 0.0, -GRAVITY_M_S2]]),
                                       np.array([[0.0, 0.0, yaw_rate_rad_s]])))
            if counted:
                statuses += out
    lv = [s for s in statuses if s.source == "learned_velocity"]
    assert lv
    return lv[0]


def _first_sway_variance(seconds, **learned_velocity):
    """The sway innovation variance of :func:`_first_lv_status` (the covariance before it the
    same whatever the skid σ)."""
    return _first_lv_status(seconds, **learned_velocity).innovation_variance[1]


def _sway_variance(skid_sigma_s, yaw_rate_rad_s, rpm=600.0):
    """The sway variance at the first epoch under thrust ``rpm`` (0.75 m/s through the
    embedded table) while the gyro turns at ``yaw_rate_rad_s``."""
    return _first_sway_variance([(rpm, yaw_rate_rad_s, True)] * 2, skid_sigma_s=skid_sigma_s)


def test_an_unknown_skid_widens_the_sway_in_a_turn_only():
    # ArduSub's BlueROV2 (arcs drive, tests.sitl.bin_drive --pattern arcs) skids 0.14 m/s at
    # 8°/s and 0.75 m/s of model speed, against the uncalibrated sway σ of 0.03 m/s: 9.1 % of
    # the valid epochs outside their 99 % ellipse. The uncalibrated prior's σ_β = 2 s:
    # GIVEN a turn at 0.1 rad/s at 0.75 m/s, THEN the sway variance takes (min(σ_β w, 0.2) u)²
    u = 0.75
    for w, expected in ((0.05, (2.0 * 0.05 * u) ** 2), (0.1, (0.2 * u) ** 2), (0.5, (0.2 * u) ** 2)):
        extra = _sway_variance(2.0, w) - _sway_variance(0.0, w)
        assert extra == pytest.approx(expected, rel=0.1), w
    # on the straight nothing changes (the same floats)
    assert _sway_variance(2.0, 0.0) == _sway_variance(0.0, 0.0)


def _pivot_sway_variance(skid_sigma_s, yaw_rate_rad_s=0.5, rpm=600.0, **learned_velocity):
    """The sway variance at the first epoch after the thrust is cut from ``rpm`` (0.75 m/s) to 0
    while the gyro turns at ``yaw_rate_rad_s`` — a pivot right after a three-second lane, the slow
    lag settled at the command — on a vehicle of unknown response (``transient_time_s`` 2 s)."""
    return _first_sway_variance([(rpm, 0.0, False)] * 3 + [(0.0, yaw_rate_rad_s, True)],
                                skid_sigma_s=skid_sigma_s, transient_time_s=2.0, **learned_velocity)


def test_a_pivot_right_after_a_lane_skids_at_the_speed_the_hull_may_still_have():
    # The Heavy's first turn (tests.sitl.bin_drive --heavy): thrust cut, yaw at 0.5 rad/s, the
    # hull still coasting at 0.13 m/s 0.075 m/s off its x axis; the skid term took the command's
    # surge (0) and the sway row pulled the velocity, and through k_speed the position, 3.9 m back.
    # And the hull turns under the velocity it keeps (the mixed drive, tests.sitl.bin_drive
    # --pattern mixed: course held within 7° while the hull yawed 116°, sway 0.09 m/s at 0.15 m/s):
    # GIVEN the thrust cut from 0.75 m/s and a pivot at 0.5 rad/s, THEN the sway variance takes
    # the skid of the slow lag's speed, min(σ_β w, 1) = 1 of it: (0.75)², not 0 nor the thrusting
    # turn's bound (0.2 · 0.75)²
    extra = _pivot_sway_variance(2.0) - _pivot_sway_variance(0.0)
    assert extra == pytest.approx(0.75 ** 2, rel=0.2)
    bounded = _pivot_sway_variance(2.0, coast_skid_max_fraction=0.2) - _pivot_sway_variance(0.0)
    assert bounded == pytest.approx((0.2 * 0.75) ** 2, rel=0.2)
    # a slower pivot: σ_β w = 0.4 of the speed
    slow = _pivot_sway_variance(2.0, yaw_rate_rad_s=0.2) - _pivot_sway_variance(0.0, yaw_rate_rad_s=0.2)
    assert slow == pytest.approx((0.4 * 0.75) ** 2, rel=0.2)


def _coast(**learned_velocity):
    """The learned velocity's status at the first epoch after the thrust is cut from 600 RPM to
    0 after a three-second lane, and the slow lag's speed then: the lane's (the lag settled at
    the command; it moves towards the command held since the previous thrust sample), on a
    vehicle of unknown response (``transient_time_s`` 2 s)."""
    status = _first_lv_status([(600.0, 0.0, False)] * 3 + [(0.0, 0.0, True)], transient_time_s=2.0,
                              **learned_velocity)
    return status, float(RpmSpeedTable().speed(600.0))


def test_a_coast_is_taken_between_the_command_and_the_slow_lag_not_at_the_command():
    # ArduSub SITL's BlueROV2 after a 0.53 m/s lane: 0.09 / 0.05 / 0.03 m/s 1.5 / 3.5 / 5.5 s
    # after the thrust is cut (quadratic drag), the command 0, the 2 s lag 0.25 / 0.09 / 0.03.
    # Taken as "0 ± 3 gaps" every 1 Hz update of the coast had an innovation of one sign, and
    # k_speed's covariance with the position moved it back 1–2.3 m at every stop.
    # GIVEN the thrust cut after a lane, THEN the surge observed is midway between the command (0)
    # and the slow lag, and its variance takes one gap, not three
    on, slow = _coast()
    off, _ = _coast(coast_mean_fraction=0.0, coast_sigma_per_gap=3.0)
    assert slow > 0.3
    assert on.observation[0] == pytest.approx(0.5 * slow, rel=1e-6)
    assert off.observation[0] == 0.0
    # (k_speed ≈ 1 here: the variance is the gap's times k_speed², plus the prior's H P Hᵀ)
    assert slow ** 2 < on.innovation_variance[0] < 1.5 * slow ** 2
    assert off.innovation_variance[0] > 8.0 * slow ** 2
    # a spin-up is a thrust under way, not a coast: observed at the command as before
    up = _first_lv_status([(0.0, 0.0, False)] * 3 + [(600.0, 0.0, True)], transient_time_s=2.0)
    assert up.observation[0] == pytest.approx(float(RpmSpeedTable().speed(600.0)), rel=1e-9)


def _accel_bias_walk(**changes):
    """The horizontal and vertical accelerometer-bias random-walk variances (q of BA) after an
    alignment at rest with ATTITUDE at 50 Hz, with ``changes`` as ``section__key`` config overrides."""
    from dataclasses import replace

    from adaptnav.fusion.state import BA

    cfg = FilterConfig()
    for name, value in changes.items():
        section, key = name.split("__")
        cfg = replace(cfg, **{section: replace(getattr(cfg, section), **{key: value})})
    est = _est(cfg)
    _run(est, 0.0, 12.0, depth_of=lambda t: DEPTH_M)
    assert est.nav_state().t_s > 0.0
    q = est._qdiag[BA]
    return float(q[0]), float(q[1]), float(q[2])


def test_the_autopilots_tilt_wander_widens_the_horizontal_accelerometer_bias_walk_of_a_consumer_imu_only():
    # ArduSub's ATTITUDE roll/pitch wander 0.05-0.2 deg and hold the filter's tilt there: with a
    # consumer IMU (the autopilot's own MEMS) and ATTITUDE at the alignment the horizontal biases'
    # walk takes (g x reference_tilt_rw_rad_rthz)^2 beside the part's own; the vertical does not
    qx, qy, qz = _accel_bias_walk(imu__grade="consumer")
    assert qx == qy == pytest.approx(qz + (GRAVITY_M_S2 * 1e-4) ** 2, rel=1e-9)
    # off, and with an IMU of another grade (its own tilt is better than the autopilot's)
    for changes in ({"imu__grade": "consumer", "attitude__reference_tilt_rw_rad_rthz": 0.0},
                    {"imu__grade": "tactical"}):
        qx, qy, qz = _accel_bias_walk(**changes)
        assert qx == qy == qz, changes


def _descend(heave_sigma_per_vertical_speed, rate_m_s=0.35, seconds=30.0):
    """A vehicle aligned at rest at 5 m, then going down level at ``rate_m_s`` (an ROV on its
    vertical thrusters: ArduSub's BlueROV2 descends at 0.35 m/s), no surge thrust; returns the
    (vertical speed, valid, invalid reasons) of the nav state each second of the descent."""
    from dataclasses import replace

    from adaptnav.fusion.samples import RpmSample

    cfg = FilterConfig()
    est = _est(replace(cfg, learned_velocity=replace(
        cfg.learned_velocity, heave_sigma_per_vertical_speed=heave_sigma_per_vertical_speed)))
    _run(est, 0.0, 12.0, depth_of=lambda t: DEPTH_M)
    out = []
    for k in range(int(seconds)):
        t0 = 12.0 + k
        est.process(RpmSample(t0, 0.0))
        _run(est, t0, t0 + 1.0, depth_of=lambda t: DEPTH_M + rate_m_s * (t - 12.0))
        s = est.nav_state()
        out.append((float(s.vel_n_m_s[2]), s.valid, tuple(est.invalid_reasons())))
    return out


def test_a_vehicle_that_heaves_on_vertical_thrusters_is_not_held_to_zero_heave():
    # "heave 0 ± 0.05 m/s" (an AUV changes depth by pitching) fights the depth sensor: the
    # learned velocity is gated, put in doubt and reset (v_d to 0 mid-descent), the solution
    # invalid for a third of the descent (brisk drive: valid 72 % of the submerged time); the
    # uncalibrated prior's heave σ = |v_d| lets the depth sensor set the vertical speed
    held = _descend(0.0)
    free = _descend(1.0)
    assert sum(not v for _, v, _ in held[10:]) >= 5, held
    assert free[-1][0] == pytest.approx(0.35, abs=0.03), free[-1]
    assert all(v for _, v, _ in free[10:]), [r for r in free if not r[1]]


def test_a_vertical_run_is_its_largest_depth_change_and_nothing_while_level():
    from adaptnav.fusion.aiding.depth import LEVEL_TIME_S, vertical_run_step

    def grown(depths, dt=0.1):
        run, total = None, 0.0
        for k, d in enumerate(depths):
            run, g = vertical_run_step(run, k * dt, d)
            total += g
        return total

    rng = np.random.default_rng(3)
    level = [5.0 + 0.01 * rng.standard_normal() for _ in range(600)]  # depth hold (the filter's), 1 min
    dive = [5.0 + 6.0 * k / 171 for k in range(172)]                   # 6 m at 0.35 m/s
    assert grown(level) == 0.0
    assert grown(level + dive + [11.0] * 100) == pytest.approx(6.0**2, abs=0.1)
    # a dive and straight back up (no level spell between): one run, its largest change
    assert grown(level + dive + dive[::-1] + [5.0] * 100) == pytest.approx(6.0**2, abs=0.1)
    # two dives with a level spell between: two runs
    pause = [11.0] * int(2 * LEVEL_TIME_S / 0.1)
    assert grown(level + dive + pause + [d + 6.0 for d in dive] + [17.0] * 50) == pytest.approx(2 * 6.0**2, abs=0.2)
    # waves at the surface: bounded by their height, however long
    waves = [0.3 + 0.2 * math.sin(2 * math.pi * k * 0.1 / 6.0) for k in range(6000)]
    assert grown(waves) < 0.45**2


def _dive_sigma_h(dvl: bool, vertical_drift_sigma_per_m: float) -> tuple[float, float, float, float]:
    """A vehicle aligned at rest at 5 m holds it for a minute, dives 6 m level at 0.35 m/s and
    holds the new depth (no thrust, a DVL at 5 Hz reading the truth when ``dvl``, the depth
    with ArduSub SITL's noise); its published north and east variances (m²) before the dive
    and at the end."""
    from dataclasses import replace

    from adaptnav.fusion.samples import DvlSample, RpmSample

    cfg = FilterConfig()
    est = _est(replace(cfg, learned_velocity=replace(cfg.learned_velocity,
                                                     vertical_drift_sigma_per_m=vertical_drift_sigma_per_m)))
    _run(est, 0.0, 12.0, depth_of=lambda t: DEPTH_M)
    # a minute at a steady depth (the sensor's noise) first: no run
    steady = _noisy_depth(SITL_DEPTH_NOISE_M)
    for k in range(60):
        est.process(RpmSample(12.0 + k, 0.0))
        _run(est, 12.0 + k, 13.0 + k, depth_of=steady)
    before = est.nav_state().cov
    noise = np.random.default_rng(2)

    def depth_of(t):  # ArduSub SITL's pressure sensor noise
        return DEPTH_M + min(0.35 * (t - 72.0), 6.0) + SITL_DEPTH_NOISE_M * noise.standard_normal()

    for k in range(30):
        t0 = 72.0 + k
        est.process(RpmSample(t0, 0.0))
        for j in range(5):
            t1 = t0 + 0.2 * j
            if dvl:
                est.process(DvlSample(t1 + 0.003, (0.0, 0.0, 0.35 if t1 < 72.0 + 6.0 / 0.35 else 0.0)))
            _run(est, t1, t1 + 0.2, depth_of=depth_of)
    cov = est.nav_state().cov
    return float(before[0, 0]), float(before[1, 1]), float(cov[0, 0]), float(cov[1, 1])


def test_a_dive_no_dvl_measured_widens_the_horizontal_covariance_by_its_drift():
    # ArduSub's simulated BlueROV2 Heavy drifts 0.36 m per metre dived, its IMU followed about
    # 70 %: the rest was outside the 99 % ellipse of an unwidened covariance
    widened, plain = _dive_sigma_h(False, 0.1), _dive_sigma_h(False, 0.0)
    # a minute at a steady depth: the filter's depth (the sensor's 0.115 m smoothed) wanders
    # out of the level band now and then, a few centimetres at most
    for axis in (0, 1):
        assert math.sqrt(widened[axis] - plain[axis]) < 0.1 * 0.3, (widened, plain)
    # the run's depth change (the filter's depth: within a few cm)
    for axis in (2, 3):
        assert math.sqrt(widened[axis] - plain[axis]) == pytest.approx(0.1 * 6.0, abs=0.01), (widened, plain)
    # a DVL over the seabed measured the drift: nothing added
    with_dvl, with_dvl_plain = _dive_sigma_h(True, 0.1), _dive_sigma_h(True, 0.0)
    for axis in (0, 1):
        added_before = with_dvl[axis] - with_dvl_plain[axis]
        assert with_dvl[axis + 2] - with_dvl_plain[axis + 2] == pytest.approx(added_before, abs=1e-9)


def _surface_sigma_h(correlated_fraction: float, seconds: float = 60.0, bias_n_m: float = 2.0,
                     sigma_fix_m: float = 2.0) -> tuple[float, float]:
    """A vehicle at rest at the surface, a receiver at 5 Hz reporting σ ``sigma_fix_m`` whose
    error is a bias (``bias_n_m`` north, what a receiver keeps for minutes) plus 0.3 m of white
    noise: (the filter's horizontal σ, its north error) after ``seconds``."""
    from adaptnav.fusion.config import GnssConfig
    from adaptnav.fusion.samples import GnssSample

    est = _est(FilterConfig(gnss=GnssConfig(correlated_fraction=correlated_fraction)))
    rng = np.random.default_rng(3)
    for k in range(int(round(seconds * IMU_HZ))):
        t = k / IMU_HZ
        est.process(AttitudeSample(t + 0.001, 0.0, 0.0, 0.0))
        if k % 5 == 0:
            est.process(DepthSample(t + 0.002, _pressure(0.2)))
        if k % 10 == 0:
            n, e = bias_n_m + 0.3 * rng.standard_normal(), 0.3 * rng.standard_normal()
            lat, lon, _ = ORIGIN.to_geodetic(np.array([n, e, 0.0]))
            est.process(GnssSample(t + 0.003, float(lat), float(lon), sigma_fix_m))
        est.process(ImuBatch(np.array([t + 1.0 / IMU_HZ]), np.array([[0.0, 0.0, -GRAVITY_M_S2]]),
                             np.zeros((1, 3))))
    s = est.nav_state()
    P = np.asarray(s.cov)[:2, :2]
    return float(math.sqrt(np.linalg.eigvalsh(P)[-1])), float(s.pos_n_m[0])


def test_a_minute_of_surface_fixes_is_not_three_hundred_independent_ones():
    # a receiver's error is correlated over minutes: a receiver reporting 2 m whose error is a
    # 2 m bias, fused at 5 Hz as independent fixes, leaves the filter at σ 0.5 m (the motion's
    # process noise holds it there) with the position 2 m off — outside its 99 % ellipse, where
    # every dive would start valid; half the fix's σ kept (stop 30's default) is inside it, the
    # default keeps the fix's σ (what a minute of a receiver's fixes leaves)
    from adaptnav.fusion.config import GnssConfig

    sigma_white, err_white = _surface_sigma_h(0.0)
    sigma_half, err_half = _surface_sigma_h(0.5)
    sigma, err = _surface_sigma_h(GnssConfig().correlated_fraction)
    for e in (err_white, err_half, err):
        assert abs(e - 2.0) < 0.3  # all where the receiver says
    assert abs(err_white) > 3.03 * sigma_white  # outside the 99 % ellipse (2-D: 3.03 σ)
    assert 0.95 <= sigma_half <= 1.3 and abs(err_half) < 3.03 * sigma_half  # inside it
    assert 1.9 <= sigma <= 2.6 and abs(err) < 3.03 * sigma
