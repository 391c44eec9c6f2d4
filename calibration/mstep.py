r"""M-step: maximise the expected complete-data log-likelihood over the motion parameters.

From M smoothed trajectories ``x̃^{[j]}_{0:T}`` the velocities that carry each step are
recovered exactly (:func:`fusion.motion_model.invert_step`; this replaces the seed's
ε_T, ε_D formulas, which are the first-order version of the same inversion, see
DESIGN.md errata): ``V̂_tj, Ŵ_tj, Ŝ_tj``. With step weights λ_t (exponential forgetting,
λ = 1 for plain EM) the objective for the surge channel is (seed §3.3, as a maximisation)::

    L_V(α, k) = −½ Σ_t λ_t (1/M) Σ_j [ log s_t + (V̂_tj − k v_t)² / s_t ],
    s_t = v_t² e^{α_1} + w_t² e^{α_2} + e^{α_3},   α = log(σ_Vv², σ_Vw², σ_V1²)

and likewise for the yaw-rate channel (mean ``w_t + b_W``, terms σ_Wv², σ_Ww², σ_W1²).
Variances are optimised in log space (Newton-CG has no bounds) with
``scipy.optimize.minimize(method="Newton-CG")`` and the analytic gradient and Hessian:
with ``u_k = d_tk e^{α_k}`` (``d_t = (v_t², w_t², 1)``), ``f = log s + R/s``::

    ∂f/∂α_k = (1/s − R/s²) u_k
    ∂²f/∂α_k∂α_l = (−1/s² + 2R/s³) u_k u_l + (1/s − R/s²) δ_kl u_k

The objective averages over the M trajectories (they are draws from one posterior, not M
data sets), so a weak Gaussian prior ``(α − α_0)²/(2τ²)`` around the current parameters keeps
weakly-informed terms from wandering (``prior_tau = inf`` disables it). The means have
closed forms given the variances (weighted least squares)::

    k = Σ λ_t v_t Σ_j V̂_tj / s_t  /  (M Σ λ_t v_t² / s_t),   b_W = Σ λ_t Σ_j (Ŵ_tj − w_t)/s_t / (M Σ λ_t / s_t)

and the two are alternated (``n_alternations``). The sway variance is ``σ_S² =
Σ λ_t Σ_j Ŝ_tj² / (M Σ λ_t)``.

Identifiability: the columns of the design ``D = (v², w², 1)`` (weighted by √λ) are
scaled to unit norm; terms are admitted in priority order (the proportional term first:
σ_Vv for V, σ_Ww for W, then the constant, then the cross term) while the condition
number of the admitted columns stays below ``max_condition``; a term whose column is
(numerically) zero or would push the condition number over the limit is *held* at its
current value and reported.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize, nnls

from fusion.motion_model import MotionParams, invert_step

V_TERMS = ("var_vv", "var_vw", "var_v1")
W_TERMS = ("var_wv", "var_ww", "var_w1")
# admission order (indices into the design columns v², w², 1)
V_PRIORITY = (0, 2, 1)
W_PRIORITY = (1, 2, 0)


@dataclass(frozen=True)
class MStepOptions:
    """Options of the M-step (see module docstring)."""

    max_condition: float = 30.0
    prior_tau: float = 3.0
    n_alternations: int = 2
    fit_k_v: bool = True
    fit_b_w: bool = True
    fit_var_s: bool = True
    var_floor: float = 1e-10


@dataclass
class MStepResult:
    params: MotionParams
    held: tuple[str, ...]
    condition_v: float
    condition_w: float
    q_value: float
    notes: list[str] = field(default_factory=list)


def identifiable_terms(design: np.ndarray, priority, max_condition: float) -> tuple[list[int], float]:
    """Indices of columns of ``design`` (T, 3) that can be separated, and their condition number."""
    norms = np.linalg.norm(design, axis=0)
    scale = max(norms.max(), 1e-300)
    kept: list[int] = []
    cond = 1.0
    for k in priority:
        if norms[k] <= 1e-8 * scale:
            continue
        trial = kept + [k]
        cols = design[:, trial] / norms[trial]
        sv = np.linalg.svd(cols, compute_uv=False)
        c = sv[0] / sv[-1] if sv[-1] > 0 else math.inf
        if c <= max_condition:
            kept, cond = trial, c
    return kept, cond


class VarianceObjective:
    """Negative expected log-likelihood of one channel over its free log-variances, with
    the analytic gradient and Hessian (module docstring). ``resid_sq`` (T,) are the
    per-step residuals squared averaged over trajectories; ``lam`` (T,) step weights."""

    def __init__(self, design, lam, resid_sq, alpha0, free, prior_tau, prior_center=None):
        self.design, self.lam, self.resid_sq = design, lam, resid_sq
        self.alpha0 = np.asarray(alpha0, dtype=float)
        self.free = np.asarray(free, dtype=int)
        self.center = self.alpha0 if prior_center is None else np.asarray(prior_center, dtype=float)
        self.inv_tau2 = 0.0 if not math.isfinite(prior_tau) else 1.0 / prior_tau**2
        self._key = None

    def unpack(self, a_free):
        a = self.alpha0.copy()
        a[self.free] = a_free
        return a

    def _parts(self, a_free):
        key = a_free.tobytes()
        if key != self._key:  # fun, jac and hess are called at the same points
            # clip: the line search may probe far-off points; exp must not overflow
            u = self.design * np.exp(np.clip(self.unpack(a_free), -60.0, 20.0))[None, :]
            self._key, self._u, self._s = key, u[:, self.free], u.sum(axis=1)
        return self._u, self._s

    def fun(self, a_free):
        _, s = self._parts(a_free)
        val = 0.5 * np.sum(self.lam * (np.log(s) + self.resid_sq / s))
        return val + 0.5 * self.inv_tau2 * np.sum((a_free - self.center[self.free]) ** 2)

    def jac(self, a_free):
        u, s = self._parts(a_free)
        f1 = self.lam * (1.0 / s - self.resid_sq / s**2)
        return 0.5 * (f1 @ u) + self.inv_tau2 * (a_free - self.center[self.free])

    def hess(self, a_free):
        u, s = self._parts(a_free)
        f1 = self.lam * (1.0 / s - self.resid_sq / s**2)
        f2 = self.lam * (-1.0 / s**2 + 2.0 * self.resid_sq / s**3)
        h = 0.5 * (u.T @ (f2[:, None] * u) + np.diag(f1 @ u))
        return h + self.inv_tau2 * np.eye(self.free.size)


def _fit_log_variances(design, lam, resid_sq, n_traj, alpha0, free, prior_tau, prior_center=None):
    """Newton-CG over the free log-variances; returns the full α vector."""
    free = np.asarray(free, dtype=int)
    if free.size == 0:
        return alpha0.copy()
    obj = VarianceObjective(design, lam, resid_sq, alpha0, free, prior_tau, prior_center)
    fun, jac, hess, unpack = obj.fun, obj.jac, obj.hess, obj.unpack

    # start from the weighted moment estimate E[r²] ≈ D σ² (non-negative least squares):
    # Newton then converges in a few steps instead of crawling through the region where
    # the Hessian is indefinite (R < M s / 2)
    x_start = alpha0[free].copy()
    held_part = design @ np.exp(alpha0) - design[:, free] @ np.exp(alpha0[free])
    sw = np.sqrt(lam) / np.maximum(design @ np.exp(alpha0), 1e-300)
    try:
        lin, _ = nnls(design[:, free] * sw[:, None], (resid_sq - held_part) * sw)
        x_start = np.log(np.maximum(lin, 1e-3 * np.exp(alpha0[free])))
    except (ValueError, RuntimeError):
        pass
    if fun(x_start) > fun(alpha0[free]):
        x_start = alpha0[free].copy()
    res = minimize(fun, x_start, method="Newton-CG", jac=jac, hess=hess,
                   options={"xtol": 1e-4, "maxiter": 30})
    a = unpack(res.x)
    return a if np.all(np.isfinite(a)) else alpha0.copy()


def m_step(trajectories: np.ndarray, v_m_s, w_rad_s, dt_s, params: MotionParams,
           step_weights=None, options: MStepOptions = MStepOptions(),
           prior_params: MotionParams | None = None) -> MStepResult:
    """New :class:`MotionParams` from smoothed trajectories (M, T+1, 3).

    ``step_weights`` (T,) are the forgetting weights λ_t (default 1). ``prior_params``
    centres the log-variance prior (default: ``params``, the current values; a fixed
    centre such as the initial calibration makes EM a MAP-EM with one fixed prior).
    """
    v = np.asarray(v_m_s, dtype=float)
    w = np.asarray(w_rad_s, dtype=float)
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape)
    T = v.size
    lam = np.ones(T) if step_weights is None else np.asarray(step_weights, dtype=float)
    n_traj = trajectories.shape[0]
    V, W, S, _ = invert_step(trajectories[:, :-1], trajectories[:, 1:], dt[None, :])  # (M, T)
    design = np.stack([v * v, w * w, np.ones(T)], axis=1)
    sq_lam = np.sqrt(lam)[:, None]
    kept_v, cond_v = identifiable_terms(design * sq_lam, V_PRIORITY, options.max_condition)
    kept_w, cond_w = identifiable_terms(design * sq_lam, W_PRIORITY, options.max_condition)
    held = tuple(V_TERMS[k] for k in range(3) if k not in kept_v) + \
        tuple(W_TERMS[k] for k in range(3) if k not in kept_w)

    alpha_v = np.log([params.var_vv, params.var_vw, params.var_v1])
    alpha_w = np.log([params.var_wv, params.var_ww, params.var_w1])
    pp = params if prior_params is None else prior_params
    center_v = np.log([pp.var_vv, pp.var_vw, pp.var_v1])
    center_w = np.log([pp.var_wv, pp.var_ww, pp.var_w1])
    k_v, b_w = params.k_v, params.b_w
    sum_V = V.sum(axis=0)
    sum_W = (W - w[None, :]).sum(axis=0)
    a_v, a_w = alpha_v, alpha_w
    n_alt = max(1, options.n_alternations) if (options.fit_k_v or options.fit_b_w) else 1
    for _ in range(n_alt):
        res_v = np.mean((V - k_v * v[None, :]) ** 2, axis=0)
        a_v = _fit_log_variances(design, lam, res_v, n_traj, alpha_v, kept_v, options.prior_tau, center_v)
        res_w = np.mean((W - w[None, :] - b_w) ** 2, axis=0)
        a_w = _fit_log_variances(design, lam, res_w, n_traj, alpha_w, kept_w, options.prior_tau, center_w)
        s_v = design @ np.exp(a_v)
        s_w = design @ np.exp(a_w)
        if options.fit_k_v:
            den = n_traj * np.sum(lam * v * v / s_v)
            if den > 0:
                k_v = float(np.sum(lam * v * sum_V / s_v) / den)
        if options.fit_b_w:
            b_w = float(np.sum(lam * sum_W / s_w) / (n_traj * np.sum(lam / s_w)))
    res_v = np.sum((V - k_v * v[None, :]) ** 2, axis=0)
    res_w = np.sum((W - w[None, :] - b_w) ** 2, axis=0)
    var_s = params.var_s
    if options.fit_var_s:
        var_s = float(np.sum(lam * np.sum(S * S, axis=0)) / (n_traj * lam.sum()))
    floor = options.var_floor
    ev, ew = np.maximum(np.exp(a_v), floor), np.maximum(np.exp(a_w), floor)
    new = replace(params, var_vv=float(ev[0]), var_vw=float(ev[1]), var_v1=float(ev[2]),
                  var_wv=float(ew[0]), var_ww=float(ew[1]), var_w1=float(ew[2]),
                  var_s=max(var_s, floor), k_v=k_v if k_v > 0 else params.k_v, b_w=b_w)
    new = replace(new, **{name: getattr(params, name) for name in held})  # exactly, not exp(log(x))
    s_v, s_w = design @ ev, design @ ew
    q = -0.5 * np.sum(lam * (n_traj * (np.log(s_v) + np.log(s_w)) + res_v / s_v + res_w / s_w)) / n_traj
    notes = [f"held {name} (controls do not separate it)" for name in held]
    return MStepResult(new, held, cond_v, cond_w, float(q), notes)
