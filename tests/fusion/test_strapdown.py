"""Strapdown mechanisation (adaptnav.fusion.strapdown) and the Kalman kernels' propagation and
error injection (adaptnav.fusion.kalman) against closed-form answers."""
import numpy as np
from scipy.spatial.transform import Rotation

from adaptnav.fusion import kalman
from adaptnav.fusion.frames import GRAVITY_M_S2, euler_to_quat, quat_to_scipy
from adaptnav.fusion.state import N_ERR, inject, initial_nominal


def _propagate(x, t, f, w, qdiag=None, P=None, cov_step=0.1):
    core = np.zeros(kalman.CORE_SIZE)
    xv, Pv, acc, clock = kalman.core_views(core)
    xv[:] = x
    if P is not None:
        Pv[:, :] = P
    clock[:] = 0.0
    kalman.propagate_core(t, f, w, core, np.zeros(N_ERR) if qdiag is None else qdiag, cov_step)
    kalman.flush_covariance(Pv, acc, clock, np.zeros(N_ERR) if qdiag is None else qdiag)
    return xv.copy(), Pv.copy()


def test_static_level_imu_stays_put():
    # GIVEN a level vehicle at rest: f_b = −g along down, no rotation
    n = 6000
    t = np.arange(1, n + 1) * 0.01
    f = np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    w = np.zeros((n, 3))
    x0 = initial_nominal((1.0, 2.0, 3.0))
    x, _ = _propagate(x0, t, f, w)
    # THEN after 60 s nothing moved
    np.testing.assert_allclose(x[0:3], [1.0, 2.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(x[3:6], 0.0, atol=1e-10)
    np.testing.assert_allclose(x[6:10], [1, 0, 0, 0], atol=1e-12)


def test_static_tilted_imu_stays_put():
    q = euler_to_quat(0.2, -0.1, 1.0)
    R = quat_to_scipy(q).as_matrix()
    n = 3000
    t = np.arange(1, n + 1) * 0.01
    f = np.tile(R.T @ [0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    x, _ = _propagate(initial_nominal(q_nb=q), t, f, np.zeros((n, 3)))
    np.testing.assert_allclose(x[0:6], 0.0, atol=1e-8)


def test_constant_rotation_integrates_to_the_rotation_vector():
    rate = np.array([0.05, -0.02, 0.1])
    n = 1000
    t = np.arange(1, n + 1) * 0.01
    x0 = initial_nominal(q_nb=euler_to_quat(0.1, 0.2, 0.3))
    x, _ = _propagate(x0, t, np.zeros((n, 3)), np.tile(rate, (n, 1)))
    expected = quat_to_scipy(x0[6:10]) * Rotation.from_rotvec(rate * 10.0)  # body-frame rotation
    got = quat_to_scipy(x[6:10])
    assert (got.inv() * expected).magnitude() < 1e-9


def test_constant_acceleration_integrates_exactly():
    n = 500
    t = np.arange(1, n + 1) * 0.01
    a = np.array([0.2, -0.1, 0.05])
    f = np.tile(a - [0, 0, GRAVITY_M_S2], (n, 1))
    x, _ = _propagate(initial_nominal(vel_n_m_s=(1.0, 0.0, 0.0)), t, f, np.zeros((n, 3)))
    T = 5.0
    np.testing.assert_allclose(x[3:6], [1.0, 0, 0] + a * T, atol=1e-9)
    np.testing.assert_allclose(x[0:3], np.array([1.0, 0, 0]) * T + 0.5 * a * T**2, atol=1e-9)


def test_velocity_random_walk_covariance_matches_closed_form():
    # GIVEN only accelerometer white noise q (m²/s³) and P0 = 0, static
    q = np.zeros(N_ERR)
    q[3:6] = 1e-4
    n = 1000
    t = np.arange(1, n + 1) * 0.01
    f = np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    _, P = _propagate(initial_nominal(), t, f, np.zeros((n, 3)), qdiag=q)
    T = 10.0
    # THEN P_vv = q T and P_pp = q T³/3 (continuous-time result)
    np.testing.assert_allclose(P[3, 3], 1e-4 * T, rtol=1e-9)
    np.testing.assert_allclose(P[0, 0], 1e-4 * T**3 / 3, rtol=0.02)


def test_injection_kernel_matches_reference_and_rotates_globally():
    rng = np.random.default_rng(3)
    x = initial_nominal((1, 2, 3), (0.5, -0.2, 0.1), euler_to_quat(0.1, -0.3, 2.0))
    x[10:19] = rng.normal(size=9) * 0.01 + np.r_[np.zeros(8), 1.0]
    dx = rng.normal(size=N_ERR) * 0.01
    ref = inject(x, dx)
    xk = x.copy()
    P = np.eye(N_ERR)
    kalman.inject_error(xk, dx, P)
    np.testing.assert_allclose(xk, ref, atol=1e-12)
    # q_new = q(δθ) ⊗ q: the rotation from old to new, in the navigation frame, is δθ
    r = quat_to_scipy(xk[6:10]) * quat_to_scipy(x[6:10]).inv()
    np.testing.assert_allclose(r.as_rotvec(), dx[6:9], atol=1e-12)
    assert np.allclose(P, P.T)
