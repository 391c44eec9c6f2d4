"""Nominal and error state layout of the ESKF, and the published :class:`NavState`.

Nominal state vector ``x`` (19 floats, a plain array so the numba kernels can use it)::

    pos_n (3, m) | vel_n (3, m/s) | q_nb (4, w x y z) | bias_acc_b (3, m/s²)
    | bias_gyro_b (3, rad/s) | current_n (2, north/east m/s) | k_speed (1, –)

Error state ``δx`` (18): ``δp, δv, δθ, δb_a, δb_g, δc, δk`` where the attitude error
``δθ`` is a rotation vector in the navigation frame (global/left perturbation,
``q_true = q(δθ) ⊗ q_nom``; Solà 2017, "Quaternion kinematics for the error-state
Kalman filter", §7). Injection: :func:`inject`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .frames import quat_mul, quat_from_rotvec, quat_to_euler

# error-state slices (never bare ints)
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
BA = slice(9, 12)
BG = slice(12, 15)
CUR = slice(15, 17)
KS = slice(17, 18)
N_ERR = 18
# parts of blocks: horizontal position and depth; tilt (rotation about north and east) and
# heading (about down) of the navigation-frame attitude error
POS_NE = slice(0, 2)
POS_D = 2
ATT_TILT = slice(6, 8)
ATT_YAW = 8

# nominal-state slices
X_POS = slice(0, 3)
X_VEL = slice(3, 6)
X_Q = slice(6, 10)
X_BA = slice(10, 13)
X_BG = slice(13, 16)
X_CUR = slice(16, 18)
X_KS = 18
N_NOM = 19
# the slow states (biases, current, k_speed): what persistence keeps and a re-alignment
# after a restore carries over, nominal and error-state blocks
X_SLOW = slice(10, 19)
SLOW = slice(9, 18)
X_DEPTH = 2  # the down component of X_POS
X_POS_NE = slice(0, 2)  # north, east of X_POS

# the step accumulator ``acc`` of the propagation kernels (adaptnav.fusion.strapdown,
# adaptnav.fusion.kalman): what one covariance step sums, the latest bias-corrected IMU
# sample, and the earth model (kept across steps, adaptnav.fusion.strapdown.set_earth)
ACC_RF = slice(0, 3)          # Σ R_nb f̂ δt over the step (m/s)
ACC_R = slice(3, 12)          # Σ R_nb δt over the step, row-major (s)
ACC_T = 12                    # Σ δt: the step's length (s)
ACC_STEP = slice(0, 13)       # the sums above: what a covariance flush clears
ACC_OMEGA = slice(13, 16)     # latest bias-corrected ω̂_b (rad/s)
ACC_F = slice(16, 19)         # latest bias-corrected f̂_b (m/s²)
ACC_EARTH = slice(19, 24)     # the earth model (zeros: flat, non-rotating)
ACC_EARTH_RATE = slice(19, 22)  # ω_ie in local axes (rad/s)
ACC_DGAMMA = 22               # normal gravity γ(L) − 9.80665 (m/s²)
ACC_G_OVER_R = 23             # γ/R, the gravity gradient (1/s²)
ACC_SIZE = 24

NAV_STATE_SCHEMA_VERSION = 1


def initial_nominal(pos_n_m=(0.0, 0.0, 0.0), vel_n_m_s=(0.0, 0.0, 0.0), q_nb=(1.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """Nominal vector with zero biases and current and ``k_speed = 1``."""
    x = np.zeros(N_NOM)
    x[X_POS] = pos_n_m
    x[X_VEL] = vel_n_m_s
    x[X_Q] = q_nb
    x[X_KS] = 1.0
    return x


def inject(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Nominal ⊕ error: returns a new nominal vector (the reference, not the hot path)."""
    out = x.copy()
    out[X_POS] += dx[POS]
    out[X_VEL] += dx[VEL]
    q = quat_mul(quat_from_rotvec(dx[ATT]), x[X_Q])
    out[X_Q] = q / np.linalg.norm(q)
    out[X_BA] += dx[BA]
    out[X_BG] += dx[BG]
    out[X_CUR] += dx[CUR]
    out[X_KS] += dx[KS][0]
    return out


@dataclass(frozen=True, init=False)
class NavState:
    """The estimator's published state at ``t_s``.

    ``cov`` is the 18×18 error-state covariance in the order of the slices above
    (attitude error in the navigation frame, rad). ``valid`` is False while the filter
    is not initialised, runs without IMU (AHRS mode) or its horizontal σ is too large
    to be used for navigation; ``invalid_reasons`` says why (empty when valid; the names of
    :meth:`adaptnav.fusion.eskf.Estimator.invalid_reasons`). ``reset_counter`` increments
    on every discontinuity (alignment, IMU gap), for MAVLink ODOMETRY.
    """

    t_s: float
    pos_n_m: np.ndarray
    vel_n_m_s: np.ndarray
    q_nb: np.ndarray
    bias_acc_b_m_s2: np.ndarray
    bias_gyro_b_rad_s: np.ndarray
    current_n_m_s: np.ndarray
    k_speed: float
    cov: np.ndarray
    valid: bool
    reset_counter: int
    invalid_reasons: tuple[str, ...] = ()

    def __init__(self, t_s: float, pos_n_m: np.ndarray, vel_n_m_s: np.ndarray, q_nb: np.ndarray,
                 bias_acc_b_m_s2: np.ndarray, bias_gyro_b_rad_s: np.ndarray, current_n_m_s: np.ndarray,
                 k_speed: float, cov: np.ndarray, valid: bool, reset_counter: int,
                 invalid_reasons: tuple[str, ...] = ()) -> None:
        # the fields in one call (a frozen dataclass's own __init__ sets them one by one
        # through object.__setattr__: 2.5 µs of every output epoch's state)
        object.__setattr__(self, "__dict__", {
            "t_s": t_s, "pos_n_m": pos_n_m, "vel_n_m_s": vel_n_m_s, "q_nb": q_nb,
            "bias_acc_b_m_s2": bias_acc_b_m_s2, "bias_gyro_b_rad_s": bias_gyro_b_rad_s,
            "current_n_m_s": current_n_m_s, "k_speed": k_speed, "cov": cov, "valid": valid,
            "reset_counter": reset_counter, "invalid_reasons": invalid_reasons})

    def euler_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) in rad, ZYX convention."""
        return quat_to_euler(self.q_nb)

    def sigma(self, sl: slice) -> np.ndarray:
        """1-σ of an error-state block, e.g. ``state.sigma(POS)``."""
        return np.sqrt(np.clip(np.diag(self.cov)[sl], 0.0, None))

    def fields(self) -> dict:
        """The fields of :meth:`to_dict`, each vector a flat float64 array (non-finite values
        kept): for an encoder that writes arrays itself (the daemon's orjson writes them
        as :meth:`to_dict`'s lists, NaN as null, without a Python float per element)."""
        roll, pitch, yaw = self.euler_rad()
        return {
            "type": "nav_state",
            "schema_version": NAV_STATE_SCHEMA_VERSION,
            "t_s": float(self.t_s),
            "pos_n_m": _flat(self.pos_n_m),
            "vel_n_m_s": _flat(self.vel_n_m_s),
            "q_nb": _flat(self.q_nb),
            "euler_rad": np.array((roll, pitch, yaw), dtype=float),
            "bias_acc_b_m_s2": _flat(self.bias_acc_b_m_s2),
            "bias_gyro_b_rad_s": _flat(self.bias_gyro_b_rad_s),
            "current_n_m_s": _flat(self.current_n_m_s),
            "k_speed": float(self.k_speed),
            "cov": _flat(self.cov),
            "valid": bool(self.valid),
            "reset_counter": int(self.reset_counter),
            "invalid_reasons": list(self.invalid_reasons),
        }

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats as None), with ``schema_version``."""
        return {k: _listed(v) if type(v) is np.ndarray else v for k, v in self.fields().items()}


def _flat(a) -> np.ndarray:
    """A vector or matrix as a flat float64 array (a view where it can be)."""
    return np.asarray(a, dtype=float).ravel()


def _listed(a: np.ndarray) -> list:
    """A flat array as a list of floats, non-finite ones as None."""
    if np.isfinite(a).all():  # the usual case: tolist() makes the floats at C speed
        return a.tolist()
    return [v if math.isfinite(v) else None for v in a.tolist()]
