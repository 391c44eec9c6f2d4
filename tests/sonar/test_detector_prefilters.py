"""The detector's tests made for all components at once before their pixels are gathered give
the sightings of the per-component tests they stand in front of (pure speed changes)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from adaptnav.sonar.objects import ObjectDetectorConfig, _components, _detect_near, local_level
from adaptnav.sonar.waterfall import Waterfall

from .test_detector_kernels import assert_same_sightings


def _near_image(rng, rows=160, cols=300):
    """Speckle with bright blobs near the nadir (some followed by a dark strip), of every size,
    mean level and range, some at the mean-level threshold."""
    img = rng.gamma(4.0, 0.25, (rows, 2 * cols)).astype(np.float32)
    img[:, cols - 20:cols + 20] = 0.0  # the water column
    for _ in range(int(rng.integers(30, 70))):
        r, c = int(rng.integers(0, rows - 12)), int(rng.integers(21, 160))
        h, w = int(rng.integers(1, 9)), int(rng.integers(1, 8))
        side = 1 if rng.random() < 0.5 else -1
        lo, hi = (cols + c, cols + c + w) if side > 0 else (cols - c - w, cols - c)
        img[r:r + h, lo:hi] = rng.uniform(2.0, 8.0) * rng.uniform(0.8, 1.2, (h, hi - lo))
        if rng.random() < 0.7:
            d0, d1 = (hi, hi + 6) if side > 0 else (lo - 6, lo)
            img[r:r + h, d0:d1] *= rng.uniform(0.05, 0.8)
    return img


def test_near_blobs_pretested_at_once_give_the_per_blob_sightings():
    rng = np.random.default_rng(52)
    res, n_found, n_cases = 0.1, 0, 0
    for trial in range(16):
        rows = 160
        img = _near_image(rng, rows)
        config = ObjectDetectorConfig()
        if trial % 4 == 1:  # looser: more blobs reach the per-blob tests
            config = replace(config, near_highlight_level=1.8, near_min_px=4, near_min_rows=1, near_mean_level=2.0,
                             near_shadow_level=3.0, near_min_contrast=1.0, near_min_along_m=0.0,
                             min_ground_range_m=0.0)
        elif trial % 4 == 2:  # stricter rows and range
            config = replace(config, near_min_rows=5, min_ground_range_m=3.0, near_mean_level=4.0)
        along = np.cumsum(rng.uniform(0.1, 0.2, rows)) if trial % 5 else np.full(rows, math.nan)
        along_res = float(np.median(np.diff(along)))
        wf = Waterfall(img, res, along_res, np.arange(rows) * 0.1 + 50.0, along, rng.uniform(-3, 3, rows),
                       np.arange(rows, dtype=float), rng.uniform(6.0, 12.0, (rows, 2)))
        lev = local_level(img, res, along_res, config, {})
        w = img.shape[1] // 2
        for side, sub in (("starboard", lev[:, w:]), ("port", lev[:, w - 1::-1])):
            if trial % 4 == 3:  # blobs whose float32 mean is the threshold itself
                blob_means = [float(v.mean()) for v in _blob_values(sub, config)]
                if blob_means:
                    config = replace(config, near_mean_level=blob_means[len(blob_means) // 2])
            a = wf.altitude_m[:, 1 if side == "starboard" else 0]
            args = (sub, side, res, along, along_res, np.arange(rows, dtype=float), wf, a, config)
            got, ref = _detect_near(*args), _detect_near(*args, pretest=False)
            assert_same_sightings(got, ref)
            n_found += len(ref)
            n_cases += 1
    assert n_found > 40, n_found


def _blob_values(sub, config):
    """The pixels of the near blobs of at least ``near_min_px`` (their float32 means: thresholds)."""
    ncol = min(int(config.near_range_m / 0.1), sub.shape[1])
    s = sub[:, :ncol + 20]
    lab, n, runs, n_px, _ = _components(s > config.near_highlight_level, s)
    return [s[lab == k] for k in range(1, n + 1) if n_px[k] >= config.near_min_px]
