"""The kernels that take the estimator's scratch array whole (kalman.WORK_*: fuse_scalar_core,
fuse_heading_core, fuse_vector_core) against the calls of separate arrays they stand for,
bit for bit, on seeded random states and edge inputs (NaN, inf, gated, an unnormalised
quaternion); dvl_bottom_track_core against the numpy model it stands for, to a few ulps; and
the estimator's arrays that are views of that scratch stay its views."""
import math

import numpy as np
import pytest

from adaptnav.fusion import kalman
from adaptnav.fusion.aiding import dvl
from adaptnav.fusion.config import DvlConfig, FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GeoOrigin, euler_to_quat
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import DvlSample
from adaptnav.fusion.state import ACC_OMEGA, ATT, N_ERR, X_CUR, initial_nominal

N_X = kalman.N_X


def _core(rng, k: int) -> np.ndarray:
    """A core array: a random state (a slightly unnormalised quaternion every third), a random
    positive-definite P, a pending propagation step, a bias-corrected rate."""
    core = np.zeros(kalman.CORE_SIZE)
    roll, pitch, yaw = rng.uniform(-0.4, 0.4), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
    x = initial_nominal(rng.normal(size=3) * 100, rng.normal(size=3), euler_to_quat(roll, pitch, yaw))
    x[X_CUR] = rng.normal(size=2) * 0.3
    x[6:10] *= 1.0 + 1e-3 * (k % 3)
    core[kalman.CORE_X] = x
    A = rng.normal(size=(N_ERR, N_ERR)) * 0.1
    core[kalman.CORE_P] = (A @ A.T + np.eye(N_ERR) * 1e-3).ravel()
    acc = core[kalman.CORE_ACC]
    acc[ACC_OMEGA] = rng.normal(size=3) * 0.1
    clock = core[kalman.CORE_CLOCK]
    clock[:] = 10.0
    return core


def _work(rng) -> np.ndarray:
    work = rng.normal(size=kalman.WORK_SIZE)  # garbage where the kernels write
    work[kalman.WORK_QDIAG:kalman.WORK_QDIAG + N_ERR] = rng.uniform(0.0, 1e-3, size=N_ERR)
    return work


def _row(rng) -> np.ndarray:
    H = np.zeros((1, N_ERR))
    H[0, rng.integers(0, N_ERR, size=3)] = rng.normal(size=3)
    return H


@pytest.mark.parametrize("heading", [False, True])
def test_the_scalar_kernels_on_the_scratch_are_the_separate_arrays_kernel(heading):
    rng = np.random.default_rng(31)
    qd, dx_at, out_at = kalman.WORK_QDIAG, kalman.WORK_DX, kalman.WORK_OUT
    row_at = kalman.WORK_H_HEADING if heading else kalman.WORK_H_DEPTH
    fused_seen = set()
    for k in range(600):
        core, work = _core(rng, k), _work(rng)
        H = _row(rng)
        if heading:
            H[0, ATT.start:ATT.start + 3] = 0.0  # (the kernel writes the attitude part)
        work[row_at:row_at + N_ERR] = H[0]
        var = float(rng.uniform(1e-4, 1.0))
        z = float(rng.normal() * (0.1 if k % 5 else 50.0))  # every fifth gated
        if k % 97 == 0:
            z = (math.nan, math.inf, -math.inf)[k % 3]
        h = float(rng.normal())
        angular = bool(k % 2)
        gate = 9.0
        # the reference: the separate arrays (copies of the same numbers)
        ref_core, ref_q = core.copy(), work[qd:qd + N_ERR].copy()
        ref_H, ref_dx, ref_out = H.copy(), np.zeros(N_ERR), np.zeros(3)
        if heading:
            yaw, h_x, h_y = kalman.heading_row(ref_core[0:N_X])
            ref_H[0, ATT.start:ATT.start + 3] = (h_x, h_y, 1.0)
            want = kalman._fuse_scalar(ref_core, ref_q, z, yaw, ref_H, var, True, gate, ref_dx, ref_out, True, 1000.0)
            got = kalman.fuse_heading_core(core, work, z, var, gate, True, 1000.0)
        else:
            want = kalman._fuse_scalar(ref_core, ref_q, z, h, ref_H, var, angular, gate, ref_dx, ref_out, True,
                                       1000.0)
            got = kalman.fuse_scalar_core(core, work, z, h, row_at, var, angular, gate, True, 1000.0)
        fused_seen.add(bool(got[0]))
        assert got == want
        assert core.tobytes() == ref_core.tobytes()
        assert work[dx_at:dx_at + N_ERR].tobytes() == ref_dx.tobytes()
        assert work[out_at:out_at + 3].tobytes() == ref_out.tobytes()
        assert work[row_at:row_at + N_ERR].tobytes() == ref_H.tobytes()
        assert work[qd:qd + N_ERR].tobytes() == ref_q.tobytes()
    assert fused_seen == {False, True}


@pytest.mark.parametrize("m", [1, 2, 3])
def test_the_vector_kernel_on_the_scratch_is_fuse_core(m):
    """fuse_vector_core (the DVL's update) against fuse_core on separate arrays and core_ok."""
    rng = np.random.default_rng(43 + m)
    qd, dx_at = kalman.WORK_QDIAG, kalman.WORK_DX
    fused_seen = set()
    for k in range(400):
        core, work = _core(rng, k), _work(rng)
        H = rng.normal(size=(m, N_ERR))
        A = rng.normal(size=(m, m)) * 0.1
        R = A @ A.T + np.eye(m) * 0.01
        z, h = rng.normal(size=m) * (1.0 if k % 5 else 100.0), rng.normal(size=m)
        if k % 97 == 0:
            z[k % m] = (math.nan, math.inf, -math.inf)[k % 3]
        flush = bool(k % 2)
        ref_core, ref_q = core.copy(), work[qd:qd + N_ERR].copy()
        ref_dx, ref_s = np.zeros(N_ERR), np.zeros(m)
        ref_y = z - h
        nis, fused = kalman.fuse_core(ref_core, ref_q, ref_y, H, R, 11.3, ref_dx, ref_s, flush)
        want = (nis, fused, kalman.core_ok(ref_core, 1000.0))
        got = kalman.fuse_vector_core(core, work, z, h, H, R, 11.3, flush, 1000.0)
        fused_seen.add(bool(got[1]))
        assert repr(got) == repr(want)  # (a NaN nis)
        assert core.tobytes() == ref_core.tobytes()
        assert work[kalman.WORK_OUT:kalman.WORK_OUT + m].tobytes() == ref_y.tobytes()
        assert work[kalman.WORK_SDIAG:kalman.WORK_SDIAG + m].tobytes() == ref_s.tobytes()
        assert work[dx_at:dx_at + N_ERR].tobytes() == ref_dx.tobytes()
    assert fused_seen == {False, True}


@pytest.mark.parametrize("lever_arm_sigma_m", [0.0, 0.5])
def test_the_dvl_model_on_the_scratch_is_the_numpy_model(lever_arm_sigma_m):
    """dvl_bottom_track_core reads the state and ω̂_b from the core and the installation from its
    packed constants, writes H, h, R and the corrected z into the scratch's DVL slots and returns
    the calibration's six numbers, which it leaves in the scratch too: the numpy model's numbers
    (dvl.measure, correct_velocity, lever_arm_doubt) to a few ulps; the core only read."""
    rng = np.random.default_rng(37)
    tight = dict(rtol=1e-13, atol=1e-14)
    for k in range(400):
        core, work = _core(rng, k), _work(rng)
        lever = rng.normal(size=3) * 0.5
        R_db = np.ascontiguousarray(dvl.rotation_db(tuple(rng.normal(size=3) * 0.5)))
        setup = dvl.DvlSetup(lever, R_db, None).with_lever(lever)
        consts = dvl.packed_setup(setup)
        assert consts.shape == (kalman.DVL_CONST_SIZE,)
        vel = rng.normal(size=3).tolist()
        s_err, psi, sigma = float(rng.normal() * 0.005), float(rng.normal() * 0.01), float(rng.uniform(0.01, 0.3))
        before = core.copy()
        got = kalman.dvl_bottom_track_core(core, consts, work, *vel, s_err, psi, sigma, lever_arm_sigma_m)
        assert core.tobytes() == before.tobytes()  # the state is only read
        assert np.array(got).tobytes() == work[kalman.WORK_DVL_AUX:kalman.WORK_DVL_AUX + 6].tobytes()
        x, omega = before[kalman.CORE_X], before[kalman.CORE_ACC][ACC_OMEGA]
        z = dvl.correct_velocity(vel, s_err, psi)
        want = dvl.measure(DvlSample(1.0, tuple(vel)), x, omega, lever, R_db, sigma, z)
        R = want.R + (dvl.lever_arm_doubt(omega, lever_arm_sigma_m, R_db) if lever_arm_sigma_m > 0 else 0.0)
        meas = dvl.work_measurement(work)
        for a, b in ((meas.H, want.H), (meas.h, want.h), (meas.R, R), (meas.z, np.asarray(z))):
            assert a.shape == b.shape
            np.testing.assert_allclose(a, b, **tight)


def _straight_run(rng, n: int):
    """DVL samples of a vehicle on a straight at 1.5 m/s, then turning (the straight legs close
    segments: the calibration's (s, ψ) change on the way), with a NaN σ, a σ worse than configured."""
    for k in range(n):
        yaw = 0.3 if k < n * 0.7 else 0.3 + 0.02 * (k - n * 0.7)
        x = initial_nominal(np.zeros(3), np.array([1.5 * math.cos(yaw), 1.5 * math.sin(yaw), 0.0]),
                            euler_to_quat(0.0, 0.0, yaw))
        x[X_CUR] = (0.1, -0.05)
        omega = rng.normal(size=3) * 0.01
        vel = (1.5 + rng.normal() * 0.01, 0.006 + rng.normal() * 0.003, rng.normal() * 0.01)
        yield x, omega, DvlSample(0.2 * k, vel, sigma_m_s=0.2 if k % 11 == 0 else math.nan)


@pytest.mark.parametrize("calibrated", [False, True])
def test_the_dvl_model_into_the_scratch_is_bottom_track(calibrated):
    """bottom_track_into (the estimator's compiled DVL path, into its arrays) against bottom_track
    (its general path, arrays of its own) on a straight-leg run: the same model and the same
    calibration, sample by sample, the velocity corrected with the estimate after the sample —
    anew where a closed segment changed (s, ψ)."""
    config = DvlConfig(enabled=True, lever_arm_b_m=(0.51, 0.12, 0.33), rotation_bd_rpy_rad=(0.01, 0.02, 0.7),
                       lever_arm_sigma_m=0.3, scale_sigma=0.005 if calibrated else 0.0,
                       misalignment_sigma_rad=0.01 if calibrated else 0.0)
    setup, ref_setup = dvl._setup(config), dvl._setup(config)
    cal, ref_cal = setup.calibration, ref_setup.calibration
    if calibrated:
        for c in (cal, ref_cal):
            c.on_fix(-1.0, (0.0, 0.0), 1.0)  # the track counts from a fix
    consts = dvl.packed_setup(setup)
    work = np.zeros(kalman.WORK_SIZE)
    meas = dvl.work_measurement(work)
    changed = 0
    for x, omega, sample in _straight_run(np.random.default_rng(41), 900):
        core = np.zeros(kalman.CORE_SIZE)
        core[kalman.CORE_X] = x
        core[kalman.CORE_ACC][ACC_OMEGA] = omega
        theta = None if cal is None else cal.theta
        dvl.bottom_track_into(sample, core, work, consts, config, setup)
        want = dvl.bottom_track(sample, x, omega, config, ref_setup)
        for a, b in zip(meas, want):
            assert a.shape == b.shape and a.tobytes() == b.tobytes()
        if cal is None:  # the head's velocity as it came
            assert meas.z.tobytes() == np.array(sample.vel_d_m_s, dtype=float).tobytes()
        else:
            # corrected with the estimate after this sample: anew (the Python correction) when a
            # segment changed it, else the kernel's with the one before (the same to the last bits)
            np.testing.assert_allclose(meas.z, cal.correct(sample.vel_d_m_s), rtol=1e-15, atol=1e-15)
            if cal.theta is not theta:
                assert meas.z.tobytes() == np.array(cal.correct(sample.vel_d_m_s)).tobytes()
            changed += cal.theta is not theta
            assert cal.theta.tobytes() == ref_cal.theta.tobytes() and cal.P.tobytes() == ref_cal.P.tobytes()
            assert cal.position_cov_ne_values() == ref_cal.position_cov_ne_values()
            # (the memo made with the sample, as bottom_track makes it: the next epoch's)
            assert cal._cov_ne_memo[3] == ref_cal._cov_ne_memo[3] and cal._cov_ne_memo[2] is cal.P
            assert (cal.straight_legs._sums, cal._track_n, cal._track_e) == \
                (ref_cal.straight_legs._sums, ref_cal._track_n, ref_cal._track_e)
    assert changed >= 2 if calibrated else changed == 0


def test_the_estimators_arrays_stay_views_of_its_scratch():
    """_qdiag, _dx, _sdiag, the fast path's outputs and the DVL's Measurement are the scratch's
    memory, also after the start set the process noise (in place: the kernels read it there)."""
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), GeoOrigin(0.7, -0.1, 0.0))

    def check():
        w = est._work
        for a in (est._qdiag, est._dx, est._sdiag, est._fast_out, *est._dvl_meas[:4]):
            assert a.base is w or a.base is w.base or np.shares_memory(a, w)
        assert est._qdiag.tobytes() == w[kalman.WORK_QDIAG:kalman.WORK_QDIAG + N_ERR].tobytes()
        assert w[kalman.WORK_H_DEPTH + 2] == 1.0 and w[kalman.WORK_H_HEADING + ATT.start + 2] == 1.0

    check()
    q0 = est._qdiag.copy()
    est._qdiag[:] = 0.0
    from adaptnav.fusion.alignment import Start

    est._begin_ins(Start(0.0, initial_nominal(), np.eye(N_ERR) * 0.01, est.imu_model, 0.7))
    check()
    assert est._qdiag.tobytes() == q0.tobytes()
