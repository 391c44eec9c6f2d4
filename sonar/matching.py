"""Descriptor matching and robust similarity fitting between two keypoint sets.

* KNN matching (k = 2) with Lowe's ratio test (IJCV 2004, sec. 7.1): keep a match when
  ``d₁ < ratio · d₂`` (nearest vs second-nearest descriptor distance) — the seed's
  "KNN based matcher" (sec. 3.4).
* RANSAC 4-DOF similarity ``p' = s R(θ) p + t`` (``cv2.estimateAffinePartial2D``),
  then a linear least-squares refit on the inliers with parameters
  ``(a, b, tx, ty)``, ``a = s cos θ``, ``b = s sin θ``::

      x' = a x − b y + tx,    y' = b x + a y + ty

  whose covariance is ``σ² (AᵀA)⁻¹`` with ``σ²`` the inlier residual variance
  (2n − 4 degrees of freedom).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def match_descriptors(desc0: np.ndarray, desc1: np.ndarray, *, norm: int = cv2.NORM_L2,
                      ratio: float = 0.75) -> np.ndarray:
    """KNN (k=2) matches passing the ratio test.

    Parameters
    ----------
    desc0, desc1 : numpy.ndarray, shape (K0, D), (K1, D)
    norm : int
        ``cv2.NORM_L2`` (SIFT) or ``cv2.NORM_HAMMING`` (ORB).
    ratio : float

    Returns
    -------
    numpy.ndarray, shape (M, 2), int
        Index pairs ``(i0, i1)``; each ``i1`` used at most once (the best).
    """
    if len(desc0) == 0 or len(desc1) < 2:
        return np.zeros((0, 2), int)
    matcher = cv2.BFMatcher(norm)
    pairs = []
    dist = []
    for m in matcher.knnMatch(desc0, desc1, k=2):
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            pairs.append((m[0].queryIdx, m[0].trainIdx))
            dist.append(m[0].distance)
    if not pairs:
        return np.zeros((0, 2), int)
    pairs_a = np.array(pairs, int)
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(pairs_a[order, 1], return_index=True)
    return pairs_a[np.sort(order[first])]


@dataclass(frozen=True)
class Similarity:
    """A fitted 2-D similarity ``p' = s R(θ) p + t`` with its covariance.

    Attributes
    ----------
    params : numpy.ndarray, shape (4,)
        ``(a, b, tx, ty)``.
    cov : numpy.ndarray, shape (4, 4)
        Covariance of ``params``.
    inliers : numpy.ndarray, shape (M,), bool
        Inlier mask over the input pairs.
    residual_rms : float
        RMS inlier residual (input units).
    """

    params: np.ndarray
    cov: np.ndarray
    inliers: np.ndarray
    residual_rms: float

    @property
    def angle_rad(self) -> float:
        return float(np.arctan2(self.params[1], self.params[0]))

    @property
    def scale(self) -> float:
        return float(np.hypot(self.params[0], self.params[1]))

    @property
    def translation(self) -> np.ndarray:
        return self.params[2:4].copy()


def _design(p: np.ndarray) -> np.ndarray:
    n = p.shape[0]
    a = np.zeros((2 * n, 4))
    a[0::2, 0], a[0::2, 1], a[0::2, 2] = p[:, 0], -p[:, 1], 1.0
    a[1::2, 0], a[1::2, 1], a[1::2, 3] = p[:, 1], p[:, 0], 1.0
    return a


def fit_similarity(p0: np.ndarray, p1: np.ndarray, *, ransac_threshold: float = 3.0,
                   min_inliers: int = 4, confidence: float = 0.995,
                   max_iters: int = 2000) -> Similarity | None:
    """RANSAC similarity from ``p0`` to ``p1``, refit on inliers with a covariance.

    Parameters
    ----------
    p0, p1 : numpy.ndarray, shape (M, 2)
        Matched points (any consistent unit; the threshold is in that unit).
    ransac_threshold : float
        Maximum reprojection error of an inlier.
    min_inliers : int
        Fewer inliers → None.

    Returns
    -------
    Similarity or None
    """
    p0 = np.asarray(p0, np.float64).reshape(-1, 2)
    p1 = np.asarray(p1, np.float64).reshape(-1, 2)
    if p0.shape[0] < max(min_inliers, 2):
        return None
    m, mask = cv2.estimateAffinePartial2D(p0.astype(np.float32), p1.astype(np.float32),
                                          method=cv2.RANSAC,
                                          ransacReprojThreshold=float(ransac_threshold),
                                          maxIters=int(max_iters), confidence=float(confidence))
    if m is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    if inl.sum() < min_inliers:
        return None
    a = _design(p0[inl])
    y = p1[inl].reshape(-1)
    params, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ params
    dof = max(resid.size - 4, 1)
    sigma2 = float(resid @ resid) / dof
    # a perfect fit (identical images) still carries the pixel quantisation: floor σ²
    sigma2 = max(sigma2, 1.0 / 12.0 * (ransac_threshold / 3.0) ** 2 * 1e-2)
    cov = sigma2 * np.linalg.pinv(a.T @ a)
    return Similarity(params, cov, inl, float(np.sqrt(np.mean(resid ** 2))))
