r"""Strapdown mechanisation and the earth model (numba kernels, the hot loop).

Mechanisation in the local NED tangent plane at the mission origin (an earth-fixed
frame, so no transport rate; Groves 2013 §5.3 "ECEF frame" written in local axes), per IMU
sample k held over ``(t_{k-1}, t_k]``::

    ω̂ = ω_m − b_g,  f̂ = f_m − b_a
    q_nb ← q(−ω_ie δt) ⊗ q_nb ⊗ q(ω̂ δt)
    a_n = ½ (R_nb⁻ + R_nb⁺) f̂ + g_n(p) − 2 ω_ie × v_n,   g_n(p) = γ (−p_N/R, −p_E/R, 1 + 2 p_D/R)
    p_n ← p_n + v_n δt + ½ a_n δt²,  v_n ← v_n + a_n δt

with the earth rate in local axes ``ω_ie = Ω (cos L, 0, −sin L)`` and the normal gravity
γ(L) of Somigliana's formula (WGS-84) when the earth model is on (navigation-grade IMUs,
:mod:`adaptnav.fusion.imu_grades`); off, ``ω_ie = 0`` and γ = 9.80665 m/s² (flat,
non-rotating: the earth rate is below a consumer or tactical gyro's noise over a dive).
With the earth model the gravity vector also turns with the position (first order in p/R,
R the Gaussian mean radius of curvature at the origin; Groves 2013 §2.4.7, §5.7): the plumb
line at 1 km from the origin leans 0.009° in the tangent plane, 1.5 mg horizontally.  Without
it the local level the vehicle keeps looks like a tilt that grows at v/R, which a DVL-aided
FOG explains as a heading error of v_N/(R Ω cos L) — the ship gyrocompass's "speed error",
0.36° at 1.5 m/s and 59° N.  It adds the Schuler loop to the error dynamics
(:mod:`adaptnav.fusion.kalman`, which propagates the covariance over the steps summed here).

Arrays shared with the Kalman kernels (all float64, mutated in place):

- ``x`` (19,) nominal state (:mod:`adaptnav.fusion.state`),
- ``acc`` (24,) step accumulators, named in :mod:`adaptnav.fusion.state` (``ACC_*``):
  Σ R f̂ δt (3), Σ R δt (9, row-major), Σ δt (1), latest bias-corrected ω̂_b (3) and
  f̂_b (3); then the earth model (kept across steps): ω_ie in local axes (3, rad/s),
  γ − 9.80665 (1, m/s²) and γ/R (1, 1/s²) — see :func:`set_earth`.
"""
from __future__ import annotations

import math

import numpy as np
from adaptnav.kernels import jit

from .frames import GRAVITY_M_S2
from .state import (ACC_DGAMMA, ACC_EARTH, ACC_EARTH_RATE, ACC_F, ACC_G_OVER_R, ACC_OMEGA, ACC_R, ACC_RF,
                    ACC_T, X_BA, X_BG, X_POS, X_Q, X_VEL)

# first indices of the state and accumulator blocks (adaptnav.fusion.state), as plain ints:
# numba takes module-level ints as compile-time constants, so ``x[_X_VEL + 1]`` costs what
# ``x[4]`` does
_X_POS, _X_VEL, _X_Q, _X_BA, _X_BG = X_POS.start, X_VEL.start, X_Q.start, X_BA.start, X_BG.start
_ACC_RF, _ACC_R, _ACC_T = ACC_RF.start, ACC_R.start, ACC_T
_ACC_OMEGA, _ACC_F = ACC_OMEGA.start, ACC_F.start
_ACC_W_IE, _ACC_DGAMMA, _ACC_G_OVER_R = ACC_EARTH_RATE.start, ACC_DGAMMA, ACC_G_OVER_R

EARTH_RATE_RAD_S = 7.292115e-5  # WGS-84 Ω_ie
# WGS-84 normal gravity (Somigliana): γ_e, k = b γ_p / (a γ_e) − 1, e²
_GAMMA_E = 9.7803253359
_SOMIGLIANA_K = 0.00193185265241
_E2 = 0.00669437999013
_A_M = 6378137.0  # WGS-84 semi-major axis


def normal_gravity_m_s2(lat_rad: float) -> float:
    """Somigliana's normal gravity on the WGS-84 ellipsoid (m/s²)."""
    s2 = math.sin(lat_rad) ** 2
    return _GAMMA_E * (1.0 + _SOMIGLIANA_K * s2) / math.sqrt(1.0 - _E2 * s2)


def set_earth(acc: np.ndarray, lat_rad: float | None) -> None:
    """Earth model into the accumulator array: ``None`` = flat, non-rotating."""
    if lat_rad is None:
        acc[ACC_EARTH] = 0.0
    else:
        acc[ACC_EARTH_RATE] = (EARTH_RATE_RAD_S * math.cos(lat_rad), 0.0, -EARTH_RATE_RAD_S * math.sin(lat_rad))
        acc[ACC_DGAMMA] = normal_gravity_m_s2(lat_rad) - GRAVITY_M_S2
        s2 = math.sin(lat_rad) ** 2
        radius_m = _A_M * math.sqrt(1.0 - _E2) / (1.0 - _E2 * s2)  # √(R_N R_E), Gaussian mean radius
        acc[ACC_G_OVER_R] = normal_gravity_m_s2(lat_rad) / radius_m


def plumb_line_rotvec(acc: np.ndarray, pos_n_m) -> np.ndarray:
    """Rotation vector (rad) from the local level and north at ``pos_n_m`` to the axes of the
    origin's tangent plane, in which the earth model's gravity ``g_n(p)`` points:
    ``(p_E/R, −p_N/R, −p_E tan L/R)`` (the plumb line's lean, and the meridians' convergence);
    zeros when the earth model is off.  An attitude levelled on the accelerometers at ``p``
    with a heading from local north is ``Exp(φ) R_nb`` in the mechanisation's frame (else a
    Schuler oscillation of amplitude ≈ |p|, and a misprojected earth rate)."""
    g_over_r = float(acc[ACC_G_OVER_R])
    if g_over_r == 0.0:
        return np.zeros(3)
    inv_r = g_over_r / (GRAVITY_M_S2 + float(acc[ACC_DGAMMA]))
    w_ie = acc[ACC_EARTH_RATE]
    tan_lat = -float(w_ie[2]) / float(w_ie[0])
    p_n, p_e = float(pos_n_m[0]), float(pos_n_m[1])
    return np.array([p_e * inv_r, -p_n * inv_r, -p_e * tan_lat * inv_r])


@jit(cache=True, fastmath=False)
def _dcm(q0, q1, q2, q3, R):
    R[0, 0] = 1 - 2 * (q2 * q2 + q3 * q3)
    R[0, 1] = 2 * (q1 * q2 - q0 * q3)
    R[0, 2] = 2 * (q1 * q3 + q0 * q2)
    R[1, 0] = 2 * (q1 * q2 + q0 * q3)
    R[1, 1] = 1 - 2 * (q1 * q1 + q3 * q3)
    R[1, 2] = 2 * (q2 * q3 - q0 * q1)
    R[2, 0] = 2 * (q1 * q3 - q0 * q2)
    R[2, 1] = 2 * (q2 * q3 + q0 * q1)
    R[2, 2] = 1 - 2 * (q1 * q1 + q2 * q2)


@jit(cache=True)
def rotvec_quat(rx, ry, rz):
    """Quaternion (w, x, y, z) of the rotation vector ``(rx, ry, rz)`` (rad), exact; the
    series of sin(θ/2)/θ and cos(θ/2) below 1e-6 rad."""
    ang = np.sqrt(rx * rx + ry * ry + rz * rz)
    if ang < 1e-6:
        k = 0.5 - ang * ang / 48.0
        c = 1.0 - ang * ang / 8.0
    else:
        k = np.sin(0.5 * ang) / ang
        c = np.cos(0.5 * ang)
    return c, k * rx, k * ry, k * rz


@jit(cache=True)
def strapdown_step(x, f_b, w_b, dt, acc, R0, R1):
    """Advance the nominal state ``x`` by one IMU sample held over ``dt`` seconds."""
    wx = w_b[0] - x[_X_BG]
    wy = w_b[1] - x[_X_BG + 1]
    wz = w_b[2] - x[_X_BG + 2]
    fx = f_b[0] - x[_X_BA]
    fy = f_b[1] - x[_X_BA + 1]
    fz = f_b[2] - x[_X_BA + 2]
    q0, q1, q2, q3 = x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3]
    _dcm(q0, q1, q2, q3, R0)
    # q ← q ⊗ q(ω̂ δt)
    d0, d1, d2, d3 = rotvec_quat(wx * dt, wy * dt, wz * dt)
    n0 = q0 * d0 - q1 * d1 - q2 * d2 - q3 * d3
    n1 = q0 * d1 + q1 * d0 + q2 * d3 - q3 * d2
    n2 = q0 * d2 - q1 * d3 + q2 * d0 + q3 * d1
    n3 = q0 * d3 + q1 * d2 - q2 * d1 + q3 * d0
    ex, ey, ez = acc[_ACC_W_IE], acc[_ACC_W_IE + 1], acc[_ACC_W_IE + 2]
    if ex != 0.0 or ey != 0.0 or ez != 0.0:
        # the local frame turns with the earth: q ← q(−ω_ie δt) ⊗ q (first order, |ω_ie δt| < 1e-5)
        e1, e2, e3 = -0.5 * ex * dt, -0.5 * ey * dt, -0.5 * ez * dt
        m0 = n0 - e1 * n1 - e2 * n2 - e3 * n3
        m1 = n1 + e1 * n0 + e2 * n3 - e3 * n2
        m2 = n2 - e1 * n3 + e2 * n0 + e3 * n1
        m3 = n3 + e1 * n2 - e2 * n1 + e3 * n0
        n0, n1, n2, n3 = m0, m1, m2, m3
    inv = 1.0 / np.sqrt(n0 * n0 + n1 * n1 + n2 * n2 + n3 * n3)
    if n0 < 0.0:
        inv = -inv
    n0 *= inv
    n1 *= inv
    n2 *= inv
    n3 *= inv
    x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3] = n0, n1, n2, n3
    _dcm(n0, n1, n2, n3, R1)
    ax = 0.0
    ay = 0.0
    az = 0.0
    for i in range(3):
        for j in range(3):
            r = 0.5 * (R0[i, j] + R1[i, j])
            acc[_ACC_R + 3 * i + j] += r * dt
        ri0 = 0.5 * (R0[i, 0] + R1[i, 0])
        ri1 = 0.5 * (R0[i, 1] + R1[i, 1])
        ri2 = 0.5 * (R0[i, 2] + R1[i, 2])
        a = ri0 * fx + ri1 * fy + ri2 * fz
        acc[_ACC_RF + i] += a * dt
        if i == 0:
            ax = a
        elif i == 1:
            ay = a
        else:
            az = a
    az += GRAVITY_M_S2 + acc[_ACC_DGAMMA]
    if ex != 0.0 or ey != 0.0 or ez != 0.0:
        # the plumb line turns with the position: g_n(p) = γ (−p_N/R, −p_E/R, 1 + 2 p_D/R)
        gr = acc[_ACC_G_OVER_R]
        ax -= gr * x[_X_POS]
        ay -= gr * x[_X_POS + 1]
        az += 2.0 * gr * x[_X_POS + 2]
        # Coriolis −2 ω_ie × v
        vn, ve, vd = x[_X_VEL], x[_X_VEL + 1], x[_X_VEL + 2]
        ax -= 2.0 * (ey * vd - ez * ve)
        ay -= 2.0 * (ez * vn - ex * vd)
        az -= 2.0 * (ex * ve - ey * vn)
    x[_X_POS] += x[_X_VEL] * dt + 0.5 * ax * dt * dt
    x[_X_POS + 1] += x[_X_VEL + 1] * dt + 0.5 * ay * dt * dt
    x[_X_POS + 2] += x[_X_VEL + 2] * dt + 0.5 * az * dt * dt
    x[_X_VEL] += ax * dt
    x[_X_VEL + 1] += ay * dt
    x[_X_VEL + 2] += az * dt
    acc[_ACC_T] += dt
    acc[_ACC_OMEGA] = wx
    acc[_ACC_OMEGA + 1] = wy
    acc[_ACC_OMEGA + 2] = wz
    acc[_ACC_F] = fx
    acc[_ACC_F + 1] = fy
    acc[_ACC_F + 2] = fz


@jit(cache=True)
def accumulate_rest_window(st, f_b, w_b):
    """Add IMU samples to a stationary-detection window ``st`` = [t0, n, Σf (3), Σf² (3),
    max |ω|] (in place; t0 is the caller's). The sums in numpy's order for these shapes
    (``f.sum(axis=0)``, ``(f*f).sum(axis=0)``, ``sqrt((w*w).sum(axis=1)).max()``: the same
    floats), without its six reductions per IMU batch (a third of a batch's filter time)."""
    n = f_b.shape[0]
    if n == 0:
        return
    st[1] += n
    for j in range(3):
        a = f_b[0, j]
        b = f_b[0, j] * f_b[0, j]
        for k in range(1, n):
            a += f_b[k, j]
            b += f_b[k, j] * f_b[k, j]
        st[2 + j] += a
        st[5 + j] += b
    m = -np.inf
    for k in range(n):
        v = np.sqrt(w_b[k, 0] * w_b[k, 0] + w_b[k, 1] * w_b[k, 1] + w_b[k, 2] * w_b[k, 2])
        if v > m:
            m = v
    if m > st[8]:
        st[8] = m


@jit(cache=True)
def imu_clean(t_s, f_b, w_b, t_last_s, gap_s):
    """True when every sample is finite, strictly after the previous one and gap-free."""
    prev = t_last_s
    for k in range(t_s.shape[0]):
        t = t_s[k]
        if not (t > prev and t - prev <= gap_s):
            return False
        for i in range(3):
            if not (np.isfinite(f_b[k, i]) and np.isfinite(w_b[k, i])):
                return False
        prev = t
    return True


@jit(cache=True)
def imu_run_in_bounds(t_s, f_b, w_b, max_f, max_w, t_lo, t_hi, max_step_s):
    """The plausibility door's test of a whole IMU run in one call
    (:meth:`adaptnav.fusion.plausibility.Door.check_batch`): every component of ``f_b`` within
    ``±max_f`` and of ``w_b`` within ``±max_w``, the first stamp within ``[t_lo, t_hi]``
    (``t_lo = −∞``: no data clock yet, not tested) and every step positive and at most
    ``max_step_s``; a NaN anywhere fails (as the numpy maxima it replaces: 3 µs of their
    calls per IMU batch)."""
    n = t_s.shape[0]
    for k in range(n):
        for i in range(3):
            if not (abs(f_b[k, i]) <= max_f and abs(w_b[k, i]) <= max_w):
                return False
    if not (t_lo == -np.inf or (t_lo <= t_s[0] and t_s[0] <= t_hi)):
        return False
    for k in range(1, n):
        step = t_s[k] - t_s[k - 1]
        if not (step > 0.0 and step <= max_step_s):
            return False
    return True
