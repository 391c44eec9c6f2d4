"""eskf._unguarded: the estimator's fast paths call the compiled aid updates without the guard
only when the kernel is a guarded compiled one (its __wrapped__), else the kernel itself (just in
time: a numba dispatcher, whose __wrapped__ is the Python function; not built; a stand-in); and
the arrays those calls take are what the guard checks for (C-contiguous float64, writeable)."""
from __future__ import annotations

import numpy as np
import pytest

from adaptnav import kernels
from adaptnav.fusion import kalman
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator, _unguarded
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

from .mission import ORIGIN


def test_a_guarded_kernel_gives_its_compiled_function():
    compiled = object()

    def call(*args):
        raise AssertionError("the guard was called")

    call.__wrapped__ = compiled
    call._kernel = ("adaptnav.fusion.kalman", "k")
    assert _unguarded(call) is compiled


def test_anything_else_is_kept():
    numba = pytest.importorskip("numba")

    def py(x):
        return x + 1.0

    dispatcher = numba.njit(py)
    assert hasattr(dispatcher, "__wrapped__")  # (the Python function: never to be taken)
    assert _unguarded(dispatcher) is dispatcher
    deferred = kernels._Deferred("adaptnav.fusion.kalman", "fuse_scalar_core")
    assert _unguarded(deferred) is deferred
    stand_in = lambda *a: a  # noqa: E731 - a test's counting stand-in
    assert _unguarded(stand_in) is stand_in


def test_the_estimator_calls_the_kernels_with_the_arrays_the_guard_wants():
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    for name in ("fuse_scalar_core", "fuse_heading_core", "fuse_vector_core"):
        kernel = getattr(kalman, name)
        want = kernel.__wrapped__ if hasattr(kernel, "_kernel") and hasattr(kernel, "__wrapped__") else kernel
        assert getattr(est, f"_{name}") is want
    meas = est._dvl_meas
    for a in (est._core, est._work, meas.z, meas.h, meas.H, meas.R):
        assert type(a) is np.ndarray and a.dtype == np.float64 and a.flags.carray
