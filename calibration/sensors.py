r"""Observation models for the calibrator's particle filter.

Every model has ``log_likelihood(poses) -> (N,)`` for particle poses ``(N, 3)`` =
``(x_north_m, y_east_m, theta_rad)`` (NED horizontal, θ yaw from north to east).

Known references
----------------
* :class:`RangeObservation` — ranges to known landmarks / acoustic beacons (the seed's
  §3.6 simulation: 4 static landmarks, range noise 2.0 or 5.0):
  ``r_l ~ N(‖p − m_l‖, σ_r²)`` independently per landmark.
* :class:`PositionFix` — USBL / GNSS horizontal fix ``z ~ N(p, σ² I₂)``.
* :class:`HeadingObservation` — compass / AHRS yaw ``ψ ~ N(θ, σ²)`` on the circle
  (the wrapped difference is used).

Side-scan landmarks with unknown positions
------------------------------------------
A side-scan keypoint seen at ping time t on side ``s`` (+1 starboard, −1 port) at ground
range ``ρ`` and along-track offset ``a`` places the landmark at ``m = p + R(θ) z`` with
``z = (a, s ρ)`` in the body frame (x forward, y starboard) and ``R(θ)`` the 2-D rotation.
Given the pose, ``y = p + R(θ) z`` is a *linear* Gaussian observation of ``m`` with
covariance ``R Σ_z Rᵀ``. So each particle carries an exact Kalman filter per landmark
(FastSLAM, Montemerlo et al. 2002, without any linearisation):
first sight ``m̂ = y, P = R Σ_z Rᵀ`` (no weight); re-observation weight
``N(y; m̂, P + R Σ_z Rᵀ)`` then the Kalman update (:class:`ParticleLandmarkMap`).

Choice for smoothing: the backward simulation needs a pose-only Markov model, which a
per-particle map breaks (each particle's likelihood depends on its own history). We
therefore run the FastSLAM forward pass once to *build* the map, freeze it (posterior mean
and covariance over particles, :meth:`ParticleLandmarkMap.fixed_map`), and run the EM's
filter + smoother against the fixed map (:class:`FixedLandmarkObservation`, with the map's
covariance added to the measurement covariance). This is the "map fixed from the forward
pass" option of DESIGN.md "Calibration"; it costs one extra forward pass and keeps
FFBSi exact for the model it smooths.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adaptnav.calibration._kernels import range_loglik

LOG_2PI = math.log(2.0 * math.pi)


def _rot(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.cos(theta), np.sin(theta)


@dataclass(frozen=True)
class RangeObservation:
    """Ranges (m) to known landmarks at ``landmarks_m`` (L, 2) with noise ``sigma_m``."""

    landmarks_m: np.ndarray
    ranges_m: np.ndarray
    sigma_m: float

    def log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        lm = np.asarray(self.landmarks_m, dtype=float).reshape(-1, 2)
        return range_loglik(np.ascontiguousarray(poses, dtype=float), lm,
                            np.asarray(self.ranges_m, dtype=float).reshape(-1), float(self.sigma_m))

    def log_likelihood_numpy(self, poses: np.ndarray) -> np.ndarray:
        """Reference implementation (numpy) of :meth:`log_likelihood`."""
        lm = np.asarray(self.landmarks_m, dtype=float).reshape(-1, 2)
        d = np.hypot(poses[:, None, 0] - lm[None, :, 0], poses[:, None, 1] - lm[None, :, 1])
        r = (d - np.asarray(self.ranges_m, dtype=float)[None, :]) / self.sigma_m
        return -0.5 * np.sum(r * r, axis=1) - lm.shape[0] * (math.log(self.sigma_m) + 0.5 * LOG_2PI)


@dataclass(frozen=True)
class PositionFix:
    """Horizontal position fix ``pos_n_m`` = (north, east) m with isotropic ``sigma_m``."""

    pos_n_m: tuple[float, float]
    sigma_m: float

    def log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        dx = (poses[:, 0] - self.pos_n_m[0]) / self.sigma_m
        dy = (poses[:, 1] - self.pos_n_m[1]) / self.sigma_m
        return -0.5 * (dx * dx + dy * dy) - 2.0 * math.log(self.sigma_m) - LOG_2PI


@dataclass(frozen=True)
class HeadingObservation:
    """Yaw ``yaw_rad`` (from north towards east) with noise ``sigma_rad``."""

    yaw_rad: float
    sigma_rad: float

    def log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        e = ((poses[:, 2] - self.yaw_rad + np.pi) % (2.0 * np.pi) - np.pi) / self.sigma_rad
        return -0.5 * e * e - math.log(self.sigma_rad) - 0.5 * LOG_2PI


@dataclass(frozen=True)
class LandmarkSighting:
    """A side-scan landmark seen from the vehicle, in the body frame.

    ``along_m`` forward of the ping's position, ``across_m`` to starboard (negative to
    port) = ``±ground_range_m``; standard deviations ``sigma_along_m``, ``sigma_across_m``;
    ``group`` the loop closure that linked it (:mod:`adaptnav.calibration.sidescan`; −1: none).
    """

    track_id: int
    along_m: float
    across_m: float
    sigma_along_m: float = 1.0
    sigma_across_m: float = 0.5
    group: int = -1

    def world_observation(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-particle landmark position ``y`` (N, 2) and its covariance (N, 2, 2)."""
        c, s = _rot(poses[:, 2])
        a, b = self.along_m, self.across_m
        y = np.stack([poses[:, 0] + c * a - s * b, poses[:, 1] + s * a + c * b], axis=1)
        va, vb = self.sigma_along_m**2, self.sigma_across_m**2
        cov = np.empty((poses.shape[0], 2, 2))
        cov[:, 0, 0] = c * c * va + s * s * vb
        cov[:, 1, 1] = s * s * va + c * c * vb
        cov[:, 0, 1] = cov[:, 1, 0] = c * s * (va - vb)
        return y, cov


def sighting_from_sonar(obs, track_id: int | None = None, sigma_along_m: float = 1.0,
                        sigma_across_m: float = 0.5) -> LandmarkSighting:
    """Convert a sonar ``LandmarkObservation`` (fields ``t_s, side, ground_range_m,
    along_track_m, descriptor, track_id, response``) to a :class:`LandmarkSighting`.

    ``track_id`` overrides the observation's own (for descriptor-based association).
    """
    side = {"starboard": 1.0, "port": -1.0}.get(getattr(obs, "side", None))
    if side is None:
        raise ValueError(f"landmark observation: side must be 'port' or 'starboard', got {obs.side!r}")
    tid = track_id if track_id is not None else obs.track_id
    if tid is None:
        raise ValueError("landmark observation without track_id: associate it first (LandmarkAssociator)")
    rng_m, along = float(obs.ground_range_m), float(obs.along_track_m)
    if not (math.isfinite(rng_m) and math.isfinite(along)) or rng_m < 0:
        raise ValueError(f"landmark observation: bad geometry range={rng_m} along={along}")
    return LandmarkSighting(int(tid), along, side * rng_m, sigma_along_m, sigma_across_m)


class LandmarkAssociator:
    """Track ids for landmark observations: the front end's ``track_id`` if given, else the
    nearest known descriptor (Euclidean, Lowe ratio test ``ratio``), else a new id."""

    def __init__(self, max_distance: float = math.inf, ratio: float = 0.8):
        self.max_distance = max_distance
        self.ratio = ratio
        self._descriptors: list[np.ndarray] = []
        self._ids: list[int] = []
        self._next_id = 1_000_000  # clear of front-end ids

    def assign(self, obs) -> int:
        desc = getattr(obs, "descriptor", None)
        desc = None if desc is None else np.asarray(desc, dtype=float).ravel()
        if obs.track_id is not None:
            tid = int(obs.track_id)
        else:
            tid = None
            if desc is not None and self._descriptors:
                d = np.array([np.linalg.norm(desc - k) for k in self._descriptors])
                order = np.argsort(d)
                best = d[order[0]]
                second = d[order[1]] if d.size > 1 else math.inf
                if best <= self.max_distance and best < self.ratio * second:
                    tid = self._ids[order[0]]
            if tid is None:
                tid = self._next_id
                self._next_id += 1
        if desc is not None and tid not in self._ids:
            self._descriptors.append(desc)
            self._ids.append(tid)
        return tid


class ParticleLandmarkMap:
    """Per-particle Gaussian landmark estimates (FastSLAM), vectorised over particles."""

    def __init__(self, n_particles: int):
        self.n = n_particles
        self.mean: dict[int, np.ndarray] = {}  # (N, 2)
        self.cov: dict[int, np.ndarray] = {}  # (N, 2, 2)
        # the particles' normalised log-weights before the current pose's observations (set
        # by the filter); with them every re-observation records the map it was scored
        # against — the earlier sightings' alone (:attr:`before`, id(sighting) → (mean, cov))
        self.log_w: np.ndarray | None = None
        self.before: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def log_likelihood_and_update(self, poses: np.ndarray, sighting: LandmarkSighting) -> np.ndarray:
        """Weight of each particle for ``sighting`` (0 on first sight), then update its map."""
        y, r_cov = sighting.world_observation(poses)
        tid = sighting.track_id
        if tid not in self.mean:
            self.mean[tid] = y
            self.cov[tid] = r_cov
            return np.zeros(poses.shape[0])
        m, p = self.mean[tid], self.cov[tid]
        if self.log_w is not None:
            self.before[id(sighting)] = _posterior(m, p, self.log_w)
        s = p + r_cov
        det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
        inv = np.empty_like(s)
        inv[:, 0, 0], inv[:, 1, 1] = s[:, 1, 1] / det, s[:, 0, 0] / det
        inv[:, 0, 1], inv[:, 1, 0] = -s[:, 0, 1] / det, -s[:, 1, 0] / det
        e = y - m
        maha = np.einsum("ni,nij,nj->n", e, inv, e)
        gain = np.einsum("nij,njk->nik", p, inv)
        self.mean[tid] = m + np.einsum("nij,nj->ni", gain, e)
        self.cov[tid] = p - np.einsum("nij,njk->nik", gain, p)
        return -0.5 * (maha + np.log(det)) - LOG_2PI

    def resample(self, idx: np.ndarray) -> None:
        for tid in self.mean:
            self.mean[tid] = self.mean[tid][idx]
            self.cov[tid] = self.cov[tid][idx]

    def fixed_map(self, log_w: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Posterior mean (2,) and covariance (2, 2) of every landmark under weights ``log_w``."""
        return {tid: _posterior(m, self.cov[tid], log_w) for tid, m in self.mean.items()}


def _posterior(mean: np.ndarray, cov: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (2,) and covariance (2, 2) over particles of per-particle Gaussians (N, 2), (N, 2, 2):
    the spread of the means (the poses' uncertainty) is part of it."""
    w = np.exp(log_w - np.max(log_w))
    w /= w.sum()
    mu = w @ mean
    d = mean - mu
    return mu, np.einsum("n,nij->ij", w, cov) + np.einsum("n,ni,nj->ij", w, d, d)


@dataclass(frozen=True)
class FixedLandmarkObservation:
    """A sighting of a landmark whose position is fixed (mean, covariance) from a forward pass."""

    sighting: LandmarkSighting
    landmark_mean_m: np.ndarray
    landmark_cov_m2: np.ndarray

    def log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        y, r_cov = self.sighting.world_observation(poses)
        s = r_cov + self.landmark_cov_m2[None]
        det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
        e = y - self.landmark_mean_m[None]
        maha = (s[:, 1, 1] * e[:, 0] ** 2 - 2 * s[:, 0, 1] * e[:, 0] * e[:, 1] + s[:, 0, 0] * e[:, 1] ** 2) / det
        return -0.5 * (maha + np.log(det)) - LOG_2PI
