"""Leg-to-leg loop closures in the filter (fusion/aiding/loop_closure.py, stochastic clones):
fused between two past epochs, the drift between them removed, the result consistent."""
from __future__ import annotations

import numpy as np
import pytest

from adaptnav.fusion.eskf import Estimator
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
