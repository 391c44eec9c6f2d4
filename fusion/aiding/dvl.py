r"""DVL bottom-track velocity in the DVL head frame (lever arm, mounting rotation).

::

    h(x) = R_db (R_nbᵀ v_n + ω̂_b × l_b),   R_db = R_bdᵀ, R_bd from ``rotation_bd_rpy_rad``

(Groves 2013 §16.3.4 / Brokloff 1994). With ``ω̂ = ω_m − b_g``: ∂(ω̂ × l)/∂δb_g = [l]×.
Jacobians: ``R_db R_nbᵀ`` (δv), ``R_db R_nbᵀ [v_n]×`` (δθ), ``R_db [l]×`` (δb_g).
"""
from __future__ import annotations

import numpy as np

from ..frames import euler_to_quat, quat_to_dcm
from ..state import ATT, BG, N_ERR, VEL, X_VEL
from .common import Measurement, dcm, make, skew


def rotation_db(rotation_bd_rpy_rad) -> np.ndarray:
    """``R_db`` (3×3) from the mounting roll/pitch/yaw of the DVL head in the body."""
    return quat_to_dcm(euler_to_quat(*rotation_bd_rpy_rad)).T


def predict(x, omega_b_rad_s, lever_arm_b_m, R_db) -> np.ndarray:
    v_b = dcm(x).T @ x[X_VEL] + np.cross(omega_b_rad_s, lever_arm_b_m)
    return R_db @ v_b


def jacobian(x, lever_arm_b_m, R_db) -> np.ndarray:
    R = dcm(x)
    H = np.zeros((3, N_ERR))
    H[:, VEL] = R_db @ R.T
    H[:, ATT] = R_db @ R.T @ skew(x[X_VEL])
    H[:, BG] = R_db @ skew(lever_arm_b_m)
    return H


def measure(sample, x, omega_b_rad_s, lever_arm_b_m, R_db, sigma_m_s) -> Measurement | None:
    """``None`` when the DVL reports no bottom lock."""
    if not sample.valid:
        return None
    lever = np.asarray(lever_arm_b_m, dtype=float)
    return make(sample.vel_d_m_s, jacobian(x, lever, R_db), np.eye(3) * sigma_m_s**2,
                predict(x, omega_b_rad_s, lever, R_db))
