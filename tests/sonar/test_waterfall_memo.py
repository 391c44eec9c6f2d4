"""Values the waterfall and the detector compute once and share."""
from __future__ import annotations

import numpy as np

from adaptnav.sonar.objects import _gaussian_weights
from adaptnav.sonar.waterfall import Waterfall


def test_unwrapped_heading_is_numpys_and_made_once():
    rng = np.random.default_rng(5)
    rows = 50
    heading = np.cumsum(rng.normal(0.0, 0.8, rows)) % (2 * np.pi) - np.pi  # wraps often
    wf = Waterfall(np.ones((rows, 8), np.float32), 0.1, 0.15, np.arange(rows) * 0.1, np.arange(rows) * 0.15,
                   heading, np.arange(rows, dtype=float), np.full((rows, 2), 8.0))
    u = wf.heading_unwrapped_rad
    assert np.array_equal(u, np.unwrap(heading)) and not np.array_equal(u, heading)
    assert wf.heading_unwrapped_rad is u
    assert wf.rows(10, 20).heading_unwrapped_rad.tobytes() == np.unwrap(heading[10:20]).tobytes()


def test_gaussian_weights_are_scipys_and_shared():
    from scipy.ndimage import gaussian_filter1d

    for sigma in (0.5, 0.7, 1.3):
        w = _gaussian_weights(sigma)
        impulse = np.zeros(2 * w.size + 1)
        impulse[w.size] = 1.0
        ref = gaussian_filter1d(impulse, sigma)[w.size - w.size // 2:w.size + w.size // 2 + 1]
        np.testing.assert_allclose(w, ref[::-1], rtol=1e-15, atol=0)
        assert _gaussian_weights(sigma) is w
