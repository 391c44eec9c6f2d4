r"""Strapdown mechanisation and error-state propagation (numba kernels, the hot loop).

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
0.36° at 1.5 m/s and 59° N.  It adds the Schuler loop to the error dynamics.

Error dynamics (global attitude error δθ, see :mod:`adaptnav.fusion.state`)::

    δṗ = δv,  δv̇ = −[R f̂]× δθ − 2[ω_ie]× δv + (γ/R) diag(−1, −1, 2) δp − R δb_a + w_a,  δθ̇ = −[ω_ie]× δθ − R δb_g + w_g,
    δḃ_a = w_ba,  δḃ_g = w_bg,  δċ = w_c,  δk̇ = w_k

The covariance is propagated every ``covariance_step_s`` T (as pyins and ArduPilot do),
with F built from the step averages of ``R f̂`` and ``R`` and
``Φ = I + F T + (F T)²/2``; ``P ← Φ (P + Q T/2) Φᵀ + Q T/2`` (trapezoidal noise).

Arrays shared by the kernels (all float64, mutated in place):

- ``x`` (19,) nominal state (:mod:`adaptnav.fusion.state`),
- ``P`` (18, 18) covariance at time ``clock[1]``,
- ``acc`` (24,) step accumulators: Σ R f̂ δt (3), Σ R δt (9, row-major), Σ δt (1),
  latest bias-corrected ω̂_b (3) and f̂_b (3); then the earth model (kept across steps):
  ω_ie in local axes (3, rad/s), γ − 9.80665 (1, m/s²) and γ/R (1, 1/s²) — see :func:`set_earth`,
- ``clock`` (2,) ``[t_state_s, t_cov_s]``,
- ``qdiag`` (18,) continuous process noise PSDs per error state.
"""
from __future__ import annotations

import math

import numpy as np
from adaptnav.kernels import jit

from .frames import GRAVITY_M_S2
from .state import ATT, BA, BG, N_ERR, N_NOM, POS, VEL, X_BA, X_BG, X_POS, X_Q, X_VEL

# first indices of the state blocks (adaptnav.fusion.state), as plain ints: numba takes
# module-level ints as compile-time constants, so ``x[_X_VEL + 1]`` costs what ``x[4]`` does
_X_POS, _X_VEL, _X_Q, _X_BA, _X_BG = X_POS.start, X_VEL.start, X_Q.start, X_BA.start, X_BG.start
_E_POS, _E_VEL, _E_ATT, _E_BA, _E_BG = POS.start, VEL.start, ATT.start, BA.start, BG.start
# the slow states follow the attitude in both vectors: error index i is nominal i + 1
_SLOW_SHIFT = _X_BA - _E_BA

ACC_SIZE = 24
# named parts of ``acc`` for Python callers (the kernels index it with literals)
ACC_OMEGA = slice(13, 16)  # latest bias-corrected ω̂_b (rad/s)
ACC_F = slice(16, 19)      # latest bias-corrected f̂_b (m/s²)
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
        acc[19:24] = 0.0
    else:
        acc[19:22] = (EARTH_RATE_RAD_S * math.cos(lat_rad), 0.0, -EARTH_RATE_RAD_S * math.sin(lat_rad))
        acc[22] = normal_gravity_m_s2(lat_rad) - GRAVITY_M_S2
        s2 = math.sin(lat_rad) ** 2
        radius_m = _A_M * math.sqrt(1.0 - _E2) / (1.0 - _E2 * s2)  # √(R_N R_E), Gaussian mean radius
        acc[23] = normal_gravity_m_s2(lat_rad) / radius_m


def plumb_line_rotvec(acc: np.ndarray, pos_n_m) -> np.ndarray:
    """Rotation vector (rad) from the local level and north at ``pos_n_m`` to the axes of the
    origin's tangent plane, in which the earth model's gravity ``g_n(p)`` points:
    ``(p_E/R, −p_N/R, −p_E tan L/R)`` (the plumb line's lean, and the meridians' convergence);
    zeros when the earth model is off.  An attitude levelled on the accelerometers at ``p``
    with a heading from local north is ``Exp(φ) R_nb`` in the mechanisation's frame (else a
    Schuler oscillation of amplitude ≈ |p|, and a misprojected earth rate)."""
    g_over_r = float(acc[23])
    if g_over_r == 0.0:
        return np.zeros(3)
    inv_r = g_over_r / (GRAVITY_M_S2 + float(acc[22]))
    tan_lat = -float(acc[21]) / float(acc[19])
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
    # q ← q ⊗ q(ω̂ δt), exact rotation-vector quaternion
    rx, ry, rz = wx * dt, wy * dt, wz * dt
    ang = np.sqrt(rx * rx + ry * ry + rz * rz)
    if ang < 1e-6:
        k = 0.5 - ang * ang / 48.0
        c = 1.0 - ang * ang / 8.0
    else:
        k = np.sin(0.5 * ang) / ang
        c = np.cos(0.5 * ang)
    d0, d1, d2, d3 = c, k * rx, k * ry, k * rz
    n0 = q0 * d0 - q1 * d1 - q2 * d2 - q3 * d3
    n1 = q0 * d1 + q1 * d0 + q2 * d3 - q3 * d2
    n2 = q0 * d2 - q1 * d3 + q2 * d0 + q3 * d1
    n3 = q0 * d3 + q1 * d2 - q2 * d1 + q3 * d0
    ex, ey, ez = acc[19], acc[20], acc[21]
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
            acc[3 + 3 * i + j] += r * dt
        ri0 = 0.5 * (R0[i, 0] + R1[i, 0])
        ri1 = 0.5 * (R0[i, 1] + R1[i, 1])
        ri2 = 0.5 * (R0[i, 2] + R1[i, 2])
        a = ri0 * fx + ri1 * fy + ri2 * fz
        acc[i] += a * dt
        if i == 0:
            ax = a
        elif i == 1:
            ay = a
        else:
            az = a
    az += GRAVITY_M_S2 + acc[22]
    if ex != 0.0 or ey != 0.0 or ez != 0.0:
        # the plumb line turns with the position: g_n(p) = γ (−p_N/R, −p_E/R, 1 + 2 p_D/R)
        gr = acc[23]
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
    acc[12] += dt
    acc[13] = wx
    acc[14] = wy
    acc[15] = wz
    acc[16] = fx
    acc[17] = fy
    acc[18] = fz


@jit(cache=True)
def transition(acc, T):
    """Φ (18×18) over the accumulated step of length ``T`` (see module docstring)."""
    F = np.zeros((N_ERR, N_ERR))
    a0 = acc[0] / T
    a1 = acc[1] / T
    a2 = acc[2] / T
    v, th = _E_VEL, _E_ATT
    for i in range(3):
        F[_E_POS + i, v + i] = 1.0
    # δv̇ = −[a]× δθ
    F[v, th + 1] = a2
    F[v, th + 2] = -a1
    F[v + 1, th] = -a2
    F[v + 1, th + 2] = a0
    F[v + 2, th] = a1
    F[v + 2, th + 1] = -a0
    for i in range(3):
        for j in range(3):
            r = acc[3 + 3 * i + j] / T
            F[v + i, _E_BA + j] = -r
            F[th + i, _E_BG + j] = -r
    # earth rotation: δv̇ += −2[ω_ie]× δv, δθ̇ += −[ω_ie]× δθ
    ex, ey, ez = acc[19], acc[20], acc[21]
    F[v, v + 1] += 2.0 * ez
    F[v, v + 2] -= 2.0 * ey
    F[v + 1, v] -= 2.0 * ez
    F[v + 1, v + 2] += 2.0 * ex
    F[v + 2, v] += 2.0 * ey
    F[v + 2, v + 1] -= 2.0 * ex
    F[th, th + 1] += ez
    F[th, th + 2] -= ey
    F[th + 1, th] -= ez
    F[th + 1, th + 2] += ex
    F[th + 2, th] += ey
    F[th + 2, th + 1] -= ex
    # gravity gradient (the Schuler loop): δv̇ += (γ/R) diag(−1, −1, 2) δp
    F[v, _E_POS] -= acc[23]
    F[v + 1, _E_POS + 1] -= acc[23]
    F[v + 2, _E_POS + 2] += 2.0 * acc[23]
    FT = F * T
    Phi = np.eye(N_ERR) + FT + 0.5 * (FT @ FT)
    return Phi


@jit(cache=True)
def propagated_covariance(P, acc, qdiag):
    """Covariance after the pending accumulated step (P itself is not changed)."""
    T = acc[12]
    if T <= 0.0:
        return P.copy()
    Phi = transition(acc, T)
    Pm = P.copy()
    for i in range(N_ERR):
        Pm[i, i] += 0.5 * qdiag[i] * T
    Pn = Phi @ Pm @ Phi.T
    for i in range(N_ERR):
        Pn[i, i] += 0.5 * qdiag[i] * T
    return 0.5 * (Pn + Pn.T)


@jit(cache=True)
def flush_covariance(P, acc, clock, qdiag):
    """Propagate ``P`` over the accumulated step and reset the accumulators."""
    if acc[12] > 0.0:
        P[:, :] = propagated_covariance(P, acc, qdiag)
        for i in range(13):
            acc[i] = 0.0
    clock[1] = clock[0]


N_X = N_NOM
N_P = N_ERR * N_ERR
CORE_SIZE = N_X + N_P + ACC_SIZE + 2
_CORE_ACC = N_X + N_P          # where acc starts in the core array
_CORE_CLOCK = _CORE_ACC + ACC_SIZE


@jit(cache=True)
def core_views(core):
    """(x, P, acc, clock) views of the contiguous core array."""
    x = core[0:N_X]
    P = core[N_X:_CORE_ACC].reshape((N_ERR, N_ERR))
    acc = core[_CORE_ACC:_CORE_CLOCK]
    clock = core[_CORE_CLOCK:CORE_SIZE]
    return x, P, acc, clock


@jit(cache=True)
def core_ok(core, max_speed_m_s):
    """Nominal state and covariance finite, every variance positive, state time finite
    and every velocity component below ``max_speed_m_s`` — the estimator's guard after
    every sample, one pass instead of five numpy reductions (~30 µs, 10 % of a replay)."""
    x, P, acc, clock = core_views(core)
    for i in range(N_X):
        if not np.isfinite(x[i]):
            return False
    for i in range(N_ERR):
        if not P[i, i] > 0.0:
            return False
        for j in range(N_ERR):
            if not np.isfinite(P[i, j]):
                return False
    if not np.isfinite(clock[0]):
        return False
    for i in range(3):
        if not abs(x[_X_VEL + i]) < max_speed_m_s:
            return False
    return True


@jit(cache=True)
def propagate_core(t_s, f_b, w_b, core, qdiag, cov_step_s):
    """:func:`propagate_imu` on the core array (fewer arguments: cheaper dispatch)."""
    x, P, acc, clock = core_views(core)
    propagate_imu(t_s, f_b, w_b, x, P, acc, clock, qdiag, cov_step_s)


@jit(cache=True)
def propagate_imu(t_s, f_b, w_b, x, P, acc, clock, qdiag, cov_step_s):
    """Propagate over IMU samples ``t_s`` (N,), ``f_b`` (N, 3), ``w_b`` (N, 3).

    The caller guarantees ``t_s`` strictly increasing, after ``clock[0]``, finite and
    without gaps (checked vectorised before). Covariance is flushed every
    ``cov_step_s``.
    """
    R0 = np.empty((3, 3))
    R1 = np.empty((3, 3))
    for k in range(t_s.shape[0]):
        dt = t_s[k] - clock[0]
        strapdown_step(x, f_b[k], w_b[k], dt, acc, R0, R1)
        clock[0] = t_s[k]
        if clock[0] - clock[1] >= cov_step_s - 1e-9:
            flush_covariance(P, acc, clock, qdiag)


@jit(cache=True)
def inject_error(x, dx, P):
    """x ← x ⊕ δx and the ESKF covariance reset ``P ← G P Gᵀ``."""
    for i in range(3):
        x[_X_POS + i] += dx[_E_POS + i]
        x[_X_VEL + i] += dx[_E_VEL + i]
    rx, ry, rz = dx[_E_ATT], dx[_E_ATT + 1], dx[_E_ATT + 2]
    ang = np.sqrt(rx * rx + ry * ry + rz * rz)
    if ang < 1e-6:
        k = 0.5 - ang * ang / 48.0
        c = 1.0 - ang * ang / 8.0
    else:
        k = np.sin(0.5 * ang) / ang
        c = np.cos(0.5 * ang)
    d0, d1, d2, d3 = c, k * rx, k * ry, k * rz
    q0, q1, q2, q3 = x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3]
    # q ← q(δθ) ⊗ q (global perturbation)
    n0 = d0 * q0 - d1 * q1 - d2 * q2 - d3 * q3
    n1 = d0 * q1 + d1 * q0 + d2 * q3 - d3 * q2
    n2 = d0 * q2 - d1 * q3 + d2 * q0 + d3 * q1
    n3 = d0 * q3 + d1 * q2 - d2 * q1 + d3 * q0
    inv = 1.0 / np.sqrt(n0 * n0 + n1 * n1 + n2 * n2 + n3 * n3)
    if n0 < 0.0:
        inv = -inv
    x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3] = n0 * inv, n1 * inv, n2 * inv, n3 * inv
    for i in range(_E_BA, N_ERR):  # biases, current, k_speed
        x[i + _SLOW_SHIFT] += dx[i]
    # reset Jacobian for the global attitude error: G_θθ = I + ½[δθ]× (Solà 2017 §7.2 for
    # the local error has the opposite sign)
    G = np.eye(N_ERR)
    th = _E_ATT
    G[th, th + 1] = -0.5 * rz
    G[th, th + 2] = 0.5 * ry
    G[th + 1, th] = 0.5 * rz
    G[th + 1, th + 2] = -0.5 * rx
    G[th + 2, th] = -0.5 * ry
    G[th + 2, th + 1] = 0.5 * rx
    P[:, :] = G @ P @ G.T


@jit(cache=True)
def gated_update(P, y, H, R, gate, dx_out, s_diag_out):
    """Chi-square gate, then the Joseph-form update (m ≤ 3 measurements, explicit loops).

    ``P ← (I−KH) P (I−KH)ᵀ + K R Kᵀ``, expanded (valid for any gain K) as
    ``P − K (PHᵀ)ᵀ − (PHᵀ) Kᵀ + K S Kᵀ``, which costs O(n² m) instead of O(n³).
    Returns ``(nis, fused)``: ``yᵀ S⁻¹ y`` and whether ``nis ≤ gate`` (NaN ⇒ False);
    ``dx_out`` ← K y (zeros if rejected), ``s_diag_out`` ← diag S.
    """
    n = P.shape[0]
    m = y.shape[0]
    PHt = np.zeros((n, m))
    for i in range(n):
        for k in range(m):
            acc = 0.0
            for j in range(n):
                acc += P[i, j] * H[k, j]
            PHt[i, k] = acc
    S = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            acc = R[a, b]
            for j in range(n):
                acc += H[a, j] * PHt[j, b]
            S[a, b] = acc
    for a in range(m):
        for b in range(a + 1, m):
            v = 0.5 * (S[a, b] + S[b, a])
            S[a, b] = v
            S[b, a] = v
        s_diag_out[a] = S[a, a]
    Sinv = np.linalg.inv(S) if m > 1 else np.array([[1.0 / S[0, 0]]])
    nis = 0.0
    for a in range(m):
        for b in range(m):
            nis += y[a] * Sinv[a, b] * y[b]
    for i in range(n):
        dx_out[i] = 0.0
    if not (nis <= gate):
        return nis, False
    K = np.zeros((n, m))
    for i in range(n):
        for b in range(m):
            acc = 0.0
            for a in range(m):
                acc += PHt[i, a] * Sinv[a, b]
            K[i, b] = acc
    KS = np.zeros((n, m))
    for i in range(n):
        for b in range(m):
            acc = 0.0
            for a in range(m):
                acc += K[i, a] * S[a, b]
            KS[i, b] = acc
    for i in range(n):
        acc = 0.0
        for a in range(m):
            acc += K[i, a] * y[a]
        dx_out[i] = acc
    for i in range(n):
        for j in range(i, n):
            acc = P[i, j]
            for a in range(m):
                acc += -K[i, a] * PHt[j, a] - PHt[i, a] * K[j, a] + KS[i, a] * K[j, a]
            P[i, j] = acc
            P[j, i] = acc
    return nis, True


@jit(cache=True)
def dcm_of(x):
    """``R_nb`` (3×3) of the nominal state ``x``."""
    R = np.empty((3, 3))
    _dcm(x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3], R)
    return R


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
def fuse(x, P, acc, clock, qdiag, y, H, R, gate, dx, s_diag_out, flush):
    """flush (INS mode) → gated Joseph update → error injection, in one call.

    Returns ``(nis, fused)`` as :func:`gated_update`.
    """
    if flush:
        flush_covariance(P, acc, clock, qdiag)
    nis, fused = gated_update(P, y, H, R, gate, dx, s_diag_out)
    if fused:
        inject_error(x, dx, P)
    return nis, fused


@jit(cache=True)
def fuse_core(core, qdiag, y, H, R, gate, dx, s_diag_out, flush):
    """:func:`fuse` on the core array."""
    x, P, acc, clock = core_views(core)
    return fuse(x, P, acc, clock, qdiag, y, H, R, gate, dx, s_diag_out, flush)
