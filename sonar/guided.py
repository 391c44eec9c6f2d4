r"""Guided re-detection: an object seen on one leg, looked for where a loop closure says it must be on the other.

Once two legs' sightings agree on one offset of the navigation error (a loop closure, its
fitted :class:`~adaptnav.sonar.association.Drift`), an object seen on one leg and not on the
other has a predicted place in the other leg's canonical (ground-range) image to a few
decimetres: ``p_b = p_a − δ(t_a, t_b)`` on the jump-free tracks, with the residual covariance
``R`` of the set's prediction plus both detectors'. The detector looks for objects over the
whole image, so its thresholds must keep the false alarms of ~10⁶ pixels per leg low; here
only the positions inside the prediction's gate (``χ²₂`` at ``gate_probability``, tens of
pixels) are tested, and the test's false-alarm rate is set by that area.

The test (:func:`redetect`) on the image *before* the median filter (which erases a tyre's
one- or two-pixel tread near the nadir), divided by its local background (box mean over
``background_m``):

* a template from what the other leg saw: as many rows as the object is long along-track
  (its ``length_along_m``); on each row the brightest of ``window_cols`` columns (the lit face:
  a tyre's is a curved arc, a boulder's a flank) and the darkest of the next ``window_cols``
  (its shadow, a pixel or two near the nadir);
* the statistic ``S``: the mean over those rows of log(brightest) − log(darkest) (levels
  floored at ``shadow_floor``), at every template position;
* the searched region: the bounding box of the prediction's gate (``χ²₂`` at
  ``gate_probability`` of ``R``); the test statistic is the largest ``S`` in it;
* its null distribution is the image's own: the same test (the largest ``S`` over a box of
  that size) at every other place of a stripe of the same leg at the same ground ranges
  (``± null_rows`` rows, box centres within ``null_cols_m`` across), away from the searched
  rows and from the detector's own sightings on that leg (a place the test runs holds none:
  an ordinary sighting inside the gate makes the associator's own tests responsible). ``p``
  is the fraction of those places where the test would have fired as strongly (undetected
  objects of the stripe stay in it: conservative), and the object is re-detected when
  ``p ≤ false_alarm``. No Gaussian or speckle model is assumed: the sediment's texture at that
  range on that leg is the null.

Measured (survey seed 1, true positions ± 0.25 m, a gate of σ 0.35 m, ``p ≤ 0.003``):
re-detected tyres at 10–20 m 82 %, at 5–10 m 27 %, boulders 83–88 %; 0–1 % of 300 places
without an object fired. The first statistic tried, a 2-px highlight box followed by the
predicted shadow, found tyres at 10–20 m 68 %; the mean |log level| 65 %, the highlight alone
26 %; weighting the box by the prediction's likelihood lost power (its centre and the object's
reported place differ by side). With the stripe's detected objects left *in* the null, boulders
were re-detected 45 % (one object in the stripe as strong as the target sets ``p`` ≈ 0.02).

What is found is an :class:`~adaptnav.sonar.objects.ObjectSighting` marked ``weak`` and
``guided`` (placed with the navigation at its row): the associator reports the pair with the
closure's ``weak_pairs`` — scored, not fused (:meth:`~adaptnav.sonar.association.LegAssociator.add`).

:class:`ImageStore` keeps the canonical image rows (before the median, float16) and the
navigation at each row for ``memory_s``: one leg of the survey and the turn (~400 s at 1.5 m/s
for 500 m legs), ~1000 columns × 10 rows/s × 2 bytes: ~20 kB/s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import maximum_filter

from adaptnav.fusion.integrity import chi2_quantile
from adaptnav.sonar.objects import ObjectDetectorConfig, ObjectSighting, local_level, with_navigation


@dataclass(frozen=True)
class GuidedConfig:
    """Settings of :func:`redetect` (see the module docstring).

    Attributes
    ----------
    false_alarm : float
        Re-detected when ``p ≤ false_alarm`` (``p``: Bonferroni over the searched positions of
        the stripe's empirical tail).
    gate_probability : float
        χ²₂ probability of the searched region about the prediction.
    max_gate_m : float
        Not tested when the region's half-axis exceeds this (m): the prediction is too vague.
    max_extrapolation_s : float
        Only sightings within this (s) of the set's own pairs on their leg are looked for on
        the other: the set's drift (a constant velocity error per leg) is interpolated, not
        carried far beyond its pairs.
    placement_sigma_m : float
        1-σ (m) of the re-detected object's place (the template's row and column), with the
        seen sighting's detector covariance in the prediction's.
    null_rows : int
        Rows on each side of the prediction in the null stripe.
    min_null : int
        Not tested with fewer places in the null (the stripe cut by the image's end).
    null_cols_m : float
        The null's places lie within this (m) across-track of the prediction (the same ground ranges).
    background_m : float
        Box (m) of the local background.
    window_cols : int
        Per row, the brightest of this many columns (the lit face) and the darkest of the next
        as many (the shadow); the statistic is their log-ratio averaged over the object's rows.
    min_rows, max_rows : int
        The object's rows: the other leg's ``length_along_m`` clipped.
    shadow_floor : float
        The levels in the statistic are floored at this (a shadow's is noise, ~0).
    min_ground_range_m, max_ground_range_m : float
        Tested only where the prediction's ground range is inside these (m).
    max_turn_rad : float
        Not tested where the heading changes more than this over ± 10 rows.
    max_heading_diff_rad : float
        The seen sighting and the rows searched are on the legs of the set: headings within this
        of the set's on each leg (rad). A prediction carried past a turn onto the next leg
        (the set's window reaches ±150 s) is meaningless there: survey seeds 3–4, 4 false pairs of
        51, each found 3–6 m from the object.
    """

    false_alarm: float = 0.003
    gate_probability: float = 0.99
    max_gate_m: float = 3.0
    placement_sigma_m: float = 0.15
    max_extrapolation_s: float = 30.0
    null_rows: int = 600
    min_null: int = 2000
    null_cols_m: float = 1.0
    background_m: float = 6.0
    window_cols: int = 3
    min_rows: int = 2
    max_rows: int = 12
    shadow_floor: float = 0.05
    min_ground_range_m: float = 4.5
    max_ground_range_m: float = 47.0
    max_turn_rad: float = 0.15
    max_heading_diff_rad: float = 0.3


class ImageStore:
    """Canonical image rows (before the median) with the navigation at each row, ``memory_s`` of them.

    Parameters
    ----------
    memory_s : float
        Rows older than this before the newest are dropped (s).
    """

    def __init__(self, memory_s: float = 900.0) -> None:
        self.memory_s = float(memory_s)
        self._chunks: list[dict] = []
        self.ground_res_m = math.nan
        self.n_side = 0

    def add(self, image: np.ndarray, ground_res_m: float, t_s, pos_n_m, yaw_rad, nav_cov, jump_n_m,
            vel_cov, altitude_m) -> None:
        """Append rows (one per ping, time-ordered).

        Parameters
        ----------
        image : (n, 2W) array
            Ground-range image rows, port flipped (:class:`~adaptnav.sonar.waterfall.Waterfall`).
        ground_res_m : float
        t_s : (n,) array
        pos_n_m : (n, 2) array
            The navigation's position at each row (m).
        yaw_rad : (n,) array
        nav_cov : (n, 2, 2) array
        jump_n_m : (n, 2) array or None
            Accumulated jumps (:attr:`~adaptnav.sonar.objects.ObjectSighting.jump_n_m`).
        vel_cov : (n, 2, 2) array
        altitude_m : (n, 2) array
            Altitude per row (port, starboard).
        """
        n = len(t_s)
        if n == 0:
            return
        if self._chunks and (image.shape[1] != 2 * self.n_side or ground_res_m != self.ground_res_m):
            self._chunks.clear()  # another geometry: the old rows cannot be searched with the new
        self.ground_res_m, self.n_side = float(ground_res_m), image.shape[1] // 2
        pos = np.asarray(pos_n_m, float).reshape(n, 2)
        jump = np.zeros((n, 2)) if jump_n_m is None else np.asarray(jump_n_m, float).reshape(n, 2)
        self._chunks.append({
            "t": np.asarray(t_s, float).copy(), "pos": pos.copy(), "smooth": pos - jump, "jump": jump.copy(),
            "yaw": np.asarray(yaw_rad, float).copy(), "cov": np.asarray(nav_cov, float).reshape(n, 2, 2).copy(),
            "vel_cov": np.asarray(vel_cov, float).reshape(n, 2, 2).copy(),
            "alt": np.asarray(altitude_m, float).reshape(n, 2).copy(),
            "image": np.asarray(image, np.float16).copy()})
        t_new = float(self._chunks[-1]["t"][-1])
        while self._chunks and self._chunks[0]["t"][-1] < t_new - self.memory_s:
            self._chunks.pop(0)

    def rows(self, t0_s: float, t1_s: float, heading_rad: float | None = None,
             max_heading_diff_rad: float = 0.3) -> dict | None:
        """The stored rows with ``t0_s ≤ t ≤ t1_s`` (and, given ``heading_rad``, a heading within
        ``max_heading_diff_rad`` of it: one leg, not the next after a turn), concatenated (None: none)."""
        parts = [c for c in self._chunks if c["t"][-1] >= t0_s and c["t"][0] <= t1_s]
        if not parts:
            return None
        out = {k: np.concatenate([c[k] for c in parts]) for k in parts[0]}
        m = (out["t"] >= t0_s) & (out["t"] <= t1_s)
        if heading_rad is not None:
            m &= np.abs(np.angle(np.exp(1j * (out["yaw"] - heading_rad)))) <= max_heading_diff_rad
        if not np.any(m):
            return None
        return {k: v[m] for k, v in out.items()}

    @property
    def nbytes(self) -> int:
        return sum(v.nbytes for c in self._chunks for v in c.values())


def abeam(rows: dict, target_n_m) -> tuple[int, str, float] | None:
    """The row abeam of a point on the jump-free track (its along-track offset changes sign
    there), the side and the ground range (m); None when the point is beyond the rows' ends or
    falls in a gap of the rows (pings missing: survey seed 4 has gaps of 1–20 s, where the rows
    either side are tens of metres apart)."""
    d = np.asarray(target_n_m, float)[None, :] - rows["smooth"]
    c, s = np.cos(rows["yaw"]), np.sin(rows["yaw"])
    along = d[:, 0] * c + d[:, 1] * s
    k = int(np.argmin(np.abs(along)))
    if k == 0 or k == along.size - 1:
        return None
    steps = np.hypot(*np.diff(rows["smooth"], axis=0).T)
    typical = float(np.median(steps))
    if max(steps[k - 1], steps[k]) > 2.0 * typical + 0.05 or abs(along[k]) > max(typical, 0.05):
        return None
    y = float(-d[k, 0] * s[k] + d[k, 1] * c[k])
    return k, ("starboard" if y > 0 else "port"), abs(y)


def redetect(store: ImageStore, seen: ObjectSighting, target_n_m, R, t0_s: float, t1_s: float,
             config: GuidedConfig = GuidedConfig(),
             detector: ObjectDetectorConfig = ObjectDetectorConfig(),
             exclude_n_m=None, heading_rad: float | None = None,
             rows: dict | None = None) -> tuple[ObjectSighting | None, dict]:
    """Look for ``seen``'s object at ``target_n_m`` (jump-free track; covariance ``R``, 2×2)
    in the stored rows of ``t0_s`` … ``t1_s`` (see the module docstring); ``exclude_n_m``: the
    (jump-free) positions of the detector's sightings on that leg, left out of the null;
    ``heading_rad``: that leg's heading (the rows of the next leg after a turn are not searched);
    ``rows``: ``store.rows(t0_s, t1_s, heading_rad, …)`` when the caller has them already.

    Returns
    -------
    sighting : ObjectSighting or None
        The object re-detected (``weak`` and ``guided``, placed with the navigation at its
        row), or None.
    info : dict
        ``reason`` (why not tested or not found, or ``"found"``), ``p`` when tested.
    """
    cfg = config
    if rows is None:
        rows = store.rows(t0_s, t1_s, heading_rad, cfg.max_heading_diff_rad)
    if rows is None:
        return None, {"reason": "no image"}
    ab = abeam(rows, target_n_m)
    if ab is None:
        return None, {"reason": "not abeam"}
    k0, side, g = ab
    if not cfg.min_ground_range_m <= g <= cfg.max_ground_range_m:
        return None, {"reason": "range"}
    n = rows["t"].size
    yaw_u = np.unwrap(rows["yaw"])
    if abs(yaw_u[min(k0 + 10, n - 1)] - yaw_u[max(k0 - 10, 0)]) > cfg.max_turn_rad:
        return None, {"reason": "turning"}
    res = store.ground_res_m
    c, s = math.cos(rows["yaw"][k0]), math.sin(rows["yaw"][k0])
    rot = np.array([[c, -s], [s, c]])  # columns: forward, starboard in (n, e)
    Rl = rot.T @ np.asarray(R, float) @ rot  # (along, across towards starboard)
    gate = chi2_quantile(cfg.gate_probability, 2)
    half_al, half_ac = math.sqrt(gate * Rl[0, 0]), math.sqrt(gate * Rl[1, 1])
    if max(half_al, half_ac) > cfg.max_gate_m:
        return None, {"reason": "gate"}
    step = np.hypot(*np.diff(rows["smooth"], axis=0).T)
    along_res = float(np.median(step)) if step.size else math.nan
    if not math.isfinite(along_res) or along_res <= 0:
        return None, {"reason": "no spacing"}
    si = 1 if side == "starboard" else 0
    H = float(rows["alt"][k0, si])
    length = seen.length_along_m if math.isfinite(seen.length_along_m) else 1.0
    n_r = int(np.clip(round(length / along_res), cfg.min_rows, cfg.max_rows))
    n_h = n_s = int(cfg.window_cols)  # the lit face's columns and the shadow's
    # the template's anchor (first row, highlight's first column) for an object centred at
    # (row, ground range): rows centre − (n_r − 1)/2 …, columns ground/res − ½ − 0.7 n_h
    # (the detector reports lead + top_weight × (top − lead))
    w = detector.top_weight
    c_obj = g / res - 0.5
    # the patch: the null stripe's rows, the columns of the stripe and a background box beyond
    r_lo, r_hi = max(k0 - cfg.null_rows, 0), min(k0 + cfg.null_rows + 1, n)
    half_c = (half_ac + cfg.null_cols_m) / res + 1
    bg_cols = int(round(cfg.background_m / res))
    c_lo = max(int(math.floor(c_obj - w * n_h - half_c)) - bg_cols, 0)
    c_hi = min(int(math.ceil(c_obj + half_c + n_h + n_s)) + bg_cols + 1, store.n_side)
    img = rows["image"][r_lo:r_hi].astype(np.float32)
    W = store.n_side
    side_img = img[:, W:] if side == "starboard" else img[:, W - 1::-1]
    patch = side_img[:, c_lo:c_hi]
    if patch.shape[0] < 3 * n_r or patch.shape[1] < n_h + n_s + 2:
        return None, {"reason": "edge"}
    lev = local_level(patch, res, along_res, replace(detector, smooth_px=(0.0, 0.0),
                                                    background_m=cfg.background_m))
    lev = np.log(np.maximum(lev, cfg.shadow_floor))
    # per row, the brightest of ``w`` columns and the darkest of the next ``w`` (a small
    # object's lit face is curved — a tyre's ring — and its shadow a pixel or two), averaged
    # over the object's rows
    n_c = lev.shape[1] - n_h - n_s + 1
    bright = np.max([lev[:, q:q + n_c] for q in range(n_h)], axis=0)
    dark = np.min([lev[:, n_h + q:n_h + q + n_c] for q in range(n_s)], axis=0)
    S = _box_mean(bright - dark, n_r, 1)
    # anchors (i, j) of S ↔ object centre row r_lo + i + (n_r − 1)/2, column c_lo + j + w n_h;
    # the searched region: the gate's bounding box about the prediction
    i_c = k0 - r_lo - 0.5 * (n_r - 1)
    j_c = c_obj - c_lo - w * n_h
    hr, hc = int(math.ceil(half_al / along_res)), int(math.ceil(half_ac / res))
    i0, i1 = int(round(i_c)) - hr, int(round(i_c)) + hr + 1
    j0, j1 = int(round(j_c)) - hc, int(round(j_c)) + hc + 1
    if i0 < 0 or j0 < 0 or i1 > S.shape[0] or j1 > S.shape[1]:
        return None, {"reason": "edge"}
    K = (i1 - i0) * (j1 - j0)
    # the searched rows are contiguous (no missing pings between them)
    r_steps = step[r_lo + i0:min(r_lo + i1 + n_r, n) - 1]
    if r_steps.size and float(r_steps.max()) > 2.0 * along_res + 0.05:
        return None, {"reason": "gap"}
    # the null: the same test (the largest S over a box of that size) at every other place of
    # the stripe — other rows, the same ground ranges (± null_cols_m)
    M = maximum_filter(S, size=(i1 - i0, j1 - j0), mode="constant", cval=-np.inf)
    ii = np.arange(S.shape[0])[:, None]
    jj = np.arange(S.shape[1])[None, :]
    ci, cj = 0.5 * (i0 + i1 - 1), 0.5 * (j0 + j1 - 1)  # the searched box's centre (M is centred)
    far = np.abs(ii - ci) >= (i1 - i0) + n_r
    inside = (ii >= hr) & (ii < S.shape[0] - hr) & (jj >= hc) & (jj < S.shape[1] - hc)
    cols = np.abs(jj - cj) * res <= cfg.null_cols_m
    keep = far & inside & cols
    # not where the detector found an object on this leg (a place the test runs has none)
    for q in () if exclude_n_m is None else exclude_n_m:
        ab_q = abeam(rows, q)
        if ab_q is None or ab_q[1] != side:
            continue
        iq = ab_q[0] - r_lo - 0.5 * (n_r - 1)
        jq = ab_q[2] / res - 0.5 - c_lo - w * n_h
        keep &= ~((np.abs(ii - iq) <= hr + n_r) & (np.abs(jj - jq) <= hc + n_h + n_s))
    null = M[keep]
    if null.size < cfg.min_null:
        return None, {"reason": "small null"}
    box = S[i0:i1, j0:j1]
    bi, bj = np.unravel_index(int(np.argmax(box)), box.shape)
    bi, bj = bi + i0, bj + j0
    s_max = float(S[bi, bj])
    p = (1 + int(np.count_nonzero(null >= s_max))) / (1 + null.size)
    info = {"reason": "not found", "p": p, "K": K, "n_null": int(null.size), "side": side, "g": g,
            "t_abeam": float(rows["t"][k0]), "box": (i1 - i0, j1 - j0)}
    if p > cfg.false_alarm:
        return None, info
    # the object re-detected: placed as the detector places its sightings
    r_c = r_lo + bi + 0.5 * (n_r - 1)
    ground = (c_lo + bj + 0.5 + w * n_h) * res
    kk = int(round(r_c))
    t = float(np.interp(r_c, np.arange(n), rows["t"]))
    pos = np.array([np.interp(r_c, np.arange(n), rows["pos"][:, q]) for q in range(2)])
    obj = ObjectSighting(t_s=t, side=side, ground_range_m=float(ground), height_m=math.nan,
                         shadow_length_m=n_s * res, length_along_m=n_r * along_res,
                         width_across_m=n_h * res, contrast=float(math.exp(s_max)), altitude_m=H,
                         row=float(r_c), weak=True, guided=True)
    vc = rows["vel_cov"][kk]
    out = with_navigation(obj, pos, rows["cov"][kk], float(np.interp(r_c, np.arange(n), yaw_u)), detector,
                          rows["jump"][kk], vc if np.isfinite(vc).all() else None)
    info["reason"] = "found"
    return out, info


def _box_mean(a: np.ndarray, nr: int, nc: int) -> np.ndarray:
    """Means of ``a`` over every ``nr`` × ``nc`` box, indexed by the box's first row and column
    (shape (M − nr + 1, N − nc + 1))."""
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = np.cumsum(np.cumsum(a, axis=0, dtype=np.float64), axis=1)
    s = c[nr:, nc:] - c[:-nr, nc:] - c[nr:, :-nc] + c[:-nr, :-nc]
    return s / (nr * nc)
