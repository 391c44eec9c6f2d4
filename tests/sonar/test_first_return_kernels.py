"""The first-return steps of the waterfall (sonar._kernels first_return_rows, median_filter_nearest)
against the numpy steps they replaced, bit for bit."""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import median_filter

from adaptnav.sonar.waterfall import detect_first_return, median_filter_nearest, row_percentile


def _first_return_numpy(samples, spacing_m, fraction, blanking_m):
    """detect_first_return's pick per ping without the smoothing over pings, in numpy (the reference)."""
    from scipy.ndimage import uniform_filter1d

    sm = uniform_filter1d(samples.astype(np.float32), 5, axis=1)
    level = row_percentile(sm, 75)
    above = sm > (fraction * level)[:, None]
    above[:, : int(math.ceil(blanking_m / spacing_m))] = False
    idx = np.argmax(above, axis=1)
    raw = samples.astype(np.float32)
    offs = np.arange(-2, 3)
    cols = np.clip(idx[:, None] + offs[None, :], 0, raw.shape[1] - 1)
    raw_above = np.take_along_axis(raw, cols, axis=1) > (fraction * level)[:, None]
    shift = np.where(raw_above.any(axis=1), offs[np.argmax(raw_above, axis=1)], 0)
    idx = (idx + shift).astype(float)
    idx[~above.any(axis=1) | (level <= 0)] = np.nan
    return (idx + 0.5) * spacing_m


def _pings(rng, p, n):
    """Noise, then a seabed echo from a random sample on (sharp, soft, or none); a few silent pings."""
    a = rng.gamma(1.0, 0.05, (p, n)).astype(np.float32)
    for i in range(p):
        k = int(rng.integers(0, n))
        kind = i % 4
        if kind == 0:
            a[i, k:] += rng.gamma(4.0, 0.5, n - k).astype(np.float32)
        elif kind == 1:
            a[i, k:] += np.linspace(0.0, 3.0, n - k, dtype=np.float32)
        elif kind == 2 and i % 8 == 2:
            a[i] = 0.0  # silent: level 0, no return
    a[rng.random(a.shape) < 0.01] = 0.0
    return a


def test_first_return_per_ping_is_the_numpy_steps():
    rng = np.random.default_rng(71)
    n_found = 0
    for trial in range(40):
        p, n = int(rng.integers(1, 60)), int(rng.choice([5, 6, 40, 512]))
        samples = _pings(rng, p, n)
        spacing = float(rng.choice([0.05, 0.0977, 0.3]))
        fraction = float(rng.uniform(0.1, 0.9))
        blanking = float(rng.choice([0.0, 0.5, 2.0, 100.0]))
        ref = _first_return_numpy(samples, spacing, fraction, blanking)
        got = detect_first_return(samples, spacing, fraction=fraction, blanking_m=blanking, smooth_pings=1)
        assert got.tobytes() == ref.tobytes(), trial
        n_found += int(np.isfinite(ref).sum())
    assert n_found > 300, n_found


def test_median_filter_nearest_is_scipys_with_nan_last():
    rng = np.random.default_rng(72)
    for size in range(1, 8):
        for n in (1, size, size + 3, 200):
            x = np.round(rng.gamma(2.0, 3.0, n), 1)  # (ties)
            np.testing.assert_array_equal(median_filter_nearest(x, size), median_filter(x, size, mode="nearest"))
            x[rng.random(n) < 0.3] = np.nan  # numpy's sort puts NaN last
            pad = np.pad(x, (size // 2, (size - 1) // 2), mode="edge")
            ref = np.sort(np.lib.stride_tricks.sliding_window_view(pad, size), axis=1)[:, size // 2]
            np.testing.assert_array_equal(median_filter_nearest(x, size), ref)
