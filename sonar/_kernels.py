r"""numba kernels for the side-scan object detector's hot loops (:mod:`adaptnav.sonar.objects`).

* :func:`local_level` — :func:`adaptnav.sonar.objects.local_level`'s image divided by its
  local background, in one compiled pass over the image instead of eight ``scipy.ndimage``
  line filters and the numpy steps between them (a third of the detector's CPU, which is two
  thirds of the calibrator child's in a replay with side-scan).

The numbers are scipy's, bit for bit: its separable filters (``gaussian_filter``,
``uniform_filter``, mode ``reflect``) copy every line into a buffer of doubles extended by
reflection, compute in double and store each pass in the array's float32. The symmetric
correlation of ``NI_Correlate1D`` is ``o = i₀ w₀ + Σ_{j=r…1} (i₋ⱼ + iⱼ) wⱼ`` (the farthest pair
first); ``NI_UniformFilter1D`` a running sum ``S₀ = Σ i``, ``Sₖ = Sₖ₋₁ + (i_{k+n−1−s₁} − i_{k−1−s₁})``
(``s₁ = n // 2``), ``oₖ = Sₖ / n`` (scipy ≥ 1.x; older versions ran the mean itself, which
the tests would catch), both per line and axis in the order scipy takes them (rows first). A float32 quotient computed in double and rounded
is the float32 quotient (a double holds more than twice float32's digits). The thresholds
are compared in float32, as numpy compares a float32 array with a Python float.
"""
from __future__ import annotations

from adaptnav.kernels import jit
import numpy as np


@jit(cache=True)
def _reflect(k, n):
    """Index of the reflect-extended line (``d c b a | a b c d | d c b a``) for ``k`` within
    one line length of the ends."""
    if k < 0:
        return -k - 1
    if k >= n:
        return 2 * n - k - 1
    return k


@jit(cache=True)
def _gauss_rows(src, w, out):
    """``NI_Correlate1D`` (symmetric ``w``, odd length) along axis 0 of ``src`` into ``out``
    (float32): every column at once, a row at a time (each element's sum in scipy's order)."""
    n_rows, n_cols = src.shape
    r = w.shape[0] // 2
    acc = np.empty(n_cols)
    for k in range(n_rows):
        w0 = w[r]
        for c in range(n_cols):
            acc[c] = np.float64(src[k, c]) * w0
        for j in range(r, 0, -1):
            a = _reflect(k - j, n_rows)
            b = _reflect(k + j, n_rows)
            wj = w[r - j]
            for c in range(n_cols):
                acc[c] += (np.float64(src[a, c]) + np.float64(src[b, c])) * wj
        for c in range(n_cols):
            out[k, c] = np.float32(acc[c])


@jit(cache=True)
def _gauss_cols(src, w, out):
    """``NI_Correlate1D`` (symmetric ``w``, odd length) along axis 1 of ``src`` into ``out``
    (float32): a row at a time, every element's sum in scipy's order."""
    n_rows, n_cols = src.shape
    r = w.shape[0] // 2
    line = np.empty(n_cols + 2 * r)
    acc = np.empty(n_cols)
    for i in range(n_rows):
        for k in range(n_cols):
            line[k + r] = np.float64(src[i, k])
        for k in range(1, r + 1):
            line[r - k] = line[r + k - 1]
            line[r + n_cols - 1 + k] = line[r + n_cols - k]
        w0 = w[r]
        for k in range(n_cols):
            acc[k] = line[k + r] * w0
        for j in range(r, 0, -1):
            wj = w[r - j]
            for k in range(n_cols):
                acc[k] += (line[k + r - j] + line[k + r + j]) * wj
        for k in range(n_cols):
            out[i, k] = np.float32(acc[k])


@jit(cache=True)
def _box_rows(src, size, out):
    """``NI_UniformFilter1D`` of ``size`` along axis 0 of ``src`` into ``out`` (float32):
    every column's running sum at once, a row at a time."""
    n_rows, n_cols = src.shape
    s1 = size // 2
    fs = np.float64(size)
    acc = np.zeros(n_cols)
    for k in range(-s1, size - s1):
        a = _reflect(k, n_rows)
        for c in range(n_cols):
            acc[c] += np.float64(src[a, c])
    for c in range(n_cols):
        out[0, c] = np.float32(acc[c] / fs)
    for k in range(1, n_rows):
        a = _reflect(k + size - 1 - s1, n_rows)
        b = _reflect(k - 1 - s1, n_rows)
        for c in range(n_cols):
            acc[c] += np.float64(src[a, c]) - np.float64(src[b, c])
            out[k, c] = np.float32(acc[c] / fs)


@jit(cache=True)
def _box_cols(src, size, out):
    """``NI_UniformFilter1D`` of ``size`` along axis 1 of ``src`` into ``out`` (float32): the
    running sums of a block of rows side by side, a column at a time."""
    n_rows, n_cols = src.shape
    s1 = size // 2
    fs = np.float64(size)
    block = 16
    acc = np.empty(block)
    for i0 in range(0, n_rows, block):
        m = min(block, n_rows - i0)
        for q in range(m):
            acc[q] = 0.0
        for k in range(-s1, size - s1):
            a = _reflect(k, n_cols)
            for q in range(m):
                acc[q] += np.float64(src[i0 + q, a])
        for q in range(m):
            out[i0 + q, 0] = np.float32(acc[q] / fs)
        for k in range(1, n_cols):
            a = _reflect(k + size - 1 - s1, n_cols)
            b = _reflect(k - 1 - s1, n_cols)
            for q in range(m):
                acc[q] += np.float64(src[i0 + q, a]) - np.float64(src[i0 + q, b])
                out[i0 + q, k] = np.float32(acc[q] / fs)


@jit(cache=True, error_model="numpy")
def local_level(image, w_rows, w_cols, box_rows, box_cols, min_weight, min_count, min_background, work, data, lev):
    """The local level of :func:`adaptnav.sonar.objects.local_level` (module docstring) into ``lev``.

    ``image`` (R, C) float32; ``w_rows``, ``w_cols``: the Gaussian's weights along rows and
    columns (odd lengths, half-widths ≤ R, C); ``box_rows``, ``box_cols`` ≥ 2 (≤ R, C): the
    background box; the thresholds (float, compared in float32); ``work`` (5, R, C) float32 and ``data`` (R, C)
    bool: scratch (the caller keeps them from call to call: fresh pages were half the
    kernel's time); ``lev`` (R, C) float32: the output.
    """
    n_rows, n_cols = image.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    # float32, as numpy compares a float32 array with a Python float
    min_weight, min_count, min_background = np.float32(min_weight), np.float32(min_count), np.float32(min_background)
    x, tmp, img, msk, wgt = work[0], work[1], work[2], work[3], work[4]
    for i in range(n_rows):
        for k in range(n_cols):
            v = image[i, k]
            d = v > zero
            data[i, k] = d
            x[i, k] = v if d else zero
            msk[i, k] = np.float32(d)
    _gauss_rows(x, w_rows, tmp)
    _gauss_cols(tmp, w_cols, img)
    _gauss_rows(msk, w_rows, tmp)
    _gauss_cols(tmp, w_cols, wgt)
    # (selects, not branches: the loops vectorise; a pixel without weight divides by 1)
    for i in range(n_rows):
        for k in range(n_cols):
            w = wgt[i, k]
            ok = w > min_weight
            q = np.float32(np.float64(img[i, k]) / np.float64(w if ok else one))
            v = q if ok else zero
            img[i, k] = v
            x[i, k] = v if data[i, k] else zero  # num's input: the image where there is data
    num = wgt
    _box_rows(x, box_rows, tmp)
    _box_cols(tmp, box_cols, num)
    den = x
    _box_rows(msk, box_rows, tmp)
    _box_cols(tmp, box_cols, den)
    for i in range(n_rows):
        for k in range(n_cols):
            d = den[i, k]
            ok = d > min_count
            q = np.float32(np.float64(num[i, k]) / np.float64(d if ok else one))
            bg = q if ok else one
            ok = bg > min_background
            v = np.float32(np.float64(img[i, k]) / np.float64(bg if ok else one))
            v = v if ok else one
            lev[i, k] = v if data[i, k] else one


@jit(cache=True)
def deep_shadow_rows(lev, row, near, far, deep_level):
    """:func:`adaptnav.sonar.objects._deep_shadow_rows` run by run: per run (image ``row``,
    columns ``near`` … ``far`` − 1 of ``lev``, any strides) the columns from ``near`` to the
    first of three pixels in a row at least ``deep_level`` (compared in float32) lying within
    the run, else the run's length; the same integers as the whole-image scan it replaces."""
    n_cols = lev.shape[1]
    level = np.float32(deep_level)
    out = np.empty(near.shape[0], np.int64)
    for q in range(near.shape[0]):
        r, a, b = row[q], near[q], far[q]
        out[q] = b - a
        if a > n_cols - 3:
            continue
        for c in range(a, b - 2):  # the three pixels c, c + 1, c + 2 lie within the run
            if lev[r, c] >= level and lev[r, c + 1] >= level and lev[r, c + 2] >= level:
                out[q] = c - a
                break
    return out
