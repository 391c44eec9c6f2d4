"""What every aiding source declares and returns, and small helpers they share.

Each source module of a *sample kind* declares ``AID = AidSource(kind, config_type,
measure, ...)`` (:class:`AidSource`): the estimator finds it by its kind
(:data:`adaptnav.fusion.aiding.AIDS`) and calls ``AID.measure(sample, ctx) -> Measurement |
None`` with an :class:`AidContext`; it does the gating, update and status once for all.
The math underneath: each source module provides ``predict(x, ...) -> h`` (the measurement model on the
nominal state, :mod:`adaptnav.fusion.state` layout) and ``measure(sample, x, ...) ->
Measurement | None`` giving ``(z, H, R)`` plus ``h`` so the estimator can form the
innovation ``y = z ⊖ h`` (angles wrapped). ``H`` is the Jacobian of ``h`` with respect
to the 18-dim error state (attitude error global, see :mod:`adaptnav.fusion.state`); the
contract test checks it against finite differences through :func:`adaptnav.fusion.state.inject`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from ..frames import wrap_angle
from ..state import N_ERR, X_Q


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
        if ang is NOT_ANGULAR.get(ang.size):  # make()'s shared all-False masks
            return y
        if ang is ALL_ANGULAR.get(ang.size):  # angles only: np.where would take every wrapped one
            return wrap_angle(y)
        if ang.size == 1:  # a heading: np.where and any() cost more than the wrap
            return wrap_angle(y) if ang[0] else y
        if ang.any():
            y = np.where(ang, wrap_angle(y), y)
        return y


class AidContext(NamedTuple):
    """What an aid source's ``measure`` may read besides its sample.

    ``x`` the nominal state (:mod:`adaptnav.fusion.state` layout); ``omega_b_rad_s`` (3,)
    the latest bias-corrected body angular rate (rad/s); ``origin`` the mission
    :class:`~adaptnav.fusion.frames.GeoOrigin`; ``config`` the aid's own section of
    :class:`~adaptnav.fusion.config.FilterConfig` (field named like the kind);
    ``setup`` what :attr:`AidSource.setup` computed once from that section (or None).
    """

    x: np.ndarray
    omega_b_rad_s: np.ndarray
    origin: Any
    config: Any
    setup: Any


@dataclass(frozen=True)
class AidSource:
    """The declaration an aid module makes (``AID = AidSource(...)``).

    Attributes
    ----------
    kind : str
        The sample kind it fuses (a row of :data:`adaptnav.fusion.samples.SENSORS` with
        role ``"aid"``); also the name of its :class:`FilterConfig` section and of its
        :class:`~adaptnav.fusion.status.AidStatus` source.
    config_type : type
        Its config section's dataclass (with an ``enabled`` flag).
    measure : callable
        ``measure(sample, ctx: AidContext) -> Measurement | None``; ``None`` is rejected
        with :attr:`none_reason` (an aid with several reasons may return the reason, a
        ``str``, instead).
    none_reason : str
        Why a ``None`` was not fused (``"invalid"``: the sample says it is not valid).
    absolute_position : bool
        A position fix: initialises the position before alignment and is trusted again
        after ``position_reset_after_rejections`` gate rejections in a row.
    without_imu : bool
        Fused in AHRS mode too (needs no dead-reckoned velocity).
    setup : callable or None
        ``setup(config_section) -> Any``, computed once per estimator (e.g. a mounting
        rotation), handed back as ``ctx.setup``.
    """

    kind: str
    config_type: type
    measure: Callable[[Any, AidContext], "Measurement | str | None"]
    none_reason: str = "invalid"
    absolute_position: bool = False
    without_imu: bool = False
    setup: Callable[[Any], Any] | None = None


# the all-False ``angular`` masks of 1–3 components, shared (read-only) by every Measurement
# without angular components: an aid building its Measurement directly passes these; and the
# all-True ones, for a measurement of angles only (the attitude's three)
NOT_ANGULAR = {m: np.zeros(m, bool) for m in (1, 2, 3)}
ALL_ANGULAR = {m: np.ones(m, bool) for m in (1, 2, 3)}
for _a in (*NOT_ANGULAR.values(), *ALL_ANGULAR.values()):
    _a.setflags(write=False)


def make(z, H, R, h, angular=None) -> Measurement:
    z = np.asarray(z, dtype=float).reshape(-1)
    m = z.size
    angular = NOT_ANGULAR[m] if angular is None else np.asarray(angular, bool)
    return Measurement(z, np.asarray(H, dtype=float).reshape(m, N_ERR),
                       np.asarray(R, dtype=float).reshape(m, m),
                       np.asarray(h, dtype=float).reshape(-1), angular)


def dcm(x: np.ndarray) -> np.ndarray:
    """``R_nb`` of the nominal state (plain Python: cheaper than a jitted call here)."""
    w, a, b, c = x[X_Q].tolist()
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
