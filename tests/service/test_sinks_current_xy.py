"""The sinks' sea current of a nav state (trajectory.csv's current columns, the recorder's
series): the same Python floats as the previous formulation, np.asarray(c, float).ravel()[:2]."""
from __future__ import annotations

import math
import types

import numpy as np
import pytest

from adaptnav.service.runtime.sinks import _current_xy


def _previous(c) -> tuple[float, float]:
    c0, c1 = np.asarray(c, dtype=float).ravel()[:2].tolist()
    return c0, c1


@pytest.mark.parametrize("current", [
    np.array([0.1234567890123, -0.2345678901234, 0.0]),
    np.array([0.3, 0.4]),
    np.array([[0.5, -0.25, 1.0]]),                       # a row vector
    np.array([1e-300, -1e300, 7.0]),
    np.array([-0.0, 0.0, 0.0]),                          # the sign of zero is kept
    np.array([math.nan, math.inf, 0.0]),
    np.array([0.1, 0.2, 0.3], dtype=np.float32),         # widened exactly, as asarray(float) does
    np.array([1, -2, 3]),                                # integers
    (0.7, -0.8, 0.0),                                    # a tuple of floats
    [np.float32(0.1), np.float64(-0.2), 0.0],            # numpy scalars in a list
    np.arange(12.0)[::4],                                # a strided view
])
def test_current_is_the_previous_formulations(current):
    got = _current_xy(types.SimpleNamespace(current_n_m_s=current))
    want = _previous(current)
    assert all(type(v) is float for v in got)
    assert [(math.copysign(1.0, v), v) if not math.isnan(v) else "nan" for v in got] == \
        [(math.copysign(1.0, v), v) if not math.isnan(v) else "nan" for v in want]
