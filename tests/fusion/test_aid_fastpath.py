"""The compiled path of depth and heading (Estimator._fast_scalar, kalman.fuse_scalar_core)
against the general one (Estimator._aid) on a seeded simulated mission: the same numbers bit
for bit — state and covariance (the whole core array), every status — also where the compiled
path hands a sample back (gated, a reset after a long rejection, not finite, late)."""
import dataclasses
import math

import numpy as np
import pytest

from adaptnav.fusion import eskf
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import DepthSample, HeadingSample

from .mission import ATM_PA, ORIGIN, RHO, make_mission, run


class _Delayed:
    """Stands in for the transport: hands over ``sample`` when the stream reaches ``t_s``."""

    KIND = "delayed"

    def __init__(self, sample, t_s):
        self.sample, self.t_s = sample, t_s


def _mission():
    m = make_mission(np.random.default_rng(17), 150.0, heading_period_s=0.2, depth_period_s=0.2,
                     dvl_period_s=0.5, usbl_period_s=10.0)
    aids = []
    for s in m.aids:
        if isinstance(s, HeadingSample) and 60.0 <= s.t_s < 68.0:
            # a compass 1 rad off for longer than reset.attitude_after_s: gated, then a reset
            s = dataclasses.replace(s, yaw_rad=math.remainder(s.yaw_rad + 1.0, 2.0 * math.pi))
        elif isinstance(s, DepthSample) and 80.0 <= s.t_s < 81.0:
            s = dataclasses.replace(s, pressure_pa=s.pressure_pa + 5e4)  # 5 m too deep: gated
        aids.append(s)
        if isinstance(s, HeadingSample) and any(abs(s.t_s - t) < 0.05 for t in (90.0, 95.0)):
            aids.append(HeadingSample(s.t_s, math.nan))  # not finite
            # measured 0.5 s before it arrives: fused at its own time, the inputs since re-run
            aids.append(_Delayed(DepthSample(s.t_s - 0.5, ATM_PA + RHO * GRAVITY_M_S2 * 10.0), s.t_s))
    m.aids = aids
    return m


def _run(m, fast: bool):
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    if not fast:
        est._fast = {}
    _, statuses = run(est, m)
    return est, statuses


def test_the_compiled_aid_path_gives_the_general_paths_numbers(monkeypatch):
    m = _mission()
    slow, slow_statuses = _run(m, fast=False)
    calls = []
    kernel, heading_kernel = eskf.kalman.fuse_scalar_core, eskf.kalman.fuse_heading_core
    monkeypatch.setattr(eskf.kalman, "fuse_scalar_core", lambda *a: calls.append(a[6]) or kernel(*a))
    monkeypatch.setattr(eskf.kalman, "fuse_heading_core", lambda *a: calls.append(True) or heading_kernel(*a))
    fast, fast_statuses = _run(m, fast=True)
    # both kinds went through the compiled path (depth: not angular; heading: its own kernel), most samples of each
    assert calls.count(False) > 500 and calls.count(True) > 500
    # and the samples it hands back happened: gated, reset, not finite, late
    assert fast.resets["attitude:heading"] >= 1
    assert any(s.source == "depth" and s.reason == "gate" for s in fast_statuses)
    assert fast.rejected["non_finite"] == 2 and fast.late_fused == 2
    assert_same_filter(fast, fast_statuses, slow, slow_statuses)
    assert fast.depth_noise.report() == slow.depth_noise.report()


def assert_same_filter(fast, fast_statuses, slow, slow_statuses):
    """Two estimators and their statuses bit for bit (also tests/fusion/test_dvl_fastpath.py)."""
    assert repr(fast_statuses) == repr(slow_statuses)  # repr: NaN test ratios compare equal
    assert fast._core.tobytes() == slow._core.tobytes()  # x, P, accumulators, clock
    assert fast._qdiag.tobytes() == slow._qdiag.tobytes()
    assert (fast.rejected, fast.resets, fast._reset_counter) == (slow.rejected, slow.resets, slow._reset_counter)
    assert fast.invalid_reasons() == slow.invalid_reasons()


@pytest.mark.parametrize("kind", ["depth", "heading", "dvl"])
def test_an_aid_off_or_at_a_lever_arm_takes_the_general_path(kind):
    """(The DVL's lever arm is in its own model: it takes the compiled path at any arm.)"""
    cfg = FilterConfig()
    off = Estimator(dataclasses.replace(cfg, **{kind: dataclasses.replace(getattr(cfg, kind), enabled=False)}),
                    MotionParams(), RpmSpeedTable(), ORIGIN)
    assert {t.KIND for t in off._fast} == {"imu", "imu_batch", "depth", "heading", "dvl"} - {kind}
    if kind == "depth":
        armed = Estimator(dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, lever_arm_b_m=(0.3, 0.0, 0.1))),
                          MotionParams(), RpmSpeedTable(), ORIGIN)
        assert {t.KIND for t in armed._fast} == {"imu", "imu_batch", "heading", "dvl"}
