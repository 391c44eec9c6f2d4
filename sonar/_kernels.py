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
def _mirrored_line(src, i, r, line):
    """Row ``i`` of ``src`` in float64 with ``r`` values mirrored beyond each end (scipy's
    ``reflect``: ``d c b a | a b c d | d c b a``) into ``line`` (length C + 2r)."""
    n_cols = src.shape[1]
    for k in range(n_cols):
        line[k + r] = np.float64(src[i, k])
    for k in range(1, r + 1):
        line[r - k] = line[r + k - 1]
        line[r + n_cols - 1 + k] = line[r + n_cols - k]


@jit(cache=True)
def _gauss_cols(src, w, out):
    """``NI_Correlate1D`` (symmetric ``w``, odd length) along axis 1 of ``src`` into ``out``
    (float32): a row at a time, every element's sum in scipy's order."""
    n_rows, n_cols = src.shape
    r = w.shape[0] // 2
    line = np.empty(n_cols + 2 * r)
    acc = np.empty(n_cols)
    for i in range(n_rows):
        _mirrored_line(src, i, r, line)
        w0 = w[r]
        # the shifted lines as views indexed by the loop variable alone: with ``k + r − j``
        # numba could not rule out a negative index, and its wrap-around test kept the loop
        # from vectorising (this pass 0.37 → 0.14 ms on a 218 × 1000 image)
        mid = line[r:r + n_cols]
        for k in range(n_cols):
            acc[k] = mid[k] * w0
        for j in range(r, 0, -1):
            wj = w[r - j]
            left = line[r - j:r - j + n_cols]
            right = line[r + j:r + j + n_cols]
            for k in range(n_cols):
                acc[k] += (left[k] + right[k]) * wj
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
def uniform_filter_rows(src, size, out):
    """``scipy.ndimage.uniform_filter1d(src, size, axis=1)`` (mode ``reflect``) of a float32
    (R, C) image into ``out`` float32 (:func:`_box_cols`; ``size`` ≤ C)."""
    _box_cols(src, size, out)


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
    # every row with data in the same columns (a waterfall: the columns beyond the slant range
    # in every ping): then the rows of the mask's filters are all equal after their pass along
    # the rows (each sum in one order, of equal lines), and the pass along the columns is made
    # for the first row only, which stands for every row (less memory written and read)
    same_rows = True
    for i in range(1, n_rows):
        differ = False
        for k in range(n_cols):  # (no break in the row: the loop vectorises, 0.21 → 0.01 ms)
            differ |= data[i, k] != data[0, k]
        if differ:
            same_rows = False
            break
    m_rows = 1 if same_rows else n_rows
    # (equal rows: the rows pass of as many rows as its reflections reach gives the same sums)
    s_rows = min(n_rows, max(w_rows.shape[0], box_rows)) if same_rows else n_rows
    for i in range(s_rows):
        for k in range(n_cols):
            msk[i, k] = np.float32(data[i, k])
    _gauss_rows(x, w_rows, tmp)
    _gauss_cols_fused(tmp, w_cols, img)
    _gauss_rows(msk[:s_rows], w_rows, tmp[:s_rows])
    _gauss_cols_fused(tmp[:m_rows], w_cols, wgt[:m_rows])
    # (selects, not branches: the loops vectorise; a pixel without weight divides by 1)
    for i in range(n_rows):
        wgt_row = wgt[0] if same_rows else wgt[i]
        for k in range(n_cols):
            w = wgt_row[k]
            ok = w > min_weight
            q = np.float32(np.float64(img[i, k]) / np.float64(w if ok else one))
            v = q if ok else zero
            img[i, k] = v
            x[i, k] = v if data[i, k] else zero  # num's input: the image where there is data
    num = wgt
    _box_rows(x, box_rows, tmp)
    _box_cols(tmp, box_cols, num)
    den = x
    _box_rows(msk[:s_rows], box_rows, tmp[:s_rows])
    _box_cols(tmp[:m_rows], box_cols, den[:m_rows])
    for i in range(n_rows):
        den_row = den[0] if same_rows else den[i]
        for k in range(n_cols):
            d = den_row[k]
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


@jit(cache=True)
def _root(parent, a):
    """Root of ``a`` in the union-find forest ``parent`` (paths halved on the way)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@jit(cache=True)
def _segments8(mask, seg, label):
    """The 8-connected components of ``mask`` (R, C) bool by its segments (the runs of True
    pixels along a row): the segments in raster order into ``seg`` (3, ≥ R ⌈C / 2⌉) int64 —
    row, first column, one past the last — and each one's component into ``label`` (≥ as many)
    int64, numbered 1…n in the raster order of the components' first pixels, as
    ``scipy.ndimage.label`` numbers them (a component's first segment holds its first pixel).
    Returns (segments, n).

    A segment joins those of the row above that overlap it or touch it diagonally; the
    union-find links every set to its earliest segment. One pass over the pixels, then work per
    segment: a shadow mask is a few per cent of the image (scipy's line buffers, then a union-find
    per pixel, took 2-3 times longer)."""
    n_rows, n_cols = mask.shape
    row_first = np.empty(n_rows + 1, np.int64)
    m = 0
    for i in range(n_rows):
        row_first[i] = m
        k = 0
        while k < n_cols:
            if mask[i, k]:
                seg[0, m] = i
                seg[1, m] = k
                while k < n_cols and mask[i, k]:
                    k += 1
                seg[2, m] = k
                m += 1
            k += 1  # (k is past the segment's end: a False pixel or the row's end)
    row_first[n_rows] = m
    parent = np.empty(max(m, 1), np.int64)
    for j in range(m):
        parent[j] = j
    for i in range(1, n_rows):
        p, p_end = row_first[i - 1], row_first[i]
        for j in range(row_first[i], row_first[i + 1]):
            first, stop = seg[1, j], seg[2, j]
            while p < p_end and seg[2, p] < first:  # ends left of the column before this one's
                p += 1
            q = p
            while q < p_end and seg[1, q] <= stop:  # starts at most at the column after its last
                a, b = _root(parent, j), _root(parent, q)
                if a < b:
                    parent[b] = a
                elif b < a:
                    parent[a] = b
                q += 1
    n = 0
    for j in range(m):  # (a root precedes its set's segments: every root is final before it is read)
        r = _root(parent, j)
        if r == j:
            n += 1
            label[j] = n
        else:
            label[j] = label[r]
    return m, n


@jit(cache=True)
def _fill_labels(seg, label, m, lab):
    """The label image ``lab`` (R, C) int32 of the ``m`` segments (:func:`_segments8`), 0 elsewhere."""
    n_rows, n_cols = lab.shape
    for i in range(n_rows):
        for k in range(n_cols):
            lab[i, k] = 0
    for j in range(m):
        i = seg[0, j]
        for k in range(seg[1, j], seg[2, j]):
            lab[i, k] = label[j]


@jit(cache=True)
def _true_count(mask):
    """Pixels of ``mask`` set (a bound of its segments, components and component rows)."""
    n = 0
    for i in range(mask.shape[0]):
        for k in range(mask.shape[1]):
            n += mask[i, k]
    return n


@jit(cache=True)
def label8(mask, lab):
    """``scipy.ndimage.label(mask, structure=np.ones((3, 3)))`` into ``lab`` (int32, (R, C)):
    the 8-connected components of ``mask`` numbered 1…n (:func:`_segments8`). Returns n."""
    cap = _true_count(mask)
    seg = np.empty((3, max(cap, 1)), np.int64)
    label = np.empty(max(cap, 1), np.int64)
    m, n = _segments8(mask, seg, label)
    _fill_labels(seg, label, m, lab)
    return n


@jit(cache=True)
def label8_runs(mask, lev, lab, runs, n_px, shadow_sum, counts):
    """:func:`label8` of ``mask`` into ``lab`` and :func:`adaptnav.sonar.objects._component_rows_numpy`
    of it from the segments: per component and row (by label, then row) into ``runs`` (4,
    ≥ the pixels set) int64 — label, row, first column, one past the last — and per label (index
    0 the background, left 0) the pixel count ``n_px`` (int64, ≥ n + 1) and the sum of ``lev`` (R,
    C, any strides) over its pixels ``shadow_sum`` (float64, ≥ n + 1), added in raster order as
    ``numpy.bincount`` adds them. ``counts`` ← (n, runs)."""
    cap = runs.shape[1]  # (≥ the segments: the caller's count of the pixels set)
    seg = np.empty((3, max(cap, 1)), np.int64)
    label = np.empty(max(cap, 1), np.int64)
    m, n = _segments8(mask, seg, label)
    _fill_labels(seg, label, m, lab)
    last_row = np.full(n + 1, -1, np.int64)
    count = np.zeros(n + 1, np.int64)
    for j in range(m):
        q = label[j]
        if last_row[q] != seg[0, j]:
            last_row[q] = seg[0, j]
            count[q] += 1
    nxt = np.zeros(n + 1, np.int64)  # each label's next run (its first, then on)
    for q in range(1, n):
        nxt[q + 1] = nxt[q] + count[q]
    n_runs = nxt[n] + count[n] if n > 0 else 0
    last_row[:] = -1
    for q in range(n + 1):
        n_px[q] = 0
        shadow_sum[q] = 0.0
    for j in range(m):  # raster order: a component's pixels in raster order too
        q = label[j]
        i, a, b = seg[0, j], seg[1, j], seg[2, j]
        n_px[q] += b - a
        for k in range(a, b):
            shadow_sum[q] += np.float64(lev[i, k])
        if last_row[q] != i:  # the component's first segment on this row
            last_row[q] = i
            r = nxt[q]
            nxt[q] = r + 1
            runs[0, r] = q
            runs[1, r] = i
            runs[2, r] = a
        runs[3, nxt[q] - 1] = b
    counts[0] = n
    counts[1] = n_runs


@jit(cache=True)
def _pairwise_leaf(a, lo, n):
    """``pairwise_sum`` of numpy for ``n`` ≤ 128 values: below 8 one by one from 0, else eight
    running sums added ((0+1)+(2+3))+((4+5)+(6+7)), then the rest one by one."""
    if n < 8:
        res = a[lo] - a[lo]  # 0 of a's type (the values summed here are finite levels)
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    stop = n - n % 8
    while i < stop:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@jit(cache=True)
def _pairwise_sum(a, lo, n):
    """``numpy.add.reduce`` of ``a[lo:lo + n]`` (contiguous, n ≥ 1) in ``a``'s dtype, in numpy's
    order (``pairwise_sum``: :func:`_pairwise_leaf` up to 128 values, beyond it the two halves,
    the first rounded down to a multiple of 8, added): the same bits as ``numpy.mean``'s sum.
    Its recursion walked with a stack of its own: numba's on-disk cache of a recursive function
    crashed the next process that loaded it."""
    if n <= 128:
        return _pairwise_leaf(a, lo, n)
    f_lo = np.empty(64, np.int64)   # the frames: start, count, halves done (depth ≤ log2 n)
    f_n = np.empty(64, np.int64)
    f_done = np.empty(64, np.int64)
    vals = np.empty(64, a.dtype)    # the sums of finished halves, innermost last
    sp, vp = 1, 0
    f_lo[0], f_n[0], f_done[0] = lo, n, 0
    while sp > 0:
        q = sp - 1
        m = f_n[q]
        if m <= 128:
            vals[vp] = _pairwise_leaf(a, f_lo[q], m)
            vp += 1
            sp -= 1
            continue
        m2 = m // 2
        m2 -= m2 % 8
        if f_done[q] == 0:
            f_done[q] = 1
            f_lo[sp], f_n[sp], f_done[sp] = f_lo[q], m2, 0
            sp += 1
        elif f_done[q] == 1:
            f_done[q] = 2
            f_lo[sp], f_n[sp], f_done[sp] = f_lo[q] + m2, m - m2, 0
            sp += 1
        else:
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
            sp -= 1
    return vals[0]


@jit(cache=True)
def _median_sorted_int(v, m):
    """``numpy.median`` of the first ``m`` integers of ``v`` (sorted here, in place)."""
    s = np.sort(v[:m])
    return (np.float64(s[(m - 1) // 2]) + np.float64(s[m // 2])) / 2.0


@jit(cache=True)
def shadowed_measures(lev, lab, run_label, run_row, run_near, run_far, deep, hl_run, hl_lead, hl_level, todo,
                      imeas, fmeas, sum32):
    """The per-candidate measurements of :func:`adaptnav.sonar.objects._detect_shadowed` for the
    components ``todo`` (labels, ascending), every number the Python loop took per candidate:

    ``imeas`` (T, 5) int64: L — the deep shadow (px, largest over the object's own rows),
    touches the image's end (0/1), first and last row of the object's span, the number of
    rows averaged for its centre; ``fmeas`` (T, 6) float64: median near column of all the
    component's rows, of its own rows, median leading edge, the sum of the centre's rows
    (integers: exact in any order), the sum of the object's highlight levels (float64, in
    ``numpy.mean``'s order) and their number; ``sum32`` (T,) float32: the sum of ``lev`` over
    the component's pixels in raster order as ``numpy.mean`` adds a float32 array (pairwise).

    ``run_*`` (:class:`adaptnav.sonar.objects._Runs`, by label then row), ``deep`` the deep
    shadow per run, ``hl_*`` (:class:`adaptnav.sonar.objects._Highlights`; ``hl_run`` ascending).
    The floating-point steps left (ranges, height, contrast, interpolation) stay in numpy."""
    n_rows, n_cols = lev.shape
    n_todo = todo.shape[0]
    n_runs = run_label.shape[0]
    n_hl = hl_run.shape[0]
    # the highlight rows' labels (ascending, as hl_run is)
    hl_label = np.empty(n_hl, np.int64)
    for q in range(n_hl):
        hl_label[q] = run_label[hl_run[q]]
    # the candidates' pixels, gathered in raster order (each component's in its own slot)
    count = np.zeros(n_todo + 1, np.int64)
    first_run = np.empty(n_todo, np.int64)
    stop_run = np.empty(n_todo, np.int64)
    for t in range(n_todo):
        first_run[t] = np.searchsorted(run_label, todo[t])
        stop_run[t] = np.searchsorted(run_label, todo[t] + 1)
        span = 0
        for j in range(first_run[t], stop_run[t]):  # ≥ the component's pixels: its runs' spans
            span += run_far[j] - run_near[j]
        count[t + 1] = count[t] + span
    px = np.empty(count[n_todo], np.float32)
    fill = count[:n_todo].copy()
    for t in range(n_todo):
        k = todo[t]
        r0, r1 = run_row[first_run[t]], run_row[stop_run[t] - 1]
        c0, c1 = n_cols, 0
        for j in range(first_run[t], stop_run[t]):
            c0 = min(c0, run_near[j])
            c1 = max(c1, run_far[j])
        for i in range(r0, r1 + 1):  # its box in raster order, as lev[sl][lab[sl] == k]
            for c in range(c0, c1):
                if lab[i, c] == k:
                    px[fill[t]] = lev[i, c]
                    fill[t] += 1
    for t in range(n_todo):
        sum32[t] = _pairwise_sum(px, count[t], fill[t] - count[t])
    buf = np.empty(max(n_runs, 1), np.int64)
    vals = np.empty(max(n_hl, 1))
    for t in range(n_todo):
        k = todo[t]
        a0, a1 = first_run[t], stop_run[t]
        m = a1 - a0
        for j in range(m):
            buf[j] = run_near[a0 + j]
        fmeas[t, 0] = _median_sorted_int(buf, m)
        h0 = np.searchsorted(hl_label, k)
        h1 = np.searchsorted(hl_label, k + 1)
        # the run of highlight rows around the brightest (the first brightest), gaps ≤ 2 rows
        best = h0
        for q in range(h0 + 1, h1):
            if hl_level[q] > hl_level[best]:
                best = q
        a, b = best, best
        while a > h0 and run_row[hl_run[a]] - run_row[hl_run[a - 1]] <= 3:
            a -= 1
        while b < h1 - 1 and run_row[hl_run[b + 1]] - run_row[hl_run[b]] <= 3:
            b += 1
        top_row, bottom_row = run_row[hl_run[a]], run_row[hl_run[b]]
        # the object's own rows: the component's rows beside them
        m_own = 0
        deep_max = 0
        touches = 0
        row_sum = 0.0
        span0, span1 = top_row, bottom_row
        first_own, last_own = -1, -1
        for j in range(a0, a1):
            r = run_row[j]
            if r >= top_row - 1 and r <= bottom_row + 1:
                buf[m_own] = run_near[j]
                if m_own == 0 or deep[j] > deep_max:
                    deep_max = deep[j]
                if run_far[j] >= n_cols - 1:
                    touches = 1
                row_sum += np.float64(r)
                if first_own < 0:
                    first_own = r
                last_own = r
                m_own += 1
        fmeas[t, 1] = _median_sorted_int(buf, m_own)
        span0 = min(span0, first_own)
        span1 = max(span1, last_own)
        for q in range(a, b + 1):
            buf[q - a] = hl_lead[q]
            row_sum += np.float64(run_row[hl_run[q]])
            vals[q - a] = np.float64(hl_level[q])
        fmeas[t, 2] = _median_sorted_int(buf, b + 1 - a)
        fmeas[t, 3] = row_sum
        fmeas[t, 4] = _pairwise_sum(vals, 0, b + 1 - a)
        fmeas[t, 5] = np.float64(b + 1 - a)
        imeas[t, 0] = deep_max
        imeas[t, 1] = touches
        imeas[t, 2] = span0
        imeas[t, 3] = span1
        imeas[t, 4] = m_own + (b + 1 - a)



@jit(cache=True)
def shadow_candidates(lev, run_label, run_row, run_near, run_far, n_px, shadow_sum, deep, h_max_m, res_m,
                      min_shadow_px, short_range_m, min_cols, short_cols, min_col0, hw, highlight_level, least,
                      min_highlight_rows, min_height_m, hl_run, hl_lead, hl_level, todo, counts):
    """The tests of :func:`adaptnav.sonar.objects._detect_shadowed` before its candidates are
    measured, for every component at once — :func:`adaptnav.sonar.objects._shadow_candidates`,
    :func:`~adaptnav.sonar.objects._may_be_high`, :func:`~adaptnav.sonar.objects._highlights`
    and the contrast bound, in that order (:func:`adaptnav.sonar.objects._candidates_numpy` is
    the reference): the highlight rows of the components that pass the size and height tests
    into ``hl_run``, ``hl_lead``, ``hl_level`` (≥ the runs), the labels to measure into ``todo``
    (≥ the labels); ``counts`` ← (highlight rows, labels to measure). The height bound, cheap,
    comes before the highlight windows are scanned: three in four components that reach it fail it.

    ``h_max_m``: the highest finite altitude (NaN: none, every component may be high); the
    thresholds compared as numpy compares them (a float32 image with a Python float: in float32)."""
    n_cols = lev.shape[1]
    n_runs = run_label.shape[0]
    n_lab = n_px.shape[0] - 1
    start = np.zeros(n_lab + 2, np.int64)  # each label's first run (every label 1…n has rows)
    for j in range(n_runs):
        start[run_label[j] + 1] = j + 1
    for q in range(1, n_lab + 2):  # (labels are ascending: the last run of each, then filled forward)
        if start[q] < start[q - 1]:
            start[q] = start[q - 1]
    lit_level = np.float32(highlight_level)
    bright = np.float32(0.5 * (1.0 + highlight_level))
    buf = np.empty(max(n_runs, 1), np.int64)
    win = np.empty(max(hw, 1), np.float32)
    n_hl = 0
    n_todo = 0
    for q in range(1, n_lab + 1):
        if n_px[q] < min_shadow_px:  # (the first test below: most components are a few pixels of speckle)
            continue
        a, b = start[q], start[q + 1]
        m = b - a
        longest = 0
        for j in range(a, b):
            buf[j - a] = run_near[j]
            if j == a or run_far[j] - run_near[j] > longest:
                longest = run_far[j] - run_near[j]
        s = buf[:m]
        s.sort()
        med = (np.float64(s[(m - 1) // 2]) + np.float64(s[m // 2])) / 2.0
        short = med * res_m < short_range_m
        if not (longest >= (short_cols if short else min_cols) and med >= min_col0):
            continue
        # the height's upper bound (from the highest altitude, the deepest shadow, the nearest column)
        if not np.isnan(h_max_m):
            d_max, near_min, far_max = deep[a], run_near[a], run_far[a]
            for j in range(a + 1, b):
                d_max = max(d_max, deep[j])
                near_min = min(near_min, run_near[j])
                far_max = max(far_max, run_far[j])
            L = d_max * res_m
            ub = h_max_m * L / ((near_min + 0.5) * res_m + L)
            if not (far_max >= n_cols - 1 or not (ub < min_height_m * (1.0 - 1e-9))):
                continue
        # its rows with a highlight in the hw columns before the shadow
        first_hl = n_hl
        top = -np.inf
        for j in range(a, b):
            cn = run_near[j]
            if cn <= 0:  # a shadow from column 0 has nothing before it
                continue
            r = run_row[j]
            best = 0
            for t in range(hw):  # the window, columns cn − hw … cn − 1 (−inf before column 0)
                c = cn - hw + t
                win[t] = lev[r, c] if c >= 0 else np.float32(-np.inf)
            for t in range(hw):  # numpy's argmax: the first NaN, else the first largest
                if np.isnan(win[t]):
                    best = t
                    break
                if win[t] > win[best]:
                    best = t
            v = win[best]
            if not v > lit_level:
                continue
            jj = 0  # first bright column of the run of bright pixels up to the brightest
            for t in range(best):
                if not (win[t] > bright) or cn - hw + t < 0:
                    jj = t + 1
            hl_run[n_hl] = j
            hl_lead[n_hl] = cn - hw + jj
            hl_level[n_hl] = v
            n_hl += 1
            if np.float64(v) > top:
                top = np.float64(v)
        if n_hl - first_hl < max(min_highlight_rows, 1):
            continue
        # the contrast's upper bound: the brightest highlight over the whole shadow's mean
        mean = shadow_sum[q] / max(n_px[q], 1)
        if not (top / max(mean, 1e-3) >= least * (1 - 1e-6)):
            continue
        todo[n_todo] = q
        n_todo += 1
    counts[0] = n_hl
    counts[1] = n_todo


@jit(cache=True)
def slant_to_ground(samples, spacing_m, altitude_m, ground_m, out):
    """:func:`adaptnav.sonar.waterfall.slant_to_ground_numpy` into ``out`` (P, n_out) float32,
    any strides (a side of the waterfall image, the port side reversed): ``samples`` (P, N)
    float32, ``altitude_m`` (P,) float32 (NaN replaced), ``ground_m`` (n_out,) float32 the
    columns' ground ranges. Every step in float32 as numpy takes it (squares, sum, square root,
    the division by the spacing rounded to float32, then ``− 0.5``, the floor, the linear
    interpolation ``a + f (b − a)``); 0 where the slant index is outside the samples. The
    slant indices are computed again only when the altitude changes from one ping to the next
    (the altimeter's reading is often the same for many pings)."""
    n_rows, n = samples.shape
    n_out = ground_m.shape[0]
    spacing = np.float32(spacing_m)
    half, zero = np.float32(0.5), np.float32(0.0)
    first = np.empty(n_out, np.int64)      # the slant samples each column lies between (clipped)
    frac = np.empty(n_out, np.float32)
    valid = np.empty(n_out, np.bool_)
    for i in range(n_rows):
        h = altitude_m[i]
        if i == 0 or not h == altitude_m[i - 1]:
            h2 = h * h
            for j in range(n_out):
                g = ground_m[j]
                k = np.sqrt(g * g + h2) / spacing - half
                k0 = np.floor(k)
                frac[j] = k - k0
                # tested before the integer conversion (k may be inf)
                valid[j] = k0 >= 0 and k0 < n - 1
                first[j] = int(k0) if valid[j] else (0 if not k0 >= 0 else n - 2)
        for j in range(n_out):
            a = samples[i, first[j]]
            v = a + frac[j] * (samples[i, first[j] + 1] - a)
            out[i, j] = v if valid[j] else zero


@jit(cache=True)
def bracket_rows(s, lo_v, hi_v, below, count, cand):
    """Per row ``i`` of ``s`` (R, M) float32: how many values are below ``lo_v[i]`` (``below``)
    and how many lie in ``[lo_v[i], hi_v[i]]`` (``count``), the first ``W`` of the latter (in
    row order) in ``cand[i]`` (R, W) float32, the rest of that row +inf
    (:func:`adaptnav.sonar.waterfall.row_medians`: the sorted row's middle values are the
    sorted candidates' ``r − below`` th when ``below ≤ r < below + count ≤ W``). Every value
    is stored and the counters advanced by the comparisons (no branch per value)."""
    n_rows, m = s.shape
    width = cand.shape[1]
    buf = np.empty(m + 1, np.float32)
    for i in range(n_rows):
        a = lo_v[i]
        b = hi_v[i]
        n_below = 0
        n = 0
        for k in range(m):
            v = s[i, k]
            n_below += v < a
            buf[n] = v
            n += (v >= a) & (v <= b)
        below[i] = n_below
        count[i] = n
        n_kept = min(n, width)
        for k in range(n_kept):
            cand[i, k] = buf[k]
        for k in range(n_kept, width):
            cand[i, k] = np.inf


@jit(cache=True)
def _gauss_cols_fused(src, w, out):
    """:func:`_gauss_cols` (the same sums in the same order: ``i₀ w₀``, then the pairs from the
    farthest in), for a half-width ``r`` ≤ 3 in one pass per row that keeps each sum in a
    register (the shifted lines as views, so that the loop vectorises; 0.41 → 0.20 ms on a
    200 × 1000 image for the detector's r = 3); wider kernels by :func:`_gauss_cols`."""
    r = w.shape[0] // 2
    if r > 3:
        _gauss_cols(src, w, out)
        return
    n_rows, n_cols = src.shape
    line = np.empty(n_cols + 2 * r)
    w0 = w[r]
    for i in range(n_rows):
        _mirrored_line(src, i, r, line)
        mid = line[r:r + n_cols]
        o = out[i]
        if r == 3:
            wa, wb, wc = w[0], w[1], w[2]
            la, ra = line[0:n_cols], line[6:6 + n_cols]
            lb, rb = line[1:1 + n_cols], line[5:5 + n_cols]
            lc, rc = line[2:2 + n_cols], line[4:4 + n_cols]
            for k in range(n_cols):
                acc = mid[k] * w0
                acc += (la[k] + ra[k]) * wa
                acc += (lb[k] + rb[k]) * wb
                acc += (lc[k] + rc[k]) * wc
                o[k] = np.float32(acc)
        elif r == 2:
            wa, wb = w[0], w[1]
            la, ra = line[0:n_cols], line[4:4 + n_cols]
            lb, rb = line[1:1 + n_cols], line[3:3 + n_cols]
            for k in range(n_cols):
                acc = mid[k] * w0
                acc += (la[k] + ra[k]) * wa
                acc += (lb[k] + rb[k]) * wb
                o[k] = np.float32(acc)
        elif r == 1:
            wa = w[0]
            la, ra = line[0:n_cols], line[2:2 + n_cols]
            for k in range(n_cols):
                acc = mid[k] * w0
                acc += (la[k] + ra[k]) * wa
                o[k] = np.float32(acc)
        else:
            for k in range(n_cols):
                o[k] = np.float32(mid[k] * w0)


@jit(cache=True)
def _extended_line(src, i, size, line):
    """Row ``i`` of ``src`` in float64, reflect-extended for a running sum of ``size``:
    ``line[j] = src[i, k]`` with ``k`` the reflection of ``j − size // 2 − 1`` (j < C + size)."""
    n_cols = src.shape[1]
    off = size // 2 + 1
    for j in range(off):
        line[j] = np.float64(src[i, _reflect(j - off, n_cols)])
    row = src[i]
    mid = line[off:off + n_cols]
    for k in range(n_cols):
        mid[k] = np.float64(row[k])
    for j in range(off + n_cols, n_cols + size):
        line[j] = np.float64(src[i, _reflect(j - off, n_cols)])


@jit(cache=True)
def _box_cols(src, size, out):
    """``NI_UniformFilter1D`` of ``size`` along axis 1 of ``src`` into ``out`` (float32): scipy's
    running sums (``S₀`` from the first ``size`` values in order, then ``Sₖ = Sₖ₋₁ +
    (i_{k+size−1−s₁} − i_{k−1−s₁})``, each divided by ``size``), four rows at a time from
    reflect-extended float64 copies of them (:func:`_extended_line`): each sum's values read in
    order from its own line, the four running sums side by side (0.5 → 0.2 ms on a 200 × 1000
    image against eight rows' sums kept a column at a time: their strided reads were the cost)."""
    n_rows, n_cols = src.shape
    fs = np.float64(size)
    lines = np.empty((4, n_cols + size))
    sums = np.empty((4, n_cols))
    i = 0
    while i < n_rows:
        m = min(4, n_rows - i)
        for q in range(m):
            _extended_line(src, i + q, size, lines[q])
        if m == 4:
            l0, l1, l2, l3 = lines[0], lines[1], lines[2], lines[3]
            s0, s1, s2, s3 = sums[0], sums[1], sums[2], sums[3]
            a0 = a1 = a2 = a3 = 0.0
            for j in range(1, size + 1):
                a0 += l0[j]
                a1 += l1[j]
                a2 += l2[j]
                a3 += l3[j]
            s0[0], s1[0], s2[0], s3[0] = a0, a1, a2, a3
            for k in range(1, n_cols):
                a0 += l0[k + size] - l0[k]
                s0[k] = a0
                a1 += l1[k + size] - l1[k]
                s1[k] = a1
                a2 += l2[k + size] - l2[k]
                s2[k] = a2
                a3 += l3[k + size] - l3[k]
                s3[k] = a3
        else:
            for q in range(m):
                lq, sq = lines[q], sums[q]
                a = 0.0
                for j in range(1, size + 1):
                    a += lq[j]
                sq[0] = a
                for k in range(1, n_cols):
                    a += lq[k + size] - lq[k]
                    sq[k] = a
        for q in range(m):
            o, sq = out[i + q], sums[q]
            for k in range(n_cols):
                o[k] = np.float32(sq[k] / fs)
        i += m


@jit(cache=True)
def first_return_rows(smoothed, raw, level, threshold, n_blank, spacing_m, out):
    """:func:`adaptnav.sonar.waterfall.detect_first_return`'s pick per ping (row), given each row's
    ``level`` and ``threshold`` (float32): the first sample from ``n_blank`` on whose ``smoothed``
    value exceeds the threshold, moved to the first of the ``raw`` samples two before to two after
    it (clipped to the row) that exceeds it too; ``out[i]`` ← its slant range ``(k + ½) spacing_m``,
    NaN when there is none or the level is ≤ 0. ``smoothed``, ``raw`` (P, N) float32; the
    comparisons in float32, as numpy's of a float32 array (one pass per row instead of a
    dozen numpy steps over the whole block)."""
    n_rows, n = smoothed.shape
    for i in range(n_rows):
        t = threshold[i]
        k = -1
        for j in range(n_blank, n):
            if smoothed[i, j] > t:
                k = j
                break
        if k < 0 or level[i] <= 0:
            out[i] = np.nan
            continue
        shift = 0
        for o in range(-2, 3):
            if raw[i, min(max(k + o, 0), n - 1)] > t:
                shift = o
                break
        out[i] = (np.float64(k + shift) + 0.5) * spacing_m


@jit(cache=True)
def median_filter_nearest(x, size, out):
    """``scipy.ndimage.median_filter(x, size, mode="nearest")`` of a 1-D float64 ``x`` into ``out``:
    per sample the value of rank ``size // 2`` of its window (the ends repeated), each window
    sorted by insertion with NaN last, as numpy sorts (:func:`adaptnav.sonar.waterfall.median_filter_nearest`)."""
    n = x.shape[0]
    before = size // 2
    win = np.empty(size)
    for i in range(n):
        for t in range(size):
            v = x[min(max(i - before + t, 0), n - 1)]
            q = t
            while q > 0 and (win[q - 1] > v or (win[q - 1] != win[q - 1] and v == v)):
                win[q] = win[q - 1]
                q -= 1
            win[q] = v
        out[i] = win[before]

