"""The side-scan object detector's compiled steps (sonar._kernels: label8, label8_runs,
shadowed_measures) against the numpy/scipy/Python they replace: the same numbers, bit for bit
(issue 17: the calibrator child's detection per block)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.ndimage import label

from adaptnav.sonar import _kernels
from adaptnav.sonar.objects import (ObjectDetectorConfig, _component_rows_numpy, _components, _detect_shadowed,
                                    _label8, local_level)


def _masks(rng, n):
    """Random masks of every density, as the detector's views take them (contiguous, a side's
    columns outwards: strided, reversed), including single rows and columns."""
    for k in range(n):
        rows, cols = int(rng.integers(1, 70)), int(rng.integers(1, 110))
        lev = rng.random((rows, cols + 9)).astype(np.float32)
        if k % 3 == 0:  # blobs, not speckle: components spanning many rows, merging late
            lev = np.cumsum(np.cumsum(lev - 0.5, axis=0), axis=1).astype(np.float32)
            lev = (lev - lev.min()) / max(float(np.ptp(lev)), 1e-6)
        p = float(rng.uniform(0.02, 0.95))
        for view in (lev[:, 4:4 + cols], lev[:, cols - 1::-1], np.ascontiguousarray(lev[:, :cols])):
            yield view, view < p


def test_label8_is_scipy_label_with_8_connectivity():
    rng = np.random.default_rng(41)
    n_big = 0
    for view, mask in _masks(rng, 150):
        got, n = _label8(mask)
        ref, n_ref = label(mask, structure=np.ones((3, 3), bool))
        assert n == n_ref and got.dtype == ref.dtype and np.array_equal(got, ref)
        n_big += n > 20
    assert n_big > 50  # (not only trivial masks)
    # a spiral: one component whose provisional labels merge many times, in both directions
    spiral = np.zeros((41, 41), bool)
    for r in range(0, 21, 2):
        spiral[r, r:41 - r] = spiral[40 - r, r:41 - r] = spiral[r:41 - r, r] = spiral[r:41 - r, 40 - r] = True
    got, n = _label8(spiral)
    ref, n_ref = label(spiral, structure=np.ones((3, 3), bool))
    assert n == n_ref and np.array_equal(got, ref)


def test_label8_runs_are_scipys_labels_and_the_numpy_runs():
    rng = np.random.default_rng(42)
    for view, mask in _masks(rng, 120):
        lab, n, runs, n_px, sums = _components(mask, view)
        ref, n_ref = label(mask, structure=np.ones((3, 3), bool))
        assert n == n_ref and lab.dtype == ref.dtype and np.array_equal(lab, ref)
        if n == 0:
            assert runs.label.size == 0 and np.array_equal(n_px, [0]) and np.array_equal(sums, [0.0])
            continue
        r_runs, r_n_px, r_sums = _component_rows_numpy(ref, n_ref, view)
        for a, b in zip(runs, r_runs):  # (the labels int64 here, the label image's int32 there)
            assert a.dtype.kind == b.dtype.kind == "i" and np.array_equal(a, b)
        assert np.array_equal(n_px, r_n_px)
        assert np.array_equal(sums.view(np.uint64), r_sums.view(np.uint64))  # raster order, as bincount adds


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pairwise_sum_is_numpys(dtype):
    """numpy.mean's sum of a contiguous array (pairwise, blocks of 8 up to 128): the same bits."""
    rng = np.random.default_rng(43)
    for n in list(range(1, 300)) + [511, 1000, 4099]:
        a = (rng.random(n) * 10.0 ** rng.uniform(-3, 3)).astype(dtype)
        lo = int(rng.integers(0, 5))
        padded = np.concatenate([rng.random(lo).astype(dtype), a])
        got = _kernels._pairwise_sum(padded, lo, n)
        assert np.asarray(got, dtype).tobytes() == np.add.reduce(a).tobytes(), n


def _image(rng, rows=200, cols=500):
    """A ground-range image with objects: a highlight then a shadow on a few rows, on speckle."""
    img = rng.gamma(4.0, 0.25, (rows, 2 * cols)).astype(np.float32)
    img[:, cols - 40:cols + 40] = 0.0  # the water column
    for _ in range(int(rng.integers(40, 90))):
        r = int(rng.integers(0, rows - 15))
        c = int(rng.integers(50, cols - 30))
        h, s, n = int(rng.integers(1, 6)), int(rng.integers(2, 40)), int(rng.integers(1, 9))
        side = 1 if rng.random() < 0.5 else -1
        n += int(rng.integers(0, 6))
        # 0-3 rows without a lit face in the middle (the object's run bridges gaps of up to 2)
        g0, g1 = n // 2, n // 2 + int(rng.integers(0, 4))
        if rng.random() < 0.1:  # a shadow running to the image's end (height unknown)
            c, s = cols - h - 5, 5
        for q in range(n):
            if g0 <= q < g1:
                img[r + q, cols + side * c:cols + side * (c + s):side] *= 0.1  # shadow, no face
                continue
            a = cols + side * c
            if side > 0:
                img[r + q, a:a + h] *= rng.uniform(2.0, 12.0)
                img[r + q, a + h:a + h + s] *= rng.uniform(0.0, 0.3)
            else:
                img[r + q, a - h + 1:a + 1] *= rng.uniform(2.0, 12.0)
                img[r + q, a - h - s + 1:a - h + 1] *= rng.uniform(0.0, 0.3)
    img[rng.random(img.shape) < 0.002] = 0.0  # holes without data
    return img


def assert_same_sightings(got, ref):
    """The same sightings, field for field: equal values of one type (NaN equal to NaN)."""
    assert len(got) == len(ref)
    for g, r in zip(got, ref):
        for key, v in vars(r).items():
            u = getattr(g, key)
            assert type(u) is type(v) and (u == v or (u != u and v != v)), (key, u, v)


def test_compiled_candidate_measurements_give_the_python_loops_sightings():
    """_detect_shadowed with its candidates measured by the kernel and tested in numpy gives the
    sightings, field for field, of the per-candidate Python loop it replaced."""
    from adaptnav.sonar.waterfall import Waterfall

    rng = np.random.default_rng(44)
    res = 0.1
    n_found = 0
    for trial in range(12):
        rows = 200
        img = _image(rng, rows)
        config = ObjectDetectorConfig()
        if trial % 3 == 1:  # lower thresholds: more candidates reach the measurements
            config = replace(config, min_contrast=3.0, compact_min_contrast=2.5, short_min_contrast=2.0,
                             min_height_m=0.05, deep_shadow_level=0.45)
        elif trial % 3 == 2:  # none: every component with a highlight is measured and reported
            config = replace(config, min_contrast=0.0, compact_min_contrast=0.0, short_min_contrast=0.0,
                             min_height_m=-1.0, min_shadow_px=1, min_ground_range_m=0.0, min_highlight_rows=1)
        along = np.cumsum(rng.uniform(0.1, 0.2, rows)) if trial % 4 else np.full(rows, math.nan)
        along_res = float(np.median(np.diff(along)))
        alt = rng.uniform(6.0, 12.0, (rows, 2))
        if trial == 5:
            alt[50:60] = math.nan  # unknown altitude: those candidates are dropped
        wf = Waterfall(img, res, along_res, np.arange(rows) * 0.1 + 100.0, along, rng.uniform(-3, 3, rows),
                       np.arange(rows, dtype=float), alt)
        lev = local_level(img, res, along_res, config, {})
        w = img.shape[1] // 2
        for side, sub in (("starboard", lev[:, w:]), ("port", lev[:, w - 1::-1])):
            a = wf.altitude_m[:, 1 if side == "starboard" else 0]
            args = (sub, side, res, along, along_res, np.arange(rows, dtype=float), wf, a, config)
            got, ref = _detect_shadowed(*args), _detect_shadowed(*args, compiled=False)
            assert_same_sightings(got, ref)
            n_found += len(ref)
    assert n_found > 100, n_found



def test_compiled_candidate_tests_are_the_numpy_ones():
    """The tests before the measurements (sizes, highlights, contrast and height bounds): the
    same highlight rows, leading edges, levels and candidates as the numpy steps."""
    from adaptnav.sonar.objects import _candidates_compiled, _candidates_numpy

    rng = np.random.default_rng(46)
    n_todo = 0
    for trial in range(10):
        img = _image(rng)
        config = ObjectDetectorConfig()
        if trial % 2:
            config = replace(config, min_contrast=2.0 + trial, short_min_contrast=1.5 + trial / 2,
                             min_height_m=0.03 * trial, highlight_level=1.2 + 0.1 * trial)
        lev = local_level(img, 0.1, 0.15, config, {})
        w = img.shape[1] // 2
        alt = rng.uniform(6.0, 12.0, img.shape[0]) if trial != 3 else np.full(img.shape[0], math.nan)
        for sub in (lev[:, w:], lev[:, w - 1::-1]):
            lab, n, runs, n_px, sums = _components(sub < config.shadow_level, sub)
            deep = np.asarray(rng.integers(0, 30, runs.label.size), np.int64)
            hw = max(int(round(config.highlight_window_m / 0.1)), 2)
            least = min(config.short_min_contrast, config.compact_min_contrast, config.min_contrast)
            args = (alt, 0.1, config, 5, 3, 40, hw, least)
            hl, todo = _candidates_compiled(sub, runs, n_px, sums, deep, *args)
            r_hl, _, r_todo = _candidates_numpy(sub, runs, n, n_px, sums, deep, *args)
            for a, b in zip(hl, r_hl):
                assert a.dtype.kind == b.dtype.kind and np.array_equal(a, b)
            assert hl.level.dtype == r_hl.level.dtype == np.float32
            assert np.array_equal(todo, r_todo)
            n_todo += todo.size
    assert n_todo > 200, n_todo
