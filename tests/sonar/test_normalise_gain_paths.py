"""normalise_gain's shortcuts (the data mask tested once for both medians; a waterfall's columns
without data zeroed by slices) against the plain steps: medians by numpy.nanmedian, the mask over
the whole image."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from adaptnav.sonar.waterfall import normalise_gain


def _reference(image):
    img = image.astype(np.float32, copy=True)
    data = img > 0
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        col = np.nanmedian(np.where(data, img, np.nan), axis=0)
        col = np.where(np.isfinite(col) & (col > 0), col, 1.0).astype(np.float32)
        img /= col[None, :]
        row = np.nanmedian(np.where(data, img, np.nan), axis=1)
    row = np.where(np.isfinite(row) & (row > 0), row, 1.0).astype(np.float32)
    img /= row[:, None]
    img[~data] = 0.0
    return img


def _images():
    rng = np.random.default_rng(41)
    out = []
    for shape in [(200, 1000), (7, 600), (1, 520), (30, 9)]:
        a = rng.gamma(2.0, 1.0, shape).astype(np.float32)
        w = a.copy()
        w[:, : shape[1] // 10] = 0.0   # a waterfall: no data beyond the slant range on either side
        w[:, shape[1] - shape[1] // 7:] = 0.0
        out.append(w)
        two = w.copy()
        two[:, shape[1] // 2] = 0.0      # the same on every row, two runs of columns
        out.append(two)
        holes = w.copy()
        holes[rng.random(shape) < 0.01] = 0.0  # rows differ
        out.append(holes)
        nan_col = w.copy()
        nan_col[:, shape[1] // 3] = np.nan  # NaN: not data
        out.append(nan_col)
        out.append(np.zeros(shape, np.float32))  # no data at all
        neg = w.copy()
        neg[:, shape[1] // 4] = -1.0
        out.append(neg)
    return out


@pytest.mark.parametrize("k", range(24))
def test_normalise_gain_is_the_plain_computation(k):
    image = _images()[k]
    got, want = normalise_gain(image), _reference(image)
    assert got.dtype == np.float32 and got.tobytes() == want.tobytes()
