"""GIVEN/WHEN/THEN scenarios of the navigation filter."""
from dataclasses import replace

import numpy as np

from adaptnav.fusion.config import LearnedVelocityConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

from .mission import ORIGIN, make_mission, run, true_error

GAP = (200.0, 260.0)


def _dvl_mission(seed):
    return make_mission(np.random.default_rng(seed), 360.0, dvl_period_s=1.0, dvl_gap=GAP,
                        usbl_period_s=None, static_s=5.0, current_n=(0.15, -0.05))


def _run(cfg, m):
    est = Estimator(cfg, MotionParams(), RpmSpeedTable(), ORIGIN)
    probes = [GAP[0] - 1.0, GAP[1] - 1.0, 355.0]
    states, statuses = run(est, m, probe_times=probes)
    return [(s, true_error(m, s, k)) for k, s in states], statuses


def test_dvl_lost_for_60_s_error_grows_as_the_motion_model_allows_then_recovers(matched_config):
    # GIVEN a survey with DVL bottom track at 1 Hz, RPM, heading and depth, no USBL
    m = _dvl_mission(7)
    # WHEN the DVL loses bottom lock for 60 s
    states, statuses = _run(matched_config, m)
    (before, e0), (end_gap, e1), (after, e2) = states
    dvl = [a for a in statuses if a.source == "dvl"]
    assert all(a.reason == "invalid" for a in dvl if GAP[0] <= a.t_s < GAP[1])
    assert all(a.fused for a in dvl if a.t_s >= GAP[1])
    # THEN the position variance grows during the gap by about what the motion model's
    # velocity noise allows (σ_V ≈ 0.075 m/s white at 2 Hz + the current's σ × 60 s):
    # a fraction of a metre to a few metres, not tens
    growth_m = np.sqrt(end_gap.cov[0, 0] + end_gap.cov[1, 1] - before.cov[0, 0] - before.cov[1, 1])
    assert 0.2 < growth_m < 3.0, growth_m
    # AND the actual drift over the gap is explained by that growth
    drift_m = np.linalg.norm(e1[:2] - e0[:2])
    assert drift_m <= 3.0 * growth_m, (drift_m, growth_m)
    # AND it recovers after: velocity uncertainty back to its level before the gap
    sv = lambda s: np.sqrt(s.cov[3, 3] + s.cov[4, 4])
    assert sv(end_gap) > 1.5 * sv(before)
    assert sv(after) < 1.2 * sv(before)
    assert np.linalg.norm(e2[3:5]) < 3 * sv(after)


def test_without_the_motion_model_the_same_gap_drifts_more(matched_config):
    # GIVEN the same mission WHEN the learned-velocity aid is off (pure INS in the gap)
    m = _dvl_mission(7)
    cfg_ins = replace(matched_config, learned_velocity=replace(LearnedVelocityConfig(), enabled=False))
    (b_m, e0m), (s_m, e1m), _ = _run(matched_config, m)[0]
    (b_i, e0i), (s_i, e1i), _ = _run(cfg_ins, m)[0]

    def growth(b, s):
        return np.sqrt(s.cov[0, 0] + s.cov[1, 1] - b.cov[0, 0] - b.cov[1, 1])

    # THEN the model-aided filter's uncertainty grows less over the gap, and so does its error
    assert growth(b_m, s_m) < 0.5 * growth(b_i, s_i)
    assert np.linalg.norm(e1m[:2] - e0m[:2]) < np.linalg.norm(e1i[:2] - e0i[:2]) + 0.5
