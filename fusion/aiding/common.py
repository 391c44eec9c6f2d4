"""What every aiding source returns, and small helpers they share.

Each source module provides ``predict(x, ...) -> h`` (the measurement model on the
nominal state, :mod:`adaptnav.fusion.state` layout) and ``measure(sample, x, ...) ->
Measurement | None`` giving ``(z, H, R)`` plus ``h`` so the estimator can form the
innovation ``y = z ⊖ h`` (angles wrapped). ``H`` is the Jacobian of ``h`` with respect
to the 18-dim error state (attitude error global, see :mod:`adaptnav.fusion.state`); the
contract test checks it against finite differences through :func:`adaptnav.fusion.state.inject`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..frames import wrap_angle
from ..state import N_ERR


class Measurement(NamedTuple):
    """``z`` (m,), ``H`` (m, 18), ``R`` (m, m), ``h`` (m,) = h(x̂), ``angular`` (m,) bool."""

    z: np.ndarray
    H: np.ndarray
    R: np.ndarray
    h: np.ndarray
    angular: np.ndarray

    def innovation(self) -> np.ndarray:
        y = self.z - self.h
        ang = self.angular
        if ang is not _NOT_ANGULAR.get(ang.size) and ang.any():  # make()'s shared all-False masks
            y = np.where(self.angular, wrap_angle(y), y)
        return y


_NOT_ANGULAR = {m: np.zeros(m, bool) for m in (1, 2, 3)}
for _a in _NOT_ANGULAR.values():
    _a.setflags(write=False)  # shared by every Measurement without angular components


def make(z, H, R, h, angular=None) -> Measurement:
    z = np.asarray(z, dtype=float).reshape(-1)
    m = z.size
    angular = _NOT_ANGULAR[m] if angular is None else np.asarray(angular, bool)
    return Measurement(z, np.asarray(H, dtype=float).reshape(m, N_ERR),
                       np.asarray(R, dtype=float).reshape(m, m),
                       np.asarray(h, dtype=float).reshape(-1), angular)


def dcm(x: np.ndarray) -> np.ndarray:
    """``R_nb`` of the nominal state (plain Python: cheaper than a jitted call here)."""
    w, a, b, c = x[6:10].tolist()
    return np.array([
        [1 - 2 * (b * b + c * c), 2 * (a * b - w * c), 2 * (a * c + w * b)],
        [2 * (a * b + w * c), 1 - 2 * (a * a + c * c), 2 * (b * c - w * a)],
        [2 * (a * c - w * b), 2 * (b * c + w * a), 1 - 2 * (a * a + b * b)],
    ])


def skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def euler_jacobian(R_nb: np.ndarray) -> np.ndarray:
    """∂(roll, pitch, yaw)/∂δθ for a global attitude error δθ (3×3).

    For ZYX angles ``δθ = M d(φ, θ, ψ)`` with columns ``R_z R_y e₁``, ``R_z e₂``, ``e₃``;
    the Jacobian is ``M⁻¹ = [[cψ/cθ, sψ/cθ, 0], [−sψ, cψ, 0], [cψ tθ, sψ tθ, 1]]``
    (singular at θ = ±90°, where Euler angles are).
    """
    pitch = -np.arcsin(np.clip(R_nb[2, 0], -1.0, 1.0))
    yaw = np.arctan2(R_nb[1, 0], R_nb[0, 0])
    cy, sy, cp, tp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.tan(pitch)
    return np.array([[cy / cp, sy / cp, 0.0], [-sy, cy, 0.0], [cy * tp, sy * tp, 1.0]])


def euler_of(R_nb: np.ndarray) -> np.ndarray:
    pitch = -np.arcsin(np.clip(R_nb[2, 0], -1.0, 1.0))
    roll = np.arctan2(R_nb[2, 1], R_nb[2, 2])
    yaw = np.arctan2(R_nb[1, 0], R_nb[0, 0])
    return np.array([roll, pitch, yaw])
