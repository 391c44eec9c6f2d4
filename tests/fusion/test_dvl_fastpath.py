"""The DVL's compiled path (Estimator._fast_dvl, kalman.fuse_vector_core) against the general
one (Estimator._aid, _fuse) on a seeded simulated mission with the scale/misalignment
calibration on: the same numbers bit for bit — the whole core array, every status, the
calibration's state — also for the samples the compiled path leaves to the general one (no
lock, water track, not finite, late) and those it answers itself without fusing (gated, a
velocity reset after a long rejection)."""
import dataclasses
import math

import numpy as np

from adaptnav.fusion import eskf
from adaptnav.fusion.samples import DvlSample, UsblSample

from .mission import ORIGIN, make_mission
from .test_aid_fastpath import _Delayed, _run, assert_same_filter


def _mission():
    m = make_mission(np.random.default_rng(23), 240.0, heading_period_s=0.5, depth_period_s=0.5,
                     dvl_period_s=0.2, usbl_period_s=5.0, dvl_gap=(150.0, 152.0))
    aids = []
    for s in m.aids:
        if isinstance(s, DvlSample):
            if 100.0 <= s.t_s < 101.0:  # 0.5 m/s off for a second: gated
                s = dataclasses.replace(s, vel_d_m_s=(s.vel_d_m_s[0] + 0.5, *s.vel_d_m_s[1:]))
            elif 170.0 <= s.t_s < 183.0:  # 2 m/s off for longer than reset.velocity_after_s: a reset
                s = dataclasses.replace(s, vel_d_m_s=(s.vel_d_m_s[0] + 2.0, *s.vel_d_m_s[1:]))
            elif 120.0 <= s.t_s < 122.0:  # water track (the fallback without bottom lock)
                s = dataclasses.replace(s, water_track=True)
            elif any(abs(s.t_s - t) < 0.05 for t in (130.0, 131.0)):
                s = dataclasses.replace(s, vel_d_m_s=(math.nan, 0.0, 0.0))  # not finite
            elif any(abs(s.t_s - t) < 0.05 for t in (135.0, 136.0)):
                s = dataclasses.replace(s, sigma_m_s=0.2)  # the head says it is worse than configured
        aids.append(s)
        if isinstance(s, DvlSample) and any(abs(s.t_s - t) < 0.05 for t in (90.0, 140.0)):
            # measured 0.4 s before it arrives: fused at its own time, the inputs since re-run
            late = dataclasses.replace(s, t_s=s.t_s - 0.4)
            aids.append(_Delayed(late, s.t_s))
    m.aids = aids
    return m


def test_the_compiled_dvl_path_gives_the_general_paths_numbers(monkeypatch):
    m = _mission()
    assert any(isinstance(s, UsblSample) for s in m.aids)  # fixes: the calibration's track counts
    slow, slow_statuses = _run(m, fast=False)
    calls = []
    kernel = eskf.kalman.fuse_vector_core
    monkeypatch.setattr(eskf.kalman, "fuse_vector_core", lambda *a: calls.append(a[2].size) or kernel(*a))
    fast, fast_statuses = _run(m, fast=True)
    assert calls.count(3) > 800  # most DVL samples took the compiled path
    # and the samples around it happened: gated, a velocity reset, no lock, water track, not finite, late
    dvl = [s for s in fast_statuses if s.source == "dvl"]
    assert any(s.reason == "gate" for s in dvl)
    assert fast.resets["velocity:dvl"] >= 1
    assert any(s.reason == "invalid" for s in dvl)
    assert fast.rejected["non_finite"] == 2 and fast.late_fused == 2
    assert any(s.fused and s.innovation_variance[0] > 0.2**2 for s in dvl)  # the head's own σ
    cal, cal_slow = fast.dvl_calibration, slow.dvl_calibration
    assert cal.pairs_used + cal.segments_used + cal.segments_rejected > 0  # the calibration learned
    assert_same_filter(fast, fast_statuses, slow, slow_statuses)
    assert (fast._t_dvl_lock, fast._t_dvl_fused) == (slow._t_dvl_lock, slow._t_dvl_fused)
    assert cal.theta.tobytes() == cal_slow.theta.tobytes() and cal.P.tobytes() == cal_slow.P.tobytes()
    assert cal.position_cov_ne().tobytes() == cal_slow.position_cov_ne().tobytes()
    assert cal.report() == cal_slow.report()
    legs, legs_slow = cal.straight_legs, cal_slow.straight_legs  # the straight legs' running sums
    assert (legs._sums, list(legs._headings), legs._straight_since) == \
        (legs_slow._sums, list(legs_slow._headings), legs_slow._straight_since)

