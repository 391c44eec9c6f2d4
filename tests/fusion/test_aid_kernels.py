"""The compiled measurement models of the commonest aids against the numpy models they
replace, on seeded random states: the same sums (BLAS's fused multiply-adds and libm's
trigonometry differ from numpy's in the last bits only), so a tolerance of a few ulps."""
import math

import numpy as np
import pytest

from adaptnav.fusion.aiding import dvl
from adaptnav.fusion.aiding.common import dcm
from adaptnav.fusion.config import DvlConfig
from adaptnav.fusion.frames import euler_to_quat
from adaptnav.fusion.samples import DvlSample
from adaptnav.fusion.state import X_CUR, initial_nominal

TIGHT = dict(rtol=1e-13, atol=1e-14)


def _states(rng, n=200):
    for _ in range(n):
        roll, pitch, yaw = rng.uniform(-0.4, 0.4), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
        x = initial_nominal(rng.normal(size=3) * 100, rng.normal(size=3), euler_to_quat(roll, pitch, yaw))
        x[X_CUR] = rng.normal(size=2) * 0.3
        yield x


@pytest.mark.parametrize("calibrated", [False, True])
@pytest.mark.parametrize("lever_arm_sigma_m", [0.0, 0.5])
def test_the_compiled_bottom_track_is_the_numpy_model(calibrated, lever_arm_sigma_m):
    rng = np.random.default_rng(11)
    config = DvlConfig(enabled=True, lever_arm_b_m=(0.51, 0.12, 0.33), rotation_bd_rpy_rad=(0.01, 0.02, 0.7),
                       lever_arm_sigma_m=lever_arm_sigma_m,
                       scale_sigma=0.005 if calibrated else 0.0, misalignment_sigma_rad=0.01 if calibrated else 0.0)
    setup = dvl._setup(config)
    lever_b, R_db, cal, _ = setup
    assert (cal is not None) == calibrated
    for k, x in enumerate(_states(rng)):
        if cal is not None:  # a calibration away from its prior's zero (replaced, never changed in place)
            cal.theta = np.array([rng.normal() * 0.005, rng.normal() * 0.01, 0.0, 0.0])
        theta = None if cal is None else cal.theta.copy()
        omega = rng.normal(size=3) * 0.1
        vel_d = tuple(rng.normal(size=3).tolist())
        sample = DvlSample(float(k), vel_d, sigma_m_s=0.2 if k % 7 == 0 else math.nan)
        got = dvl.bottom_track(sample, x, omega, config, setup)
        if cal is not None and cal.theta is not theta:
            theta = cal.theta  # a straight-leg segment closed (not with random states)
        z = vel_d if cal is None else dvl.correct_velocity(vel_d, float(theta[0]), float(theta[1]))
        want = dvl.measure(sample, x, omega, lever_b, R_db, config.sigma_m_s, z)
        R = want.R + (dvl.lever_arm_doubt(omega, lever_arm_sigma_m, R_db) if lever_arm_sigma_m > 0 else 0.0)
        np.testing.assert_allclose(got.H, want.H, **TIGHT)
        np.testing.assert_allclose(got.h, want.h, **TIGHT)
        np.testing.assert_allclose(got.R, R, **TIGHT)
        np.testing.assert_allclose(got.z, want.z, **TIGHT)
        assert got.H.shape == (3, 18) and not got.angular.any()
        assert np.all(got.H[:, [0, 1, 2, 9, 10, 11, 15, 16, 17]] == 0.0)


def test_the_compiled_bottom_track_feeds_the_calibration_what_numpy_computes():
    """The uncorrected velocity in n and its heading-aligned parts, as the numpy model had them."""
    from adaptnav.fusion import kalman
    from adaptnav.fusion.state import ACC_OMEGA

    rng = np.random.default_rng(5)
    R_db = np.ascontiguousarray(dvl.rotation_db((0.01, -0.02, 0.3)))
    lever = np.array([0.4, -0.1, 0.2])
    consts = dvl.packed_setup(dvl.DvlSetup(lever, R_db, None).with_lever(lever))
    for x in _states(rng):
        vel_d = rng.normal(size=3)
        core, work = np.zeros(kalman.CORE_SIZE), np.zeros(kalman.WORK_SIZE)
        core[kalman.CORE_X] = x
        core[kalman.CORE_ACC][ACC_OMEGA] = rng.normal(size=3)
        aux = kalman.dvl_bottom_track_core(core, consts, work, *vel_d.tolist(), 0.003, -0.004, 0.03, 0.5)
        R_nb = dcm(x)
        v_n = R_nb @ (R_db.T @ vel_d)
        c0, s0 = R_nb[0, 0], R_nb[1, 0]
        ch, sh = c0 / math.hypot(c0, s0), s0 / math.hypot(c0, s0)
        cn, ce = x[X_CUR]
        want = [v_n[0], v_n[1], ch * v_n[0] + sh * v_n[1], -sh * v_n[0] + ch * v_n[1], math.atan2(s0, c0),
                ch * cn + sh * ce]
        np.testing.assert_allclose(aux, want, **TIGHT)
        z = work[kalman.WORK_DVL_Z:kalman.WORK_DVL_Z + 3]
        np.testing.assert_allclose(z, dvl.correct_velocity(vel_d, 0.003, -0.004), **TIGHT)


def test_the_error_injection_is_g_p_gt():
    """inject_error's covariance reset on the attitude rows and columns only: G P Gᵀ with
    G = I + ½[δθ]× in the attitude block — every other entry exactly, those to the last bits."""
    from adaptnav.fusion import kalman
    from adaptnav.fusion.state import ATT, N_ERR

    rng = np.random.default_rng(3)
    for _ in range(200):
        A = rng.normal(size=(N_ERR, N_ERR))
        P = A @ A.T
        x = initial_nominal(rng.normal(size=3), rng.normal(size=3), euler_to_quat(*rng.uniform(-1, 1, 3)))
        dx = rng.normal(size=N_ERR) * 0.01
        rx, ry, rz = dx[ATT]
        G = np.eye(N_ERR)
        G[ATT, ATT] += 0.5 * np.array([[0.0, -rz, ry], [rz, 0.0, -rx], [-ry, rx, 0.0]])
        want = G @ P @ G.T
        got = P.copy()
        kalman.inject_error(x, dx, got)
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * np.abs(P).max())
        other = np.ones(N_ERR, bool)
        other[ATT] = False
        assert np.array_equal(got[np.ix_(other, other)], P[np.ix_(other, other)])


@pytest.mark.parametrize("spread", [1.0, 0.0])  # spread 0: many equal values
def test_the_median_window_is_the_sorted_list_and_bisect(spread):
    """median_window_push against what DepthNoise kept before: a deque of the window and a
    sorted list (del s[bisect_left(s, oldest)], insort), the median as numpy.median — exactly."""
    from bisect import bisect_left, insort
    from collections import deque

    from adaptnav.fusion import kalman

    rng = np.random.default_rng(9)
    W = 60
    window = np.zeros(2 + 2 * W)
    ring, srt = deque(maxlen=W), []
    for _ in range(1000):
        v = float(np.round(abs(rng.normal()) * 0.05, 2 if spread == 0.0 else 12))
        if len(ring) == W:
            del srt[bisect_left(srt, ring[0])]
        ring.append(v)
        insort(srt, v)
        n, med = kalman.median_window_push(window, v)
        assert n == len(srt) and med == np.median(srt)
        assert window[2 + W:2 + W + n].tolist() == srt


def test_the_compiled_heading_row_is_yaw_row_exactly():
    """The heading's compiled path (kalman.fuse_heading_core) computes h and the row with
    heading_row, its general path with heading.yaw_row (which calls it: one model, whatever
    either becomes); against the numpy model (euler_of, euler_jacobian) to the last bits."""
    from adaptnav.fusion import kalman
    from adaptnav.fusion.aiding import heading

    rng = np.random.default_rng(17)
    for k, x in enumerate(_states(rng, 2000)):
        x[6:10] *= 1.0 + 1e-3 * (k % 3)  # a slightly unnormalised quaternion too
        got = kalman.heading_row(x)
        assert got == heading.yaw_row(x)
        np.testing.assert_allclose(got[0], heading.predict(x)[0], rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(got[1:], heading.jacobian(x)[0, 6:8], rtol=1e-14, atol=1e-15)


def test_the_dvl_track_covariance_is_the_numpy_formula():
    """DvlCalibration.position_cov_ne on floats: H P Hᵀ + k kᵀ with H = [[−d0, −d1], [−d1, d0]],
    k = H θ̂ − applied, as numpy's products computed them — to the last bits."""
    rng = np.random.default_rng(21)
    for _ in range(300):
        cal = dvl.DvlCalibration(0.005, 0.01)
        cal.on_fix(0.0, (0.0, 0.0), 1.0)
        A = rng.normal(size=(4, 4)) * 0.01
        cal.P = A @ A.T
        cal.theta = rng.normal(size=4) * 0.01
        d0, d1 = rng.normal(size=2) * 300.0
        cal._track_n, cal._track_e = d0, d1
        cal._applied_n, cal._applied_e = rng.normal(size=2)
        H = np.array([[-d0, -d1], [-d1, d0]])
        k = H @ cal.theta[:2] - np.array([cal._applied_n, cal._applied_e])
        want = H @ cal.P[:2, :2] @ H.T + np.outer(k, k)
        got = cal.position_cov_ne()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        assert got.flags.writeable and not cal.position_cov_ne(copy=False).flags.writeable


def test_the_dvl_track_covariance_values_follow_the_array():
    """position_cov_ne_values (what every published state adds) is position_cov_ne's array as
    floats, exactly — zero before the first fix, and again after the track or P changed (the
    memo they share is not kept past either)."""
    cal = dvl.DvlCalibration(0.005, 0.01)
    assert cal.position_cov_ne_values() == (0.0, 0.0, 0.0, 0.0)
    cal.on_fix(0.0, (0.0, 0.0), 1.0)
    rng = np.random.default_rng(5)
    for step in range(6):
        if step % 2 == 0:
            cal._track_n, cal._track_e = (rng.normal(size=2) * 100.0).tolist()
        else:
            A = rng.normal(size=(4, 4)) * 0.01
            cal.P = A @ A.T
        values = cal.position_cov_ne_values()
        assert values == tuple(cal.position_cov_ne().ravel().tolist())
        assert all(type(v) is float for v in values)
        d0, d1 = cal._track_n, cal._track_e
        H = np.array([[-d0, -d1], [-d1, d0]])
        k = H @ cal.theta[:2] - np.array([cal._applied_n, cal._applied_e])
        want = H @ cal.P[:2, :2] @ H.T + np.outer(k, k)  # of this step's track and P
        np.testing.assert_allclose(np.reshape(values, (2, 2)), want, rtol=1e-12, atol=1e-12 * np.abs(want).max())


def test_the_compiled_positive_definite_check_is_lapacks_verdict():
    """The last-good-state check (Estimator.settle): the compiled Cholesky's verdict is
    np.linalg.cholesky's, on positive definite covariances, ones made indefinite or singular
    (a pivot well below zero, every variance positive but a correlation beyond 1), asymmetric ones (both read the lower triangle);
    a NaN or an infinity in the lower triangle fails it."""
    from adaptnav.fusion import kalman

    rng = np.random.default_rng(5)
    n = kalman.N_ERR
    core = np.zeros(kalman.CORE_SIZE)
    P = core[kalman.CORE_P].reshape(n, n)  # a view: written in place below

    def lapack(A):
        try:
            np.linalg.cholesky(A)
        except np.linalg.LinAlgError:
            return False
        return True

    verdicts = []
    for k in range(300):
        A = rng.normal(size=(n, n)) * np.exp(rng.uniform(-6, 3, size=n))
        M = A @ A.T + np.diag(np.exp(rng.uniform(-12, 2, size=n)))
        case = k % 6
        if case == 1:  # indefinite: one direction's variance well below zero
            v = rng.normal(size=n)
            v /= np.linalg.norm(v)
            M -= (np.linalg.eigvalsh(M).max() * 2.0) * np.outer(v, v)
        elif case == 2:  # every variance positive, a correlation beyond 1: row i = -2 × row j, variance 2 × j's
            i, j = rng.choice(n, size=2, replace=False)
            M[i, :], M[:, i] = -2.0 * M[j, :], -2.0 * M[:, j]
            M[i, i] = 2.0 * M[j, j]
        elif case == 3:  # asymmetric upper triangle (what neither reads)
            M = M + np.triu(rng.normal(size=(n, n)) * 1e3, 1)
        elif case == 4:
            i, j = rng.integers(n), rng.integers(n)
            M[i, j] = rng.choice([np.nan, np.inf, -np.inf])
        elif case == 5:  # a negative variance
            i = rng.integers(n)
            M[i, i] = -abs(M[i, i])
        P[:, :] = M
        # a non-finite number where the factorisation reads it fails (OpenBLAS's potrf lets a
        # NaN through: no error, a factor of NaNs); elsewhere LAPACK's verdict
        expected = False if case == 4 and i >= j else lapack(P.copy())
        assert kalman.core_positive_definite(core) == expected, (k, case)
        verdicts.append(expected)
    assert sum(verdicts) > 50 and len(verdicts) - sum(verdicts) > 50  # both verdicts tested
