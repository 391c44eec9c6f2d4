"""Keypoints and descriptors on waterfall images (SIFT default, ORB option, pluggable).

The seed (sec. 3.2) detects SURF interest points with a high Hessian threshold so that
only a few (≤ 4) strong landmarks remain.  SURF is patented and absent from OpenCV
wheels (DESIGN.md errata), so we use SIFT (Lowe, IJCV 2004) by default, ORB (Rublee
et al., ICCV 2011) as the cheap option, and generalise the threshold to *keep the K
strongest responses*.  Detection may run on an image downsampled by an integer factor
(``cv2.resize`` with area averaging), which also averages speckle; keypoint coordinates
are returned in full-resolution pixels.

Any object with ``name``, ``norm`` (an OpenCV norm for matching) and
``detect(image_u8, mask) -> Features`` is a detector (:class:`Detector` protocol).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one image, strongest first.

    Attributes
    ----------
    xy : numpy.ndarray, shape (K, 2), float32
        (column, row) in full-resolution image pixels.
    response : numpy.ndarray, shape (K,)
        Detector response (strength).
    size : numpy.ndarray, shape (K,)
        Keypoint diameter (full-resolution pixels).
    descriptors : numpy.ndarray, shape (K, D)
        float32 (SIFT) or uint8 (ORB).
    """

    xy: np.ndarray
    response: np.ndarray
    size: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, idx) -> "Features":
        """The keypoints at ``idx`` (index array or mask)."""
        return Features(self.xy[idx], self.response[idx], self.size[idx], self.descriptors[idx])

    def shifted(self, d_col: float, d_row: float) -> "Features":
        """The same keypoints with coordinates offset (e.g. from a crop to its parent)."""
        return Features(self.xy + np.float32([d_col, d_row]), self.response, self.size,
                        self.descriptors)


@runtime_checkable
class Detector(Protocol):
    """A keypoint detector/descriptor."""

    name: str
    norm: int

    def detect(self, image_u8: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Keypoints of an 8-bit image (full-resolution coordinates), strongest first."""
        ...


def _empty(dim: int, dtype) -> Features:
    return Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                    np.zeros(0, np.float32), np.zeros((0, dim), dtype))


class _OpenCvDetector:
    """Shared detect(): optional downsampling, keep the K strongest, rescale."""

    name = "opencv"
    norm = cv2.NORM_L2
    _dim = 128
    _dtype = np.float32

    def __init__(self, max_keypoints: int, downsample: int) -> None:
        if max_keypoints < 1 or downsample < 1:
            raise ValueError("max_keypoints and downsample must be ≥ 1")
        self.max_keypoints = int(max_keypoints)
        self.downsample = int(downsample)
        self._cv = self._make()

    def _make(self):  # pragma: no cover - overridden
        raise NotImplementedError

    def detect(self, image_u8: np.ndarray, mask: np.ndarray | None = None) -> Features:
        img = np.ascontiguousarray(image_u8, dtype=np.uint8)
        f = self.downsample
        if f > 1:
            h, w = img.shape[0] // f, img.shape[1] // f
            if h < 8 or w < 8:
                return _empty(self._dim, self._dtype)
            img = cv2.resize(img[: h * f, : w * f], (w, h), interpolation=cv2.INTER_AREA)
            if mask is not None:
                mask = cv2.resize(np.ascontiguousarray(mask[: h * f, : w * f], np.uint8), (w, h),
                                  interpolation=cv2.INTER_NEAREST)
        kps, desc = self._cv.detectAndCompute(img, mask)
        if desc is None or not kps:
            return _empty(self._dim, self._dtype)
        response = np.array([k.response for k in kps], np.float32)
        order = np.argsort(-response, kind="stable")[: self.max_keypoints]
        xy = np.array([k.pt for k in kps], np.float32)[order]
        # a pixel centre at (i + ½) scales to (i + ½) f
        xy = (xy + 0.5) * f - 0.5
        size = np.array([k.size for k in kps], np.float32)[order] * f
        return Features(xy, response[order], size, desc[order])


class SiftDetector(_OpenCvDetector):
    """SIFT keypoints (128-float descriptors, L2 norm).

    Parameters
    ----------
    max_keypoints : int
        K: keep the K strongest responses.
    downsample : int
        Integer factor of the detection image (1 = full resolution).
    contrast_threshold : float
        SIFT's DoG contrast threshold (higher → fewer, stronger keypoints).
    """

    name = "sift"
    norm = cv2.NORM_L2

    def __init__(self, max_keypoints: int = 500, downsample: int = 1,
                 contrast_threshold: float = 0.04) -> None:
        self.contrast_threshold = float(contrast_threshold)
        super().__init__(max_keypoints, downsample)

    def _make(self):
        # nfeatures lets OpenCV drop weak points early; we still sort and cap ourselves
        return cv2.SIFT_create(nfeatures=self.max_keypoints,
                               contrastThreshold=self.contrast_threshold)


class OrbDetector(_OpenCvDetector):
    """ORB keypoints (32-byte binary descriptors, Hamming norm) — the cheap option."""

    name = "orb"
    norm = cv2.NORM_HAMMING
    _dim = 32
    _dtype = np.uint8

    def __init__(self, max_keypoints: int = 500, downsample: int = 1,
                 fast_threshold: int = 10) -> None:
        self.fast_threshold = int(fast_threshold)
        super().__init__(max_keypoints, downsample)

    def _make(self):
        return cv2.ORB_create(nfeatures=self.max_keypoints, fastThreshold=self.fast_threshold,
                              edgeThreshold=15, patchSize=15)


DETECTORS = {"sift": SiftDetector, "orb": OrbDetector}


def make_detector(name: str = "sift", **kwargs) -> Detector:
    """Detector by name (``"sift"`` or ``"orb"``)."""
    try:
        return DETECTORS[name](**kwargs)
    except KeyError:
        raise ValueError(f"unknown detector {name!r}; choose from {sorted(DETECTORS)}") from None
