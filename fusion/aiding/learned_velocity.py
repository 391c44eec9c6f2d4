r"""Learned-velocity aiding: the motion model's surge from RPM, sway/heave ≈ 0.

Water-relative body velocity (DESIGN.md "Fusion"; Hegrenaes & Hallingstad 2011)::

    v_b = R_nbᵀ (v_n − [c_n, c_e, 0]ᵀ)

How ``k_V`` (learned) and ``k_speed`` (filter state) combine. The calibrator learns the
motion model ``V ~ N(k_V f(n), σ_V²(v, w))`` (seed §2.1) and releases it now and then;
the filter state ``k_speed`` is the *residual* scale error around that learned
``k_V`` (nominal 1), so the true surge is modelled as::

    V = k_speed · k_V · f(n) + ε,   ε ~ N(0, σ_V²(f(n), w))

and the filter follows a change of water (density, temperature) through ``k_speed``
while absolute fixes (USBL, GNSS, DVL) exist, between two calibrator releases. When a
new release arrives (:meth:`adaptnav.fusion.eskf.Estimator.set_motion_params`) the product
``k_speed · k_V`` is kept continuous (k_speed is rescaled by k_V_old / k_V_new).

Measurement (z, h) — the observation is the model's prediction with the learned scale,
the state-dependent rest goes into h so H stays exact::

    z = (k_V u (1 − κ w²), k_V u_y + β u w + s₀ k_V u (1 − κ w²), 0),   u = f(rpm), u_y = s_y sign(r_y) f(|r_y|)
    h(x) = (v_b,x − (k_speed − 1) k_V u (1 − κ w²),  v_b,y − (k_speed − 1) k_V u_y,  v_b,z − h_w v_b,x)
    R = diag(σ_V²(u, w), σ_S² + u_y² σ_Vv², σ_heave²)

The third row is the flow angle, not a speed: ``h_w = heave_per_surge = tan α`` (a heavy or
trimmed vehicle flies nose-up by the angle of attack α that holds its depth, so the water
meets the body at α: ``v_b,z = tan α · v_b,x``). Written as ``v_b,z − h_w v_b,x = 0`` it
constrains the direction of the flow in the body and carries no speed; the speed is the
surge row's alone. (Written as ``v_b,z = h_w k_V u`` it restated the model's speed a second
time, without ``k_speed``: with h_w 10 % off, or 0 for a model that does not know the
vehicle pitches, it pulled the horizontal speed, and ``k_speed`` with it, through a DVL outage
— dvl_outage seed 2, static model: k_speed 0.956 → 0.896 over the 20 min, truth 0.949.)

with ``r_y`` the lateral thrust as RPM (vehicles with lateral thrusters; 0 otherwise, then
sway ≈ 0 is the non-holonomic pseudo-measurement) and ``s_y`` the lateral speed per RPM
relative to the surge table (``learned_velocity.sway_speed_scale``).

with ``w`` the yaw rate from the gyro, fused at the motion model's step rate (1 Hz by
default: its variances are per step). When the water changes, the released variances
are too tight until the calibrator catches up; the estimator then scales σ_V² up to the
innovation-based estimate ``E[y²] − H P Hᵀ`` (Mehra 1972, IEEE TAC 17(5); see
:class:`adaptnav.fusion.adaptive_noise.SurgeVariance`), never down — except for
``adaptive_suspend_after_release_s`` after a release, when the released variance is used as it
is (the calibrator has caught up). Jacobians (global attitude error)::

    ∂v_b/∂δv = R_nbᵀ,  ∂v_b/∂δθ = R_nbᵀ [v_n − c]×,  ∂v_b/∂δc = −R_nbᵀ[:, :2]
    ∂h_x/∂δk = −k_V u,   row z: ∂(v_b,z − h_w v_b,x) = ∂v_b,z − h_w ∂v_b,x
"""
from __future__ import annotations

import numpy as np

from ..motion_model import MotionParams
from ..state import ATT, CUR, KS, N_ERR, VEL, X_CUR, X_KS, X_VEL
from .common import Measurement, dcm, make, skew


def _frame(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R_nb`` (3, 3) and the water-relative velocity ``v_n − c`` (3,), m/s."""
    rel = x[X_VEL].copy()
    rel[:2] -= x[X_CUR]
    return dcm(x), rel


def water_velocity_b(x: np.ndarray) -> np.ndarray:
    """``v_b`` (3,), water-relative velocity in body axes, m/s."""
    R, rel = _frame(x)
    return R.T @ rel


def predict(x: np.ndarray, model_speed_m_s: float, model_sway_m_s: float = 0.0,
            heave_per_surge: float = 0.0) -> np.ndarray:
    """h(x) for a model speed ``k_V u``, sway ``k_V u_y`` (m/s) and flow angle ``tan α``."""
    return _predict(*_frame(x), x, model_speed_m_s, model_sway_m_s, heave_per_surge)


def jacobian(x: np.ndarray, model_speed_m_s: float, model_sway_m_s: float = 0.0,
             heave_per_surge: float = 0.0) -> np.ndarray:
    return _jacobian(*_frame(x), model_speed_m_s, model_sway_m_s, heave_per_surge)


def _predict(R: np.ndarray, rel: np.ndarray, x: np.ndarray, model_speed_m_s: float, model_sway_m_s: float,
             heave_per_surge: float) -> np.ndarray:
    v_b = R.T @ rel
    v_b[2] -= heave_per_surge * v_b[0]
    v_b[0] -= (x[X_KS] - 1.0) * model_speed_m_s
    v_b[1] -= (x[X_KS] - 1.0) * model_sway_m_s
    return v_b


def _jacobian(R: np.ndarray, rel: np.ndarray, model_speed_m_s: float, model_sway_m_s: float,
              heave_per_surge: float) -> np.ndarray:
    H = np.zeros((3, N_ERR))
    H[:, VEL] = R.T
    H[:, ATT] = R.T @ skew(rel)
    H[:, CUR] = -R.T[:, :2]
    H[2] -= heave_per_surge * H[0]
    H[0, KS] = -model_speed_m_s
    H[1, KS] = -model_sway_m_s
    return H


def measure(x: np.ndarray, speed_m_s: float, yaw_rate_rad_s: float, params: MotionParams,
            sigma_heave_m_s: float, variance_scale: float = 1.0, sway_m_s: float = 0.0,
            R_nb: np.ndarray | None = None) -> Measurement:
    """Measurement for RPM speed ``u = f(rpm)`` (m/s), lateral ``u_y`` (m/s) and gyro yaw rate (rad/s);
    ``R_nb``: ``dcm(x)`` when the caller has it."""
    # the model's surge k_V u (1 − κ w²): a turn costs speed (motion_model.MotionParams.turn_speed_loss)
    model = params.k_v * speed_m_s * (1.0 - params.turn_speed_loss * yaw_rate_rad_s**2)
    sway = params.k_v * sway_m_s
    # a turning vehicle skids, β u w, and the teaching DVL sees a crab s₀ on the straight
    # (MotionParams.sway_per_turn, sway_per_surge); not scaled by k_speed
    skid = params.sway_per_turn * speed_m_s * yaw_rate_rad_s + params.sway_per_surge * model
    # σ_V²(v, w) of the motion model (velocity_variances), inlined: this runs at the fusion rate
    var_V = speed_m_s**2 * params.var_vv + yaw_rate_rad_s**2 * params.var_vw + params.var_v1
    R = np.zeros((3, 3))
    R[0, 0] = var_V * variance_scale
    R[1, 1] = (params.var_s + sway_m_s**2 * params.var_vv) * variance_scale
    R[2, 2] = sigma_heave_m_s**2 * variance_scale
    h_w = params.heave_per_surge
    # the rotation and the water-relative velocity once for h and H (once a second on the
    # way to the nav state: each small NumPy step there costs ~1 µs, several cold)
    if R_nb is None:
        R_nb, rel = _frame(x)
    else:
        rel = x[X_VEL].copy()
        rel[:2] -= x[X_CUR]
    return make([model, sway + skid, 0.0], _jacobian(R_nb, rel, model, sway, h_w), R,
                _predict(R_nb, rel, x, model, sway, h_w))


def kernel_params(params: MotionParams, config) -> np.ndarray:
    """The (``kalman.LV_N_PARAMS``,) numbers the compiled epoch reads
    (:func:`adaptnav.fusion.kalman.lv_epoch`, indices ``kalman.LV_*``): the motion model's, the
    learned velocity's (:class:`~adaptnav.fusion.config.LearnedVelocityConfig`: the estimator's
    additions and the surge variance's adaptation, as
    :class:`~adaptnav.fusion.adaptive_noise.SurgeVariance` takes them) and 2.0 — the exponent of
    Python's ``x ** 2``, read at run time: a constant one is compiled into ``x * x``, which
    differs from libm's ``pow`` (Python's) in the last bit of ~1 square in 1000."""
    adaptive = config.adaptive_window_s > 0
    alpha = min(1.0, (1.0 / config.rate_hz) / config.adaptive_window_s) if adaptive else 0.0
    return np.array([params.k_v, params.turn_speed_loss, params.sway_per_turn, params.sway_per_surge,
                     params.var_vv, params.var_vw, params.var_v1, params.var_s, params.heave_per_surge,
                     config.sigma_heave_m_s, config.variance_scale, config.transient_time_s,
                     config.coast_mean_fraction, config.coast_sigma_per_gap, config.transient_sigma_per_gap,
                     config.skid_sigma_s, config.coast_skid_max_fraction, config.skid_max_fraction,
                     config.heave_sigma_per_vertical_speed, 1.0 if adaptive else 0.0, alpha,
                     config.adaptive_max_scale, config.adaptive_suspend_after_release_s, 2.0], dtype=float)
