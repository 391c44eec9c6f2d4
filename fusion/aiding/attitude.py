r"""External AHRS attitude (ArduSub ATTITUDE): ``h(x) = (φ, θ, ψ)`` ZYX, angles wrapped.

Used when logs carry ATTITUDE but no usable IMU rate (real ArduSub telemetry: IMU at
2 Hz, ATTITUDE at 20 Hz). ``H_att = M⁻¹`` (:func:`adaptnav.fusion.aiding.common.euler_jacobian`).
"""
from __future__ import annotations

import numpy as np

from ..state import ATT, N_ERR
from ..config import AttitudeConfig
from .common import AidContext, AidSource, Measurement, dcm, euler_jacobian, euler_of, make


def predict(x) -> np.ndarray:
    return euler_of(dcm(x))


def jacobian(x) -> np.ndarray:
    H = np.zeros((3, N_ERR))
    H[:, ATT] = euler_jacobian(dcm(x))
    return H


def measure(sample, x, sigma_roll_pitch_rad, sigma_yaw_rad) -> Measurement:
    R = np.diag([sigma_roll_pitch_rad**2, sigma_roll_pitch_rad**2, sigma_yaw_rad**2])
    return make([sample.roll_rad, sample.pitch_rad, sample.yaw_rad], jacobian(x), R, predict(x),
                [True, True, True])


def _measure(sample, ctx: AidContext) -> Measurement:
    return measure(sample, ctx.x, ctx.config.sigma_roll_pitch_rad, ctx.config.sigma_yaw_rad)


AID = AidSource("attitude", AttitudeConfig, _measure, without_imu=True)
