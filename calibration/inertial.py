r"""Surge-noise evidence from the IMU: velocity increments between consecutive model steps.

Why. With position fixes alone the surge noise σ_Vv is barely observable: USBL fixes of σ 2 m
one a minute see 60 s of white surge noise only as a few m² added to an 8 m² fix-difference
variance (:mod:`adaptnav.calibration.online`). The IMU, on the other hand, measures velocity *changes*
to mm/s over a second. The navigation filter hands the calibrator its free-inertial velocity
(:class:`adaptnav.fusion.samples.InertialVelocitySample`: the strapdown's increments summed without
aiding corrections — the value drifts, its changes are the IMU's, attitude-compensated).

Model. Sub-steps ``j`` of the model step ``δ`` (``model_step_s``) on the absolute grid
``t = j δ``. With ``P(t)`` the time integral of the free-inertial velocity (kept by the
filter, sampled about once a second and interpolated linearly to the grid edges), the mean
velocity over sub-step j is ``ū_j = (P(t_{j+1}) − P(t_j)) / δ`` and, along the chord heading
``φ_j`` (the yaw at the sub-step's midpoint; the chord of an arc is at ``θ + W δ/2``),

    a_j = (ū_j − c) · (cos φ_j, sin φ_j) = V_j + (drift of the free-inertial value)

with ``c`` the sea current (ground vs water velocity) and ``V_j = k_V v_j + e_j``,
``e_j ~ N(0, s_j)``, ``s_j = d_j · σ²``, ``d_j = (v_j², w_j², 1)`` the motion model's surge
(DESIGN.md "Motion model"). Consecutive differences

    Δa_j = a_j − a_{j−1} ~ N(k_V (v_j − v_{j−1}), s_j + s_{j−1})

are free of the unknown offset and of slow drifts (accelerometer bias, attitude error) and
nearly free of the current (only through the heading change). They are linear in the
variances, so they enter the M-step's surge objective as extra rows with design
``d_j + d_{j−1}`` (:func:`adaptnav.calibration.mstep.m_step`).

Composite likelihood. Each ``e_j`` enters two differences, so the differences are not
independent (correlation −½). They are treated as independent with weight 2/3: for equal
variances the sandwich variance of the resulting σ̂² is ``3σ⁴/n`` against the ``2σ⁴/n`` the
naive likelihood claims, so the weight makes the curvature honest next to the particle
smoother's rows and the prior.

Step length. EM runs with the variances of the window step ``Δ = step_s``
(``× δ/Δ``, :func:`adaptnav.fusion.motion_model.rescale_step`); the rows are scaled by ``√(δ/Δ)``
so that their variance is ``(d_j + d_{j−1}) · σ²_Δ``.

What the rows do not use: k_V and the current come from the position information (the
increments carry k_V only through speed changes, the current only through turns).
Pure math: no clock, no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adaptnav.fusion.motion_model import MotionParams

# weight of one difference row (module docstring: composite likelihood)
DIFFERENCE_WEIGHT = 2.0 / 3.0


@dataclass(frozen=True)
class InertialTrack:
    """Free-inertial samples: ``t_s`` (N,) increasing, ``pos_ne_m`` (N, 2) the time integral of
    the free-inertial velocity (north, east), ``yaw_rad`` (N,), ``reset_counter`` (N,)
    (changes across an IMU gap)."""

    t_s: np.ndarray
    pos_ne_m: np.ndarray
    yaw_rad: np.ndarray
    reset_counter: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.size)


@dataclass(frozen=True)
class SurgeIncrements:
    """Rows of the surge objective from the IMU, in window-step units (module docstring).

    ``dv_obs`` (n,) observed ``Δa·√(δ/Δ)`` (m/s); ``dv_ctrl`` (n,) ``Δv·√(δ/Δ)``;
    ``design`` (n, 3) ``d_j + d_{j−1}``; ``weight`` (n,) forgetting × composite weight.
    """

    dv_obs: np.ndarray
    dv_ctrl: np.ndarray
    design: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return int(self.dv_obs.size)

    def residual_sq(self, k_v: float) -> np.ndarray:
        """(n,) squared residuals ``(Δa − k_V Δv)²``."""
        return (self.dv_obs - k_v * self.dv_ctrl) ** 2

    def log_likelihood(self, params: MotionParams) -> float:
        """Weighted (composite) Gaussian log-likelihood of the rows under ``params``
        (variances for the window step)."""
        if len(self) == 0:
            return 0.0
        s = self.design @ np.array([params.var_vv, params.var_vw, params.var_v1])
        r2 = self.residual_sq(params.k_v)
        return float(-0.5 * np.sum(self.weight * (np.log(2.0 * math.pi * s) + r2 / s)))


def surge_increments(track: InertialTrack, t_start_s: float, step_s: float, v_m_s, w_rad_s,
                     step_weights=None, model_step_s: float = 1.0, current_n_m_s=(0.0, 0.0),
                     max_gap_s: float = 1.5) -> SurgeIncrements:
    """IMU surge increments over a window of ``T`` steps starting at ``t_start_s``.

    Parameters
    ----------
    track : InertialTrack
        Free-inertial velocity samples (any span; those outside the window are ignored).
    t_start_s, step_s : float
        The window: step τ covers ``[t_start + τ Δ, t_start + (τ+1) Δ)``, ``Δ = step_s``.
    v_m_s, w_rad_s : (T,) array
        The window's controls; a sub-step takes the controls of the step holding its midpoint.
    step_weights : (T,) array, optional
        Forgetting weights λ_τ (default 1).
    model_step_s : float
        Sub-step ``δ`` (the motion model's reference step).
    current_n_m_s : (2,)
        Sea current (north, east) removed before the projection.
    max_gap_s : float
        A sub-step whose samples are further apart than this is not used (the runner sends
        one a second).

    Returns
    -------
    SurgeIncrements
        Rows for every pair of consecutive usable sub-steps (possibly none).
    """
    v = np.asarray(v_m_s, dtype=float)
    w = np.asarray(w_rad_s, dtype=float)
    T = v.size
    lam = np.ones(T) if step_weights is None else np.asarray(step_weights, dtype=float)
    empty = SurgeIncrements(np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0))
    t = np.asarray(track.t_s, dtype=float)
    if t.size < 3 or T == 0:
        return empty
    d = model_step_s
    t_end = t_start_s + T * step_s
    j0 = math.ceil(max(t_start_s, t[0]) / d - 1e-9)
    j1 = math.floor(min(t_end, t[-1]) / d + 1e-9)  # last edge
    if j1 - j0 < 2:
        return empty
    edges = np.arange(j0, j1 + 1) * d  # (K+1,)
    P = np.asarray(track.pos_ne_m, dtype=float)
    P = P - P[0]  # only differences matter; keeps the interpolation well-conditioned
    dt = np.diff(t)
    P_edges = np.column_stack([np.interp(edges, t, P[:, 0]), np.interp(edges, t, P[:, 1])])
    u_mean = np.diff(P_edges, axis=0) / d  # (K, 2)
    mid = edges[:-1] + 0.5 * d
    phi = np.interp(mid, t, np.unwrap(np.asarray(track.yaw_rad, dtype=float)))
    cur = np.asarray(current_n_m_s, dtype=float)
    a = (u_mean[:, 0] - cur[0]) * np.cos(phi) + (u_mean[:, 1] - cur[1]) * np.sin(phi)
    # usable sub-steps: no reset and no sample gap inside
    lo = np.searchsorted(t, edges[:-1], side="right") - 1
    hi = np.searchsorted(t, edges[1:], side="left")
    resets = np.asarray(track.reset_counter)
    ok = (lo >= 0) & (hi < t.size)
    lo_c, hi_c = np.clip(lo, 0, t.size - 1), np.clip(hi, 0, t.size - 1)
    ok &= resets[lo_c] == resets[hi_c]
    gap_ok = np.concatenate([dt <= max_gap_s, [True]])  # gap after sample i
    bad_cum = np.concatenate([[0], np.cumsum(~gap_ok)])
    ok &= (bad_cum[hi_c] - bad_cum[lo_c]) == 0
    ok &= np.isfinite(a)
    tau = np.floor((mid - t_start_s) / step_s).astype(np.int64)
    ok &= (tau >= 0) & (tau < T)
    pair = ok[1:] & ok[:-1]
    if not np.any(pair):
        return empty
    tc = np.clip(tau, 0, T - 1)
    D = np.column_stack([v[tc] ** 2, w[tc] ** 2, np.ones(tc.size)])
    scale = math.sqrt(model_step_s / step_s)
    dv_obs = (a[1:] - a[:-1])[pair] * scale
    dv_ctrl = (v[tc[1:]] - v[tc[:-1]])[pair] * scale
    design = (D[1:] + D[:-1])[pair]
    weight = DIFFERENCE_WEIGHT * lam[tc[1:]][pair]
    return SurgeIncrements(dv_obs, dv_ctrl, design, weight)
