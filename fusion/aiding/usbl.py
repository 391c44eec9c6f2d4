r"""USBL acoustic position fix: ``z = NED(lat, lon)[:2]`` (+ depth when ``sigma_v_m`` is finite).

``h(x) = p_n[:2]`` (or ``p_n``); geodetic → local through the mission :class:`GeoOrigin`.
"""
from __future__ import annotations

import math

import numpy as np

from ..frames import GeoOrigin
from ..state import N_ERR, X_POS
from ..config import UsblConfig
from .common import AidContext, AidSource, Measurement, make


def predict(x, with_depth: bool) -> np.ndarray:
    return x[X_POS][: 3 if with_depth else 2].copy()


def jacobian(x, with_depth: bool) -> np.ndarray:
    m = 3 if with_depth else 2
    H = np.zeros((m, N_ERR))
    for i in range(m):
        H[i, i] = 1.0
    return H


def measure(sample, x, origin: GeoOrigin) -> Measurement:
    with_depth = math.isfinite(sample.sigma_v_m)
    ned = origin.to_ned(sample.lat_rad, sample.lon_rad)
    if with_depth:
        z = [ned[0], ned[1], sample.depth_m]
        R = np.diag([sample.sigma_h_m**2, sample.sigma_h_m**2, sample.sigma_v_m**2])
    else:
        z, R = ned[:2], np.eye(2) * sample.sigma_h_m**2
    return make(z, jacobian(x, with_depth), R, predict(x, with_depth))


def _measure(sample, ctx: AidContext) -> Measurement:
    return measure(sample, ctx.x, ctx.origin)


AID = AidSource("usbl", UsblConfig, _measure, absolute_position=True, without_imu=True)
