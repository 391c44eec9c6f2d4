r"""Side-scan visual motion (along/across-track displacement between two sonar windows).

Approximation (no state cloning): the displacement over ``Δt = t − t₀`` divided by Δt
is taken as the ground-referenced body velocity at ``t``::

    z = (along, across) / Δt,   h(x) = (R_nbᵀ v_n)[:2],   R = cov[:2, :2] / Δt²

The yaw change is not fused (the heading aid and gyro are far better). Valid while the
velocity is near constant over the window (a survey leg); a proper two-epoch
(stochastic-cloning) measurement is future work.
"""
from __future__ import annotations

import numpy as np

from ..state import ATT, N_ERR, VEL, X_VEL
from ..config import VisualMotionConfig
from .common import AidContext, AidSource, Measurement, dcm, make, skew


def predict(x) -> np.ndarray:
    return (dcm(x).T @ x[X_VEL])[:2]


def jacobian(x) -> np.ndarray:
    R = dcm(x)
    H = np.zeros((2, N_ERR))
    H[:, VEL] = R.T[:2]
    H[:, ATT] = (R.T @ skew(x[X_VEL]))[:2]
    return H


def measure(sample, x) -> Measurement | None:
    dt = sample.t_s - sample.t0_s
    if not dt > 0:
        return None
    cov = np.asarray(sample.cov, dtype=float).reshape(3, 3)[:2, :2] / dt**2
    if not np.all(np.linalg.eigvalsh(cov) > 0):
        return None
    return make([sample.along_m / dt, sample.across_m / dt], jacobian(x), cov, predict(x))


def _measure(sample, ctx: AidContext) -> Measurement | None:
    return measure(sample, ctx.x)


AID = AidSource("visual_motion", VisualMotionConfig, _measure)
