"""The hot paths that call compiled kernels without their guard (adaptnav.kernels.unguarded) take
the compiled function when the kernel is built, and pass only what the guard would have let
through every time: C-contiguous, writeable float64 arrays of their own (the estimator's core,
scratch and their views, the learned velocity's kit, a snapshot's core; the DVL model's arrays;
DepthNoise's window), never a sample's or a batch's."""
from __future__ import annotations

import dataclasses

import numpy as np

from adaptnav.fusion import eskf, kalman
from adaptnav.fusion.aiding import depth as aid_depth
from adaptnav.fusion.aiding import dvl as aid_dvl
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

from adaptnav.fusion.samples import DvlSample

from .mission import ORIGIN, make_mission, run
from .test_aid_fastpath import _Delayed


def _want(kernel):
    return kernel.__wrapped__ if hasattr(kernel, "_kernel") and hasattr(kernel, "__wrapped__") else kernel


def _native(a) -> bool:
    return type(a) is np.ndarray and a.dtype == np.float64 and a.flags.carray


def test_the_estimator_takes_the_compiled_functions_and_passes_its_own_arrays():
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    for name in ("fuse_scalar_core", "fuse_heading_core", "fuse_vector_core", "propagated_covariance",
                 "lv_epoch", "core_positive_definite"):
        assert getattr(est, f"_{name}") is _want(getattr(kalman, name))
    assert aid_dvl._bottom_track_core is _want(kalman.dvl_bottom_track_core)
    assert aid_depth._median_window_push is _want(kalman.median_window_push)
    meas = est._dvl_meas
    for a in (est._core, est._work, est._P, est._acc, est._qdiag, est._dx, meas.z, meas.h, meas.H, meas.R,
              est._dvl_consts, est.depth_noise._window, est._snapshot().core):
        assert _native(a)
    assert est._P.shape == (kalman.N_ERR, kalman.N_ERR) and est._dvl_consts.shape == (kalman.DVL_CONST_SIZE,)


def test_every_unguarded_call_of_a_mission_gets_what_its_guard_wants(monkeypatch):
    """Each unguarded kernel replaced by a checker of its arguments (arrays: C-contiguous
    writeable float64; the rest numbers or bools) around the kernel, over a mission with DVL,
    depth, heading, USBL and the learned velocity, late samples and output states included:
    every unguarded kernel called, every call checked."""
    names = {id(getattr(kalman, n)): n for n in _UNGUARDED}
    calls: dict[str, int] = {}

    def checking(kernel):
        name = names[id(kernel)]

        def call(*args):
            for a in args:
                ok = _native(a) if isinstance(a, np.ndarray) else isinstance(a, (bool, int, float, np.number))
                assert ok, (name, type(a), getattr(a, "flags", None))
            calls[name] = calls.get(name, 0) + 1
            return kernel(*args)
        return call

    monkeypatch.setattr(eskf, "unguarded", checking)
    monkeypatch.setattr(aid_dvl, "_bottom_track_core", checking(kalman.dvl_bottom_track_core))
    monkeypatch.setattr(aid_depth, "_median_window_push", checking(kalman.median_window_push))
    m = make_mission(np.random.default_rng(29), 120.0, heading_period_s=0.5, depth_period_s=0.2,
                     dvl_period_s=0.2, usbl_period_s=5.0)
    aids = []
    for s in m.aids:
        aids.append(s)
        if isinstance(s, DvlSample) and any(abs(s.t_s - t) < 0.05 for t in (60.0, 90.0)):
            aids.append(_Delayed(dataclasses.replace(s, t_s=s.t_s - 0.4), s.t_s))  # fused late
    m.aids = aids
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    run(est, m, probe_times=np.arange(1.03, 120.0, 0.5))  # (between covariance steps)
    assert est.late_fused >= 1
    assert set(calls) == set(_UNGUARDED), calls
    assert min(calls.values()) > 10, calls


_UNGUARDED = ("fuse_scalar_core", "fuse_heading_core", "fuse_vector_core", "propagated_covariance", "lv_epoch",
              "core_positive_definite", "dvl_bottom_track_core", "median_window_push")
