"""Leg-to-leg loop closures in the filter (fusion/aiding/loop_closure.py, stochastic clones):
fused between two past epochs, the drift between them removed, the result consistent."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from adaptnav.fusion import kalman
from adaptnav.fusion.aiding import attitude as aid_attitude
from adaptnav.fusion.aiding import loop_closure as aid_loop
from adaptnav.fusion.aiding.common import make
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.samples import HeadingSample, ImuBatch
from adaptnav.fusion.state import ACC_T, ATT, KS, N_ERR, POS, SLOW, VEL, X_KS, X_POS, X_POS_NE, X_VEL
from adaptnav.fusion.status import rejected
from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate

T_A, T_B = 70.0, 235.0  # after the last USBL fix; the end of the run
SIGMA_M = 0.5           # the closure's own noise (m, per axis)


def _run(seed: int, offset_bias_m=(0.0, 0.0)):
    """Short survey, USBL lost at 60 s, k_V 1 → 0.9 at 100 s; one closure between T_A and T_B
    whose offset is the filter's true error difference e(T_A) − e(T_B) plus noise."""
    sc = load_scenario("short", [f"seed={seed}", "duration_s=240.0", "usbl.lost_after_s=60.0",
                                 "environment.change_at_s=100.0"])
    res = simulate(sc)
    cfg = build_config(sc)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    dense = res.dense
    rng = np.random.default_rng(seed)
    clones: dict[float, np.ndarray] = {}
    for item in res.iter_blocks():
        est.process(item)
        if item.KIND == "imu_batch" and est.clone_position():
            ns = est.nav_state()
            clones[ns.t_s] = ns.pos_n_m[:2].copy()

    def err(t):
        k = int(np.argmin(np.abs(dense.t_s - t)))
        return clones[t] - dense.pos_n_m[k, :2]

    ta = min(clones, key=lambda t: abs(t - T_A))
    tb = min(clones, key=lambda t: abs(t - T_B))
    offset = err(ta) - err(tb) + rng.normal(0.0, SIGMA_M, 2) + np.asarray(offset_bias_m)
    ns0 = est.nav_state()
    k = int(np.argmin(np.abs(dense.t_s - ns0.t_s)))
    before = ns0.pos_n_m[:2] - dense.pos_n_m[k, :2]
    status = est.fuse_loop_closure(ta, tb, offset, np.eye(2) * SIGMA_M ** 2)
    ns1 = est.nav_state()
    after = ns1.pos_n_m[:2] - dense.pos_n_m[k, :2]
    nees = float(after @ np.linalg.solve(ns1.cov[:2, :2], after))
    return status, before, after, err(ta), nees, est


@pytest.mark.parametrize("seed", [1])
def test_closure_that_disagrees_is_gated_and_one_before_any_clone_is_too_late(seed):
    status, before, after, _, _, est = _run(seed, offset_bias_m=(80.0, -60.0))
    assert status.source == "loop_closure" and not status.fused and status.reason == "gate"
    assert np.allclose(before, after)
    # the error difference of two epochs of one outage is smaller than the later epoch's
    # error (its common part cancels): the gate a loop closure's association needs
    rel = est.relative_position_covariance(T_A, T_B)
    assert np.all(np.linalg.eigvalsh(rel) > 0)
    assert np.trace(rel) < np.trace(est.nav_state().cov[:2, :2])
    assert est.relative_position_covariance(-500.0, T_B) is None
    early = est.fuse_loop_closure(-500.0, T_B, np.zeros(2), np.eye(2))
    assert not early.fused and early.reason == "too_late"
    assert est.fuse_loop_closure(T_A, T_B, np.array([np.nan, 0.0]), np.eye(2)).reason == "invalid"


def test_closure_removes_the_drift_between_the_two_epochs_consistently():
    errs_before, errs_after, errs_a, nees = [], [], [], []
    for seed in (1, 2, 3, 4):
        status, before, after, e_a, n, _ = _run(seed)
        assert status.fused and status.source == "loop_closure" and status.test_ratio < 1.0
        errs_before.append(np.linalg.norm(before))
        errs_after.append(np.linalg.norm(after))
        errs_a.append(np.linalg.norm(e_a))
        nees.append(n)
    # the error falls back towards what it was at T_A (plus the little drift since T_B)
    assert np.mean(errs_after) < 0.5 * np.mean(errs_before), (errs_before, errs_after)
    assert np.mean(errs_after) < np.mean(errs_a) + 2.0
    # consistent: mean NEES of the horizontal position (2 dof) within a generous χ² band
    assert np.mean(nees) < 2.0 * 2.5, nees


# ---------------------------------------------------------------- resets while clones exist
def _filter_with_clones():
    """An estimator 100 s into the short survey (USBL lost at 60 s), cloning every period,
    stopped just after a clone: (estimator, clone times, the IMU samples that follow)."""
    sc = load_scenario("short", ["seed=2", "duration_s=110.0", "usbl.lost_after_s=60.0"])
    res = simulate(sc)
    cfg = build_config(sc)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    clone_t = []
    for item in res.iter_blocks():
        est.process(item)
        if item.KIND == "imu_batch" and est.clone_position():
            clone_t.append(est.nav_state().t_s)
            if clone_t[-1] > 100.0:
                break
    k = int(np.searchsorted(res.imu.t_s, clone_t[-1], side="right"))
    imu = (res.imu.t_s[k:], res.imu.specific_force_b_m_s2[k:], res.imu.omega_b_rad_s[k:])
    return est, clone_t, imu


def _propagate_part(est, imu, start: int, n: int) -> np.ndarray:
    """``n`` IMU samples into the state without a covariance step (the pending step grows);
    returns Φ of the pending step, as the next flush will compute it."""
    t, f, w = (a[start:start + n] for a in imu)
    kalman.propagate_core(t, f, w, est._core, est._qdiag, 1e9)
    assert est._acc[ACC_T] > 0.0
    return kalman.transition(est._acc.copy(), est._acc[ACC_T])


def _flush_bf(J, Phi, qdiag, T):
    """The brute-force augmented filter's covariance step: the 18 states step, the clones stay."""
    J = J.copy()
    J[:N_ERR, :N_ERR] = kalman.covariance_step(J[:N_ERR, :N_ERR], Phi, qdiag, T)
    J[:N_ERR, N_ERR:] = Phi @ J[:N_ERR, N_ERR:]
    J[N_ERR:, :N_ERR] = J[:N_ERR, N_ERR:].T
    return J


def _reset(est, what: str):
    """Apply one of the estimator's resets; returns the error-state rows it replaced (or
    inflated) and whether they are replaced by independent values (else: noise added)."""
    x = est._x
    status = rejected(float(est._clock[0]), "dvl" if what == "velocity" else "attitude", "gate")
    if what == "velocity":
        v = x[X_VEL].copy()
        H = np.zeros((3, N_ERR))
        H[:, VEL] = np.eye(3)
        est._reset_velocity(make(v + np.array([0.3, -0.2, 0.05]), H, np.eye(3) * 0.01, v), status)
        return VEL, True
    if what == "attitude":
        roll, pitch, yaw = aid_attitude.predict(x)
        sample = SimpleNamespace(roll_rad=roll + 0.01, pitch_rad=pitch - 0.01, yaw_rad=yaw + 0.1)
        z = [sample.roll_rad, sample.pitch_rad, sample.yaw_rad]
        est._reset_attitude(sample, make(z, np.zeros((3, N_ERR)), np.diag([1e-4, 1e-4, 1e-3]), z), status)
        return ATT, True
    if what == "slow_states":  # a restart's saved biases, current and k_speed
        saved = est.slow_states()
        saved.update(current_n_m_s=[0.05, -0.02], k_speed=1.05)
        est.restore_slow_states(saved)
        return SLOW, True
    est._doubt_k_speed()
    return KS, False


@pytest.mark.parametrize("what", ["velocity", "attitude", "slow_states", "k_speed_doubt"])
def test_reset_between_clones_and_closure_matches_the_augmented_filter(what):
    """A reset while clones exist, then a loop closure: the filter's covariance, correction and
    the clones' cross-covariances equal those of a brute-force filter that carries the clones
    as (consider) states and applies the same reset to the whole augmented covariance: a
    replaced state is independent of the clones (its cross-covariances zero), a doubted one
    only has its variance grown. (Before the fix the clones kept a reset state's old
    cross-covariances and the closure corrected the new velocity or attitude by them.)"""
    est, clone_t, imu = _filter_with_clones()
    bank = est._clones
    n = len(bank.t_s)
    a, b = bank.nearest(60.0), n - 1
    J = bank.joint_covariance(est._P)
    qdiag = est._qdiag.copy()
    # part of a covariance step pending: the reset's own flush takes it first
    Phi, T = _propagate_part(est, imu, 0, 4), float(est._acc[ACC_T])
    J = _flush_bf(J, Phi, qdiag, T)
    rows, replaced = _reset(est, what)
    if replaced:
        J[rows, :] = 0.0
        J[:, rows] = 0.0
    J[rows, rows] = est._P[rows, rows]
    np.testing.assert_allclose(J[:N_ERR, :N_ERR], est._P, rtol=0, atol=1e-12 * np.abs(J).max())
    # a pending step again: the zeroed rows must have gone into the clones' map before it
    Phi, T = _propagate_part(est, imu, 4, 5), float(est._acc[ACC_T])
    J = _flush_bf(J, Phi, qdiag, T)
    # the closure (Schmidt: the clones' estimates stay; Joseph form on the augmented state)
    y, R = np.array([0.6, -0.4]), np.eye(2) * 0.25
    H = np.zeros((2, J.shape[0]))
    H[:, N_ERR + 2 * a:N_ERR + 2 * a + 2] = -np.eye(2)
    H[:, N_ERR + 2 * b:N_ERR + 2 * b + 2] = np.eye(2)
    S = H @ J @ H.T + R
    K = np.zeros((J.shape[0], 2))
    K[:N_ERR] = J[:N_ERR] @ H.T @ np.linalg.inv(S)
    A = np.eye(J.shape[0]) - K @ H
    J = A @ J @ A.T + K @ R @ K.T
    dx = K[:N_ERR] @ y
    G = np.eye(J.shape[0])
    G[:N_ERR, :N_ERR] = aid_loop.reset_jacobian(dx)
    J = G @ J @ G.T
    x0 = est._x.copy()
    status = est.fuse_loop_closure(clone_t[a], clone_t[b], y, R)
    assert status.fused
    np.testing.assert_allclose(est._x[X_POS] - x0[X_POS], dx[POS], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est._x[X_VEL] - x0[X_VEL], dx[VEL], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est._x[X_KS] - x0[X_KS], dx[KS][0], rtol=1e-9, atol=1e-15)
    scale = np.abs(J).max()
    np.testing.assert_allclose(est._P, J[:N_ERR, :N_ERR], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(bank.joint_covariance(est._P), J, rtol=0, atol=1e-10 * scale)


def test_loop_closure_survives_a_second_late_measurement():
    """A late measurement re-runs the inputs since its time, the loop closure among them; a
    second late one older than the closure re-runs them again: the closure must still be
    there (it was re-run but not recorded again, and the second re-run lost it)."""
    ends = []
    for with_closure in (True, False):
        est, clone_t, imu = _filter_with_clones()
        t_end = float(est._clock[0])
        if with_closure:
            st = est.fuse_loop_closure(clone_t[-8], clone_t[-1], np.array([3.0, -2.0]), np.eye(2) * 0.25)
            assert st.fused
        est.process(ImuBatch(*(a[:50] for a in imu)))
        yaw = float(aid_attitude.predict(est._x)[2])
        for dt in (0.2, 0.1):  # both older than the closure's input (state time t_end)
            est.process(HeadingSample(t_s=t_end - dt, yaw_rad=yaw))
        assert est.late_fused == 2
        ends.append(est._x[X_POS_NE].copy())
    with_end, without_end = ends
    assert np.linalg.norm(with_end - without_end) > 2.0, (with_end, without_end)


def test_many_relative_covariances_are_the_single_ones_bit_for_bit():
    """The association's batch lookup (:meth:`CloneBank.nearest_many`, :meth:`CloneBank.relative_covs`)
    gives exactly what one call per time gives: ties half-way between clones, times outside every
    clone's period, clones older and newer than the other epoch, and the same clone."""
    *_, est = _run(1)
    cl = est._clones
    ts = np.array(cl.t_s)
    mid = 0.5 * (ts[:-1] + ts[1:])
    t = np.concatenate([ts, mid, mid + 1e-9, ts + 2.4, [-500.0, ts[0] - cl.period_s, ts[-1] + cl.period_s + 1.0]])
    near = cl.nearest_many(t)
    assert near.tolist() == [-1 if cl.nearest(v) is None else cl.nearest(v) for v in t.tolist()]
    for b in (0, len(ts) // 2, len(ts) - 1):
        a = near[near >= 0]
        many = cl.relative_covs(a, b)
        one = np.array([cl.relative_cov(k, b) for k in a.tolist()])
        assert many.tobytes() == one.tobytes()


def test_relative_covariances_from_the_rows_stacks_after_pruning_and_in_a_snapshot():
    """:meth:`CloneBank.relative_covs` and the columns of Σ :meth:`CloneBank.apply` uses
    gather from the rows' stacks: bit for bit what :meth:`CloneBank.relative_cov` and
    :meth:`CloneBank.sigma` read entry by entry, after clones were pruned (rows that
    start before the oldest kept clone), for older, newer and the same clone, with a Σ_bb that
    is not exactly symmetric (it is added as stored, not transposed), and in a snapshot taken
    before more clones were made (its rows are not the live bank's)."""
    rng = np.random.default_rng(7)
    bank = aid_loop.CloneBank(period_s=1.0, horizon_s=6.5)

    def clone(t):
        P = rng.standard_normal((N_ERR, N_ERR))
        P = P @ P.T + np.eye(N_ERR)
        P[0, 1] += 1e-3  # not symmetric in the last bits
        bank.transform(np.eye(N_ERR) + 0.1 * rng.standard_normal((N_ERR, N_ERR)))
        assert bank.maybe_clone(t, np.zeros(2), P)

    def check(cl):
        n = len(cl.t_s)
        for i in range(n):  # the columns apply() reads
            assert cl._sigma_column(i).tobytes() == np.array([cl.sigma(i, j) for j in range(n)]).tobytes()
        a = np.array([k for k in range(n) for _ in range(2)])
        for b in range(n):
            many = cl.relative_covs(a, b)
            one = np.array([cl.relative_cov(k, b) for k in a.tolist()])
            assert many.tobytes() == one.tobytes()

    for t in range(5):
        clone(float(t))
    snap = bank.copy()
    for t in range(5, 12):
        clone(float(t))
    assert bank.t_s[0] > 0.0  # pruned
    check(bank)
    check(snap)
    assert snap.relative_covs(np.array([0]), 4).tobytes() != bank.relative_covs(np.array([0]), 4).tobytes()


def test_a_restored_snapshot_reads_no_relative_covariance_of_the_discarded_clones():
    """The estimator restores a snapshot to fuse a late sample at its time and runs on from
    there: its next clone takes the id a discarded clone of the live bank had. A relative
    covariance the live bank computed for that id must not be read back for the new clone
    (the snapshot starts with its own cache)."""
    rng = np.random.default_rng(11)

    def clone(bank, t):
        P = rng.standard_normal((N_ERR, N_ERR))
        P = P @ P.T + np.eye(N_ERR)
        assert bank.maybe_clone(t, np.zeros(2), P)

    live = aid_loop.CloneBank(period_s=1.0, horizon_s=100.0)
    for t in range(3):
        clone(live, float(t))
    snap = live.copy()
    clone(live, 3.0)
    live.relative_cov(3, 0)  # cached for (id 3, id 0) in the live bank
    clone(snap, 3.0)  # the restored snapshot's own clone 3: another P
    want = snap.sigma(3, 3) + snap.sigma(0, 0) - snap.sigma(3, 0) - snap.sigma(0, 3)
    assert snap.relative_cov(3, 0).tobytes() == want.tobytes()
    assert snap.relative_covs(np.array([3]), 0)[0].tobytes() == want.tobytes()
