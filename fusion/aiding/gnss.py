r"""Surface GNSS position: ``z = NED(lat, lon)[:2]`` via the mission origin, ``h(x) = p_n[:2]``.

Only at the surface: the estimator fuses it when the estimated depth is below
``gnss.max_depth_m`` (a submerged antenna reports nothing true).
"""
from __future__ import annotations

import numpy as np

from ..frames import GeoOrigin
from ..state import N_ERR, X_POS
from ..config import GnssConfig
from .common import AidContext, AidSource, Measurement, make


def at_surface(x, max_depth_m: float) -> bool:
    return bool(x[X_POS][2] < max_depth_m)


def predict(x) -> np.ndarray:
    return x[X_POS][:2].copy()


def jacobian(x) -> np.ndarray:
    H = np.zeros((2, N_ERR))
    H[0, 0] = H[1, 1] = 1.0
    return H


def measure(sample, x, origin: GeoOrigin) -> Measurement:
    ned = origin.to_ned(sample.lat_rad, sample.lon_rad)
    return make(ned[:2], jacobian(x), np.eye(2) * sample.sigma_h_m**2, predict(x))


def _measure(sample, ctx: AidContext) -> Measurement | None:
    if not at_surface(ctx.x, ctx.config.max_depth_m):
        return None
    return measure(sample, ctx.x, ctx.origin)


AID = AidSource("gnss", GnssConfig, _measure, none_reason="surface_only", absolute_position=True,
                without_imu=True)
