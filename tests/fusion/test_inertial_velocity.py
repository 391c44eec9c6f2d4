"""The estimator's free-inertial velocity: the IMU's velocity changes, without aiding corrections."""
import numpy as np

from adaptnav.fusion.samples import ImuBatch

from .mission import make_mission
from .test_estimator import _est


def _feed_with_probes(est, m, probe_times):
    """Replay-order feed (as tests.fusion.mission.run) returning inertial velocity samples at the probes."""
    events = sorted([(s.t_s, 1, s) for s in m.aids] + [(float(t), 2, None) for t in probe_times],
                    key=lambda e: (e[0], e[1]))
    out, k0 = [], 0
    for t, kind, s in events:
        k1 = int(np.searchsorted(m.t_imu, t, side="right"))
        if k1 > k0:
            est.process(ImuBatch(m.t_imu[k0:k1], m.f_b[k0:k1], m.w_b[k0:k1]))
            k0 = k1
        if kind == 1:
            est.process(s)
        else:
            out.append((k1 - 1, est.inertial_velocity()))
    return out


def test_free_inertial_velocity_changes_are_the_true_changes_not_the_corrected_estimate():
    # GIVEN a 300 s mission with the motion model's surge noise, USBL every 10 s pulling the
    # estimate around, and IMU noise and biases
    m = make_mission(np.random.default_rng(7), 300.0, usbl_period_s=10.0)
    est = _est()
    probes = np.arange(60.0, 290.0, 1.0)
    got = _feed_with_probes(est, m, probes)
    assert all(s is not None for _, s in got)
    k = np.array([i for i, _ in got])
    v_in = np.array([s.vel_n_m_s[:2] for _, s in got])
    v_true = m.vel_n[k, :2]
    # THEN the change over 1 s matches the truth's to a few mm/s (only IMU noise, bias, attitude error)
    d_err = np.diff(v_in, axis=0) - np.diff(v_true, axis=0)
    assert np.sqrt(np.mean(d_err ** 2)) < 0.01
    # and over 10 s still to a few cm/s (the value drifts slowly: bias and attitude errors)
    d10_err = (v_in[10:] - v_in[:-10]) - (v_true[10:] - v_true[:-10])
    assert np.sqrt(np.mean(d10_err ** 2)) < 0.05
    # while the true surge changes per second are an order larger (the signal the calibrator wants)
    assert np.sqrt(np.mean(np.diff(v_true, axis=0) ** 2)) > 5 * np.sqrt(np.mean(d_err ** 2))
    # AND its integral gives the per-second mean velocities whose changes are the truth's
    mean_in = np.diff(np.array([s.pos_n_m[:2] for _, s in got]), axis=0)
    mean_true = np.diff(m.pos_n[k, :2], axis=0)
    assert np.sqrt(np.mean((np.diff(mean_in, axis=0) - np.diff(mean_true, axis=0)) ** 2)) < 0.01
    # AND the samples carry the time of the state and a yaw near the truth
    assert got[0][1].t_s == m.t_imu[k[0]]
    yaw_err = np.angle(np.exp(1j * (np.array([s.yaw_rad for _, s in got]) - m.yaw[k])))
    assert np.max(np.abs(yaw_err)) < np.radians(3.0)


def test_free_inertial_velocity_is_none_before_alignment_and_survives_late_refusion():
    m = make_mission(np.random.default_rng(8), 60.0, usbl_period_s=10.0)
    assert _est().inertial_velocity() is None
    late = next(s for s in m.aids if s.KIND == "usbl" and 35.0 < s.t_s < 45.0)
    t_probe = late.t_s + 0.5  # within max_delay_s
    # reference: everything on time
    a = _feed_with_probes(_est(), m, [t_probe])[0][1]
    # the same fix handed over 0.5 s late: fused at its time by restore + re-run of the IMU; the
    # free-inertial sum must come out the same (restored with the snapshot, not double-counted)
    est = _est()
    k0 = 0
    for s in m.aids:
        if s.t_s > t_probe:
            break
        if s is late:
            continue
        k = int(np.searchsorted(m.t_imu, s.t_s, side="right"))
        est.process(ImuBatch(m.t_imu[k0:k], m.f_b[k0:k], m.w_b[k0:k]))
        k0 = k
        est.process(s)
    k = int(np.searchsorted(m.t_imu, t_probe, side="right"))
    est.process(ImuBatch(m.t_imu[k0:k], m.f_b[k0:k], m.w_b[k0:k]))
    est.process(late)
    assert est.late_fused == 1
    b = est.inertial_velocity()
    assert b.t_s == a.t_s
    np.testing.assert_allclose(b.vel_n_m_s, a.vel_n_m_s, atol=1e-4)
