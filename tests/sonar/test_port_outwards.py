"""The port half outwards as a contiguous flipped copy (objects._port_outwards) against the
reversed view it replaced: the same values, and the detector's sightings the same."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from adaptnav.sonar import objects
from adaptnav.sonar.objects import ObjectDetectorConfig, _port_outwards, detect_objects
from adaptnav.sonar.waterfall import Waterfall

from .test_detector_prefilters import _near_image


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape, w", [((200, 1000), 500), ((7, 60), 30), ((1, 8), 4), ((5, 9), 1), ((5, 8), 0),
                                      ((0, 10), 5), ((6, 200), 37)])
def test_port_outwards_is_the_reversed_view(dtype, shape, w):
    rng = np.random.default_rng(3)
    lev = rng.gamma(2.0, 0.5, shape).astype(dtype)
    if lev.size:
        lev.flat[::7] = np.nan
        lev.flat[::11] = np.inf
    got, want = _port_outwards(lev, w), lev[:, w - 1::-1] if w > 0 else lev[:, w - 1::-1]
    assert got.shape == want.shape and got.dtype == want.dtype
    assert np.ascontiguousarray(got).tobytes() == np.ascontiguousarray(want).tobytes()
    if dtype == np.float32 and w > 0 and shape[0] > 0:
        assert got.flags.c_contiguous


def _shadow_image(rng, rows=180, cols=400):
    """Speckle, bright faces and the dark shadows beyond them on both sides, some near the nadir."""
    img = _near_image(rng, rows, cols)
    for _ in range(int(rng.integers(20, 40))):
        r, c = int(rng.integers(0, rows - 15)), int(rng.integers(40, cols - 40))
        h, w, L = int(rng.integers(2, 12)), int(rng.integers(1, 4)), int(rng.integers(3, 25))
        side = 1 if rng.random() < 0.5 else -1
        if side > 0:
            img[r:r + h, cols + c:cols + c + w] *= rng.uniform(2.0, 6.0)
            img[r:r + h, cols + c + w:cols + c + w + L] *= rng.uniform(0.0, 0.3)
        else:
            img[r:r + h, cols - c - w:cols - c] *= rng.uniform(2.0, 6.0)
            img[r:r + h, max(cols - c - w - L, 0):cols - c - w] *= rng.uniform(0.0, 0.3)
    return img


def test_detector_sightings_are_those_of_the_reversed_view(monkeypatch):
    rng = np.random.default_rng(54)
    found = 0
    for trial in range(6):
        rows = 180
        raw = _shadow_image(rng, rows)
        img = raw.copy()
        img[1:-1, 1:-1] = np.median(np.stack([raw[1 + a:rows - 1 + a, 1 + b:raw.shape[1] - 1 + b]
                                              for a in (-1, 0, 1) for b in (-1, 0, 1)]), axis=0)
        along = np.cumsum(rng.uniform(0.12, 0.2, rows))
        wf = Waterfall(img, 0.1, float(np.median(np.diff(along))), np.arange(rows) * 0.1 + 50.0, along,
                       rng.uniform(-3, 3, rows), np.arange(rows, dtype=float), rng.uniform(6.0, 12.0, (rows, 2)))
        config = ObjectDetectorConfig(min_contrast=3.0, short_min_contrast=2.0, compact_min_contrast=2.5,
                                      min_height_m=0.0)
        got = detect_objects(wf, along, config, unfiltered=raw, work={})
        with monkeypatch.context() as m:
            m.setattr(objects, "_port_outwards", lambda lev, w: lev[:, w - 1::-1])
            want = detect_objects(wf, along, config, unfiltered=raw, work={})
        assert pickle.dumps(got) == pickle.dumps(want)
        found += sum(o.side == "port" for o in got)
    assert found > 10
