"""A position reset needs consistent evidence (issue 12 item 3, issue 11 item 4): several
mutually consistent fixes, each within reach of the last accepted fix at the vehicle's
top speed. Spoofed fixes 1 km away, however many and however consistent among
themselves, must not move the solution; a filter that really drifted still resets."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.samples import HeadingSample, ImuBatch, RpmSample, UsblSample, replay_order_key

from .mission import ORIGIN, make_mission, run

SPOOF_FROM_S, N_SPOOF, SPOOF_PERIOD_S = 150.0, 10, 10.0


def _spoofed(m, offset_n_m=1000.0):
    """The real USBL replaced by a spoofer from ``SPOOF_FROM_S`` for ``N_SPOOF`` fixes that
    are consistent among themselves (they follow the true track, 1 km north)."""
    t_end = SPOOF_FROM_S + N_SPOOF * SPOOF_PERIOD_S
    aids = [s for s in m.aids if not (s.KIND == "usbl" and SPOOF_FROM_S <= s.t_s < t_end)]
    baseline = list(aids)
    for k in range(N_SPOOF):
        t = SPOOF_FROM_S + k * SPOOF_PERIOD_S + 0.5
        p = m.truth_at(t)["pos"].copy()
        p[0] += offset_n_m
        lat, lon, _ = ORIGIN.to_geodetic(p)
        aids.append(UsblSample(t, float(lat), float(lon), float(p[2]), 2.0))
    return sorted(aids, key=lambda s: replay_order_key(s, 0)), baseline


def _filter(cfg=FilterConfig()):
    return Estimator(cfg, MotionParams(), RpmSpeedTable(), ORIGIN)


def test_ten_spoofed_fixes_1_km_away_move_the_solution_less_than_3_sigma():
    m = make_mission(np.random.default_rng(5), 300.0, usbl_period_s=10.0)
    spoofed, baseline = _spoofed(m)
    probes = np.arange(SPOOF_FROM_S, 300.0, 5.0)
    m.aids = baseline
    ref = _filter()
    ref_states, _ = run(ref, m, probes)
    m.aids = spoofed
    est = _filter()
    states, statuses = run(est, m, probes)
    worst = 0.0
    for (_, s), (_, r) in zip(states, ref_states):
        sigma_h = np.sqrt(s.cov[0, 0] + s.cov[1, 1])
        worst = max(worst, np.linalg.norm(s.pos_n_m[:2] - r.pos_n_m[:2]) / sigma_h)
    assert worst < 3.0, f"the spoofer moved the solution by {worst:.1f} σ"
    assert est.rejected["position_reset"] == 0
    fakes = [a for a in statuses if a.source == "usbl" and SPOOF_FROM_S <= a.t_s < SPOOF_FROM_S + 100]
    assert len(fakes) == N_SPOOF and not any(a.fused for a in fakes)
    # nothing learned from the fakes: no bogus current left to persist
    cur = np.asarray(est.slow_states()["current_n_m_s"])
    assert np.linalg.norm(cur - np.asarray(ref.slow_states()["current_n_m_s"])) < 0.05


def _static_batch(t0, n, rate=100.0):
    t = t0 + np.arange(1, n + 1) / rate
    f = np.tile([0.0, 0.0, -GRAVITY_M_S2], (n, 1))
    return ImuBatch(t, f, np.zeros((n, 3)))


def test_a_wrong_start_is_reset_once_the_motion_since_the_accepted_fix_allows_it():
    # GIVEN a filter started on a fix at the origin (2 m), at rest
    est = _filter()
    lat0, lon0, _ = ORIGIN.to_geodetic(np.zeros(3))
    est.process(UsblSample(0.5, float(lat0), float(lon0), 0.0, 2.0))
    est.process(_static_batch(0.0, 100))
    est.process(HeadingSample(1.0, 0.0))
    assert est.initialized
    # WHEN fixes 200 m away arrive every second (the start fix was the wrong one)
    lat, lon, _ = ORIGIN.to_geodetic(np.array([0.0, 200.0, 0.0]))
    fixes = []
    for k in range(1, 120):
        est.process(RpmSample(k + 0.25, 0.0))  # the motion model says: at rest
        est.process(_static_batch(float(k), 100))
        fixes += est.process(UsblSample(1.0 + k, float(lat), float(lon), 0.0, 2.0))
    # THEN they are gated until 200 m are within reach of the start fix at 3 m/s (+ 3σ),
    # then the filter resets onto them, once, and reports the size
    reach_s = (200.0 - 3.0 * np.hypot(2.0, 2.0)) / 3.0
    (t_reset, source, size_m), = est.position_resets
    assert source == "usbl" and 0.5 + reach_s <= t_reset <= 0.5 + reach_s + 3.0
    assert all(f.reason == "gate" for f in fixes if f.t_s < t_reset)
    assert size_m == pytest.approx(200.0, abs=5.0)
    assert est.nav_state().pos_n_m[1] == pytest.approx(200.0, abs=5.0)
