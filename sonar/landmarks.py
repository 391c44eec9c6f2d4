"""Landmark observations from side-scan keypoints, and a tracker that gives them ids.

For the calibrator's particle filter (the seed, sec. 3.2: "landmarks from side sonar
images"; DESIGN.md "Calibration", sensor model (b)): every kept keypoint becomes an
observation ``(t, side, ground range, along-track position, descriptor)``.  Its
position in the local frame, given the vehicle pose ``(n, e, ψ)`` at time ``t``, is

    p = (n, e) + ρ · u_side,   u_starboard = (−sin ψ, cos ψ),  u_port = −u_starboard

with ``ρ`` the ground range.  :class:`LandmarkTracker` associates observations with
earlier tracks by a geometry gate on that position (distance ≤ ``gate_m`` from the
track's mean position) and the descriptor distance (nearest track inside the gate,
accepted if below ``max_descriptor_distance`` and, when two tracks compete, passing
the ratio test); the rest start new tracks.  The navigation error is mostly common to
a batch (one window or pass): the offset most gated pairs agree on is removed first
and the association made with a tighter gate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from adaptnav.sonar.features import Detector, SiftDetector
from adaptnav.sonar.waterfall import Waterfall, to_uint8


@dataclass(frozen=True, eq=False)
class LandmarkObservation:
    """One side-scan landmark sighting.

    Attributes
    ----------
    t_s : float
        Time of the ping that saw it (s).
    side : str
        ``"port"`` or ``"starboard"``.
    ground_range_m : float
        Horizontal distance from the track (m, ≥ 0).
    along_track_m : float
        Along-track distance of the sighting from the start of its waterfall (m; NaN
        when the speed is unknown).
    descriptor : numpy.ndarray, shape (D,)
    track_id : int or None
        Identity of the physical landmark, None until the tracker assigns one.
    response : float
        Detector response (strength).
    """

    t_s: float
    side: str
    ground_range_m: float
    along_track_m: float
    descriptor: np.ndarray
    track_id: int | None = None
    response: float = 0.0

    def position_n_m(self, pos_n_m, yaw_rad: float) -> np.ndarray:
        """Local (north, east) position of the landmark given the vehicle pose at ``t_s``."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        sign = 1.0 if self.side == "starboard" else -1.0
        return np.asarray(pos_n_m, float)[:2] + sign * self.ground_range_m * np.array([-s, c])


def extract_landmarks(waterfall: Waterfall, detector: Detector | None = None, *,
                      max_landmarks: int = 50, min_ground_range_m: float = 1.0,
                      image_u8: np.ndarray | None = None,
                      refine_edge: bool = True, dedupe_m: float = 0.5,
                      min_edge_contrast: float = 3.0) -> list[LandmarkObservation]:
    """Keypoints of a waterfall → landmark observations (strongest first, no track id).

    Parameters
    ----------
    waterfall : Waterfall
    detector : Detector or None
        Default ``SiftDetector(max_keypoints=max_landmarks)``.
    max_landmarks : int
        K strongest kept (the seed's "high threshold, few landmarks").
    min_ground_range_m : float
        Keypoints closer to the track (nadir artefacts) are dropped.
    image_u8 : numpy.ndarray or None
        Precomputed 8-bit image of the waterfall.
    refine_edge : bool
        Move each keypoint across-track to the steepest highlight → shadow drop near
        it (see :func:`_highlight_shadow_edge`): the range of the object's top rather
        than of the blob's centre, which SIFT puts on the highlight or in the shadow.
    min_edge_contrast : float
        With ``refine_edge``, keypoints whose highlight/shadow contrast is lower are
        dropped: texture points that look different on the next pass; objects stay.
    dedupe_m : float
        Keypoints closer than this (m, across and along, assuming square pixels) to a
        stronger kept one are dropped.
    """
    det = detector if detector is not None else SiftDetector(max_keypoints=4 * max_landmarks)
    img = to_uint8(waterfall.image) if image_u8 is None else image_u8
    feats = det.detect(img, (waterfall.image > 0).astype(np.uint8) * 255)
    rows = np.arange(waterfall.image.shape[0], dtype=float)
    out: list[LandmarkObservation] = []
    kept: list[tuple[float, float]] = []
    dedupe_px = dedupe_m / waterfall.ground_res_m
    for i in range(len(feats)):
        col, row = float(feats.xy[i, 0]), float(feats.xy[i, 1])
        if refine_edge:
            col, contrast = _highlight_shadow_edge(waterfall, col, row, float(feats.size[i]))
            if contrast < min_edge_contrast:
                continue
        across = float(waterfall.across_m(col))
        if abs(across) < min_ground_range_m:
            continue
        # highlight and shadow of one object refine to the same spot: keep the stronger
        if any(abs(row - r) <= dedupe_px and abs(col - c) <= dedupe_px for r, c in kept):
            continue
        kept.append((row, col))
        out.append(LandmarkObservation(
            t_s=float(np.interp(row, rows, waterfall.t_s)),
            side="starboard" if across > 0 else "port",
            ground_range_m=abs(across),
            along_track_m=float(np.interp(row, rows, waterfall.along_m)),
            descriptor=np.asarray(feats.descriptors[i]),
            response=float(feats.response[i])))
        if len(out) >= max_landmarks:
            break
    return out


def _highlight_shadow_edge(waterfall: Waterfall, col: float, row: float,
                           size_px: float) -> tuple[float, float]:
    """Column of the steepest outward bright→dark drop within ±size of a keypoint.

    An object standing on the seabed returns a highlight on its face and casts a shadow
    behind it; the drop from one to the other lies at the object's top, which is the
    object's ground range (to within its radius × the grazing angle).  Intensity is
    averaged over ±1 row and smoothed over 3 columns; "outward" is away from nadir.
    Returns the column and the contrast (mean of 3 px before the edge / 3 px after).
    """
    img = waterfall.image
    h, w = img.shape
    r0, r1 = max(int(round(row)) - 1, 0), min(int(round(row)) + 2, h)
    half = max(int(round(size_px)), 3)
    c0, c1 = max(int(round(col)) - half, 0), min(int(round(col)) + half + 1, w)
    if c1 - c0 < 5:
        return col, 1.0
    prof = img[r0:r1, c0:c1].mean(axis=0)
    prof = np.convolve(prof, np.ones(3) / 3.0, mode="same")
    grad = np.gradient(prof)
    outward = 1.0 if col >= w / 2 else -1.0
    k = int(np.argmin(outward * grad[1:-1])) + 1
    if outward * grad[k] >= 0:
        return col, 1.0
    kk = c0 + k
    near = img[r0:r1, max(kk - 3, 0):kk] if outward > 0 else img[r0:r1, kk + 1:kk + 4]
    far = img[r0:r1, kk + 1:kk + 4] if outward > 0 else img[r0:r1, max(kk - 3, 0):kk]
    if near.size == 0 or far.size == 0:
        return float(kk), 1.0
    return float(kk), float(near.mean() / max(float(far.mean()), 1e-6))


class LandmarkTracker:
    """Assigns track ids to landmark observations (geometry gate + descriptor).

    Parameters
    ----------
    gate_m : float
        Maximum distance between an observation's estimated position and a track's.
    max_descriptor_distance : float
        Largest accepted descriptor distance (L2 for SIFT descriptors, whose norm is
        ≈ 512; Hamming bits for ORB).
    ratio : float
        When two tracks are inside the gate, the best must be this much closer in
        descriptor space than the second.
    hamming : bool
        Binary (ORB) descriptors.
    refine_gate_m : float or None
        The batch's common navigation error — the position offset most gated
        observation/track pairs agree on (to within this distance) — is removed and the
        batch associated with this tighter gate.  None: one pass with ``gate_m``.
    consensus_m : float
        Pairs whose offsets agree to this distance support the same navigation error
        (about the repeatability of a landmark position).
    """

    def __init__(self, gate_m: float = 1.5, max_descriptor_distance: float = 650.0,
                 ratio: float = 0.95, hamming: bool = False,
                 refine_gate_m: float | None = 0.75, consensus_m: float = 0.3) -> None:
        self.consensus_m = float(consensus_m)
        self.gate_m = float(gate_m)
        self.refine_gate_m = None if refine_gate_m is None else float(refine_gate_m)
        self.max_descriptor_distance = float(max_descriptor_distance)
        self.ratio = float(ratio)
        self.hamming = bool(hamming)
        self._pos: list[np.ndarray] = []
        self._n: list[int] = []
        self._desc: list[np.ndarray] = []

    @property
    def n_tracks(self) -> int:
        return len(self._pos)

    def _dist(self, d: np.ndarray, descs: np.ndarray) -> np.ndarray:
        if self.hamming:
            return np.unpackbits(np.bitwise_xor(descs, d[None, :]), axis=1).sum(axis=1).astype(float)
        return np.linalg.norm(descs.astype(float) - d[None, :].astype(float), axis=1)

    def _common_offset(self, pos: np.ndarray) -> np.ndarray | None:
        """Consensus translation (track − observation) over all pairs within 2 gates.

        The navigation error is nearly common to a batch: the offset agreed by most
        pairs (within ``consensus_m`` of each other) is it; wrong pairs scatter.
        """
        tpos = np.array(self._pos)
        diff = tpos[None, :, :] - pos[:, None, :]
        within = np.linalg.norm(diff, axis=2) <= 2.0 * self.gate_m
        offs = diff[within]
        if offs.shape[0] < 3:
            return None
        close = np.linalg.norm(offs[:, None, :] - offs[None, :, :], axis=2) <= self.consensus_m
        support = close.sum(axis=1)
        best = int(np.argmax(support))
        if support[best] < 3:
            return None
        return offs[close[best]].mean(axis=0)

    def _candidates(self, observations, pos: np.ndarray, gate_m: float) -> list[tuple[float, int, int]]:
        """(descriptor distance, observation index, track index) of acceptable pairs."""
        cand: list[tuple[float, int, int]] = []
        if not self._pos:
            return cand
        tpos = np.array(self._pos)
        tdesc = np.array(self._desc)
        for i, obs in enumerate(observations):
            near = np.flatnonzero(np.linalg.norm(tpos - pos[i], axis=1) <= gate_m)
            if near.size == 0:
                continue
            dist = self._dist(obs.descriptor, tdesc[near])
            order = np.argsort(dist)
            best = float(dist[order[0]])
            if best > self.max_descriptor_distance:
                continue
            if near.size > 1 and best > self.ratio * float(dist[order[1]]):
                continue
            cand.append((best, i, int(near[order[0]])))
        return cand

    def update(self, observations: Sequence[LandmarkObservation],
               positions_n_m: np.ndarray) -> list[LandmarkObservation]:
        """Associate a batch of observations (e.g. one window) and return them with ids.

        Parameters
        ----------
        observations : sequence of LandmarkObservation
        positions_n_m : numpy.ndarray, shape (K, 2)
            Estimated local position of each observation (from the navigation estimate,
            e.g. :meth:`LandmarkObservation.position_n_m`).

        Returns
        -------
        list of LandmarkObservation
            Same order, ``track_id`` set.  One track takes at most one observation per
            batch (greedy by descriptor distance).
        """
        pos = np.asarray(positions_n_m, float).reshape(-1, 2)
        cand = self._candidates(observations, pos, self.gate_m)
        if self.refine_gate_m is not None and self._pos and len(pos):
            offset = self._common_offset(pos)
            if offset is not None:
                pos = pos + offset
                cand = self._candidates(observations, pos, self.refine_gate_m)
        assigned: dict[int, int] = {}
        used: set[int] = set()
        for _, i, t in sorted(cand):
            if i in assigned or t in used:
                continue
            assigned[i] = t
            used.add(t)
        out = []
        for i, obs in enumerate(observations):
            t = assigned.get(i)
            if t is None:
                t = len(self._pos)
                self._pos.append(pos[i].copy())
                self._n.append(1)
                self._desc.append(np.asarray(obs.descriptor).copy())
            else:
                k = self._n[t] + 1
                self._pos[t] = self._pos[t] + (pos[i] - self._pos[t]) / k
                self._n[t] = k
            out.append(replace(obs, track_id=int(t)))
        return out
