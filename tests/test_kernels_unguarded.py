"""kernels.unguarded: a hot path's call of a kernel without its argument guard gets the compiled
function only when the kernel is a guarded compiled one (its __wrapped__), else the kernel itself
(just in time: a numba dispatcher, whose __wrapped__ is the Python function; not built; a
stand-in). Where the callers use it and which arrays they pass: tests/fusion/test_unguarded_kernels.py."""
from __future__ import annotations

import pytest

from adaptnav import kernels
from adaptnav.kernels import unguarded


def test_a_guarded_kernel_gives_its_compiled_function():
    compiled = object()

    def call(*args):
        raise AssertionError("the guard was called")

    call.__wrapped__ = compiled
    call._kernel = ("adaptnav.fusion.kalman", "k")
    assert unguarded(call) is compiled


def test_anything_else_is_kept():
    numba = pytest.importorskip("numba")

    def py(x):
        return x + 1.0

    dispatcher = numba.njit(py)
    assert hasattr(dispatcher, "__wrapped__")  # (the Python function: never to be taken)
    assert unguarded(dispatcher) is dispatcher
    deferred = kernels._Deferred("adaptnav.fusion.kalman", "fuse_scalar_core")
    assert unguarded(deferred) is deferred
    stand_in = lambda *a: a  # noqa: E731 - a test's counting stand-in
    assert unguarded(stand_in) is stand_in


def test_a_real_guard_unwraps_to_the_function_it_guards():
    """kernels._guarded's own product (what jit returns ahead of time): its __wrapped__."""
    compiled = lambda a: ("compiled", a)  # noqa: E731
    fallback = lambda a: ("fallback", a)  # noqa: E731
    guard = kernels._guarded(compiled, [["float", "", 0, False]], fallback)
    guard._kernel = ("adaptnav.fusion.kalman", "k")
    assert guard("x") == ("fallback", "x")  # (the guard routes a non-number away)
    assert unguarded(guard) is compiled
