r"""Bootstrap particle filter over a window of T motion steps (seed §2.2, Algorithm 1).

Model: ``x_{t+1} ~ p(· | x_t, v_t, w_t, δt_t)`` (:mod:`adaptnav.fusion.motion_model`) and observations
``y_t`` at pose ``x_t`` for t = 0..T, each with ``log g_t(x_t)`` (:mod:`adaptnav.calibration.sensors`).

Weights are kept in the log domain. Resampling is systematic and adaptive: before the
move t → t+1 it happens only when ``ESS < ess_fraction · N`` (Doucet & Johansen 2009).
The incremental log-likelihood uses the normalised weights carried into step t
(uniform right after a resampling, the previous weights otherwise)::

    log p(y_t | y_{0:t−1}) ≈ log Σ_i W_{t−1}^i g_t(x_t^i)

which is the correct estimator under adaptive resampling; the window's log-likelihood is
their sum (with ``t = 0`` relative to the prior cloud). The result stores all particles,
normalised log-weights and ancestor indices for backward smoothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.calibration._kernels import (OBS_FIX, OBS_FIXED_LANDMARK, OBS_HEADING, OBS_RANGE, box_muller_into,
                                          filter_window, heading_loglik, move, pack, pf_advance, pf_weigh, reweight)
from adaptnav.calibration.resampling import systematic_resample
from adaptnav.calibration.sensors import (FixedLandmarkObservation, HeadingObservation, LandmarkSighting,
                                         ParticleLandmarkMap, PositionFix, RangeObservation)


@dataclass
class FilterResult:
    """Particles ``poses`` (T+1, N, 3), normalised ``log_w`` (T+1, N), ``ancestors`` (T, N)
    (``ancestors[t, j]`` is the index at t of particle j's parent at t+1), per-step
    ``log_lik_increments`` (T+1,), ``resampled`` (T,) flags and the window's ``log_likelihood``."""

    poses: np.ndarray
    log_w: np.ndarray
    ancestors: np.ndarray
    log_lik_increments: np.ndarray
    resampled: np.ndarray
    landmark_map: ParticleLandmarkMap | None = None

    @property
    def log_likelihood(self) -> float:
        return float(np.sum(self.log_lik_increments))

    def mean_poses(self) -> np.ndarray:
        """Filter means (T+1, 3); the heading by circular mean."""
        w = np.exp(self.log_w)
        xy = np.einsum("tn,tnk->tk", w, self.poses[:, :, :2])
        th = np.arctan2(np.einsum("tn,tn->t", w, np.sin(self.poses[:, :, 2])),
                        np.einsum("tn,tn->t", w, np.cos(self.poses[:, :, 2])))
        return np.concatenate([xy, th[:, None]], axis=1)


_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def _observation_log_lik(obs_list, poses, landmark_map):
    if obs_list is not None and len(obs_list) == 1 and not isinstance(obs_list[0], LandmarkSighting):
        ob = obs_list[0]
        if type(ob) is HeadingObservation:  # most poses: one heading (numba, same floats)
            return heading_loglik(poses, ob.yaw_rad, ob.sigma_rad, math.log(ob.sigma_rad), _HALF_LOG_2PI)
        return ob.log_likelihood(poses)
    g = np.zeros(poses.shape[0])
    for ob in obs_list or ():
        if isinstance(ob, LandmarkSighting):
            if landmark_map is None:
                raise ValueError("LandmarkSighting needs a landmark map (map_landmarks=True)")
            g += landmark_map.log_likelihood_and_update(poses, ob)
        else:
            g += ob.log_likelihood(poses)
    return g


def _reweight(log_w, g):
    lw, inc, ess_now = reweight(log_w, g)
    if not np.isfinite(inc):
        raise FloatingPointError("all particle weights are zero (or non-finite): the observations "
                                 "are impossible under every particle")
    return lw, inc, ess_now


def move_normals(rng: np.random.Generator, shape) -> np.ndarray:
    """Standard normals of ``shape`` for the particles' moves, from ``rng``'s raw 64-bit
    words (one per two normals) by the Box–Muller transform
    (:func:`adaptnav.calibration._kernels.box_muller_into`): half the time of
    ``rng.standard_normal`` — in an EM iteration the filter's T·3·N normals were a third of
    its time. Same ``rng`` state, same normals."""
    size = math.prod(shape)
    out = np.empty(size + size % 2)
    box_muller_into(rng.bit_generator.random_raw((size + 1) // 2), out)
    return out[:size].reshape(shape)


def pack_observations(observations):
    """The window's observations as the arrays of :func:`adaptnav.calibration._kernels.filter_window`:
    ``(obs_ptr (T+2,), obs_kind (K,), obs_off (K,), fdata)``; None when one of them has
    no packed form (a :class:`LandmarkSighting` updates a per-particle map)."""
    ptr, kinds, offs, chunks = [0], [], [], []
    size = 0  # floats in ``chunks`` so far
    for obs_list in observations:
        for ob in obs_list or ():
            kind = type(ob)
            if kind is RangeObservation:
                lm = np.asarray(ob.landmarks_m, dtype=float).reshape(-1, 2)
                kinds.append(OBS_RANGE)
                chunk = np.concatenate(([lm.shape[0], ob.sigma_m], lm[:, 0], lm[:, 1],
                                        np.asarray(ob.ranges_m, dtype=float).reshape(-1)))
            elif kind is PositionFix:
                kinds.append(OBS_FIX)
                chunk = (ob.pos_n_m[0], ob.pos_n_m[1], ob.sigma_m)
            elif kind is HeadingObservation:
                kinds.append(OBS_HEADING)
                chunk = (ob.yaw_rad, ob.sigma_rad)
            elif kind is FixedLandmarkObservation:
                s = ob.sighting
                kinds.append(OBS_FIXED_LANDMARK)
                chunk = np.concatenate(([s.along_m, s.across_m, s.sigma_along_m ** 2, s.sigma_across_m ** 2],
                                        np.asarray(ob.landmark_mean_m, dtype=float).reshape(2),
                                        np.asarray(ob.landmark_cov_m2, dtype=float).reshape(4)))
            else:
                return None
            offs.append(size)
            chunks.append(chunk)
            size += len(chunk)
        ptr.append(len(kinds))
    fdata = np.concatenate(chunks).astype(float, copy=False) if chunks else np.empty(0)
    return (np.asarray(ptr, dtype=np.int64), np.asarray(kinds, dtype=np.int64),
            np.asarray(offs, dtype=np.int64), fdata)


def _no_particle_explains(t: int):
    return FloatingPointError(f"all particle weights are zero (or non-finite) at pose {t}: the observations "
                              "are impossible under every particle")


def run_particle_filter(params: MotionParams, v_m_s, w_rad_s, dt_s, observations, init_poses,
                        rng: np.random.Generator, n_particles: int | None = None,
                        ess_fraction: float = 0.5, map_landmarks: bool = False,
                        current_n_m_s=None) -> FilterResult:
    """Run the filter over one window.

    The random numbers are drawn up front from ``rng`` (T·3·N standard normals for the
    moves by :func:`move_normals`, then T uniforms for the resamplings, used or not), and
    the window runs in one compiled call (:func:`adaptnav.calibration._kernels.filter_window`); with a per-particle
    landmark map the same kernels run step by step around the map's Python update, with
    the same draws (so the same particles for the same seed).

    Parameters
    ----------
    params : motion parameters used for the moves
    v_m_s, w_rad_s, dt_s : (T,) reported surge speed (m/s), yaw rate (rad/s), step (s)
        carrying pose t to t+1
    observations : sequence of length T+1; ``observations[t]`` is a list of observation
        objects at pose t (may be empty)
    init_poses : (N0, 3) prior particle cloud at t = 0 (equally weighted); resampled to
        ``n_particles`` if that differs from N0
    rng : random generator (moves and resampling)
    n_particles : N (default N0)
    ess_fraction : resample when ESS < ess_fraction · N
    map_landmarks : keep a per-particle map for :class:`LandmarkSighting` (FastSLAM)
    current_n_m_s : optional (2,) sea current (north, east) in m/s added to every move
    """
    v = np.ascontiguousarray(v_m_s, dtype=float)
    w = np.ascontiguousarray(w_rad_s, dtype=float)
    dt = np.ascontiguousarray(np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape))
    T = v.size
    if len(observations) != T + 1:
        raise ValueError(f"observations: expected T+1 = {T + 1} entries, got {len(observations)}")
    init = np.asarray(init_poses, dtype=float).reshape(-1, 3)
    N = init.shape[0] if n_particles is None else int(n_particles)
    if init.shape[0] != N:
        init = init[rng.integers(0, init.shape[0], N)]
    X = np.empty((T + 1, N, 3))
    LW = np.empty((T + 1, N))
    A = np.empty((T, N), dtype=np.int64)
    inc = np.empty(T + 1)
    resampled = np.zeros(T, dtype=bool)
    X[0] = init
    LW[0] = -math.log(N)
    z = move_normals(rng, (T, 3, N))
    u = rng.random(T)
    threshold = float(ess_fraction * N)
    pvec = pack(params, current_n_m_s)
    packed = None if map_landmarks else pack_observations(observations)
    lmap = ParticleLandmarkMap(N) if map_landmarks else None
    if packed is not None:
        failed = filter_window(X, LW, A, inc, resampled, v, w, dt, pvec, z, u, threshold, *packed)
        if failed >= 0:
            raise _no_particle_explains(int(failed))
        return FilterResult(X, LW, A, inc, resampled, None)
    W = np.empty(N)
    cdf = np.empty(N)
    ess_now = 0.0
    for t in range(T + 1):
        if t > 0:
            resample = bool(ess_now < threshold)
            pf_advance(X, LW, W, A, resampled, t - 1, resample, u[t - 1], z[t - 1], v[t - 1], w[t - 1],
                       dt[t - 1], pvec, cdf)
            if resample and lmap is not None:
                lmap.resample(A[t - 1])
        if lmap is not None:
            lmap.log_w = LW[t]  # the weights carried into pose t (for the map's records)
        g = np.ascontiguousarray(_observation_log_lik(observations[t], X[t], lmap), dtype=float)
        inc[t], ess_now = pf_weigh(LW, W, t, g)  # LW[t] is normalised: inc = log Σ W g
        if not np.isfinite(inc[t]):
            raise _no_particle_explains(t)
    return FilterResult(X, LW, A, inc, resampled, lmap)


def filter_step(params: MotionParams, poses: np.ndarray, log_w: np.ndarray, v: float, w: float,
                dt: float, obs_list, rng: np.random.Generator, ess_fraction: float = 0.5,
                current_n_m_s=None):
    """One online step of the same filter: (resample if ESS low) → move → weight.

    Returns new ``(poses (N,3), normalised log_w (N,), log-likelihood increment)``.
    """
    N = poses.shape[0]
    wts = np.exp(log_w)
    idx = np.arange(N)
    if 1.0 / np.sum(wts * wts) < ess_fraction * N:
        idx = systematic_resample(wts, rng)
        log_w = np.full(N, -np.log(N))
    poses = move(poses, idx, move_normals(rng, (3, N)), float(v), float(w), float(dt), pack(params, current_n_m_s))
    g = _observation_log_lik(obs_list, poses, None)
    log_w, inc, _ = _reweight(log_w, g)
    return poses, log_w, float(inc)


def weighted_mean_pose(poses: np.ndarray, log_w: np.ndarray) -> np.ndarray:
    """Weighted mean pose (3,), heading by circular mean."""
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    return np.array([w @ poses[:, 0], w @ poses[:, 1],
                     math.atan2(w @ np.sin(poses[:, 2]), w @ np.cos(poses[:, 2]))])
