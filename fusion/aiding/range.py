r"""Acoustic range to a beacon at a known local NED position (LBL / one-way travel time).

::

    z = range_m,   h(x) = ‖p_n − b_n‖,   H[δp] = (p_n − b_n)ᵀ / ‖p_n − b_n‖,   R = σ²

σ is the sample's ``sigma_m`` times ``range.sigma_scale``. A range is a sphere, not a fix:
it constrains position along the line of sight only (Kinsey, Eustice & Whitcomb, IFAC
MCMC 2006, §3.2 on LBL navigation); the thesis simulation's landmark sensor is the same
model. At the beacon itself the direction is undefined: a predicted range below
``range.min_range_m`` is not fused (``too_close``).
"""
from __future__ import annotations

import numpy as np

from ..config import RangeConfig
from ..state import N_ERR, POS, X_POS
from .common import AidContext, AidSource, Measurement, make


def predict(x, beacon_pos_n_m) -> np.ndarray:
    return np.array([np.linalg.norm(x[X_POS] - np.asarray(beacon_pos_n_m, dtype=float))])


def jacobian(x, beacon_pos_n_m) -> np.ndarray:
    d = x[X_POS] - np.asarray(beacon_pos_n_m, dtype=float)
    H = np.zeros((1, N_ERR))
    H[0, POS] = d / np.linalg.norm(d)
    return H


def measure(sample, x, sigma_scale: float = 1.0, min_range_m: float = 0.0) -> Measurement | None:
    """``None`` closer than ``min_range_m`` to the beacon (the line of sight is undefined)."""
    h = predict(x, sample.beacon_pos_n_m)
    if not h[0] > min_range_m:
        return None
    return make([sample.range_m], jacobian(x, sample.beacon_pos_n_m), [[(sample.sigma_m * sigma_scale) ** 2]], h)


def _measure(sample, ctx: AidContext) -> Measurement | None:
    return measure(sample, ctx.x, ctx.config.sigma_scale, ctx.config.min_range_m)


AID = AidSource("range", RangeConfig, _measure, none_reason="too_close")
