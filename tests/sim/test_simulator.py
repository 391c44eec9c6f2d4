"""Simulator: exact IMU, motion-model consistency, environment change, determinism, sensors."""
import math

import numpy as np
import pytest

from adaptnav.fusion.frames import GRAVITY_M_S2, quat_from_rotvec, quat_mul, quat_to_dcm
from adaptnav.fusion.motion_model import invert_step, velocity_variances
from adaptnav.fusion.samples import ImuBatch, replay_order_key
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate

DEG = math.pi / 180


@pytest.fixture(scope="module")
def perfect():
    """5 min, environment change at 150 s, perfect IMU, DVL on with an outage."""
    return simulate(load_scenario("short", ['imu.grade="perfect"', "dvl.enabled=true",
                                            "dvl.outages_s=[[100.0, 160.0]]"]))


@pytest.fixture(scope="module")
def tactical():
    # the DVL without its systematic errors (those have their own test): white beam noise only
    return simulate(load_scenario("short", ["dvl.enabled=true", "dvl.outages_s=[[100.0, 160.0]]",
                                            "dvl.scale_factor_error=0.0", "dvl.misalignment_rpy_deg=[0, 0, 0]",
                                            "dvl.beam_bias_m_s=[0, 0, 0, 0]", "dvl.outlier_prob=0.0"]))


def _textbook_strapdown(result, i0: int, n: int):
    """``(q, v, p)`` after ``n`` IMU samples from instant ``i0``, integrated by a textbook
    strapdown from the truth at ``i0``."""
    d, imu = result.dense, result.imu
    dt = imu.t_s[1] - imu.t_s[0]
    q, v, p = d.q_nb[i0].copy(), d.vel_n_m_s[i0].copy(), d.pos_n_m[i0].copy()
    g = np.array([0.0, 0.0, GRAVITY_M_S2])
    for i in range(i0, i0 + n):
        dth = imu.omega_b_rad_s[i] * dt
        q_mid = quat_mul(q, quat_from_rotvec(0.5 * dth))
        q = quat_mul(q, quat_from_rotvec(dth))
        v_new = v + quat_to_dcm(q_mid) @ imu.specific_force_b_m_s2[i] * dt + g * dt
        p = p + 0.5 * (v + v_new) * dt
        v = v_new
    return q, v, p


def test_perfect_imu_reproduces_the_truth(perfect):
    # GIVEN a perfect IMU, WHEN a textbook strapdown integrates it from the true initial
    # state for 60 s, THEN it lands on the truth to rounding error.
    d = perfect.dense
    n = 6000
    q, v, p = _textbook_strapdown(perfect, 0, n)
    assert np.abs(p - d.pos_n_m[n]).max() < 1e-6
    assert np.abs(v - d.vel_n_m_s[n]).max() < 1e-9
    assert abs(abs(np.dot(q, d.q_nb[n])) - 1.0) < 1e-12
    # and the truth moved: the check is not trivially satisfied
    assert np.linalg.norm(d.pos_n_m[n] - d.pos_n_m[0]) > 50.0


def _inverted_steps(result):
    """(V̂, Ŵ, Ŝ) per step from the truth poses (ground position minus the current drift)."""
    s, d = result.steps, result.dense
    m = int(round(result.scenario.motion.step_s * result.scenario.imu.rate_hz))
    idx = np.arange(len(s.t_s)) * m
    cur = np.array(result.scenario.current.vel_n_m_s())
    water = d.pos_n_m[idx, :2] - cur[None, :] * d.t_s[idx, None]
    pose = np.column_stack([water, d.euler_rad[idx, 2]])
    V, W, S, _ = invert_step(pose[:-1], pose[1:], result.scenario.motion.step_s)
    return s.t_s[:-1], V, W, S


def test_truth_per_step_follows_the_motion_model_moments(perfect):
    sc = perfect.scenario
    t, V, W, S = _inverted_steps(perfect)
    v, w = perfect.steps.v_m_s, perfect.steps.w_rad_s
    for params, sel in ((sc.params_before(), t < 150.0), (sc.params_after(), t >= 150.0)):
        var_V, var_W, var_S = velocity_variances(params, v[sel], w[sel])
        zs = [(V[sel] - params.k_v * v[sel]) / np.sqrt(var_V),
              (W[sel] - w[sel] - params.b_w) / np.sqrt(var_W),
              S[sel] / np.sqrt(var_S)]
        n = sel.sum()
        for z in zs:
            assert abs(z.mean()) < 4.0 / math.sqrt(n)
            # chi-square(n)/n is within ±4 sd (sd = sqrt(2/n)) of 1
            assert abs(np.mean(z * z) - 1.0) < 4.0 * math.sqrt(2.0 / n)


def test_environment_change_switches_k_v_at_the_right_time(perfect):
    t, V, _, _ = _inverted_steps(perfect)
    v = perfect.steps.v_m_s
    before, after = (V / v)[t < 150.0], (V / v)[t >= 150.0]
    assert abs(before.mean() - 1.0) < 0.02
    assert abs(after.mean() - 0.9) < 0.04
    truth = perfect.samples["truth"]
    k = np.array([s.k_v for s in truth])
    tt = np.array([s.t_s for s in truth])
    assert np.all(k[tt < 150.0] == 1.0) and np.all(k[tt >= 150.0] == 0.9)


def test_same_seed_same_output_and_streams_are_independent():
    a = simulate(load_scenario("short", ["duration_s=30"]))
    b = simulate(load_scenario("short", ["duration_s=30"]))
    assert np.array_equal(a.imu.specific_force_b_m_s2, b.imu.specific_force_b_m_s2)
    assert np.array_equal(a.imu.omega_b_rad_s, b.imu.omega_b_rad_s)
    assert a.samples == b.samples
    c = simulate(load_scenario("short", ["duration_s=30", "seed=8"]))
    assert not np.array_equal(a.imu.omega_b_rad_s, c.imu.omega_b_rad_s)
    # enabling a sensor does not change the others' noise
    d = simulate(load_scenario("short", ["duration_s=30", "dvl.enabled=true", "beacons.enabled=true"]))
    assert "dvl" in d.samples and "range" in d.samples
    assert d.samples["heading"] == a.samples["heading"] and d.samples["depth"] == a.samples["depth"]
    assert np.array_equal(d.imu.omega_b_rad_s, a.imu.omega_b_rad_s)


@pytest.mark.parametrize("grade, gyro_white, acc_white", [
    # datasheet-class densities (STIM300 / HG1700 class; BMI088 class), see sim/imu.py
    ("tactical", 0.15 * DEG / 60.0, 0.06 / 60.0),
    ("consumer", 0.014 * DEG, 175e-6 * GRAVITY_M_S2),
])
def test_imu_white_noise_matches_grade(perfect, grade, gyro_white, acc_white):
    noisy = simulate(load_scenario("short", [f'imu.grade="{grade}"', "duration_s=60"]))
    n = len(noisy.imu)
    dt = noisy.imu.t_s[1] - noisy.imu.t_s[0]
    err_w = noisy.imu.omega_b_rad_s - perfect.imu.omega_b_rad_s[:n]
    err_f = noisy.imu.specific_force_b_m_s2 - perfect.imu.specific_force_b_m_s2[:n]
    # first differences cancel the slow biases: std = sqrt(2) σ_white
    for err, density in ((err_w, gyro_white), (err_f, acc_white)):
        ratio = np.diff(err, axis=0).std(axis=0) / (math.sqrt(2.0) * density / math.sqrt(dt))
        assert np.all(np.abs(ratio - 1.0) < 0.03), ratio


def test_aiding_sensors(tactical):
    sc, d = tactical.scenario, tactical.dense
    usbl = tactical.samples["usbl"]
    assert [u.t_s for u in usbl] == [30.0 * k for k in range(1, 11)]
    gnss = tactical.samples["gnss"]
    assert [g.t_s for g in gnss] == [0.0]  # at the surface at t = 0
    dt = 1.0 / sc.imu.rate_hz
    idx = lambda t: int(round(t / dt))  # noqa: E731
    # heading error ~ N(0, 0.5°)
    head = tactical.samples["heading"]
    err = np.array([(h.yaw_rad - d.euler_rad[idx(h.t_s), 2] + math.pi) % (2 * math.pi) - math.pi for h in head])
    assert abs(err.std() / (sc.heading.sigma_deg * DEG) - 1.0) < 0.06 and abs(err.mean()) < 0.001
    # depth from pressure with the density in force
    dep = tactical.samples["depth"]
    depth = np.array([(s.pressure_pa - 101325.0) / (1025.0 * GRAVITY_M_S2) for s in dep])
    derr = depth - np.array([d.pos_n_m[idx(s.t_s), 2] for s in dep])
    assert abs(derr.std() / sc.depth.sigma_m - 1.0) < 0.06 and abs(derr.mean()) < 0.005
    # DVL: body velocity + lever-arm term, invalid during the outage
    dvl = tactical.samples["dvl"]
    assert not any(s.valid for s in dvl if 100.0 <= s.t_s < 160.0)
    ok = [s for s in dvl if s.valid and 0.0 < s.t_s < sc.duration_s]
    assert len(ok) > 0.9 * (len(dvl) - 300)
    lever = np.array(sc.dvl.lever_arm_b_m)
    verr = []
    for s in ok:
        i = idx(s.t_s)
        vb = quat_to_dcm(d.q_nb[i]).T @ d.vel_n_m_s[i]
        # body rate from the truth attitudes around t (central difference)
        dq = quat_mul(d.q_nb[i - 1] * np.array([1, -1, -1, -1]), d.q_nb[i + 1])
        omega = 2.0 * dq[1:] / (2.0 * dt)
        verr.append(np.array(s.vel_d_m_s) - vb - np.cross(omega, lever))
    verr = np.array(verr)
    assert np.all(np.abs(verr.mean(axis=0)) < 0.0015)
    # beam noise through the 4-beam least squares: σ_b/(√2 sin 30°) across, σ_b/(2 cos 30°) down
    sigma_b, beam = sc.dvl.beam_sigma_m_s, math.radians(sc.dvl.beam_angle_deg)
    expected = np.array([1, 1, 0]) * sigma_b / (math.sqrt(2) * math.sin(beam)) \
        + np.array([0, 0, 1]) * sigma_b / (2 * math.cos(beam))
    assert np.all(np.abs(verr.std(axis=0) / expected - 1.0) < 0.08)


def test_usbl_lost_after_and_gnss_only_at_surface():
    r = simulate(load_scenario("short", ["duration_s=200", "usbl.lost_after_s=90.0",
                                         "gnss.fix_times_s=[0.0, 150.0]"]))
    assert [u.t_s for u in r.samples["usbl"]] == [30.0, 60.0, 90.0]
    assert [g.t_s for g in r.samples["gnss"]] == [0.0]  # at 150 s it is 10 m down


def test_iteration_is_in_replay_order(tactical):
    items = list(tactical.iter_samples())
    keys = [replay_order_key(s, i) for i, s in enumerate(items)]
    assert [k[:2] for k in keys] == sorted(k[:2] for k in keys)
    assert sum(1 for s in items if s.KIND == "imu") == len(tactical.imu)
    flat = []
    for b in tactical.iter_blocks():
        flat.extend(b.samples() if isinstance(b, ImuBatch) else [b])
    assert flat == items
    assert len(items) == sum(tactical.counts().values())


def test_sonar_pings_when_renderer_present():
    pytest.importorskip("adaptnav.sim.sidescan")
    pytest.importorskip("adaptnav.sim.seabed")
    r = simulate(load_scenario("demo", ["duration_s=20", "sonar.ping_rate_hz=2.0", "sonar.range_m=20.0",
                                        "sonar.samples_per_side=128", "sonar.seabed_res_m=0.25"]))
    pings = r.samples["sonar"]
    assert [p.t_s for p in pings] == [k * 0.5 for k in range(41)]
    assert all(p.n_samples == 128 and p.slant_range_m == 20.0 for p in pings)
    assert r.seabed is not None and len(r.seabed.seabed.objects_n_m) > 0


def test_start_delay_keeps_the_propeller_stopped_at_the_surface():
    r = simulate(load_scenario("short", ["duration_s=30", "trajectory.start_delay_s=10"]))
    rpm = {s.t_s: s.rpm for s in r.samples["rpm"]}
    assert all(v == 0.0 for t, v in rpm.items() if t < 10.0) and rpm[10.0] > 0.0
    gnss = simulate(load_scenario("short", ["duration_s=30", "trajectory.start_delay_s=10",
                                            "gnss.rate_hz=1.0"])).samples["gnss"]
    assert [g.t_s for g in gnss][:11] == [float(k) for k in range(11)]  # at the surface while stopped
    assert gnss[-1].t_s < 20.0  # then it dives (below 0.5 m some 7 s into the descent)
    d = r.dense
    at_rest = d.t_s <= 10.0
    # drifts with the current only (water-relative speed ~ σ_V1), still at the surface
    ground_speed = np.linalg.norm(d.vel_n_m_s[at_rest, :2] - np.array(r.scenario.current.vel_n_m_s()), axis=1)
    assert ground_speed.max() < 0.05 and np.abs(d.pos_n_m[at_rest, 2]).max() == 0.0


def test_project_strapdown_follows_the_truth_with_a_perfect_imu(perfect):
    # the filter's own mechanisation (½(R⁻+R⁺) rotation, flat earth) agrees with the
    # simulator to its second-order discretisation error, far below any IMU grade's noise
    sd = pytest.importorskip("adaptnav.fusion.strapdown")
    state = pytest.importorskip("adaptnav.fusion.state")
    d = perfect.dense
    x = state.initial_nominal(d.pos_n_m[0], d.vel_n_m_s[0], d.q_nb[0])
    acc, r0, r1 = np.zeros(state.ACC_SIZE), np.zeros((3, 3)), np.zeros((3, 3))
    f = np.ascontiguousarray(perfect.imu.specific_force_b_m_s2)
    w = np.ascontiguousarray(perfect.imu.omega_b_rad_s)
    dt = 1.0 / perfect.scenario.imu.rate_hz
    for i in range(len(f)):
        sd.strapdown_step(x, f[i], w[i], dt, acc, r0, r1)
    assert np.linalg.norm(x[state.X_POS] - d.pos_n_m[-1]) < 0.01       # 300 s, ~500 m travelled
    assert np.linalg.norm(x[state.X_VEL] - d.vel_n_m_s[-1]) < 1e-4
    assert abs(abs(np.dot(x[state.X_Q], d.q_nb[-1])) - 1.0) < 1e-9


@pytest.mark.parametrize("pattern", ["straight", "circle"])
def test_guidance_follows_the_pattern(pattern):
    r = simulate(load_scenario("short", [f'trajectory.pattern="{pattern}"', "trajectory.heading_deg=30.0"]))
    h = math.radians(30.0)
    along, across = np.array([math.cos(h), math.sin(h)]), np.array([-math.sin(h), math.cos(h)])
    p = r.dense.pos_n_m[3000:, :2]  # after the first 30 s
    if pattern == "straight":
        assert np.abs(p @ across).max() < 2.0 and (p[-1] @ along) > 400.0
    else:
        radius = np.linalg.norm(p - 100.0 * across, axis=1)
        assert np.abs(radius - 100.0).max() < 3.0


def test_survey_scenario_streams():
    # the reference survey of issue 2, simulated in full (a few seconds)
    r = simulate(load_scenario("survey"))
    c = r.counts()
    assert c["imu"] == 360_000 and c["truth"] == 36_001 and "dvl" not in c
    usbl = [u.t_s for u in r.samples["usbl"]]
    assert usbl[0] == 60.0 and usbl[-1] == 2400.0 and len(usbl) == 40
    assert [g.t_s for g in r.samples["gnss"]] == [0.0]
    k = {s.t_s: s.k_v for s in r.samples["truth"]}
    assert k[1799.9] == 1.0 and k[1800.0] == 0.9
    # lawnmower legs 500 m apart by 50 m, at 20 m depth after the descent
    p = r.dense.pos_n_m
    assert 450.0 < p[:, 0].max() < 600.0 and np.abs(p[36_000:, 2] - 20.0).max() < 1e-3
    east_per_leg = 50.0
    assert p[-1, 1] > 5 * east_per_leg


def test_dvl_scale_misalignment_outliers_and_lock_over_a_trench():
    # GIVEN a DVL with a 0.8 % scale error and a 0.6° yaw misalignment, outliers, and a
    # trench (seabed 30 → 140 m) across the second leg's east coordinate
    sc = load_scenario("short", ["duration_s=300", "dvl.enabled=true", "dvl.scale_factor_error=0.008",
                                 "dvl.misalignment_rpy_deg=[0, 0, 0.6]", "dvl.outlier_prob=0.01", "dvl.beam_bias_m_s=[0, 0, 0, 0]",
                                 "environment.trench_east_m=[20.0, 60.0]", "environment.trench_depth_m=110.0"])
    r = simulate(sc)
    d = r.dense
    dt = d.t_s[1] - d.t_s[0]
    dvl = r.samples["dvl"]
    idx = [int(round(s.t_s / dt)) for s in dvl]
    east = d.pos_n_m[idx, 1]
    valid = np.array([s.valid for s in dvl])
    # THEN no bottom lock while over the trench (altitude ~130 m > 80 m), lock elsewhere
    over = (east > 25.0) & (east < 55.0)
    assert over.sum() > 20 and not valid[over].any()
    assert valid[~over & (east < 10.0)].mean() > 0.9
    # AND the measured horizontal velocity is the true one scaled by 1.008 and rotated by
    # the misalignment (a least-squares fit on the samples with lock; outliers trimmed)
    lever = np.array(sc.dvl.lever_arm_b_m)

    def head_velocity(i):  # body velocity + ω × lever (ω from the truth attitudes around i)
        dq = quat_mul(d.q_nb[i - 1] * np.array([1, -1, -1, -1]), d.q_nb[i + 1])
        return quat_to_dcm(d.q_nb[i]).T @ d.vel_n_m_s[i] + np.cross(2.0 * dq[1:] / (2.0 * dt), lever)

    vb = np.array([head_velocity(i) for i in np.array(idx)[valid]])
    vm = np.array([s.vel_d_m_s for s in dvl if s.valid])
    keep = np.linalg.norm(vm[:, :2] - vb[:, :2], axis=1) < 0.1
    assert 0.005 < 1 - keep.mean() < 0.1  # outliers are there, and rare
    zb = vb[keep, 0] + 1j * vb[keep, 1]
    zm = vm[keep, 0] + 1j * vm[keep, 1]
    g = np.vdot(zb, zm) / np.vdot(zb, zb)  # zm ≈ g zb, g = (1 + s) e^{-iψ}
    assert abs(abs(g) - 1.008) < 0.001
    assert abs(math.degrees(-np.angle(g)) - 0.6) < 0.05


def test_a_surface_drift_carries_the_vehicle_in_the_surface_layer_only():
    # a minute afloat in 0.15 m/s of surface drift (leeway, wind drift) towards 200°, over a
    # current of 0.1 m/s towards 45° at depth, then the dive to 10 m
    r = simulate(load_scenario("short", ["duration_s=150", "trajectory.start_delay_s=60",
                                         "current.surface_drift_speed_m_s=0.15",
                                         "current.surface_drift_direction_deg=200"]))
    cur = np.array(r.scenario.current.vel_n_m_s())
    a = math.radians(200.0)
    drift = 0.15 * np.array([math.cos(a), math.sin(a)])
    d = r.dense
    afloat = d.t_s <= 60.0
    assert np.abs(d.pos_n_m[afloat, 2]).max() == 0.0
    # afloat the ground moves with current + drift (the hull's own speed at rest ~ σ_V1)
    moved = d.pos_n_m[np.searchsorted(d.t_s, 60.0), :2] - d.pos_n_m[0, :2]
    assert np.linalg.norm(moved - (cur + drift) * 60.0) < 1.0, moved
    assert np.linalg.norm(moved - cur * 60.0) > 7.0  # the drift's 9 m are there
    # the truth's current is the water's at the vehicle's depth
    truth = {round(s.t_s, 3): s for s in r.samples["truth"]}
    np.testing.assert_allclose(truth[30.0].current_n_m_s[:2], cur + drift, atol=1e-12)
    deep = [s for s in r.samples["truth"] if s.pos_n_m[2] >= r.scenario.current.surface_layer_m]
    assert deep and all(np.allclose(s.current_n_m_s[:2], cur, atol=1e-12) for s in deep)
    # the IMU is drawn from the same truth: a perfect one integrates through the descent's
    # fading drift onto it
    p = simulate(load_scenario("short", ["duration_s=150", "trajectory.start_delay_s=60", 'imu.grade="perfect"',
                                         "current.surface_drift_speed_m_s=0.15",
                                         "current.surface_drift_direction_deg=200"]))
    i0 = int(np.searchsorted(p.dense.t_s, 55.0))
    _, _, pos = _textbook_strapdown(p, i0, 3000)  # 55 s → 85 s: the vehicle leaves the surface layer
    assert p.dense.pos_n_m[i0 + 3000, 2] > 2.0
    assert np.abs(pos - p.dense.pos_n_m[i0 + 3000]).max() < 1e-6
