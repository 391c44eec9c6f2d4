r"""Heading (compass/AHRS yaw): ``h(x) = ψ = atan2(R₁₀, R₀₀)``, innovation wrapped to [−π, π).

``∂ψ/∂δθ`` is the last row of the Euler Jacobian (:func:`fusion.aiding.common.euler_jacobian`):
``(−R₀₀R₂₀, −R₁₀R₂₀, R₀₀² + R₁₀²) / (R₀₀² + R₁₀²)``.
"""
from __future__ import annotations

import numpy as np

from ..state import ATT, N_ERR
from .common import Measurement, dcm, euler_jacobian, euler_of, make


def predict(x) -> np.ndarray:
    return euler_of(dcm(x))[2:3]


def jacobian(x) -> np.ndarray:
    H = np.zeros((1, N_ERR))
    H[0, ATT] = euler_jacobian(dcm(x))[2]
    return H


def measure(sample, x, sigma_rad) -> Measurement:
    return make([sample.yaw_rad], jacobian(x), [[sigma_rad**2]], predict(x), [True])
