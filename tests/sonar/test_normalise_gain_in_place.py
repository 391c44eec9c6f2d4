"""normalise_gain(copy=False) — build_waterfall's, on its own image — against the plain steps: the
same bytes, written into the float32 image itself; any other dtype is converted (a new array)."""
from __future__ import annotations

import numpy as np
import pytest

from adaptnav.sonar.waterfall import masked_median, normalise_gain
from tests.sonar.test_normalise_gain_paths import _images, _reference


@pytest.mark.parametrize("k", range(24))
def test_normalise_gain_in_place_is_the_plain_computation(k):
    image = _images()[k]
    want = _reference(image)
    work = image.copy()
    got = normalise_gain(work, copy=False)
    assert got is work and got.tobytes() == want.tobytes()
    as64 = image.astype(np.float64)
    before = as64.tobytes()
    got64 = normalise_gain(as64, copy=False)
    assert got64.dtype == np.float32 and as64.tobytes() == before and got64.tobytes() == want.tobytes()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_column_medians_of_a_waterfall_are_nanmedian(dtype):
    """masked_median along the columns of one run of data columns (OpenCV's transpose for float32)."""
    rng = np.random.default_rng(9)
    img = rng.gamma(2.0, 1.0, (37, 300)).astype(dtype)
    img[:, :20] = 0.0
    img[:, 260:] = 0.0
    img[5, 100] = np.nan  # a NaN inside the data columns: sorted last, as the sort puts it
    data = np.zeros(img.shape, bool)
    data[:, 20:260] = True
    got = masked_median(img, data, axis=0)
    s = np.sort(img[:, 20:260].T.copy(), axis=1)
    want = np.full(300, np.nan, dtype)
    want[20:260] = (s[:, 18] + s[:, 18]) / dtype(2)
    assert got.dtype == dtype and got.tobytes() == want.tobytes()
