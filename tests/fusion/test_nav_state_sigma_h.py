"""Estimator._add_considered returns the horizontal σ of the covariance it leaves (nav_state's
validity test): _sigma_h_m of the result, taken of the DVL terms' sums at hand — on random,
NaN, inf, negative and zero entries, with and without the calibration, heading frame and
density terms."""
from __future__ import annotations

import math
import types

import numpy as np

from adaptnav.fusion.eskf import Estimator, _sigma_h_m
from adaptnav.fusion.state import N_ERR, X_Q

_SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -0.0, -1e-300, 1e308)


class _Calibration:
    def __init__(self, values):
        self.values = values

    def position_cov_ne_values(self):
        return self.values


def _estimator(rng, cal_values, yaw_sigma_rad: float, density_sigma: float):
    x = rng.normal(size=19)  # (the nominal state)
    x[X_Q] = x[X_Q] / np.linalg.norm(x[X_Q])
    return types.SimpleNamespace(
        dvl_calibration=None if cal_values is None else _Calibration(cal_values),
        _reference_yaw_sigma_rad=yaw_sigma_rad, _yaw_frame=yaw_sigma_rad > 0.0,
        _anchor_ne=rng.normal(size=2) * 100.0, _x=x, _density_sigma_kg_m3=(density_sigma, 1025.0))


def _pick(rng, special: bool) -> float:
    return float(rng.choice(_SPECIAL)) if special else float(rng.normal() * 10.0 ** rng.integers(-6, 6))


def test_returned_sigma_is_that_of_the_covariance_left():
    rng = np.random.default_rng(55)
    for k in range(3000):
        special = k % 3 == 0
        cov = rng.normal(size=(N_ERR, N_ERR))
        for ij in ((0, 0), (0, 1), (1, 0), (1, 1)):
            cov[ij] = _pick(rng, special and rng.random() < 0.5)
        cal = None if k % 7 == 0 else tuple(_pick(rng, special and rng.random() < 0.3) for _ in range(4))
        est = _estimator(rng, cal, 0.02 if k % 11 == 0 else 0.0, 5.0 if k % 2 else 0.0)
        sigma = Estimator._add_considered(est, cov)
        expected = _sigma_h_m(cov)
        assert type(sigma) is float
        assert sigma == expected or (math.isnan(sigma) and math.isnan(expected)), (k, sigma, expected)


def test_returned_sigma_on_an_empty_calibration_is_the_block_s():
    cov = np.eye(N_ERR) * 4.0
    cov[1, 1] = 9.0
    est = _estimator(np.random.default_rng(1), (0.0, 0.0, 0.0, 0.0), 0.0, 0.0)
    assert Estimator._add_considered(est, cov) == 3.0
