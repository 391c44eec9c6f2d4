"""The stationary window's quiet test on floats (eskf._rest_window_quiet) is the numpy one it
replaced, on seeded random windows and the edge cases (too few samples, NaN, inf, overflow)."""
import math

import numpy as np
import pytest

from adaptnav.fusion.eskf import _rest_window_quiet


def _quiet_numpy(st: np.ndarray, max_acc_std_m_s2: float, max_gyro_rad_s: float) -> bool:
    """The previous formulation (Estimator._rest_window_end before: numpy on the window's slices)."""
    n = st[1]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        var = st[5:8] / n - (st[2:5] / n) ** 2
    return bool(n >= 3 and float(np.sqrt(max(var.max(), 0.0))) <= max_acc_std_m_s2 and st[8] <= max_gyro_rad_s)


def _window(rng, n: int, acc_std: float, gyro: float) -> np.ndarray:
    f = rng.normal([0.1, -0.2, -9.8], acc_std, size=(n, 3))
    return np.array([rng.uniform(0, 100), float(n), *f.sum(0), *(f * f).sum(0), gyro])


def test_quiet_as_numpy_on_random_windows():
    rng = np.random.default_rng(52)
    verdicts = set()
    for _ in range(3000):
        n = int(rng.integers(0, 60))
        st = _window(rng, n, 10 ** rng.uniform(-4, 0), abs(rng.normal(0, 0.02)))
        max_acc, max_gyro = 10 ** rng.uniform(-3, -0.5), 10 ** rng.uniform(-3, -1)
        got = _rest_window_quiet(st.tolist(), max_acc, max_gyro)
        assert got == _quiet_numpy(st, max_acc, max_gyro)
        verdicts.add(got)
    assert verdicts == {True, False}


@pytest.mark.parametrize("index,value", [(2, math.nan), (6, math.nan), (8, math.nan), (3, math.inf),
                                         (7, math.inf), (4, 1e200), (5, 1e300), (1, 2.0), (1, 0.0),
                                         (1, math.nan), (6, -1.0)])
def test_quiet_as_numpy_on_edge_windows(index, value):
    st = _window(np.random.default_rng(7), 10, 1e-4, 1e-3)
    assert _rest_window_quiet(st.tolist(), 0.05, 0.01)  # the unmodified window is quiet
    st[index] = value
    assert _rest_window_quiet(st.tolist(), 0.05, 0.01) == _quiet_numpy(st, 0.05, 0.01)


def test_constant_samples_are_quiet():
    """Σf² / n − (Σf / n)² of identical samples rounds below zero on some axes (clipped) and
    to ~1e-14 (σ ~1.2e-7) on another: quiet within 1e-6, not within 1e-9."""
    f = np.full((7, 3), [0.3, -0.1, -9.80665])
    st = np.array([0.0, 7.0, *f.sum(0), *(f * f).sum(0), 0.0])
    assert _rest_window_quiet(st.tolist(), 1e-6, 0.0) and _quiet_numpy(st, 1e-6, 0.0)
    assert not _rest_window_quiet(st.tolist(), 1e-9, 0.0) and not _quiet_numpy(st, 1e-9, 0.0)
