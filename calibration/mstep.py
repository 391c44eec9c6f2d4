r"""M-step: maximise the expected complete-data log-likelihood over the motion parameters.

From M smoothed trajectories ``x̃^{[j]}_{0:T}`` the velocities that carry each step are
recovered exactly (:func:`adaptnav.fusion.motion_model.invert_step`; this replaces the seed's
ε_T, ε_D formulas, which are the first-order version of the same inversion, see
DESIGN.md errata): ``V̂_tj, Ŵ_tj, Ŝ_tj``. With step weights λ_t (exponential forgetting,
λ = 1 for plain EM) the objective for the surge channel is (seed §3.3, as a maximisation)::

    L_V(α, k) = −½ Σ_t λ_t (1/M) Σ_j [ log s_t + (V̂_tj − k v_t)² / s_t ],
    s_t = v_t² e^{α_1} + w_t² e^{α_2} + e^{α_3},   α = log(σ_Vv², σ_Vw², σ_V1²)

and likewise for the yaw-rate channel (mean ``w_t + b_W``, terms σ_Wv², σ_Ww², σ_W1²).
Variances are optimised in log space (Newton-CG has no bounds) with the steps of
``scipy.optimize.minimize(method="Newton-CG")`` in one compiled call
(:func:`adaptnav.calibration._kernels.newton_cg_variances`: scipy's per-iteration Python
overhead was ~1.5 ms per fit for at most 3 unknowns) and the analytic gradient and Hessian:
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

Sway variance and missing information. The sway is never observed directly: fixes a
minute apart at σ 2 m say almost nothing about a 0.01 m/s lateral noise (60 s of it moves
the vehicle ~8 cm). The smoothed Ŝ are then draws from the prior, and EM's update of σ_S²
moves by a fraction ``1 − f`` of the way per iteration, where ``f`` is the fraction of
missing information (Dempster, Laird & Rubin 1977; Meng & Rubin 1991). With f ≈ 1 the update
is Monte-Carlo noise plus the smoother's own shrinkage (resampled trajectories share
ancestors, so their spread understates the posterior's): on the survey it drifted ~30 %
low and the filter, trusting a too-tight non-holonomic constraint, drifted more. ``f`` is
estimated from the trajectories themselves::

    f = Σ λ_t Var_j(Ŝ_tj) / Σ λ_t (1/M) Σ_j Ŝ_tj²

(across-trajectory spread over the total second moment: 1 when the data leave the sway
where the prior put it, 0 when they pin it). When ``f > max_missing_information_s`` σ_S² is
held and reported.

Sea current (``fit_current``). Positions are ground-referenced, so the step displacement
is ``c R(φ) [V, S]ᵀ + u δt`` (:mod:`adaptnav.fusion.motion_model`). Given the variances, k_V and
``u = (u_n, u_e)`` enter linearly: with ``g = δt/c``,
``V̂⁰ = k v + g (cos φ u_n + sin φ u_e) + e_V`` and ``Ŝ⁰ = g (−sin φ u_n + cos φ u_e) + e_S``
(``V̂⁰, Ŝ⁰`` inverted without current), so (k_V, u_n, u_e) is one weighted least-squares
problem (weights λ_t/s_t and λ_t/σ_S²), alternated with the variances like k_V alone
(:func:`fit_means`). A lawnmower separates k_V from the along-track current through the
alternating legs; where the window cannot (one straight leg at constant speed), the
inseparable column is held.

Identifiability: the columns of the design ``D = (v², w², 1)`` (weighted by √λ) are
scaled to unit norm; terms are admitted in priority order (the proportional term first:
σ_Vv for V, σ_Ww for W, then the constant, then the cross term) while the condition
number of the admitted columns stays below ``max_condition``; a term whose column is
(numerically) zero or would push the condition number over the limit is *held* at its
current value and reported.

Information on k_V. The condition test compares columns with each other; it does not see
that a column carries no information at all. A vehicle at rest with a blip of thrust has a
well-conditioned, nearly empty k_V column, and the least-squares k_V then follows the
blip's noise (a real BlueROV2 log: 1.0 → 0.61 from one window). k_V is held when its
standard error exceeds ``max_k_v_sigma`` (0.05; a survey window of 8 fixes at 1.5 m/s gives
~0.01) (:func:`k_v_informed`).

Surge terms at constant speed. A survey at constant speed has ``v² ≈ const`` so the columns
``v²`` and ``1`` are collinear: σ_Vv² v² and σ_V1² cannot be told apart. The priority order
then admits σ_Vv (the term the targets and the seed's σ_Dd are about) and holds σ_V1 at its
prior value, i.e. the surge variance seen at that speed is attributed to σ_Vv.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import nnls

from adaptnav.calibration._kernels import mean_design, newton_cg_variances, variance_objective
from adaptnav.fusion.motion_model import MotionParams

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
    fit_current: bool = False  # estimate the sea current with k_V (positions are ground-referenced)
    # invert each step on the heading-change branch nearest the expected turn (w + b_W) δt
    # instead of (−π, π]: needed when turns per step can exceed π (fusion.motion_model.invert_step)
    turn_about_mean: bool = False
    # variance terms always held at their current values (e.g. ("var_vw", "var_wv")): terms
    # the controls separate on paper (condition number) but the data barely inform
    hold_terms: tuple[str, ...] = ()
    # σ_S² is held when the fraction of missing information on the sway exceeds this (module docstring)
    max_missing_information_s: float = 0.5
    # k_V is held when its standard error over the window exceeds this (module docstring)
    max_k_v_sigma: float = 0.05
    var_floor: float = 1e-10


@dataclass
class MStepResult:
    params: MotionParams
    held: tuple[str, ...]
    condition_v: float
    condition_w: float
    q_value: float
    notes: list[str] = field(default_factory=list)
    current_n_m_s: tuple[float, float] = (0.0, 0.0)
    missing_information_s: float = math.nan   # f of the sway channel (module docstring)


def identifiable_terms(design: np.ndarray, priority, max_condition: float) -> tuple[list[int], float]:
    """Indices of columns of ``design`` (T, 3) that can be separated, and their condition number."""
    return identifiable_terms_gram(design.T @ design, priority, max_condition)


def identifiable_terms_gram(gram: np.ndarray, priority, max_condition: float) -> tuple[list[int], float]:
    """:func:`identifiable_terms` from the Gram matrix ``DᵀD`` (k, k) of the design: the
    condition number of the unit-norm columns is √(λ_max / λ_min) of their Gram matrix
    (the limit of 30 is far from where squaring it loses digits), and a design of many
    rows (M trajectories × T steps) never has to be built."""
    norms = np.sqrt(np.maximum(np.diag(gram), 0.0))
    scale = max(norms.max(), 1e-300)
    kept: list[int] = []
    cond = 1.0
    for k in priority:
        if norms[k] <= 1e-8 * scale:
            continue
        trial = kept + [k]
        ev = np.linalg.eigvalsh(gram[np.ix_(trial, trial)] / np.outer(norms[trial], norms[trial]))
        c = math.sqrt(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
        if c <= max_condition:
            kept, cond = trial, c
    return kept, cond


def least_squares_sigmas(weighted_design: np.ndarray) -> np.ndarray:
    """Standard errors of the coefficients of a weighted least-squares problem whose rows are
    already scaled by √weight (weights = inverse variances): √diag((AᵀA)⁻¹); inf for a
    column the rows do not inform."""
    return _sigmas_from_information(weighted_design.T @ weighted_design)


def _sigmas_from_information(info: np.ndarray) -> np.ndarray:
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full(info.shape[0], math.inf)
    d = np.diag(cov)
    return np.where(d > 0, np.sqrt(np.abs(d)), math.inf)


def k_v_informed(weighted_design: np.ndarray, free: list[int], max_sigma: float,
                 n_copies: int = 1) -> tuple[bool, float]:
    """Whether k_V (column 0 of ``weighted_design``) is pinned to ``max_sigma`` by the rows,
    with the other ``free`` columns estimated alongside; and its standard error.

    ``n_copies``: the rows are that many draws of the same data (M smoothed trajectories),
    so the information per data set is 1/n_copies of the rows'.
    """
    return k_v_informed_gram(weighted_design.T @ weighted_design, free, max_sigma, n_copies)


def k_v_informed_gram(info: np.ndarray, free: list[int], max_sigma: float,
                      n_copies: int = 1) -> tuple[bool, float]:
    """:func:`k_v_informed` from the information matrix ``AᵀA`` of the weighted design."""
    if 0 not in free:
        return False, math.nan
    sig = _sigmas_from_information(info[np.ix_(free, free)])[free.index(0)] * math.sqrt(n_copies)
    return bool(sig <= max_sigma), float(sig)


class VarianceObjective:
    """Negative expected log-likelihood of one channel over its free log-variances, with
    the analytic gradient and Hessian (module docstring; compiled:
    :func:`adaptnav.calibration._kernels.variance_objective`). ``resid_sq`` (T,) are the
    per-step residuals squared averaged over trajectories; ``lam`` (T,) step weights."""

    def __init__(self, design, lam, resid_sq, alpha0, free, prior_tau, prior_center=None):
        f64 = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        self.design, self.lam, self.resid_sq = f64(design), f64(lam), f64(resid_sq)
        self.alpha0 = f64(alpha0)
        self.free = np.ascontiguousarray(free, dtype=np.int64)
        self.center = self.alpha0 if prior_center is None else f64(prior_center)
        self.inv_tau2 = 0.0 if not math.isfinite(prior_tau) else 1.0 / prior_tau**2

    def unpack(self, a_free):
        a = self.alpha0.copy()
        a[self.free] = a_free
        return a

    def _args(self):
        return self.free, self.alpha0, self.design, self.lam, self.resid_sq, self.center, self.inv_tau2

    def _eval(self, a_free):
        k = self.free.size
        grad, hess = np.empty(k), np.empty((k, k))
        val = variance_objective(np.ascontiguousarray(a_free, dtype=float), *self._args(), grad, hess)
        return val, grad, hess

    def fun(self, a_free):
        return self._eval(a_free)[0]

    def jac(self, a_free):
        return self._eval(a_free)[1]

    def hess(self, a_free):
        return self._eval(a_free)[2]

    def minimise(self, a_start, xtol: float = 1e-4, maxiter: int = 30):
        """Newton-CG from ``a_start`` (free log-variances): :func:`adaptnav.calibration._kernels.newton_cg_variances`."""
        return newton_cg_variances(np.ascontiguousarray(a_start, dtype=float), *self._args(), float(xtol),
                                   int(maxiter))


def _fit_log_variances(design, lam, resid_sq, n_traj, alpha0, free, prior_tau, prior_center=None):
    """Newton-CG over the free log-variances; returns the full α vector."""
    free = np.asarray(free, dtype=int)
    if free.size == 0:
        return alpha0.copy()
    obj = VarianceObjective(design, lam, resid_sq, alpha0, free, prior_tau, prior_center)

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
    if obj.fun(x_start) > obj.fun(alpha0[free]):
        x_start = alpha0[free].copy()
    a = obj.unpack(obj.minimise(x_start))
    return a if np.all(np.isfinite(a)) else alpha0.copy()


def _mean_design(trajectories, dt, turn_ref_rad=None):
    """Regressors of the mean model for every (trajectory, step).

    With zero-current inversions ``V̂⁰, Ŝ⁰`` (:func:`adaptnav.fusion.motion_model.invert_step`) and
    ``g = δt / c``, the water-relative velocities are ``V̂ = V̂⁰ − g (cos φ u_n + sin φ u_e)``,
    ``Ŝ = Ŝ⁰ − g (−sin φ u_n + cos φ u_e)``. Returns ``V0, W, S0`` (M, T) and the current's
    columns ``gv = g (cos φ, sin φ)``, ``gs = g (−sin φ, cos φ)`` as (M, T, 2)
    (compiled: :func:`adaptnav.calibration._kernels.mean_design`).
    """
    T = dt.shape[0]
    ref = np.zeros(T) if turn_ref_rad is None else np.broadcast_to(np.asarray(turn_ref_rad, dtype=float), (1, T))[0]
    return mean_design(np.ascontiguousarray(trajectories, dtype=float), np.ascontiguousarray(dt, dtype=float),
                       np.ascontiguousarray(ref, dtype=float))


def _water_relative(V0, S0, gv, gs, current):
    """``V̂, Ŝ`` (M, T) with the current (2,) m/s removed (:func:`_mean_design`)."""
    if current[0] == 0.0 and current[1] == 0.0:
        return V0, S0
    return (V0 - gv[..., 0] * current[0] - gv[..., 1] * current[1],
            S0 - gs[..., 0] * current[0] - gs[..., 1] * current[1])


def fit_means(V0, S0, gv, gs, v, lam, s_v, var_s, k_v, current, fit_k_v, fit_current, max_condition,
              max_k_v_sigma: float = math.inf):
    """Weighted least squares for (k_V, u_n, u_e) given the variances (closed form).

    Rows ``V̂⁰_tj = k v_t + gv_tj · u + e``, weight ``λ_t / s_V,t``, and ``Ŝ⁰_tj = gs_tj · u + e``,
    weight ``λ_t / σ_S²``, summed over the M trajectories. Columns the rows cannot separate
    (e.g. k_V and the along-track current on a single straight leg at constant speed) are
    held at their current values (:func:`identifiable_terms`, priority k_V, u_n, u_e).

    k_V is also held when its standard error exceeds ``max_k_v_sigma`` (:func:`k_v_informed`;
    the complete-data error, which is smaller than the observed-data one: when even that is
    too large the window's speeds do not inform k_V, e.g. a vehicle at rest with a blip of
    thrust).

    Returns ``(k_v, current (2,), held names, σ of k_V)``.
    """
    M, T = V0.shape
    theta = np.array([k_v, current[0], current[1]], dtype=float)
    want = [k for k, on in ((0, fit_k_v), (1, fit_current), (2, fit_current)) if on]
    if not want:
        return k_v, np.asarray(current, float), (), math.nan
    # normal equations: information AᵀA and AᵀWy summed over the M·T rows of each channel
    # (rows never built: at M = 100 the (2MT, 3) design cost milliseconds per M-step)
    wv = lam / s_v
    ws = lam / var_s
    if fit_current:
        Xv = np.empty((M, T, 3))
        Xv[..., 0] = v
        Xv[..., 1:] = gv
        Xv_w = Xv * wv[None, :, None]
        gs_w = gs * ws[None, :, None]
        info = Xv_w.reshape(-1, 3).T @ Xv.reshape(-1, 3)
        info[1:, 1:] += gs_w.reshape(-1, 2).T @ gs.reshape(-1, 2)
        rhs = Xv_w.reshape(-1, 3).T @ V0.reshape(-1)
        rhs[1:] += gs_w.reshape(-1, 2).T @ S0.reshape(-1)
    else:  # the current is given: k_V's column alone, against the water-relative V̂
        V, _ = _water_relative(V0, S0, gv, gs, theta[1:])
        info = np.zeros((3, 3))
        rhs = np.zeros(3)
        info[0, 0] = M * np.sum(wv * v * v)
        rhs[0] = np.sum(wv * v * V.sum(axis=0))
    # condition test on the per-step design (trajectory-averaged), not the M-fold copy
    kept, _ = identifiable_terms_gram(info[np.ix_(want, want)], list(range(len(want))), max_condition)
    free = [want[i] for i in kept]
    ok, sigma_k = k_v_informed_gram(info, free, max_k_v_sigma, n_copies=M)
    if not ok and 0 in free:
        free.remove(0)
    fixed = [k for k in range(3) if k not in free]
    held = tuple(("k_v", "current_n", "current_e")[k] for k in want if k not in free)
    if free:
        b = rhs[free] - info[np.ix_(free, fixed)] @ theta[fixed]
        try:
            sol = np.linalg.solve(info[np.ix_(free, free)], b)
        except np.linalg.LinAlgError:
            sol = np.full(len(free), math.nan)
        if np.all(np.isfinite(sol)):
            theta[free] = sol
    return float(theta[0]), theta[1:].copy(), held, sigma_k


def m_step(trajectories: np.ndarray, v_m_s, w_rad_s, dt_s, params: MotionParams,
           step_weights=None, options: MStepOptions = MStepOptions(),
           prior_params: MotionParams | None = None, current_n_m_s=None,
           surge_increments=None) -> MStepResult:
    """New :class:`MotionParams` (and sea current) from smoothed trajectories (M, T+1, 3).

    ``step_weights`` (T,) are the forgetting weights λ_t (default 1). ``prior_params``
    centres the log-variance prior (default: ``params``, the current values; a fixed
    centre such as the initial calibration makes EM a MAP-EM with one fixed prior).
    ``current_n_m_s`` (2,) m/s is the current of the E-step (default zero); it is
    re-estimated with k_V when ``options.fit_current`` (:func:`fit_means`), else kept.
    ``surge_increments`` (:class:`adaptnav.calibration.inertial.SurgeIncrements`, window-step units)
    are extra rows of the surge-variance objective: the IMU's velocity changes between
    model steps, observed directly rather than smoothed (same design, own weights).
    """
    v = np.asarray(v_m_s, dtype=float)
    w = np.asarray(w_rad_s, dtype=float)
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), v.shape)
    T = v.size
    lam = np.ones(T) if step_weights is None else np.asarray(step_weights, dtype=float)
    n_traj = trajectories.shape[0]
    current = np.zeros(2) if current_n_m_s is None else np.asarray(current_n_m_s, dtype=float).copy()
    turn_ref = (w + params.b_w)[None, :] * dt[None, :] if options.turn_about_mean else None
    V0, W, S0, gv, gs = _mean_design(trajectories, dt, turn_ref)

    V, S = _water_relative(V0, S0, gv, gs, current)
    design = np.stack([v * v, w * w, np.ones(T)], axis=1)
    sq_lam = np.sqrt(lam)[:, None]
    kept_v, cond_v = identifiable_terms(design * sq_lam, V_PRIORITY, options.max_condition)
    kept_w, cond_w = identifiable_terms(design * sq_lam, W_PRIORITY, options.max_condition)
    kept_v = [k for k in kept_v if V_TERMS[k] not in options.hold_terms]
    kept_w = [k for k in kept_w if W_TERMS[k] not in options.hold_terms]
    held = tuple(V_TERMS[k] for k in range(3) if k not in kept_v) + \
        tuple(W_TERMS[k] for k in range(3) if k not in kept_w)

    alpha_v = np.log([params.var_vv, params.var_vw, params.var_v1])
    alpha_w = np.log([params.var_wv, params.var_ww, params.var_w1])
    pp = params if prior_params is None else prior_params
    center_v = np.log([pp.var_vv, pp.var_vw, pp.var_v1])
    center_w = np.log([pp.var_wv, pp.var_ww, pp.var_w1])
    k_v, b_w = params.k_v, params.b_w
    var_s = params.var_s
    sum_W = (W - w[None, :]).sum(axis=0)
    a_v, a_w = alpha_v, alpha_w
    held_means: tuple[str, ...] = ()
    sigma_k = math.nan
    missing_s = math.nan
    hold_s = False  # σ_S² held: the data carry little information on the sway
    fit_means_any = options.fit_k_v or options.fit_current
    n_alt = max(1, options.n_alternations) if (fit_means_any or options.fit_b_w) else 1
    for _ in range(n_alt):
        # means given the variances (the first pass uses the E-step's, which are close)
        s_v = design @ np.exp(a_v)
        s_w = design @ np.exp(a_w)
        if fit_means_any:
            k_new, current, held_means, sigma_k = fit_means(V0, S0, gv, gs, v, lam, s_v, var_s, k_v, current,
                                                            options.fit_k_v, options.fit_current,
                                                            options.max_condition, options.max_k_v_sigma)
            k_v = k_new if k_new > 0 else k_v
            V, S = _water_relative(V0, S0, gv, gs, current)
        if options.fit_b_w:
            b_w = float(np.sum(lam * sum_W / s_w) / (n_traj * np.sum(lam / s_w)))
        # variances given the means
        res_v = np.mean((V - k_v * v[None, :]) ** 2, axis=0)
        if surge_increments is not None and len(surge_increments):
            inc = surge_increments
            a_v = _fit_log_variances(np.concatenate([design, inc.design]), np.concatenate([lam, inc.weight]),
                                     np.concatenate([res_v, inc.residual_sq(k_v)]), n_traj, alpha_v, kept_v,
                                     options.prior_tau, center_v)
        else:
            a_v = _fit_log_variances(design, lam, res_v, n_traj, alpha_v, kept_v, options.prior_tau, center_v)
        res_w = np.mean((W - w[None, :] - b_w) ** 2, axis=0)
        a_w = _fit_log_variances(design, lam, res_w, n_traj, alpha_w, kept_w, options.prior_tau, center_w)
        if options.fit_var_s:
            missing_s = sway_missing_information(S, lam)
            hold_s = missing_s > options.max_missing_information_s  # NaN (one trajectory): fit
            var_s = params.var_s if hold_s else \
                max(float(np.sum(lam * np.sum(S * S, axis=0)) / (n_traj * lam.sum())), options.var_floor)
    res_v = np.sum((V - k_v * v[None, :]) ** 2, axis=0)
    res_w = np.sum((W - w[None, :] - b_w) ** 2, axis=0)
    floor = options.var_floor
    ev, ew = np.maximum(np.exp(a_v), floor), np.maximum(np.exp(a_w), floor)
    new = replace(params, var_vv=float(ev[0]), var_vw=float(ev[1]), var_v1=float(ev[2]),
                  var_wv=float(ew[0]), var_ww=float(ew[1]), var_w1=float(ew[2]),
                  var_s=max(var_s, floor), k_v=k_v if k_v > 0 else params.k_v, b_w=b_w)
    new = replace(new, **{name: getattr(params, name) for name in held})  # exactly, not exp(log(x))
    s_v, s_w = design @ ev, design @ ew
    q = -0.5 * np.sum(lam * (n_traj * (np.log(s_v) + np.log(s_w)) + res_v / s_v + res_w / s_w)) / n_traj
    # why each term was held, one clause per reason (it goes into the release record)
    k_v_uninformed = "k_v" in held_means and sigma_k > options.max_k_v_sigma
    configured = [name for name in held if name in options.hold_terms]
    by_controls = [name for name in held + held_means
                   if name not in configured and not (name == "k_v" and k_v_uninformed)]
    notes = []
    if by_controls:
        notes.append(f"held {','.join(by_controls)} (the controls do not separate "
                     f"{'it' if len(by_controls) == 1 else 'them'})")
    if configured:
        notes.append(f"held {','.join(configured)} (configured)")
    if k_v_uninformed:
        notes.append(f"held k_v (the speeds do not inform it: σ {sigma_k:.2g} > {options.max_k_v_sigma:g})")
    held_s: tuple[str, ...] = ()
    if hold_s:
        held_s = ("var_s",)
        notes.append(f"held var_s (the data carry little information on the sway: missing-information "
                     f"fraction {missing_s:.2f} > {options.max_missing_information_s:g})")
    return MStepResult(new, held + held_means + held_s, cond_v, cond_w, float(q), notes,
                       (float(current[0]), float(current[1])), missing_s)


def sway_missing_information(S: np.ndarray, lam: np.ndarray) -> float:
    """Fraction of missing information on the sway, ``f`` of the module docstring.

    ``S`` (M, T) smoothed sway velocities (m/s), ``lam`` (T,) step weights. 1 when the
    trajectories scatter as the prior does, 0 when the data pin every step's sway; NaN
    for fewer than two trajectories (no spread to measure).
    """
    if S.shape[0] < 2:
        return math.nan
    total = float(np.sum(lam * np.mean(S * S, axis=0)))
    if not total > 0.0:
        return math.nan
    return float(np.sum(lam * np.var(S, axis=0))) / total


def surge_variances_from_increments(params: MotionParams, increments, options: MStepOptions = MStepOptions(),
                                    prior_params: MotionParams | None = None) -> MStepResult:
    """Surge variances from the IMU's increments alone (no trajectories: no position information).

    The means (k_V, b_W, the current) and the other channels are not observable from the
    increments and stay as they are; the surge terms are fitted by the same Newton-CG
    objective over the increment rows only, with the same identifiability test and prior.
    ``increments`` is a :class:`adaptnav.calibration.inertial.SurgeIncrements` in window-step units.
    """
    inc = increments
    design, lam = inc.design, inc.weight
    kept, cond = identifiable_terms(design * np.sqrt(lam)[:, None], V_PRIORITY, options.max_condition)
    kept = [k for k in kept if V_TERMS[k] not in options.hold_terms]
    alpha = np.log([params.var_vv, params.var_vw, params.var_v1])
    pp = params if prior_params is None else prior_params
    center = np.log([pp.var_vv, pp.var_vw, pp.var_v1])
    a = _fit_log_variances(design, lam, inc.residual_sq(params.k_v), 1, alpha, kept, options.prior_tau, center)
    ev = np.maximum(np.exp(a), options.var_floor)
    held = tuple(V_TERMS[k] for k in range(3) if k not in kept)
    new = replace(params, var_vv=float(ev[0]), var_vw=float(ev[1]), var_v1=float(ev[2]))
    new = replace(new, **{name: getattr(params, name) for name in held})
    s_v = design @ np.array([new.var_vv, new.var_vw, new.var_v1])
    q = -0.5 * float(np.sum(lam * (np.log(s_v) + inc.residual_sq(params.k_v) / s_v)))
    return MStepResult(new, held, cond, math.nan, q, [f"held {n} (controls do not separate it)" for n in held])
