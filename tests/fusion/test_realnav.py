"""What real vehicles need from the filter: a trustworthy heading seed, resets out of
rejection, IMU grades, earth rotation, honest validity, rest detection, moving start."""
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from adaptnav.fusion import imu_grades
from adaptnav.fusion import strapdown as sd
from adaptnav.fusion.config import (FilterConfig, ImuConfig, IntegrityConfig, StationaryConfig)
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, euler_to_quat, quat_to_dcm
from adaptnav.fusion.integrity import NisMonitor
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import (AttitudeSample, DepthSample, DvlSample, HeadingSample, ImuBatch, RpmSample)

from .mission import ATM_PA, ORIGIN, RHO

SMALL_BIN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mavlink" / "ardusub-4.1.0-small.BIN"


def _est(cfg=None, origin=ORIGIN):
    return Estimator(cfg or FilterConfig(), MotionParams(), RpmSpeedTable(), origin)


def _imu(t0, n, rate=50.0, f=(0.0, 0.0, -GRAVITY_M_S2), w=(0.0, 0.0, 0.0), rng=None, sigma=(0.0, 0.0)):
    t = t0 + np.arange(1, n + 1) / rate
    fb = np.tile(np.asarray(f, float), (n, 1))
    wb = np.tile(np.asarray(w, float), (n, 1))
    if rng is not None:
        fb = fb + sigma[0] * rng.standard_normal((n, 3))
        wb = wb + sigma[1] * rng.standard_normal((n, 3))
    return ImuBatch(t, fb, wb)


def _interleave(est, t_end, rate=50.0, att=None, imu_kw=None, extra=None, t0=0.0):
    """Feed IMU at ``rate`` with an ATTITUDE (yaw from ``att(t)``) before each IMU sample."""
    out = []
    k = 0
    t = t0
    while t < t_end - 1e-9:
        if att is not None:
            out += est.process(AttitudeSample(t + 0.5 / rate, 0.0, 0.0, att(t)))
        if extra is not None:
            for s in extra(t, k):
                out += est.process(s)
        out += est.process(_imu(t, 1, rate, **(imu_kw or {})))
        t += 1.0 / rate
        k += 1
    return out


def test_heading_is_seeded_only_once_the_autopilots_yaw_has_settled():
    # GIVEN ArduSub's start-up: ATTITUDE before the first IMU sample; yaw 3.0 (DCM), then 0
    # while EKF3 starts, then the aligned 1.2 rad
    est = _est()

    def yaw(t):
        return 3.0 if t < 1.0 else (0.0 if t < 2.5 else 1.2)

    _interleave(est, 8.0, att=yaw)
    # THEN the filter is an INS (not stuck in AHRS mode) with the settled yaw
    s = est.nav_state()
    assert est.initialized and s.valid
    assert est.nav_state().euler_rad()[2] == pytest.approx(1.2, abs=0.01)
    assert est.resets == {}


def test_attitude_rejected_for_5_s_resets_the_attitude_counted_and_invalid_until_converged():
    cfg = FilterConfig()
    est = _est(cfg)
    _interleave(est, 5.0, att=lambda t: 0.0)
    r0 = est.nav_state().reset_counter
    assert est.nav_state().euler_rad()[2] == pytest.approx(0.0, abs=0.01)
    # WHEN the autopilot's yaw jumps by 1 rad (its EKF re-aligned) and stays there
    statuses = _interleave(est, 11.5, att=lambda t: 1.0, t0=5.0)
    # THEN it is gated for attitude_after_s, then the attitude is reset to it (counted)
    gated = [a for a in statuses if a.source == "attitude" and a.reason == "gate"]
    assert gated and gated[-1].t_s - gated[0].t_s == pytest.approx(cfg.reset.attitude_after_s, abs=0.1)
    assert est.resets == {"attitude:attitude": 1}
    s = est.nav_state()
    assert s.euler_rad()[2] == pytest.approx(1.0, abs=0.01) and s.reset_counter == r0 + 1
    # AND the solution is invalid while converging, valid again after integrity.after_reset_s
    assert not s.valid and "converging" in est.invalid_reasons()
    _interleave(est, 11.5 + cfg.integrity.after_reset_s + 0.5, att=lambda t: 1.0, t0=11.5)
    assert est.nav_state().valid


def test_learned_velocity_rejected_for_10_s_resets_the_velocity():
    est = _est()
    rpm = lambda t, k: [RpmSample(t, 0.0)] if k % 10 == 0 else []  # noqa: E731 (thrusters idle)
    _interleave(est, 5.0, att=lambda t: 0.0, extra=rpm)
    # WHEN the IMU says the vehicle shot off at 10 m/s (a shock) while the thrusters are idle
    _interleave(est, 5.5, att=lambda t: 0.0, extra=rpm, imu_kw={"f": (20.0, 0.0, -GRAVITY_M_S2)}, t0=5.0)
    assert est.nav_state().vel_n_m_s[0] > 5.0
    statuses = _interleave(est, 20.0, att=lambda t: 0.0, extra=rpm, t0=5.5)
    # THEN the learned velocity is gated, then after velocity_after_s the velocity is reset
    assert any(a.source == "learned_velocity" and a.reason == "gate" for a in statuses)
    assert est.resets.get("velocity:learned_velocity", 0) >= 1
    assert np.linalg.norm(est.nav_state().vel_n_m_s) < 0.2


def test_auto_grade_from_quantisation_and_measured_noise():
    rng = np.random.default_rng(3)
    n, dt = 200, 0.02
    # RAW_IMU: integers of 1 mg and 1 mrad/s ⇒ consumer, with quantisation noise
    f = np.round((np.array([0, 0, -GRAVITY_M_S2]) + 0.02 * rng.standard_normal((n, 3))) / imu_grades.MG) * imu_grades.MG
    w = np.round(2e-3 * rng.standard_normal((n, 3)) / 1e-3) * 1e-3
    r = imu_grades.resolve(ImuConfig(), f, w, dt)
    assert r.grade == "consumer" and r.quantized and not r.earth_rotation
    assert r.figures.gyro_noise_rad_s_rthz >= imu_grades.PROFILES["consumer"].gyro_noise_rad_s_rthz
    # float samples with a tactical gyro's noise ⇒ tactical; a FOG's ⇒ navigation + earth model
    dt = 0.01
    f = np.array([0, 0, -GRAVITY_M_S2]) + 1e-3 * rng.standard_normal((n, 3))
    tac = imu_grades.resolve(ImuConfig(), f, 4e-5 / math.sqrt(dt) * rng.standard_normal((n, 3)), dt)
    nav = imu_grades.resolve(ImuConfig(), f, 7e-7 / math.sqrt(dt) * rng.standard_normal((n, 3)), dt)
    assert (tac.grade, tac.earth_rotation) == ("tactical", False)
    assert (nav.grade, nav.earth_rotation) == ("navigation", True)
    # a FOG on a vehicle whose turn rate steps in the window (a rudder kick; the simulator's
    # 1 s motion steps: 0.25–4 mrad/s) is still a FOG: the std of the second differences
    # called it tactical
    w_nav = 7e-7 / math.sqrt(dt) * rng.standard_normal((n, 3))
    k = np.arange(n)
    w_nav[:, 2] += 2e-3 * (k >= 60) - 1.5e-3 * (k >= 140)
    assert imu_grades.white_sigma(w_nav) * math.sqrt(dt) > imu_grades.NAVIGATION_GYRO_DENSITY_MAX
    stepped = imu_grades.resolve(ImuConfig(), f, w_nav, dt)
    assert (stepped.grade, stepped.earth_rotation) == ("navigation", True), stepped.why
    # AND every figure can be overridden, the grade can be forced
    forced = imu_grades.resolve(ImuConfig(grade="navigation", gyro_bias_sigma_rad_s=1e-6, earth_rotation="off"), f, w, dt)
    assert forced.figures.gyro_bias_sigma_rad_s == 1e-6 and not forced.earth_rotation
    # quantisation adds q²/12 per sample: the density grows accordingly
    q = imu_grades.resolve(ImuConfig(grade="tactical", quantization="raw_imu"), f, w, 0.02)
    assert q.figures.gyro_noise_rad_s_rthz == pytest.approx(
        math.hypot(imu_grades.PROFILES["tactical"].gyro_noise_rad_s_rthz, 1e-3 * math.sqrt(0.02 / 12)))


def test_auto_grade_trusts_the_source_over_an_implausibly_quiet_stream():
    """ArduSub's simulator streams the autopilot's HIGHRES_IMU nearly noise-free (5.9e-6
    rad/s/√Hz at rest, a tactical gyro's figure): the autopilot's own IMU is a MEMS part
    whatever its stream shows; a stream quieter than any physical gyro promotes nothing; a
    dedicated IMU with a FOG's noise is still navigation grade."""
    rng = np.random.default_rng(5)
    n, dt = 200, 0.02
    f = np.array([0, 0, -GRAVITY_M_S2]) + 1e-4 * rng.standard_normal((n, 3))
    sitl_w = 5.9e-6 / math.sqrt(dt) * rng.standard_normal((n, 3))
    assert imu_grades.resolve(ImuConfig(), f, sitl_w, dt).grade == "tactical"  # the noise alone
    ap = imu_grades.resolve(ImuConfig(), f, sitl_w, dt, source="autopilot")
    assert (ap.grade, ap.earth_rotation, ap.source) == ("consumer", False, "autopilot")
    assert "autopilot" in ap.why and "below any MEMS" in ap.why
    # the consumer figures, never below the datasheet class's (the measured noise only raises them)
    assert ap.figures.gyro_noise_rad_s_rthz == imu_grades.PROFILES["consumer"].gyro_noise_rad_s_rthz
    # a noise-free stream of unknown origin (a simulator's) is not taken for a FOG
    for quiet in (np.zeros((n, 3)), 1e-8 * rng.standard_normal((n, 3))):
        r = imu_grades.resolve(ImuConfig(), f, quiet, dt)
        assert r.grade == "consumer" and "below any physical gyro" in r.why, r
    # a FOG's noise from a dedicated IMU (or of unknown origin) is navigation grade
    fog_w = 7e-7 / math.sqrt(0.01) * rng.standard_normal((n, 3))
    for source in ("dedicated", ""):
        assert imu_grades.resolve(ImuConfig(), f, fog_w, 0.01, source=source).grade == "navigation"
    # a configured grade is the grade, whatever the source
    assert imu_grades.resolve(ImuConfig(grade="navigation"), f, sitl_w, dt, source="autopilot").grade == "navigation"


def _static_navigation_grade(est, lat_rad, duration_s, rate=100.0):
    """A perfect IMU at rest on the rotating earth: it senses the earth rate and normal gravity."""
    w_n = np.array([sd.EARTH_RATE_RAD_S * math.cos(lat_rad), 0.0, -sd.EARTH_RATE_RAD_S * math.sin(lat_rad)])
    R_nb = quat_to_dcm(euler_to_quat(0.0, 0.0, 0.3))
    f_b = R_nb.T @ np.array([0.0, 0.0, -sd.normal_gravity_m_s2(lat_rad)])
    w_b = R_nb.T @ w_n
    est.process(HeadingSample(0.0, 0.3))
    n = int(duration_s * rate)
    for k0 in range(0, n, 1000):
        m = min(1000, n - k0)
        est.process(_imu(k0 / rate, m, rate, f=f_b, w=w_b))
    return est.nav_state()


def test_earth_rate_coriolis_and_normal_gravity_matter_for_a_navigation_grade_imu():
    lat = math.radians(60.0)
    origin = GeoOrigin(lat, 0.1, 0.0)
    cfg = replace(FilterConfig(), imu=ImuConfig(grade="navigation"))
    on = _static_navigation_grade(_est(cfg, origin), lat, 600.0)
    off = _static_navigation_grade(_est(replace(cfg, imu=ImuConfig(grade="navigation", earth_rotation="off")),
                                        origin), lat, 600.0)
    # THEN with the earth model a FOG at rest stays put for 10 min; without, the sensed
    # earth rate (15 °/h) turns the attitude and gravity leaks into the velocity
    assert np.linalg.norm(on.pos_n_m[:2]) < 1.0 and np.linalg.norm(on.vel_n_m_s) < 0.01
    assert np.linalg.norm(off.pos_n_m[:2]) > 100.0


def test_nis_monitor_flags_an_aid_whose_innovations_exceed_its_covariance():
    rng = np.random.default_rng(1)
    mon = NisMonitor(20, 0.9999)
    for v in rng.chisquare(2, 500):
        mon.add("usbl", float(v), 2)
        assert not mon.failing()
    for v in 9.0 * rng.chisquare(2, 20):  # innovations 3σ where 1σ is claimed
        mon.add("usbl", float(v), 2)
    assert mon.failing() == ["usbl"]


def test_nis_monitor_verdicts_are_those_of_the_last_window_whatever_the_order_of_calls():
    """failing() is kept up to date by add() and clear() (it is asked with every published
    state): against the sums of the last window recomputed from scratch."""
    rng = np.random.default_rng(3)
    window = 5
    mon = NisMonitor(window, 0.99)
    seen: dict[str, list] = {}
    for _ in range(3000):
        r = rng.uniform()
        source = str(rng.choice(["dvl", "depth", "usbl"]))
        if r < 0.01:
            mon.clear(source)
            seen.pop(source, None)
        elif r < 0.012:
            mon.clear()
            seen.clear()
        else:
            dof = {"dvl": 3, "depth": 1, "usbl": 2}[source]
            nis = float(rng.chisquare(dof) * rng.choice([1.0, 4.0]))
            mon.add(source, nis, dof)
            seen.setdefault(source, []).append(min(nis, mon.cap(dof)))
        expected = sorted(s for s, v in seen.items()
                          if len(v) >= window and sum(v[-window:]) > mon.bound({"dvl": 3, "depth": 1, "usbl": 2}[s]))
        assert mon.failing() == expected


def test_solution_invalid_when_an_aid_says_the_covariance_lies():
    # GIVEN a depth sensor that wanders by 0.5 m while the filter is told σ = 0.05 m
    cfg = replace(FilterConfig(), integrity=IntegrityConfig(nis_window=10))
    est = _est(cfg)
    rng = np.random.default_rng(2)

    def depth(t, k):
        if k % 5:
            return []
        d = 10.0 + 0.5 * math.sin(t)
        return [DepthSample(t, ATM_PA + RHO * GRAVITY_M_S2 * d + rng.normal(0, 50.0))]

    _interleave(est, 30.0, att=lambda t: 0.0, extra=depth)
    state = est.nav_state()
    assert not state.valid and "nis:depth" in est.invalid_reasons()
    # the published state says why (bus payload, lifecycle log)
    assert "nis:depth" in state.invalid_reasons and "nis:depth" in state.to_dict()["invalid_reasons"]


def test_zero_velocity_updates_on_deck_hold_the_position():
    # GIVEN a consumer IMU at rest on deck (depth 0), thrusters idle
    rng = np.random.default_rng(4)
    est = _est()

    def idle(t, k):
        return [RpmSample(t, 0.0), DepthSample(t, ATM_PA)] if k % 10 == 0 else []

    _interleave(est, 120.0, att=lambda t: 0.0, extra=idle, imu_kw={"rng": rng, "sigma": (0.02, 0.002)})
    s = est.nav_state()
    # THEN zero-velocity updates ran and the track stayed within centimetres
    assert est.zero_velocity_updates > 60
    assert np.linalg.norm(s.pos_n_m[:2]) < 0.1 and s.sigma(slice(3, 6)).max() < 0.02
    # AND not in the water: an idle vehicle drifts with the current there
    est2 = _est(replace(FilterConfig(), stationary=StationaryConfig(max_depth_m=-1.0)))
    _interleave(est2, 10.0, att=lambda t: 0.0, extra=idle, imu_kw={"rng": rng, "sigma": (0.02, 0.002)})
    assert est2.zero_velocity_updates == 0


def test_velocity_is_seeded_from_the_dvl_on_a_moving_start():
    # GIVEN a vehicle cruising at 2 m/s (no acceleration) heading 0.5 rad, DVL before alignment
    est = _est()

    def dvl(t, k):
        return [DvlSample(t, (2.0, 0.0, 0.0))] if k % 5 == 0 else []

    _interleave(est, 3.0, att=lambda t: 0.5, extra=dvl)
    v = est.nav_state().vel_n_m_s
    np.testing.assert_allclose(v[:2], [2.0 * math.cos(0.5), 2.0 * math.sin(0.5)], atol=0.05)


@pytest.mark.realdata
def test_real_vehicle_at_rest_stays_within_half_a_metre_and_is_never_valid_beyond():
    if not SMALL_BIN.is_file():
        pytest.skip(f"real data absent: {SMALL_BIN}")
    from adaptnav.service.transport.tlog_source import TlogSource

    est = _est()
    states = []
    for sample in TlogSource(SMALL_BIN):
        est.process(sample)
        if est.initialized and sample.KIND == "attitude":
            states.append(est.nav_state())
    assert len(states) > 150 and est.imu_model.grade == "consumer"
    excursion = np.array([np.hypot(*s.pos_n_m[:2]) for s in states])
    valid = np.array([s.valid for s in states])
    assert excursion.max() < 0.5
    assert not np.any(valid & (excursion >= 0.5))


def test_each_position_aid_at_its_own_point_and_the_solution_at_the_output_point():
    from adaptnav.fusion.config import UsblConfig
    from adaptnav.fusion.samples import UsblSample

    # GIVEN the IMU 0.5 m aft of the vehicle reference, a USBL transponder 1 m above it and
    # 2 m forward, the output point (a sonar) 1.5 m forward; vehicle at rest heading east
    cfg = replace(FilterConfig(), imu=ImuConfig(lever_arm_b_m=(-0.5, 0.0, 0.0)),
                  usbl=UsblConfig(lever_arm_b_m=(2.0, 0.0, -1.0)), output_point_b_m=(1.5, 0.0, 0.0))
    est = _est(cfg)
    yaw = math.pi / 2
    imu_ne = np.array([10.0, 20.0])   # where the IMU truly is
    tr_ne = imu_ne + np.array([0.0, 2.5])  # the transponder: 2.5 m ahead of the IMU, i.e. east

    def fixes(t, k):
        if k % 25:
            return []
        lat, lon, _ = ORIGIN.to_geodetic(np.array([tr_ne[0], tr_ne[1], 0.0]))
        return [UsblSample(t, float(lat), float(lon), math.nan, 0.3)]

    _interleave(est, 60.0, att=lambda t: yaw, extra=fixes)
    s = est.nav_state()
    # THEN the reported position is the output point's: 2 m ahead of the IMU (east)
    np.testing.assert_allclose(s.pos_n_m[:2], imu_ne + np.array([0.0, 2.0]), atol=0.1)
    assert est.resets == {}


def test_lever_arm_jacobian_matches_finite_differences():
    from adaptnav.fusion.aiding.common import make
    from adaptnav.fusion.eskf import _at_lever
    from adaptnav.fusion.state import N_ERR, initial_nominal, inject

    x = initial_nominal((1.0, 2.0, 3.0), (0.5, 0.0, 0.0), euler_to_quat(0.1, -0.2, 1.0))
    arm = np.array([1.0, -0.5, 0.3])

    def h(xx):
        H = np.zeros((3, N_ERR))
        H[:, :3] = np.eye(3)
        return _at_lever(make(np.zeros(3), H, np.eye(3), xx[:3]), xx, arm)

    m = h(x)
    num = np.zeros((3, N_ERR))
    for i in range(N_ERR):
        dx = np.zeros(N_ERR)
        dx[i] = 1e-6
        num[:, i] = (h(inject(x, dx)).h - h(inject(x, -dx)).h) / 2e-6
    np.testing.assert_allclose(m.H, num, atol=1e-6)
