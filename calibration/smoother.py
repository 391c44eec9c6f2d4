r"""Forward-filtering backward-simulation (FFBSi) of M trajectories from p(x_{0:T} | data).

Godsill, Doucet & West (2004); the seed's Algorithm 2 (Yap & Shelton 2008). Backward
kernel at step t, for a trajectory whose pose at t+1 is ``x̃_{t+1}``::

    P(x̃_t = x_t^i) ∝ W_t^i · p(x̃_{t+1} | x_t^i, v_t, w_t)

* :func:`ffbsi_exact` evaluates the kernel for all N particles: O(N·M·T). The reference.
* :func:`ffbsi_mcmc` is the MCMC backward kernel of Dau & Chopin (2022, "On backward
  smoothing algorithms", Ann. Statist.; after Bunch & Godsill 2013): start from the
  trajectory's genealogical ancestor (``ancestors[t]``), which is a valid draw from the
  extended target, and apply ``n_mcmc`` independent Metropolis–Hastings moves with
  proposal ``i' ~ W_t``, accepted with probability
  ``min(1, p(x̃_{t+1} | x_t^{i'}) / p(x̃_{t+1} | x_t^{i}))``. O(M·T·n_mcmc), vectorised
  over the M trajectories. Each MH move leaves the backward kernel invariant, so the
  trajectories have the FFBSi distribution; the moves de-correlate them from the
  (degenerate) genealogy.

The transition density includes the lateral velocity term of DESIGN.md's errata, so it is
non-singular in (x, y, θ).
"""
from __future__ import annotations

import numpy as np

from adaptnav.fusion.motion_model import MotionParams, transition_logpdf
from adaptnav.calibration.particle_filter import FilterResult
from adaptnav.calibration.resampling import multinomial_indices
from adaptnav.calibration._kernels import backward_exact, backward_mcmc, pack


def _sample_rows(log_p: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One index per row of ``log_p`` (M, N), drawn ∝ exp(row)."""
    p = np.exp(log_p - log_p.max(axis=1, keepdims=True))
    cdf = np.cumsum(p, axis=1)
    u = rng.random(p.shape[0]) * cdf[:, -1]
    idx = (cdf < u[:, None]).sum(axis=1)
    return np.minimum(idx, p.shape[1] - 1)


def ffbsi_exact(fr: FilterResult, params: MotionParams, v_m_s, w_rad_s, dt_s, n_traj: int,
                rng: np.random.Generator, current_n_m_s=None, turn_about_mean: bool = False) -> np.ndarray:
    """Exact FFBSi: ``n_traj`` trajectories (M, T+1, 3) in O(N·M·T) (numba).

    ``turn_about_mean``: heading-change branch nearest the expected turn (:func:`adaptnav.calibration._kernels.pack`)."""
    v, w, dt = _controls(v_m_s, w_rad_s, dt_s)
    idx = multinomial_indices(fr.log_w[-1], n_traj, rng)
    u = rng.random((v.size, n_traj))
    return backward_exact(fr.poses, fr.log_w, v, w, dt, pack(params, current_n_m_s, turn_about_mean), idx, u)


def _controls(v_m_s, w_rad_s, dt_s):
    v = np.ascontiguousarray(v_m_s, dtype=float)
    w = np.ascontiguousarray(w_rad_s, dtype=float)
    dt = np.ascontiguousarray(np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape))
    return v, w, dt


def ffbsi_exact_numpy(fr: FilterResult, params: MotionParams, v_m_s, w_rad_s, dt_s, n_traj: int,
                      rng: np.random.Generator, current_n_m_s=None) -> np.ndarray:
    """Exact FFBSi written with :func:`adaptnav.fusion.motion_model.transition_logpdf` (the
    independent reference for the numba kernels; O(N·M·T) memory-light numpy)."""
    v, w, dt = _controls(v_m_s, w_rad_s, dt_s)
    T = v.size
    out = np.empty((n_traj, T + 1, 3))
    idx = multinomial_indices(fr.log_w[T], n_traj, rng)
    out[:, T] = fr.poses[T, idx]
    for t in range(T - 1, -1, -1):
        lp = fr.log_w[t][None, :] + transition_logpdf(
            params, fr.poses[t][None, :, :], out[:, t + 1][:, None, :], v[t], w[t], dt[t], current_n_m_s)
        idx = _sample_rows(lp, rng)
        out[:, t] = fr.poses[t, idx]
    return out


def ffbsi_mcmc(fr: FilterResult, params: MotionParams, v_m_s, w_rad_s, dt_s, n_traj: int,
               rng: np.random.Generator, n_mcmc: int = 2, current_n_m_s=None,
               turn_about_mean: bool = False) -> np.ndarray:
    """FFBSi with the MCMC backward kernel: (M, T+1, 3) trajectories in O(M·T·n_mcmc) (numba);
    ``turn_about_mean`` as :func:`ffbsi_exact`."""
    v, w, dt = _controls(v_m_s, w_rad_s, dt_s)
    T = v.size
    # drawn in one go: the ends, every step's proposals (inverse CDF of W_t in the kernel), the acceptances
    u_last = rng.random(n_traj)
    u_prop = rng.random((T, n_mcmc, n_traj))
    log_u = np.log(rng.random((T, n_mcmc, n_traj)))
    return backward_mcmc(fr.poses, np.exp(fr.log_w), fr.ancestors, v, w, dt, pack(params, current_n_m_s, turn_about_mean),
                         u_last, u_prop, log_u)


def ffbsi_mcmc_numpy(fr: FilterResult, params: MotionParams, v_m_s, w_rad_s, dt_s, n_traj: int,
                     rng: np.random.Generator, n_mcmc: int = 2, current_n_m_s=None) -> np.ndarray:
    """Numpy version of :func:`ffbsi_mcmc` (reference for the kernel)."""
    v, w, dt = _controls(v_m_s, w_rad_s, dt_s)
    T = v.size
    out = np.empty((n_traj, T + 1, 3))
    idx = multinomial_indices(fr.log_w[T], n_traj, rng)
    out[:, T] = fr.poses[T, idx]
    for t in range(T - 1, -1, -1):
        nxt = out[:, t + 1]
        cur = fr.ancestors[t, idx]
        lp_cur = transition_logpdf(params, fr.poses[t, cur], nxt, v[t], w[t], dt[t], current_n_m_s)
        props = multinomial_indices(fr.log_w[t], (n_mcmc, n_traj), rng)
        log_u = np.log(rng.random((n_mcmc, n_traj)))
        for k in range(n_mcmc):
            prop = props[k]
            lp_prop = transition_logpdf(params, fr.poses[t, prop], nxt, v[t], w[t], dt[t], current_n_m_s)
            accept = log_u[k] < lp_prop - lp_cur
            cur = np.where(accept, prop, cur)
            lp_cur = np.where(accept, lp_prop, lp_cur)
        idx = cur
        out[:, t] = fr.poses[t, idx]
    return out
