r"""Heading (compass/AHRS yaw): ``h(x) = ψ = atan2(R₁₀, R₀₀)``, innovation wrapped to [−π, π).

``∂ψ/∂δθ`` is the last row of the Euler Jacobian (:func:`adaptnav.fusion.aiding.common.euler_jacobian`):
``(−R₀₀R₂₀, −R₁₀R₂₀, R₀₀² + R₁₀²) / (R₀₀² + R₁₀²)``.
"""
from __future__ import annotations

import numpy as np

from .. import kalman
from ..state import ATT, N_ERR, X_Q
from ..config import HeadingConfig
from .common import AidContext, AidSource, Measurement, dcm, euler_jacobian

_ANGULAR = np.ones(1, bool)
_ANGULAR.setflags(write=False)


def predict(x) -> np.ndarray:
    """``[ψ]``: the yaw of :func:`~.common.euler_of` (``arctan2(R₁₀, R₀₀)`` of :func:`~.common.dcm`'s
    elements, the same floats and the same numpy function) without building ``R_nb`` and the
    roll and pitch nobody reads here (7 → 1 µs; the free-inertial velocity asks every data
    second)."""
    w, a, b, c = x[X_Q].tolist()
    return np.array([np.arctan2(2 * (a * b + w * c), 1 - 2 * (b * b + c * c))])


def jacobian(x) -> np.ndarray:
    H = np.zeros((1, N_ERR))
    H[0, ATT] = euler_jacobian(dcm(x))[2]
    return H


def yaw_row(x) -> tuple:
    """``(ψ, ∂ψ/∂δθ_x, ∂ψ/∂δθ_y)``: :func:`predict` and the attitude part of :func:`jacobian`
    (``∂ψ/∂δθ_z`` = 1) from one attitude (R₀₀, R₁₀, R₂₀ as in common.dcm; yaw, pitch as in
    common.euler_of / euler_jacobian) without building R twice and the full Euler Jacobian
    (a heading every 0.1 s): :func:`adaptnav.fusion.kalman.heading_row`, which the compiled
    heading update computes too — libm's trigonometry: numpy's on a Python float cost ~1 µs a
    call (5 µs of a heading's 25 µs), and its atan2/asin/tan differ from libm's in the last
    bit only (for ~8 % of inputs); both estimator paths measure with this."""
    return kalman.heading_row(x)


def measure(sample, x, sigma_rad) -> Measurement:
    yaw, h_x, h_y = yaw_row(x)
    H = np.zeros((1, N_ERR))
    H[0, ATT] = (h_x, h_y, 1.0)
    return Measurement(np.array([float(sample.yaw_rad)]), H, np.array([[sigma_rad**2]], dtype=float),
                       np.array([yaw]), _ANGULAR)


def _measure(sample, ctx: AidContext) -> Measurement:
    return measure(sample, ctx.x, ctx.config.sigma_rad)


AID = AidSource("heading", HeadingConfig, _measure, without_imu=True)
