r"""Speed scale and sea current from position fixes vs dead reckoning (a closed-form CM step).

Why. In EM the sea current ``u`` is a parameter of the motion model (:mod:`adaptnav.fusion.motion_model`)
and the M-step re-estimates it from smoothed trajectories (:func:`adaptnav.calibration.mstep.fit_means`).
But the smoother's trajectories can only show what the motion prior lets them: a cross-track
current of 0.07 m/s drifts ~4 m per minute, while the sway noise σ_S (~0.01 m/s) allows
centimetres, so the smoothed sway barely shows the current and EM's update of it moves by a
tiny fraction of the way per iteration (EM's rate → 1 when the latent prior is tight;
Dempster, Laird & Rubin 1977; Meng & Rubin 1993). An ECME step (Liu & Rubin 1994) instead
maximises the *observed-data* likelihood for some parameters: here that of the fixes for
(k_V, u) under the linear-Gaussian approximation of dead reckoning between fixes.
Side-scan objects re-found on another leg add the displacement between their two poses
(:func:`adaptnav.calibration.sidescan.landmark_pairs`), the same rows without the fixes'
absolute positions: the fit that still informs k_V and the current when the fixes are gone.

Model. Fixes ``p_a`` at poses a (σ_a, isotropic), headings ``θ_t`` at the poses (the forward
filter's circular means; the heading aid makes them precise), reported surge ``v_t``. The
water-relative dead-reckoned displacement of step t at unit speed scale is
``d_t = c_t v_t (cos φ_t, sin φ_t)``, ``φ_t = θ_t + Δθ_t/2``, ``c_t = 2 sin(Δθ_t/2)/(Δθ_t/δt_t)``
(:mod:`adaptnav.fusion.motion_model`). For consecutive fixes a < b::

    p_b − p_a = k_V Σ_{t=a}^{b−1} d_t + u Σ_{t=a}^{b−1} δt_t + e,   Cov e ≈ (σ_a² + σ_b² + q_ab) I

with ``q_ab = Σ_t δt_t² (v_t² σ_Vv² + σ_V1² + σ_S²)`` the dead-reckoning noise. This is a
weighted least-squares problem in (k_V, u_n, u_e), weights λ (forgetting at the later fix).
Columns the pairs cannot separate (k_V and the along-track current on one straight leg at
constant speed) are held (:func:`adaptnav.calibration.mstep.identifiable_terms`, priority u_n, u_e, k_V:
the current is what EM cannot find by itself).

A k_V that changes. Side-scan pairs span up to 16 min (the landmark memory) and carry k_V
where the vehicle turned between their two poses; under one k_V with forgetting by the later
pose, a pair whose earlier leg was in the old water counts its old k_V as new, and after a
change of water the fit lagged by ~4 % for 10 min (landmark survey, k_V 1.0 → 0.9). With
``k_v_walk_var_per_step`` > 0 (and side-scan rows present) k_V is a random walk along the
steps instead: the k_V column of every row is split by step, the walk's increments join
as rows ``(k_{t+1} − k_t)/√q``, and the fit returns k_V at the last pose, its σ from the
same least squares (held when above ``max_k_v_sigma``). The walk is the forgetting then, and
the rows are not weighted by λ. Fixes alone keep one k_V under forgetting: a fix pair spans a
minute, and its forgetting weight is at the right time.
"""
from __future__ import annotations

import math

import numpy as np

from adaptnav.calibration.mstep import identifiable_terms, k_v_informed
from adaptnav.calibration.sensors import PositionFix


def fix_pairs(observations) -> list[tuple[int, PositionFix]]:
    """``(pose index, first PositionFix)`` for every pose with a fix, in order."""
    out = []
    for t, obs in enumerate(observations):
        for o in obs or ():
            if isinstance(o, PositionFix):
                out.append((t, o))
                break
    return out


def dead_reckoning(v_m_s, dt_s, headings_rad, params):
    """Cumulative dead-reckoned displacement at unit speed scale (T+1, 2) (m), time (T+1,) (s)
    and dead-reckoning variance per axis (T+1,) (m², ``params`` for the step ``dt_s``) from
    pose 0, for surges ``v_m_s`` (T,) and headings at the poses (T+1,) (module docstring)."""
    v = np.asarray(v_m_s, dtype=float)
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape)
    th = np.asarray(headings_rad, dtype=float)
    dth = (np.diff(th) + np.pi) % (2.0 * np.pi) - np.pi
    phi = th[:-1] + 0.5 * dth
    c = dt * np.sinc(dth / (2.0 * np.pi))  # 2 sin(Δθ/2)/(Δθ/δt)
    d = (c * v)[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])
    cum_d = np.vstack([np.zeros(2), np.cumsum(d, axis=0)])
    cum_t = np.concatenate([[0.0], np.cumsum(dt)])
    q_step = dt**2 * (v**2 * params.var_vv + params.var_v1 + params.var_s)
    return cum_d, cum_t, np.concatenate([[0.0], np.cumsum(q_step)])


def fix_regression(v_m_s, dt_s, headings_rad, observations, params, k_v: float, current_n_m_s,
                   step_weights=None, max_condition: float = 30.0, max_k_v_sigma: float = math.inf,
                   landmark_rows=None, k_v_walk_var_per_step: float = 0.0):
    """(k_V, current (2,), held names) from fixes vs dead reckoning (module docstring).

    Parameters
    ----------
    v_m_s : (T,) reported surge (m/s) of steps t → t+1
    dt_s : float or (T,) step lengths (s)
    headings_rad : (T+1,) headings at the poses (rad)
    observations : length T+1 lists; :class:`PositionFix` entries are used
    params : :class:`adaptnav.fusion.motion_model.MotionParams` for the step ``dt_s`` (the noise weights)
    k_v, current_n_m_s : the values held where the fixes do not separate a term
    step_weights : (T,) forgetting weights λ_t (default 1)
    max_k_v_sigma : k_V is held when its standard error exceeds this
        (:func:`adaptnav.calibration.mstep.k_v_informed`)
    landmark_rows : (X (2K, 3), y (2K,), w (2K,), X_k (2K, M)), optional
        More rows of the same regression with their weights: side-scan pairs
        (:func:`adaptnav.calibration.sidescan.landmark_rows`, over the calibrator's longer memory
        of M steps ending at the window's last pose); ``X_k`` their k_V column split by step
    k_v_walk_var_per_step : float
        > 0: k_V is a random walk along the steps with this variance per step (module docstring,
        "A k_V that changes"); ``step_weights`` are then not used (the walk is the forgetting)
        and the k_V returned is the one at the window's last pose. 0: one k_V for all rows.

    Returns
    -------
    (k_v, (u_n, u_e), held) — the inputs unchanged (all held) with fewer than two fixes.
    """
    v = np.asarray(v_m_s, dtype=float)
    T = v.size
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (T,))
    th = np.asarray(headings_rad, dtype=float)
    lam = np.ones(T) if step_weights is None else np.asarray(step_weights, dtype=float)
    theta0 = np.array([k_v, float(current_n_m_s[0]), float(current_n_m_s[1])])
    fixes = fix_pairs(observations)
    extra = landmark_rows if landmark_rows is not None and len(landmark_rows[1]) else None
    if len(fixes) < 2 and extra is None:
        return k_v, (theta0[1], theta0[2]), ("k_v", "current_n", "current_e")
    walk = k_v_walk_var_per_step > 0.0 and extra is not None
    if walk:
        lam = np.ones(T)
    cum_d, cum_t, cum_q = dead_reckoning(v, dt, th, params)
    d_step = np.diff(cum_d, axis=0)
    M = extra[3].shape[1] if extra is not None else T  # steps of the landmark memory
    N = max(T, M)  # steps of the walk, aligned at the last pose
    rows, ys, ws, k_rows = [], [], [], []
    for (a, fa), (b, fb) in zip(fixes[:-1], fixes[1:]):
        D = cum_d[b] - cum_d[a]
        tau = cum_t[b] - cum_t[a]
        var = fa.sigma_m**2 + fb.sigma_m**2 + (cum_q[b] - cum_q[a])
        w = lam[b - 1] / var
        rows += [[D[0], tau, 0.0], [D[1], 0.0, tau]]
        ys += [fb.pos_n_m[0] - fa.pos_n_m[0], fb.pos_n_m[1] - fa.pos_n_m[1]]
        ws += [w, w]
        if walk:
            per_step = np.zeros((2, N))
            per_step[:, N - T + a:N - T + b] = d_step[a:b].T
            k_rows.append(per_step)
    if extra is not None:  # side-scan pairs (calibration.sidescan.landmark_rows), already weighted
        rows += [list(r) for r in extra[0]]
        ys += list(extra[1])
        ws += list(extra[2])
        if walk:
            k_rows.append(np.pad(extra[3], ((0, 0), (N - M, 0))))
    X, y, sw = np.array(rows), np.array(ys), np.sqrt(np.array(ws))
    order = (1, 2, 0)  # current first, then k_V
    kept, _ = identifiable_terms(X * sw[:, None], order, max_condition)
    free = sorted(kept)
    theta = theta0.copy()
    if walk and 0 in free:
        k_end, cur, sigma = _walk_solution(np.vstack(k_rows), X, y, sw, free, theta0, k_v_walk_var_per_step)
        if math.isfinite(k_end) and sigma <= max_k_v_sigma:
            theta[0] = k_end
            theta[[i for i in free if i]] = cur
            return float(theta[0]), (float(theta[1]), float(theta[2])), \
                tuple(("k_v", "current_n", "current_e")[k] for k in range(3) if k not in free)
        free.remove(0)
    if not k_v_informed(X * sw[:, None], free, max_k_v_sigma)[0] and 0 in free:
        free.remove(0)
    fixed = [k for k in range(3) if k not in free]
    if free:
        r = y - X[:, fixed] @ theta0[fixed]
        sol, *_ = np.linalg.lstsq(X[:, free] * sw[:, None], r * sw, rcond=None)
        if np.all(np.isfinite(sol)):
            theta[free] = sol
    held = tuple(("k_v", "current_n", "current_e")[k] for k in fixed)
    return float(theta[0]), (float(theta[1]), float(theta[2])), held


def _walk_solution(Xk, X, y, sw, free, theta0, q_step):
    """(k_V at the last step, the free currents, σ of that k_V) for a k_V that is a random walk
    of variance ``q_step`` per step: least squares over the rows (k_V columns ``Xk`` (R, N)
    by step, current columns of ``X`` (R, 3)) and the walk's increments
    ``(k_{t+1} − k_t)/√q_step``; held currents are moved to the right-hand side."""
    R, N = Xk.shape
    cur_free = [i for i in free if i]
    cur_fixed = [i for i in (1, 2) if i not in free]
    r = y - X[:, cur_fixed] @ theta0[cur_fixed]
    A = np.hstack([Xk, X[:, cur_free]]) * sw[:, None]
    P = np.zeros((N - 1, N + len(cur_free)))
    i = np.arange(N - 1)
    P[i, i], P[i, i + 1] = -1.0, 1.0
    A = np.vstack([A, P / math.sqrt(q_step)])
    b = np.concatenate([r * sw, np.zeros(N - 1)])
    info = A.T @ A
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return math.nan, np.zeros(len(cur_free)), math.inf
    sol = cov @ (A.T @ b)
    if not (np.all(np.isfinite(sol)) and cov[N - 1, N - 1] > 0):
        return math.nan, np.zeros(len(cur_free)), math.inf
    return float(sol[N - 1]), sol[N:], math.sqrt(cov[N - 1, N - 1])


def circular_mean_headings(clouds) -> np.ndarray:
    """(T+1,) circular mean heading of each equally weighted (N, 3) pose cloud."""
    th = np.stack([cl[:, 2] for cl in clouds])
    return np.arctan2(np.sin(th).mean(axis=1), np.cos(th).mean(axis=1))


__all__ = ["fix_regression", "fix_pairs", "circular_mean_headings"]
