r"""Depth from absolute pressure (hydrostatic): ``d = (p − p_atm) / (ρ g)``; ``h(x) = p_d``.

Water density ρ (kg/m³) and atmospheric pressure (Pa) come from the config (sea water
≈ 1025, fresh ≈ 1000; UNESCO 1983 gives the full equation of state, unnecessary at
AUV depths for a 0.05 m sensor).
"""
from __future__ import annotations

import numpy as np

from ..frames import GRAVITY_M_S2
from ..state import N_ERR, X_POS
from ..config import DepthConfig
from .common import _NOT_ANGULAR, AidContext, AidSource, Measurement


def pressure_to_depth(pressure_pa, water_density_kg_m3: float, atmospheric_pressure_pa: float):
    """Depth (m, positive down) of an absolute pressure (Pa)."""
    return (np.asarray(pressure_pa, dtype=float) - atmospheric_pressure_pa) / (
        water_density_kg_m3 * GRAVITY_M_S2)


def predict(x) -> np.ndarray:
    return np.array([x[X_POS][2]])


def jacobian(x) -> np.ndarray:
    H = np.zeros((1, N_ERR))
    H[0, 2] = 1.0
    return H


def measure(sample, x, sigma_m, water_density_kg_m3, atmospheric_pressure_pa) -> Measurement:
    # pressure_to_depth(), jacobian() and predict() written out: the same operations on the
    # same floats without make()'s conversions (a depth every 0.1 s)
    depth = (float(sample.pressure_pa) - atmospheric_pressure_pa) / (water_density_kg_m3 * GRAVITY_M_S2)
    H = np.zeros((1, N_ERR))
    H[0, 2] = 1.0
    return Measurement(np.array([depth]), H, np.array([[sigma_m**2]], dtype=float), np.array([float(x[X_POS.start + 2])]),
                       _NOT_ANGULAR[1])


def _measure(sample, ctx: AidContext) -> Measurement:
    c = ctx.config
    return measure(sample, ctx.x, c.sigma_m, c.water_density_kg_m3, c.atmospheric_pressure_pa)


AID = AidSource("depth", DepthConfig, _measure, without_imu=True)
