"""heading.predict (the yaw alone) is, bit for bit, the yaw of common.euler_of(common.dcm(x)) it
was: seeded random attitudes (unit and not quite unit quaternions), level, upside down, pitch
±90°, and NaN."""
import math

import numpy as np
import pytest

from adaptnav.fusion.aiding import heading
from adaptnav.fusion.aiding.common import dcm, euler_of
from adaptnav.fusion.state import X_Q, initial_nominal


def _reference(x) -> np.ndarray:
    return euler_of(dcm(x))[2:3]


def _state(q) -> np.ndarray:
    x = initial_nominal()
    x[X_Q] = q
    return x


def test_as_euler_of_on_random_attitudes():
    rng = np.random.default_rng(52)
    for _ in range(20000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= 1.0 + rng.normal(0.0, 1e-6)  # (a quaternion between normalisations)
        x = _state(q)
        got, ref = heading.predict(x), _reference(x)
        assert got.shape == ref.shape == (1,) and got.dtype == ref.dtype
        assert got.tobytes() == ref.tobytes()


@pytest.mark.parametrize("q", [(1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                               (math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0), (math.sqrt(0.5), 0.0, -math.sqrt(0.5), 0.0),
                               (0.5, 0.5, 0.5, 0.5), (math.nan, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, math.inf)])
def test_as_euler_of_on_edges(q):
    x = _state(q)
    assert heading.predict(x).tobytes() == _reference(x).tobytes()
