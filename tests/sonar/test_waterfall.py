import math

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from adaptnav.sonar.ping import SonarPing
from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall, detect_first_return, slant_to_ground


def _flat_pings(n_pings, altitude_m, target_ground_m, side="starboard", speed=1.0):
    """Pings of a flat seabed (constant 1 beyond the bottom) with one bright target."""
    n, rng_m = 1000, 30.0
    dr = rng_m / n
    r = (np.arange(n) + 0.5) * dr
    base = np.where(r > altitude_m, 1.0, 0.01)
    tgt = math.hypot(target_ground_m, altitude_m)
    bright = base + 20.0 * (np.abs(r - tgt) < 0.6 * dr)
    pings = []
    for i in range(n_pings):
        s, p = (bright, base) if side == "starboard" else (base, bright)
        pings.append(SonarPing(t_s=0.5 * i, port=p, starboard=s, slant_range_m=rng_m,
                               altitude_m=math.nan, speed_m_s=speed))
    return pings


@pytest.mark.parametrize("side", ["starboard", "port"])
def test_target_lands_at_its_ground_range_on_its_side(side):
    pings = _flat_pings(20, altitude_m=6.0, target_ground_m=12.0, side=side)
    wf = build_waterfall(pings, WaterfallConfig(ground_res_m=0.05, median_ksize=1,
                                                gain_normalise=False))
    col = int(np.argmax(wf.image[10]))
    across = float(wf.across_m(col))
    expect = 12.0 if side == "starboard" else -12.0
    assert abs(across - expect) < 0.1
    # the water column is gone: ground columns from 1 m out are seabed, not the 0.01 water
    w = wf.n_side
    assert np.all(wf.image[10, w + 20: w + 200] > 0.5) and np.all(wf.image[10, w - 200: w - 20] > 0.5)


def test_bottom_detection_finds_altitude_when_the_file_has_none():
    pings = _flat_pings(30, altitude_m=7.3, target_ground_m=10.0)
    s = np.stack([p.starboard for p in pings])
    h = detect_first_return(s, pings[0].sample_spacing_m)
    assert np.all(np.abs(h - 7.3) < 0.1)


def test_slant_to_ground_geometry():
    # a sample at slant r appears at ground sqrt(r² − H²)
    x = np.zeros((1, 500), np.float32)
    x[0, 300] = 1.0  # r = 300.5 * 0.05 = 15.025 m
    out = slant_to_ground(x, 0.05, np.array([9.0]), 0.01, 1500)
    g = (np.argmax(out[0]) + 0.5) * 0.01
    assert abs(g - math.sqrt(15.025 ** 2 - 81.0)) < 0.02


def test_along_track_resampling_uses_distance_travelled():
    pings = _flat_pings(41, altitude_m=5.0, target_ground_m=8.0, speed=2.0)  # 0.5 s → 1 m/ping
    wf = build_waterfall(pings, WaterfallConfig(along_res_m=0.25))
    assert wf.image.shape[0] == 161
    assert np.allclose(np.diff(wf.along_m), 0.25) and abs(wf.along_m[-1] - 40.0) < 1e-9
    assert np.allclose(wf.ping_index[::4], np.arange(41))


def test_median_and_gain_normalisation_remove_line_noise():
    pings = _flat_pings(60, altitude_m=5.0, target_ground_m=8.0)
    rng = np.random.default_rng(0)
    noisy = []
    for i, p in enumerate(pings):
        gain = 1.0 + (3.0 if i % 7 == 3 else 0.0)  # bright horizontal lines
        sp = rng.gamma(4.0, 0.25, p.n_samples)
        noisy.append(SonarPing(t_s=p.t_s, port=p.port * gain * sp, starboard=p.starboard * gain * sp,
                               slant_range_m=p.slant_range_m, speed_m_s=p.speed_m_s))
    raw = build_waterfall(noisy, WaterfallConfig(gain_normalise=False, median_ksize=1))
    clean = build_waterfall(noisy, WaterfallConfig())
    def line_ratio(img):
        rows = np.median(img[:, img.shape[1] // 2 + 100:], axis=1)
        return rows[3::7].mean() / np.delete(rows, np.s_[3::7]).mean()
    assert line_ratio(raw.image) > 2.5
    assert abs(line_ratio(clean.image) - 1.0) < 0.15


def test_scotsman_wreck_is_the_strongest_structure_near_the_annotated_hit(scotsman_pings):
    from tests.sonar.conftest import SCOTSMAN

    pings, _ = scotsman_pings
    channel, x_hit, y_hit = map(int, (SCOTSMAN.parent / "scotsman-iver2.xtf.hits").read_text().split()[:3])
    assert channel == 1  # OpenSidescan channel 1 = starboard; x = slant sample, y = ping
    wf = build_waterfall(pings, WaterfallConfig(resample_along=False, ground_res_m=0.1))
    r_hit = (x_hit + 0.5) * pings[0].sample_spacing_m
    h = wf.altitude_m[y_hit, 1]
    g_hit = math.sqrt(max(r_hit ** 2 - h ** 2, 0.0))
    # structure = local std of log intensity (highlights next to shadows), 15 pings × 2 m
    log_i = np.log(np.maximum(wf.image, 1e-3))
    box = (15, 21)
    m1, m2 = uniform_filter(log_i, box), uniform_filter(log_i ** 2, box)
    sd = np.sqrt(np.maximum(m2 - m1 ** 2, 0.0))
    sd[uniform_filter((wf.image > 0).astype(float), box) < 0.99] = 0.0
    row, col = np.unravel_index(np.argmax(sd), sd.shape)
    across = float(wf.across_m(col))
    assert across > 0, "strongest structure must be on the starboard side"
    assert abs(row - y_hit) < 90 and abs(across - g_hit) < 15.0
    # and the starboard side around the hit is far more structured than port at the same pings
    rows = slice(y_hit - 60, y_hit + 60)
    w = wf.n_side
    stbd = sd[rows, w + 20: w + 160].mean()
    port = sd[rows, w - 160: w - 20].mean()
    assert stbd > 1.5 * port


def test_clean_pings_sorts_and_counts_bad_ones():
    from adaptnav.sonar.waterfall import clean_pings

    def ping(t, n=16, rng_m=20.0):
        return SonarPing(t_s=t, port=np.ones(n), starboard=np.ones(n), slant_range_m=rng_m)

    raw = [ping(0.0), ping(2.0), ping(1.0), ping(math.nan), ping(2.0), ping(3.0, n=8),
           ping(4.0, rng_m=30.0), ping(5.0), ping(6.0, rng_m=0.0)]
    kept, dropped = clean_pings(raw)
    assert [p.t_s for p in kept] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    # the range changed: on the common geometry, not dropped
    assert all(p.n_samples == 16 and p.slant_range_m == 20.0 for p in kept)
    assert dropped == {"non-finite time": 1, "no geometry": 1, "resampled": 2,
                       "duplicate time": 1, "reordered": 1}
    # non-finite samples do not poison the image
    bad = [SonarPing(t_s=float(i), port=np.full(64, np.inf if i == 3 else 1.0),
                     starboard=np.full(64, np.nan if i == 4 else 1.0), slant_range_m=10.0,
                     altitude_m=2.0) for i in range(10)]
    wf = build_waterfall(bad, WaterfallConfig(bottom="altitude"))
    assert np.all(np.isfinite(wf.image))


def test_masked_median_equals_numpy_nanmedian_on_the_data_pixels():
    import warnings

    from adaptnav.sonar.waterfall import masked_median

    rng = np.random.default_rng(3)
    for _ in range(20):
        h, w = rng.integers(1, 60), rng.integers(1, 90)
        img = (rng.gamma(1.0, 1.0, (h, w)) * (rng.random((h, w)) > rng.random())).astype(np.float32)
        img[:, rng.integers(0, w)] = 0.0  # a column without data
        if _ % 3 == 0:  # data in the same columns on every row (a waterfall's far ends without)
            img = rng.gamma(1.0, 1.0, (h, w)).astype(np.float32) * (rng.random(w) > 0.2)
        data = img > 0
        if _ % 6 == 0:
            data = np.broadcast_to(rng.random(w) > 0.5, img.shape)
        for axis in (0, 1):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                ref = np.nanmedian(np.where(data, img, np.nan), axis=axis)
            got = masked_median(img, data, axis)
            assert got.dtype == ref.dtype
            np.testing.assert_array_equal(got, ref)


def _pings_with_returns(port_first_m, stbd_first_m, altimeter_m, n_pings=30):
    """Flat-seabed pings whose first return starts at the given slant range per side."""
    n, rng_m = 1000, 30.0
    r = (np.arange(n) + 0.5) * rng_m / n
    port = np.where(r > port_first_m, 1.0, 0.01).astype(np.float32)
    stbd = np.where(r > stbd_first_m, 1.0, 0.01).astype(np.float32)
    return [SonarPing(t_s=0.5 * i, port=port, starboard=stbd, slant_range_m=rng_m, altitude_m=altimeter_m)
            for i in range(n_pings)]


@pytest.mark.parametrize("port_m, stbd_m, expect_port_m, expect_stbd_m", [
    (8.5, 6.0, 6.0, 6.0),   # late on one side only (a weak nadir return, mud): the altimeter stays
    (8.5, 8.5, 8.5, 8.5),   # late on both sides: the echo overrules the altimeter
    (4.0, 6.0, 4.0, 6.0),   # early on one side: an echo cannot come from below the seabed
])
def test_auto_bottom_takes_a_late_echo_over_the_altimeter_only_when_both_sides_see_it(
        port_m, stbd_m, expect_port_m, expect_stbd_m):
    from adaptnav.sonar.waterfall import _altitudes

    pings = _pings_with_returns(port_m, stbd_m, altimeter_m=6.0)
    sides = np.stack([[p.port for p in pings], [p.starboard for p in pings]])
    alt = _altitudes(pings, sides, WaterfallConfig(bottom="auto"))
    assert np.allclose(alt[:, 0], expect_port_m, atol=0.15), alt[:, 0]
    assert np.allclose(alt[:, 1], expect_stbd_m, atol=0.15), alt[:, 1]


def test_row_percentile_equals_numpy_percentile():
    from adaptnav.sonar.waterfall import row_percentile

    rng = np.random.default_rng(5)
    for i in range(60):
        rows, n = rng.integers(1, 20), rng.integers(1, 600)
        a = (rng.gamma(1.0, 1.0, (rows, n)) * rng.choice([1e-3, 1.0, 1e4])).astype([np.float32, np.float64][i % 2])
        if i % 3 == 0:
            a = np.round(a, 1)  # ties
        if i % 4 == 0:
            a[rng.integers(0, rows), rng.integers(0, n)] = np.nan
        for q in (0, 10, 33.3, 50, 62.5, 75, 99, 100):
            ref = np.percentile(a, q, axis=1)
            got = row_percentile(a, q)
            assert got.dtype == ref.dtype
            np.testing.assert_array_equal(got, ref)


def test_compiled_slant_to_ground_equals_numpy():
    import warnings

    from adaptnav.sonar.waterfall import slant_to_ground_numpy

    rng = np.random.default_rng(6)
    samples = rng.gamma(2.0, 0.5, (40, 300)).astype(np.float32)
    altitudes = (np.full(40, 10.0), rng.uniform(0.0, 40.0, 40), np.repeat(rng.uniform(0.0, 20.0, 8), 5),
                 np.where(rng.random(40) < 0.3, np.nan, 7.7), np.r_[np.inf, np.full(39, 5.0)])
    for alt in altitudes:
        for res in (0.1, 0.0371, 0.5):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # numpy's overflow on the infinite altitude
                ref = slant_to_ground_numpy(samples, 0.05, alt, res, 400)
            got = slant_to_ground(samples, 0.05, alt, res, 400)
            np.testing.assert_array_equal(got, ref)
            image = np.zeros((40, 800), np.float32)  # into a reversed view, as the waterfall's port side
            slant_to_ground(samples, 0.05, alt, res, 400, out=image[:, 399::-1])
            np.testing.assert_array_equal(image[:, 399::-1], ref)


def test_first_return_filters_are_scipys():
    from scipy.ndimage import median_filter, uniform_filter1d

    from adaptnav.sonar import _kernels
    from adaptnav.sonar.waterfall import median_filter_nearest

    rng = np.random.default_rng(7)
    for size in range(1, 8):
        for n in (size, size + 3, 200):
            x = np.round(rng.gamma(2.0, 3.0, n), 1)  # (ties)
            np.testing.assert_array_equal(median_filter_nearest(x, size), median_filter(x, size, mode="nearest"))
    for shape in ((1, 5), (30, 512), (7, 6)):
        samples = (rng.gamma(1.0, 1.0, shape) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
        out = np.empty(shape, np.float32)
        _kernels.uniform_filter_rows(samples, 5, out)
        np.testing.assert_array_equal(out.view(np.uint32), uniform_filter1d(samples, 5, axis=1).view(np.uint32))


def test_row_medians_are_numpys_median():
    """The bracketed selection (sonar._kernels.bracket_rows) against the sorted rows' middle values,
    bit for bit: speckle-like rows, ties, NaN, rows whose bracket misses the middle (sorted whole)."""
    from adaptnav.sonar.waterfall import row_medians

    rng = np.random.default_rng(11)
    for trial in range(40):
        r, m = int(rng.integers(1, 60)), int(rng.integers(512, 1400))
        s = rng.gamma(float(rng.uniform(0.3, 3.0)), 1.0, (r, m)).astype(np.float32)
        if trial % 4 == 1:
            s = np.round(s, 1)  # ties (a bracket of equal values)
        if trial % 4 == 2:
            s[rng.random((r, m)) < 0.3] = np.nan  # sorted last, as numpy sorts
        if trial % 4 == 3:
            s[: r // 2, : m // 2 + 3] = 2.0  # more than half one value: the candidates overflow
            s[r // 2:, ::4] = 0.0  # the sample all at the bottom: the bracket misses the middle
        t = np.sort(s, axis=1)  # the reference: the two middle values of the sorted row, their mean
        ref = (t[:, (m - 1) // 2] + t[:, m // 2]) / np.float32(2)
        if trial % 4 != 2:
            np.testing.assert_array_equal(ref, np.median(s, axis=1))  # (which is numpy.median's without NaN)
        got = row_medians(s.copy())
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))
    small = rng.gamma(1.0, 1.0, (5, 200)).astype(np.float32)  # (short rows: sorted)
    np.testing.assert_array_equal(row_medians(small.copy()), np.median(small, axis=1))
