"""Visual motion between two side-scan windows (the seed, sec. 3.4).

Each window is a piece of ground-range waterfall with its own metric frame: origin at
the vehicle at the window's centre row, ``x`` along-track (forward, ``along_res_m`` per
row), ``y`` across-track (starboard, ``ground_res_m`` per column).  The same seabed
point seen in windows A and B satisfies, if frame B sits at ``d = (dx, dy)`` with yaw
``dψ`` in frame A,

    p_B = R(−dψ) (p_A − d)

so the similarity ``p_B = s R(θ) p_A + t`` fitted to matched keypoints (SIFT, KNN ratio
test, RANSAC; :mod:`adaptnav.sonar.matching`) gives ``dψ = −θ`` and ``d = −R(dψ) t``.  The
covariance of ``(dx, dy, dψ)`` is the fit covariance pushed through this map
(numerical Jacobian).  ``s`` should be 1 (both windows are in metres); it is reported.

Speed: a :class:`WindowRegistrar` detects on an image whose columns are averaged to
square pixels (a ping-indexed window has pixels ~8× longer than wide), keeps the K
strongest keypoints and caches the features of the previous window, so a stream of
windows costs one detection per window.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import cv2
import numpy as np

from adaptnav.sonar.features import Detector, Features, SiftDetector
from adaptnav.sonar.matching import Similarity, fit_similarity, match_descriptors
from adaptnav.sonar.waterfall import Waterfall, to_uint8


@dataclass(frozen=True, eq=False)
class VisualMotion:
    """Displacement of window B's frame in window A's frame.

    Attributes
    ----------
    t_s : float
        Centre time of window B (s).
    t0_s : float
        Centre time of window A (s).
    along_m, across_m : float
        Displacement along-track (forward) and across-track (starboard), m.
    dheading_rad : float
        Yaw change B − A (rad).
    cov : numpy.ndarray, shape (3, 3)
        Covariance of (along_m, across_m, dheading_rad).
    inliers : int
        RANSAC inliers.
    matches : int
        Ratio-test matches.
    scale : float
        Fitted scale (≈ 1 when the geometry is right).
    """

    t_s: float
    t0_s: float
    along_m: float
    across_m: float
    dheading_rad: float
    cov: np.ndarray
    inliers: int
    matches: int
    scale: float = 1.0

    def cov_tuple(self) -> tuple[float, ...]:
        """Row-major 9-tuple of :attr:`cov` (the bus sample's form)."""
        return tuple(float(x) for x in np.asarray(self.cov).reshape(9))

    def to_record(self) -> dict:
        """JSON-ready summary (the ``adaptnav sonar motion`` record)."""
        return {"t_s": self.t_s, "t0_s": self.t0_s, "along_m": self.along_m,
                "across_m": self.across_m, "dheading_rad": self.dheading_rad,
                "inliers": self.inliers, "matches": self.matches,
                "cov": [float(x) for x in np.asarray(self.cov).reshape(9)]}


def window_metric_xy(window: Waterfall, xy_px: np.ndarray, along_res_m: float) -> np.ndarray:
    """Keypoint pixels (col, row) of a window → (x along, y across) metres, centre origin."""
    rows_c = 0.5 * (window.image.shape[0] - 1)
    x = (xy_px[:, 1] - rows_c) * along_res_m
    y = window.across_m(xy_px[:, 0])
    return np.column_stack([x, y])


def similarity_to_motion(sim: Similarity) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy, dψ) and its 3×3 covariance from a fitted similarity."""

    def f(params: np.ndarray) -> np.ndarray:
        a, b, tx, ty = params
        dpsi = -math.atan2(b, a)
        c, s = math.cos(dpsi), math.sin(dpsi)
        return np.array([-(c * tx - s * ty), -(s * tx + c * ty), dpsi])

    p = sim.params
    y0 = f(p)
    jac = np.zeros((3, 4))
    for k in range(4):
        h = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros(4)
        dp[k] = h
        jac[:, k] = (f(p + dp) - f(p - dp)) / (2 * h)
    return y0, jac @ sim.cov @ jac.T


class WindowRegistrar:
    """Registers side-scan windows; caches the features of the last window it saw.

    Parameters
    ----------
    detector : Detector or None
        Default: ``SiftDetector(max_keypoints=400, downsample=2)`` (SIFT doubles its
        input internally, so a 2× smaller image loses little and costs 4× less).
    ratio : float
        Lowe ratio.
    ransac_threshold_m : float
        RANSAC inlier threshold (m).
    min_inliers : int
        Fewer inliers → no estimate.
    square_pixels : bool
        Average columns so that detection pixels are about square.
    max_downsample : int
        Largest column averaging factor.
    """

    def __init__(self, detector: Detector | None = None, *, ratio: float = 0.8,
                 ransac_threshold_m: float = 0.3, min_inliers: int = 6,
                 square_pixels: bool = True, max_downsample: int = 8) -> None:
        self.detector = detector if detector is not None else SiftDetector(max_keypoints=400, downsample=2)
        self.square_pixels = bool(square_pixels)
        self.max_downsample = int(max_downsample)
        self.ratio = float(ratio)
        self.ransac_threshold_m = float(ransac_threshold_m)
        self.min_inliers = int(min_inliers)
        self._cache: tuple[int, Features] | None = None

    def features(self, window: Waterfall, image_u8: np.ndarray | None = None,
                 cache_key: int | None = None) -> Features:
        """Keypoints of a window (on data pixels only), cached under ``cache_key``."""
        if cache_key is not None and self._cache is not None and self._cache[0] == cache_key:
            return self._cache[1]
        img = to_uint8(window.image) if image_u8 is None else image_u8
        mask = (window.image > 0).astype(np.uint8) * 255
        fx = self._across_factor(window)
        if fx > 1:
            # ping-indexed windows have pixels many times longer than wide: average
            # columns to square pixels (SIFT assumes them; it is also far cheaper)
            w = img.shape[1] // fx
            img = cv2.resize(img[:, : w * fx], (w, img.shape[0]), interpolation=cv2.INTER_AREA)
            mask = cv2.resize(mask[:, : w * fx], (w, mask.shape[0]), interpolation=cv2.INTER_NEAREST)
        feats = self.detector.detect(img, mask)
        if fx > 1:
            xy = feats.xy.copy()
            xy[:, 0] = (xy[:, 0] + 0.5) * fx - 0.5
            feats = Features(xy, feats.response, feats.size * fx, feats.descriptors)
        if cache_key is not None:
            self._cache = (cache_key, feats)
        return feats

    def _across_factor(self, window: Waterfall) -> int:
        """Column averaging factor that makes the detection pixels roughly square."""
        if not self.square_pixels or not math.isfinite(window.along_res_m):
            return 1
        f = int(round(window.along_res_m / window.ground_res_m))
        return int(min(max(f, 1), self.max_downsample))

    def register(self, win_a: Waterfall, win_b: Waterfall, *, feats_a: Features | None = None,
                 feats_b: Features | None = None, along_res_m: float | None = None) -> VisualMotion | None:
        """Motion of window B's frame relative to window A's (None if no reliable fit).

        Parameters
        ----------
        win_a, win_b : Waterfall
            Windows with the same ground resolution.
        feats_a, feats_b : Features or None
            Precomputed keypoints (else detected here).
        along_res_m : float or None
            Metres per row; default the windows' ``along_res_m`` (must be finite).
        """
        res = float(along_res_m if along_res_m is not None else win_a.along_res_m)
        if not math.isfinite(res) or res <= 0:
            raise ValueError("along-track resolution unknown (no speed): pass along_res_m")
        fa = feats_a if feats_a is not None else self.features(win_a)
        fb = feats_b if feats_b is not None else self.features(win_b)
        pairs = match_descriptors(fa.descriptors, fb.descriptors, norm=self.detector.norm,
                                  ratio=self.ratio)
        if len(pairs) < self.min_inliers:
            return None
        pa = window_metric_xy(win_a, fa.xy[pairs[:, 0]], res)
        pb = window_metric_xy(win_b, fb.xy[pairs[:, 1]], res)
        sim = fit_similarity(pa, pb, ransac_threshold=self.ransac_threshold_m,
                             min_inliers=self.min_inliers)
        if sim is None:
            return None
        d, cov = similarity_to_motion(sim)
        t_a = float(np.median(win_a.t_s)) if win_a.t_s.size else math.nan
        t_b = float(np.median(win_b.t_s)) if win_b.t_s.size else math.nan
        return VisualMotion(t_b, t_a, float(d[0]), float(d[1]), float(d[2]), cov,
                            int(sim.inliers.sum()), int(len(pairs)), sim.scale)

    def register_stream(self, waterfall: Waterfall, window: int, step: int) -> Iterator[tuple[int, int, VisualMotion | None]]:
        """Register consecutive windows ``[i, i+window)`` and ``[i+step, i+step+window)``.

        Yields ``(row_a, row_b, motion_or_None)``; each window is detected once.
        """
        if window < 8 or step < 1:
            raise ValueError("window must be ≥ 8 rows and step ≥ 1")
        self._cache = None  # another waterfall: features cached from the last one are not its
        img = to_uint8(waterfall.image)
        n = waterfall.image.shape[0]
        starts = list(range(0, n - window + 1, step))
        for a, b in zip(starts[:-1], starts[1:]):
            wa, wb = waterfall.rows(a, a + window), waterfall.rows(b, b + window)
            fa = self.features(wa, img[a:a + window], cache_key=a)
            fb = self.features(wb, img[b:b + window], cache_key=b)
            yield a, b, self.register(wa, wb, feats_a=fa, feats_b=fb)
