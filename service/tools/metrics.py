r"""Navigation metrics against ground truth (replay of simulated missions).

Given the estimated track (nav states at the output rate) and the simulator's truth,
interpolated linearly onto the estimate's times (only inside the truth's time span):

- horizontal error ``e_k = ‖p̂_k[N,E] − p_k[N,E]‖`` (m); ``final_horizontal_error_m = e_K``,
  ``rms_horizontal_error_m = sqrt(mean e_k²)``;
- ``distance_travelled_m``: horizontal path length of the truth, ``Σ ‖p_{j+1} − p_j‖``;
- ``drift_percent_since_fix = 100 · e_K / D_fix`` where ``D_fix`` is the truth's
  horizontal path length since the last *fused* absolute position fix (USBL/GNSS);
  without any fix, since the start (the initial position is the fix). A percentage of a
  path shorter than :data:`MIN_PERCENT_PATH_M` says nothing (a log that ends with surface
  fixes: a few mm since the last one, 800 %): then ``None``, as for
  ``percent_distance_travelled`` of a vehicle that hardly moved;
- ``current_error_m_s``: ``‖ĉ[N,E] − c[N,E]‖`` at the end (and at the last fix);
- NEES ``ε_k = δx_kᵀ P_k⁻¹ δx_k`` over the navigation states position, velocity and
  attitude (d = 9): ``δp = p̂ − p``, ``δv = v̂ − v`` and the attitude error in the
  navigation frame ``δθ = Log(q ⊗ q̂⁻¹)`` (the estimator's left perturbation,
  ``q_true = q(δθ) ⊗ q̂``, fusion/state.py), the truth attitude slerped to the epoch.
  ``nees_mean`` and ``nees_fraction_in_95``: the fraction of epochs inside the two-sided
  95 % band of χ²(d), ``[χ²_{0.025}(d), χ²_{0.975}(d)]`` (Bar-Shalom, Li & Kirubarajan,
  *Estimation with Applications to Tracking and Navigation*, 2001, §5.4).
  ``nees_mean_by_block``: the same with each block's marginal covariance alone (pos, vel, att;
  d = 3 each, mean 3 when consistent), to say *which* states a too-large NEES comes from.

Through a DVL outage (:func:`dvl_outage_metrics`; the longest stretch without bottom lock,
at least ``min_outage_s``, from the last sample with lock ``t_a`` to the first again ``t_b``):

- ``outage_drift_percent = 100 · e(t_b⁻) / D_out``: the horizontal error of the last state
  before the DVL is re-admitted over the truth's path length ``D_out`` in ``[t_a, t_b]``;
- ``outage_start_error_m``: the horizontal error ``e(t_a)`` of the last state at or before
  ``t_a`` — what the DVL navigation before the outage left (its scale factor and
  misalignment, unobservable without fixes); ``outage_growth_m = ‖e⃗(t_b⁻) − e⃗(t_a)‖``: what
  the outage itself added (the vector difference, so an error the model carries unchanged
  counts zero);
- ``recovery_correction_sigma``: the largest position correction after the DVL returns, in
  units of the published covariance just before. The correction is what the published
  position does beyond its own velocity: ``C_j = Σ_{k≤j} (p_k − p_{k−1} − ½(v_k + v_{k−1})Δt)``
  over the epochs of ``[t_b, t_b + window_s]`` (horizontal); reported as the largest
  Mahalanobis length ``√(C_jᵀ P_h⁻¹ C_j)`` with ``P_h`` the horizontal position covariance
  at the last epoch before ``t_b`` (``recovery_correction_m`` its length in metres).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackArrays:
    """Estimated track. ``t_s`` (N,), ``pos_n_m`` (N,3), ``vel_n_m_s`` (N,3),
    ``q_nb`` (N,4) w,x,y,z, ``cov_pva`` (N,9,9) covariance of (pos, vel, att) errors
    in m, m/s, rad, ``current_n_m_s`` (N,2) horizontal current estimate."""

    t_s: np.ndarray
    pos_n_m: np.ndarray
    vel_n_m_s: np.ndarray
    q_nb: np.ndarray
    cov_pva: np.ndarray
    current_n_m_s: np.ndarray


@dataclass(frozen=True)
class TruthArrays:
    """Ground truth. ``t_s`` (M,) increasing, ``pos_n_m`` (M,3), ``vel_n_m_s`` (M,3),
    ``q_nb`` (M,4) w,x,y,z, ``current_n_m_s`` (M,2)."""

    t_s: np.ndarray
    pos_n_m: np.ndarray
    vel_n_m_s: np.ndarray
    q_nb: np.ndarray
    current_n_m_s: np.ndarray


# the shortest path a drift is given as a percentage of (m): an error of metres over a few
# metres of path is a position error, not a drift rate
MIN_PERCENT_PATH_M = 10.0


def _percent_of_path(err_m: float, path_m: float) -> float | None:
    return 100.0 * err_m / path_m if path_m >= MIN_PERCENT_PATH_M else None


def interp_rows(t_query_s: np.ndarray, t_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of each column of ``values`` (M, k) at ``t_query_s`` (N,)."""
    values = np.asarray(values, dtype=float)
    return np.stack([np.interp(t_query_s, t_s, values[:, j]) for j in range(values.shape[1])], axis=1)


def horizontal_path_length_m(pos_n_m: np.ndarray) -> np.ndarray:
    """Cumulative horizontal path length (N,) of positions (N,3), starting at 0."""
    pos = np.asarray(pos_n_m, dtype=float)
    if len(pos) == 0:
        return np.zeros(0)
    steps = np.hypot(np.diff(pos[:, 0]), np.diff(pos[:, 1]))
    return np.concatenate([[0.0], np.cumsum(steps)])


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """NEES ``δxᵀ P⁻¹ δx`` per row; ``err`` (N,d), ``cov`` (N,d,d). NaN where P is singular."""
    err = np.asarray(err, dtype=float)
    cov = np.asarray(cov, dtype=float)
    out = np.full(len(err), np.nan)
    if len(err) == 0:
        return out
    ok = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(err).all(axis=1)
    if not np.any(ok):
        return out
    rows = slice(None) if ok.all() else ok  # all finite (the usual case): no copy of cov
    try:
        chol = np.linalg.cholesky(cov[rows])
    except np.linalg.LinAlgError:
        # some covariance is not positive definite: evaluate row by row, skip those
        for i in np.flatnonzero(ok):
            try:
                L = np.linalg.cholesky(cov[i])
            except np.linalg.LinAlgError:
                continue
            y = np.linalg.solve(L, err[i])
            out[i] = float(y @ y)
        return out
    y = np.linalg.solve(chol, err[rows][..., None])[..., 0]
    out[rows] = np.einsum("ij,ij->i", y, y)
    return out


def attitude_error_n_rad(t_s: np.ndarray, q_est: np.ndarray, truth: TruthArrays) -> np.ndarray:
    """``Log(q_true ⊗ q̂⁻¹)`` (N,3) rad, the truth attitude slerped to ``t_s``."""
    from scipy.spatial.transform import Rotation, Slerp

    # our quaternions are (w, x, y, z); scipy stores (x, y, z, w)
    q_true = Rotation.from_quat(np.asarray(truth.q_nb, dtype=float)[:, [1, 2, 3, 0]])
    r_true = Slerp(truth.t_s, q_true)(np.clip(t_s, truth.t_s[0], truth.t_s[-1]))
    r_est = Rotation.from_quat(np.asarray(q_est, dtype=float)[:, [1, 2, 3, 0]])
    return (r_true * r_est.inv()).as_rotvec()


def chi2_band_95(dim: int) -> tuple[float, float]:
    """Two-sided 95 % band ``[χ²_{0.025}(dim), χ²_{0.975}(dim)]`` of one NEES value."""
    from scipy.stats import chi2  # here: the daemon imports this module (sinks), never calls it

    return float(chi2.ppf(0.025, dim)), float(chi2.ppf(0.975, dim))


def compute_metrics(track: TrackArrays, truth: TruthArrays, last_fix_t_s: float | None) -> dict:
    """Metrics of the module docstring; empty dict when track and truth do not overlap."""
    if len(track.t_s) == 0 or len(truth.t_s) < 2:
        return {}
    inside = (track.t_s >= truth.t_s[0]) & (track.t_s <= truth.t_s[-1])
    if not np.any(inside):
        return {}
    # every epoch inside (the usual case): views of the track, no copies
    rows = slice(None) if inside.all() else inside
    t = track.t_s[rows]
    pos_true = interp_rows(t, truth.t_s, truth.pos_n_m)
    vel_true = interp_rows(t, truth.t_s, truth.vel_n_m_s)
    cur_true = interp_rows(t, truth.t_s, truth.current_n_m_s[:, :2])
    pos_est = track.pos_n_m[rows]
    err_h = np.hypot(pos_est[:, 0] - pos_true[:, 0], pos_est[:, 1] - pos_true[:, 1])

    # truth path: truth samples inside [t0, tK] plus the interpolated end points
    t0, tK = float(t[0]), float(t[-1])
    mid = (truth.t_s > t0) & (truth.t_s < tK)
    path_t = np.concatenate([[t0], truth.t_s[mid], [tK]])
    path_pos = np.concatenate([pos_true[:1], truth.pos_n_m[mid], pos_true[-1:]])
    path_len = horizontal_path_length_m(path_pos)
    distance = float(path_len[-1])
    fix_t = t0 if last_fix_t_s is None or not math.isfinite(last_fix_t_s) else min(max(last_fix_t_s, t0), tK)
    distance_since_fix = distance - float(np.interp(fix_t, path_t, path_len))

    cur_err = np.linalg.norm(track.current_n_m_s[rows][:, :2] - cur_true, axis=1)
    i_fix = int(np.searchsorted(t, fix_t, side="right")) - 1

    att_err = attitude_error_n_rad(t, track.q_nb[rows], truth)
    err_pva = np.concatenate([pos_est - pos_true, track.vel_n_m_s[rows] - vel_true, att_err], axis=1)
    cov_pva = track.cov_pva[rows]
    eps = nees(err_pva, cov_pva)
    eps_ok = eps[np.isfinite(eps)]
    lo, hi = chi2_band_95(9)
    by_block = {}
    for name, sl in (("pos", slice(0, 3)), ("vel", slice(3, 6)), ("att", slice(6, 9))):
        e_b = nees(err_pva[:, sl], cov_pva[:, sl, sl])
        e_b = e_b[np.isfinite(e_b)]
        by_block[name] = float(np.mean(e_b)) if len(e_b) else None

    final_err = float(err_h[-1])
    return {
        "final_horizontal_error_m": final_err,
        "rms_horizontal_error_m": float(np.sqrt(np.mean(err_h**2))),
        "max_horizontal_error_m": float(np.max(err_h)),
        "distance_travelled_m": distance,
        "last_fix_t_s": None if last_fix_t_s is None else float(last_fix_t_s),
        "distance_since_fix_m": distance_since_fix,
        "drift_percent_since_fix": _percent_of_path(final_err, distance_since_fix),
        "percent_distance_travelled": _percent_of_path(final_err, distance),
        "current_error_m_s": float(cur_err[-1]),
        "current_error_at_last_fix_m_s": float(cur_err[max(i_fix, 0)]),
        "nees_dim": 9,
        "nees_states": "pos,vel,att",
        "nees_mean": float(np.mean(eps_ok)) if len(eps_ok) else None,
        "nees_band_95": [lo, hi],
        "nees_fraction_in_95": float(np.mean((eps_ok >= lo) & (eps_ok <= hi))) if len(eps_ok) else None,
        "nees_mean_by_block": by_block,
        "epochs": int(len(t)),
        "duration_s": tK - t0,
    }


def dvl_outage_metrics(track: TrackArrays, truth: TruthArrays, dvl_t_s: np.ndarray, dvl_lock: np.ndarray,
                       min_outage_s: float = 60.0, window_s: float = 60.0) -> dict:
    """Outage metrics of the module docstring; empty when no outage of ``min_outage_s``.

    ``dvl_t_s`` (K,) times of DVL samples, ``dvl_lock`` (K,) bool: the sample had bottom lock
    (fused or gated; not "invalid").
    """
    t = np.asarray(dvl_t_s, dtype=float)
    lock = np.asarray(dvl_lock, dtype=bool)
    if t.size < 2 or not lock.any() or len(track.t_s) < 2:
        return {}
    order = np.argsort(t, kind="stable")
    t, lock = t[order], lock[order]
    tl = t[lock]
    gaps = np.diff(tl)
    if not gaps.size or gaps.max() < min_outage_s:
        return {}
    i = int(np.argmax(gaps))
    t_a, t_b = float(tl[i]), float(tl[i + 1])
    if t_b > truth.t_s[-1] or t_a < truth.t_s[0]:
        return {}
    path_t = np.concatenate([[t_a], truth.t_s[(truth.t_s > t_a) & (truth.t_s < t_b)], [t_b]])
    path = interp_rows(path_t, truth.t_s, truth.pos_n_m)
    distance = float(horizontal_path_length_m(path)[-1])
    k_before = int(np.searchsorted(track.t_s, t_b, side="left")) - 1
    if k_before < 1 or distance <= 0:
        return {}
    tb = track.t_s[k_before]
    k_start = max(int(np.searchsorted(track.t_s, t_a, side="right")) - 1, 0)
    p_true = interp_rows(track.t_s[[k_start, k_before]], truth.t_s, truth.pos_n_m)
    e_start, e_end = track.pos_n_m[[k_start, k_before], :2] - p_true[:, :2]
    err = float(np.hypot(*e_end))
    P_h = track.cov_pva[k_before, :2, :2]
    sel = np.nonzero((track.t_s > tb) & (track.t_s <= t_b + window_s))[0]
    worst_sigma, worst_m = 0.0, 0.0
    if sel.size:
        ks = np.concatenate([[k_before], sel])
        dp = np.diff(track.pos_n_m[ks, :2], axis=0)
        dt = np.diff(track.t_s[ks])[:, None]
        vbar = 0.5 * (track.vel_n_m_s[ks[1:], :2] + track.vel_n_m_s[ks[:-1], :2])
        C = np.cumsum(dp - vbar * dt, axis=0)
        m = np.sqrt(np.einsum("ij,jk,ik->i", C, np.linalg.inv(P_h), C))
        j = int(np.argmax(m))
        worst_sigma, worst_m = float(m[j]), float(np.hypot(*C[j]))
    return {
        "outage_start_s": t_a, "outage_end_s": t_b, "outage_distance_m": distance,
        "outage_error_m": err, "outage_drift_percent": 100.0 * err / distance,
        "outage_start_error_m": float(np.hypot(*e_start)), "outage_growth_m": float(np.hypot(*(e_end - e_start))),
        "sigma_h_before_recovery_m": float(math.sqrt(max(P_h[0, 0], P_h[1, 1]))),
        "recovery_correction_m": worst_m, "recovery_correction_sigma": worst_sigma,
    }
