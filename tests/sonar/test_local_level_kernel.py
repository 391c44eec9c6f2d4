"""The object detector's compiled local level (sonar._kernels.local_level) against the scipy
filters it replaces: the same float32 numbers, bit for bit (issue 17: replay speed)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.sonar.objects import ObjectDetectorConfig, local_level, local_level_filters


def _scipy_local_level(image, ground_res_m, along_res_m, config):
    """sonar.objects.local_level through scipy.ndimage's filters (the reference)."""
    along = along_res_m if math.isfinite(along_res_m) and along_res_m > 0 else ground_res_m
    box = (max(int(round(config.background_m / along)), 3), max(int(round(config.background_m / ground_res_m)), 3))
    return local_level_filters(image, box, config.smooth_px)


def _images(rng, n):
    for k in range(n):
        rows, cols = int(rng.integers(3, 120)), int(rng.integers(3, 400))
        image = (rng.gamma(1.0, 1.0, (rows, cols)) * (rng.random((rows, cols)) > 0.3 * rng.random())).astype(np.float32)
        if k % 4 == 0:  # a water column / beyond-range band without data
            image[:, : int(rng.integers(0, cols))] = 0.0
        if k % 3 == 1:  # data in the same columns on every row (a waterfall: its far ends without)
            image = rng.gamma(1.0, 1.0, (rows, cols)).astype(np.float32) + np.float32(1e-3)
            image[:, : int(rng.integers(0, cols // 3 + 1))] = 0.0
            image[:, cols - int(rng.integers(0, cols // 3 + 1)):] = 0.0
        if k % 5 == 0:  # values the mask must leave out
            image[rng.random((rows, cols)) < 0.05] = -1.0
            image[0, 0] = np.nan
        yield image, float(rng.uniform(0.05, 0.5)), (float(rng.uniform(0.05, 0.5)) if k % 7 else math.nan)


@pytest.mark.parametrize("smooth_px", [(0.5, 0.7), (1.3, 0.4), (2.0, 2.0)])
def test_compiled_local_level_is_the_scipy_one_bit_for_bit(smooth_px):
    config = ObjectDetectorConfig(smooth_px=smooth_px)
    work: dict = {}
    rng = np.random.default_rng(17)
    for image, res, along in _images(rng, 60):
        ref = _scipy_local_level(image, res, along, config)
        for w in (None, work):
            got = local_level(image, res, along, config, w)
            assert got.dtype == ref.dtype == np.float32 and got.shape == ref.shape
            assert np.array_equal(got.view(np.uint32), ref.view(np.uint32))


def test_local_level_of_a_strided_read_only_or_float64_image_is_the_scipy_one():
    config = ObjectDetectorConfig()
    rng = np.random.default_rng(3)
    image = rng.gamma(1.0, 1.0, (90, 300)).astype(np.float32)
    image[:, :40] = 0.0
    view = image[:, 20:260]          # not contiguous
    frozen = image.copy()
    frozen.setflags(write=False)     # as a waterfall of read-only echoes may be
    for im in (view, frozen, image.astype(np.float64)):
        ref = _scipy_local_level(im, 0.1, 0.15, config)
        assert np.array_equal(local_level(im, 0.1, 0.15, config, {}).view(np.uint32), ref.view(np.uint32))


def test_deep_shadow_rows_run_by_run_are_the_whole_image_scan():
    from adaptnav.sonar.objects import _deep_shadow_rows, _deep_shadow_rows_scan, _Runs

    rng = np.random.default_rng(5)
    for _ in range(40):
        lev = rng.random((30, 80)).astype(np.float32) * 0.6
        lev[rng.random(lev.shape) < 0.02] = np.nan
        w = 40
        for side in (lev[:, w:], lev[:, w - 1::-1], np.ascontiguousarray(lev)):
            n = int(rng.integers(1, 60))
            near = rng.integers(0, side.shape[1], n)
            far = np.minimum(near + rng.integers(1, 30, n), side.shape[1])
            runs = _Runs(rng.integers(1, 9, n), rng.integers(0, side.shape[0], n), near, far)
            for level in (0.3, 0.45, 0.1):
                assert np.array_equal(_deep_shadow_rows(side, runs, level), _deep_shadow_rows_scan(side, runs, level))


def test_fused_gaussian_along_columns_is_scipys():
    """sonar._kernels._gauss_cols_fused (one pass for half-widths 0-3, the general pass beyond)
    against scipy.ndimage.gaussian_filter1d along the rows' columns, bit for bit."""
    from scipy.ndimage import gaussian_filter1d

    from adaptnav.sonar import _kernels
    from adaptnav.sonar.objects import _gaussian_weights

    rng = np.random.default_rng(23)
    for sigma in (0.1, 0.2, 0.5, 0.7, 1.0):  # half-widths 0, 1, 2, 3, 4
        w = _gaussian_weights(sigma)
        for shape in ((1, 9), (7, 4), (30, 257)):
            src = (rng.gamma(1.0, 1.0, shape) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
            out = np.empty(shape, np.float32)
            _kernels._gauss_cols_fused(src, w, out)
            ref = gaussian_filter1d(src, sigma, axis=1, mode="reflect")
            np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))


def test_box_along_columns_by_lines_is_scipys():
    """sonar._kernels._box_cols (four rows' running sums side by side, the rest one by one)
    against scipy.ndimage.uniform_filter1d along the rows' columns, bit for bit."""
    from scipy.ndimage import uniform_filter1d

    from adaptnav.sonar import _kernels

    rng = np.random.default_rng(29)
    for shape in ((1, 9), (4, 60), (7, 61), (30, 257)):
        for size in (2, 3, 4, 7, min(60, shape[1])):
            if size > shape[1]:
                continue
            src = (rng.gamma(1.0, 1.0, shape) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
            out = np.empty(shape, np.float32)
            _kernels._box_cols(src, size, out)
            ref = uniform_filter1d(src, size, axis=1, mode="reflect")
            np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))
