"""The output epoch's shortcuts in the estimator (fusion.eskf, fusion.frames, fusion.aiding.dvl):

- nav_state's covariance: the considered DVL terms added as Python floats and written back,
  the bit pattern of numpy's in-place additions entry by entry (and the density term after);
  its validity and reasons as invalid_reasons() says;
- the IMU run's history record made before the kernel's own check (no imu_clean call), taken
  out again when the run is not clean: the history of the general path, entry for entry;
- quat_to_euler's clamp without min/max: the pitch of min(1, max(-1, r20)), NaN included;
- the DVL consider term's memo made with the DVL sample: the next epoch finds it."""
from __future__ import annotations

import dataclasses
import math
import random
import struct

import numpy as np
import pytest

from adaptnav.fusion import frames
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import ImuBatch, ImuSample
from adaptnav.fusion.state import POS_D, X_DEPTH
from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate

from .mission import ORIGIN, make_mission, run
from .test_imu_fastpath import _mission


def _reference_cov(est: Estimator) -> np.ndarray:
    """The published covariance as numpy's in-place additions made it (no lever arm, no
    heading frame in this scenario)."""
    cov = est._cov_now()
    cal = est.dvl_calibration
    a00, a01, a10, a11 = cal.position_cov_ne_values()
    cov[0, 0] += a00
    cov[0, 1] += a01
    cov[1, 0] += a10
    cov[1, 1] += a11
    sigma_rho, rho = est._density_sigma_kg_m3
    if sigma_rho > 0.0:
        cov[POS_D, POS_D] += (float(est._x[X_DEPTH]) * sigma_rho / rho) ** 2
    return cov


def test_nav_state_covariance_is_the_in_place_additions():
    sc = load_scenario("short", ["seed=4", "duration_s=200.0", "dvl.enabled=true", "usbl.lost_after_s=60.0"])
    res = simulate(sc)
    cfg = build_config(sc)
    fcfg = dataclasses.replace(cfg.filter, depth=dataclasses.replace(cfg.filter.depth, density_sigma_kg_m3=5.0))
    est = Estimator(fcfg, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    compared = asymmetric = 0
    for k, item in enumerate(res.iter_blocks()):
        est.process(item)
        if k % 5 or not est.initialized:
            continue
        ref = _reference_cov(est)
        ns = est.nav_state()
        assert ns.cov.tobytes() == ref.tobytes()
        assert list(ns.invalid_reasons) == est.invalid_reasons() and ns.valid == (not ns.invalid_reasons)
        a = est.dvl_calibration.position_cov_ne_values()
        compared += any(a)
        asymmetric += a[1] != a[2]
    assert compared > 100 and asymmetric > 10, (compared, asymmetric)


def _history(est: Estimator) -> list:
    return [(kind, t, snap is None, [np.asarray(p).tobytes() for p in payload] if kind == "imu" else repr(payload))
            for t, (kind, payload, snap) in zip(est._hist_t, est._hist)] + [est._t_hist_snap]


class _Tail:
    """Feeds the estimator (each IMU sample alone for ``singles``) and keeps, after every input,
    the history's length, its newest entry (kind, time, with a snapshot) and the snapshot time."""

    def __init__(self, est, singles: bool):
        self.est, self.singles, self.tails = est, singles, []

    def _one(self, sample):
        out = self.est.process(sample)
        est = self.est
        newest = _history(est)[-2:] if est._hist else []
        self.tails.append((len(est._hist), newest, est._t_hist_snap))
        return out

    def process(self, sample):
        if not (self.singles and sample.KIND == "imu_batch"):
            return self._one(sample)
        out = []
        for t, f, w in zip(sample.t_s.tolist(), sample.specific_force_b_m_s2.tolist(), sample.omega_b_rad_s.tolist()):
            out += self._one(ImuSample(t, tuple(f), tuple(w)))
        return out


def _sparse_mission():
    """Aids once a second (the IMU runs take the history's snapshots between them) and
    duplicated stamps: runs handed back that the general path records nothing of."""
    m = make_mission(np.random.default_rng(29), 80.0, depth_m=0.0, static_s=20.0, usbl_period_s=None,
                     heading_period_s=1.0, depth_period_s=1.0)
    for k in np.searchsorted(m.t_imu, np.arange(50.0, 70.0, 0.37)):
        m.t_imu[k] = m.t_imu[k - 1]
    return m


@pytest.mark.parametrize("sparse", [False, True])
@pytest.mark.parametrize("max_batch", [None, 7, 1])  # 1: single ImuSamples
def test_the_imu_paths_history_is_the_general_paths(max_batch, sparse):
    # an IMU gap and a sample not finite, or duplicated stamps: runs handed back after their record
    m = _sparse_mission() if sparse else _mission()
    tails = []
    for fast in (True, False):
        est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
        if not fast:
            del est._fast[ImuBatch], est._fast[ImuSample]
        feed = _Tail(est, max_batch == 1)
        run(feed, m, max_batch=max_batch)
        assert (est.rejected["duplicate"] > 40) if sparse else (est.rejected["imu_gap"] == 1 and est.rejected["non_finite"] == 1)
        tails.append(feed.tails)
    assert len(tails[0]) > 300 and max(n for n, _, _ in tails[0]) > 50
    assert tails[0] == tails[1]


def test_quat_to_euler_clamps_as_min_max():
    rng = random.Random(11)
    quats = [(1.0, 0.0, 0.0, 0.0), (math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0), (math.sqrt(0.5), 0.0, -math.sqrt(0.5), 0.0),
             (0.5, 0.5, 0.5, 0.5), (math.nan, 0.0, 0.0, 0.0), (1.0, math.inf, 0.0, 0.0), (0.0, -0.0, 0.0, -0.0)]
    for _ in range(20000):
        q = np.array([rng.gauss(0.0, 1.0) for _ in range(4)])
        q *= rng.choice([1.0, 1.0 + 1e-12, 1.0 - 1e-12, 2.0]) / np.linalg.norm(q)
        quats.append(tuple(q.tolist()))
        w, x, y, z = q
        quats.append((w, -w if rng.random() < 0.5 else w, z, z))  # pitch near ±90°: r20 at ±1
    clamped = 0
    for q in quats:
        w, x, y, z = q
        r20 = 2.0 * (x * z - w * y)
        want = -math.asin(min(1.0, max(-1.0, r20)))
        clamped += not -1.0 <= r20 <= 1.0
        got = frames.quat_to_euler(np.array(q))[1]
        assert struct.pack("<d", got) == struct.pack("<d", want) or (math.isnan(got) and math.isnan(want)), q
    assert clamped > 100


def test_the_dvl_sample_leaves_the_epoch_its_consider_memo():
    sc = load_scenario("short", ["seed=4", "duration_s=120.0", "dvl.enabled=true"])
    res = simulate(sc)
    cfg = build_config(sc)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    cal = est.dvl_calibration
    after_dvl = 0
    for item in res.iter_blocks():
        est.process(item)
        if item.KIND == "dvl" and cal._fix is not None:
            memo = cal._cov_ne_memo
            est.nav_state()
            assert cal._cov_ne_memo is memo  # found, not made again
            after_dvl += 1
    assert after_dvl > 100
