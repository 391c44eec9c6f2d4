"""eskf._all_finite (the state's finiteness test of nav_state and horizontal_nav: its sum first)
is numpy's isfinite().all() on seeded random vectors and the edge cases: NaN, ±inf, both infs
(a NaN sum), finite values whose sum overflows, nothing."""
import math

import numpy as np
import pytest

from adaptnav.fusion.eskf import _all_finite


def test_as_numpy_on_random_vectors():
    rng = np.random.default_rng(52)
    seen = set()
    for _ in range(2000):
        x = rng.normal(0.0, 10 ** rng.uniform(-3, 306), 19)
        for i in rng.integers(0, 19, int(rng.integers(0, 3))):
            x[i] = rng.choice([math.nan, math.inf, -math.inf])
        got = _all_finite(x.tolist())
        assert got == bool(np.isfinite(x).all())
        seen.add(got)
    assert seen == {True, False}


@pytest.mark.parametrize("values", [[], [0.0], [math.nan], [1.0, math.inf], [-math.inf, 2.0],
                                    [math.inf, -math.inf], [1e308, 1e308], [-1e308, -1e308, 5.0],
                                    [1e308, 1e308, math.nan], [1e308, -1e308, math.inf]])
def test_as_numpy_on_edges(values):
    assert _all_finite(list(values)) == bool(np.isfinite(np.array(values, dtype=float)).all())
