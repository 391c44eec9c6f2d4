r"""The Kalman kernels of the ESKF: covariance propagation, error injection and the gated
update (numba kernels, the hot loop; the mechanisation is :mod:`adaptnav.fusion.strapdown`).

Error dynamics (global attitude error δθ, see :mod:`adaptnav.fusion.state`)::

    δṗ = δv,  δv̇ = −[R f̂]× δθ − 2[ω_ie]× δv + (γ/R) diag(−1, −1, 2) δp − R δb_a + w_a,  δθ̇ = −[ω_ie]× δθ − R δb_g + w_g,
    δḃ_a = w_ba,  δḃ_g = w_bg,  δċ = w_c,  δk̇ = w_k

The covariance is propagated every ``covariance_step_s`` T (as pyins and ArduPilot do),
with F built from the step averages of ``R f̂`` and ``R`` that :func:`~adaptnav.fusion.strapdown.strapdown_step`
sums in ``acc``, and ``Φ = I + F T + (F T)²/2``; ``P ← Φ (P + Q T/2) Φᵀ + Q T/2``
(trapezoidal noise). A measurement is gated on its normalised innovation (chi-square) and
fused in Joseph form; the error is injected into the nominal state and the covariance
reset (:func:`inject_error`).

Arrays shared by the kernels (all float64, mutated in place):

- ``x`` (19,) nominal state (:mod:`adaptnav.fusion.state`),
- ``P`` (18, 18) covariance at time ``clock[1]``,
- ``acc`` (24,) step accumulators and earth model (:mod:`adaptnav.fusion.strapdown`; named
  ``ACC_*`` in :mod:`adaptnav.fusion.state`),
- ``clock`` (2,) ``[t_state_s, t_cov_s]``,
- ``qdiag`` (18,) continuous process noise PSDs per error state,
- ``core`` (:data:`CORE_SIZE`,) all of ``x``, ``P``, ``acc`` and ``clock`` in one array
  (:data:`CORE_X`, :data:`CORE_P`, :data:`CORE_ACC`, :data:`CORE_CLOCK`): the estimator's
  state, copied whole for a late-measurement snapshot; then the clones' pending map ``M``
  (18, 18) (:data:`CORE_M`) and its switch (:data:`CORE_TRACK`).

Stochastic clones (:mod:`adaptnav.fusion.aiding.loop_closure`) need their cross-covariances
``C = Cov(δx, d)`` (18 × 2 per clone) to follow every linear map of the error state:
``C ← Φ C`` per covariance step, ``C ← G (I − K H) C`` per update. While ``core[CORE_TRACK]``
is set, the kernels compose those maps into ``M`` instead (``C_true = M C_stored``: 18 × 18
per step instead of 18 × 2n, and no Python between the steps of an IMU run); the clone bank
applies ``M`` when it reads ``C`` (a new clone, a closure: every few seconds).
"""
from __future__ import annotations

import math

import numpy as np
from adaptnav.kernels import jit

from .state import (ACC_EARTH_RATE, ACC_G_OVER_R, ACC_R, ACC_RF, ACC_SIZE, ACC_STEP, ACC_T, ATT, BA, BG, N_ERR,
                    N_NOM, POS, VEL, X_BA, X_CUR, X_POS, X_Q, X_VEL)
from .strapdown import _dcm, accumulate_rest_window, imu_clean, rotvec_quat, strapdown_step

# first indices of the state and accumulator blocks (adaptnav.fusion.state), as plain ints:
# numba takes module-level ints as compile-time constants, so ``x[_X_VEL + 1]`` costs what
# ``x[4]`` does
_X_POS, _X_VEL, _X_Q, _X_BA = X_POS.start, X_VEL.start, X_Q.start, X_BA.start
_E_POS, _E_VEL, _E_ATT, _E_BA, _E_BG = POS.start, VEL.start, ATT.start, BA.start, BG.start
# the slow states follow the attitude in both vectors: error index i is nominal i + 1
_SLOW_SHIFT = _X_BA - _E_BA
_ACC_RF, _ACC_R, _ACC_T, _ACC_STEP_END = ACC_RF.start, ACC_R.start, ACC_T, ACC_STEP.stop
_ACC_W_IE, _ACC_G_OVER_R = ACC_EARTH_RATE.start, ACC_G_OVER_R

# the core array: x | P (row-major) | acc | clock
N_X = N_NOM
N_P = N_ERR * N_ERR
_CORE_ACC = N_X + N_P          # where acc starts in the core array
_CORE_CLOCK = _CORE_ACC + ACC_SIZE
_CORE_M = _CORE_CLOCK + 2       # the clones' pending map M (row-major)
_CORE_TRACK = _CORE_M + N_P     # > 0: the kernels compose the error-state maps into M
CORE_SIZE = _CORE_TRACK + 1
CORE_X = slice(0, N_X)
CORE_P = slice(N_X, _CORE_ACC)
CORE_ACC = slice(_CORE_ACC, _CORE_CLOCK)
CORE_CLOCK = slice(_CORE_CLOCK, _CORE_M)
CORE_M = slice(_CORE_M, _CORE_TRACK)
CORE_TRACK = _CORE_TRACK


@jit(cache=True)
def transition(acc, T):
    """Φ (18×18) over the accumulated step of length ``T`` (see module docstring)."""
    F = np.zeros((N_ERR, N_ERR))
    a0 = acc[_ACC_RF] / T
    a1 = acc[_ACC_RF + 1] / T
    a2 = acc[_ACC_RF + 2] / T
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
            r = acc[_ACC_R + 3 * i + j] / T
            F[v + i, _E_BA + j] = -r
            F[th + i, _E_BG + j] = -r
    # earth rotation: δv̇ += −2[ω_ie]× δv, δθ̇ += −[ω_ie]× δθ
    ex, ey, ez = acc[_ACC_W_IE], acc[_ACC_W_IE + 1], acc[_ACC_W_IE + 2]
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
    g_over_r = acc[_ACC_G_OVER_R]
    F[v, _E_POS] -= g_over_r
    F[v + 1, _E_POS + 1] -= g_over_r
    F[v + 2, _E_POS + 2] += 2.0 * g_over_r
    FT = F * T
    Phi = np.eye(N_ERR) + FT + 0.5 * (FT @ FT)
    return Phi


@jit(cache=True)
def covariance_step(P, Phi, qdiag, T):
    """``Φ (P + Q T/2) Φᵀ + Q T/2``, symmetrised (a new array)."""
    Pm = P.copy()
    for i in range(N_ERR):
        Pm[i, i] += 0.5 * qdiag[i] * T
    Pn = Phi @ Pm @ Phi.T
    for i in range(N_ERR):
        Pn[i, i] += 0.5 * qdiag[i] * T
    return 0.5 * (Pn + Pn.T)


@jit(cache=True)
def propagated_covariance(P, acc, qdiag):
    """Covariance after the pending accumulated step (P itself is not changed)."""
    T = acc[_ACC_T]
    if T <= 0.0:
        return P.copy()
    return covariance_step(P, transition(acc, T), qdiag, T)


@jit(cache=True)
def flush_covariance(P, acc, clock, qdiag):
    """Propagate ``P`` over the accumulated step and reset the accumulators."""
    if acc[_ACC_T] > 0.0:
        P[:, :] = propagated_covariance(P, acc, qdiag)
        for i in range(_ACC_STEP_END):
            acc[i] = 0.0
    clock[1] = clock[0]




@jit(cache=True)
def core_views(core):
    """(x, P, acc, clock) views of the contiguous core array."""
    x = core[0:N_X]
    P = core[N_X:_CORE_ACC].reshape((N_ERR, N_ERR))
    acc = core[_CORE_ACC:_CORE_CLOCK]
    clock = core[_CORE_CLOCK:CORE_SIZE]
    return x, P, acc, clock


@jit(cache=True)
def flush_core(core, qdiag):
    """:func:`flush_covariance` on the core array; while clones are tracked, ``M ← Φ M``."""
    x, P, acc, clock = core_views(core)
    T = acc[_ACC_T]
    if T > 0.0:
        Phi = transition(acc, T)
        if core[_CORE_TRACK] > 0.0:
            M = core[_CORE_M:_CORE_TRACK].reshape((N_ERR, N_ERR))
            M[:, :] = Phi @ M
        P[:, :] = covariance_step(P, Phi, qdiag, T)
        for i in range(_ACC_STEP_END):
            acc[i] = 0.0
    clock[1] = clock[0]


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
def core_positive_definite(core):
    """The covariance of the core array positive definite: its Cholesky factorisation (of the
    lower triangle, as LAPACK's ``potrf``, which ``np.linalg.cholesky`` calls) finds every
    pivot positive (a NaN fails). The check of the state the estimator keeps as the last good
    one, once per data second: ``np.linalg.cholesky`` there cost ~40 µs in a replay (its
    error-state set-up and LAPACK's code cold), 3 % of the replaying process. The verdict can
    differ from LAPACK's only on a pivot within rounding of zero (the sums' order differs)."""
    P = core[N_X:_CORE_ACC].reshape((N_ERR, N_ERR))
    L = np.zeros((N_ERR, N_ERR))
    for j in range(N_ERR):
        d = P[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        ljj = math.sqrt(d)
        L[j, j] = ljj
        for i in range(j + 1, N_ERR):
            s = P[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / ljj
    return True


@jit(cache=True)
def propagate_core(t_s, f_b, w_b, core, qdiag, cov_step_s):
    """Propagate the core array over IMU samples ``t_s`` (N,), ``f_b`` (N, 3), ``w_b`` (N, 3).

    The caller guarantees ``t_s`` strictly increasing, after the state time, finite and
    without gaps (checked vectorised before). The covariance is stepped every
    ``cov_step_s``; each step also goes into the clones' map (:func:`flush_core`)."""
    _propagate_span(t_s, f_b, w_b, 0, t_s.shape[0], core, qdiag, cov_step_s)


@jit(cache=True)
def _propagate_span(t_s, f_b, w_b, start, stop, core, qdiag, cov_step_s):
    """:func:`propagate_core` over the samples ``start`` to ``stop`` (excluded)."""
    x, P, acc, clock = core_views(core)
    R0 = np.empty((3, 3))
    R1 = np.empty((3, 3))
    for k in range(start, stop):
        dt = t_s[k] - clock[0]
        strapdown_step(x, f_b[k], w_b[k], dt, acc, R0, R1)
        clock[0] = t_s[k]
        if clock[0] - clock[1] >= cov_step_s - 1e-9:
            flush_core(core, qdiag)


@jit(cache=True)
def ins_run(t_s, f_b, w_b, start, core, qdiag, cov_step_s, next_lv_t, inertial_n, gap_s, rest, rest_window_s,
            max_speed_m_s):
    """One piece of an IMU run in INS mode (:meth:`adaptnav.fusion.eskf.Estimator._imu_pieces`):
    from sample ``start`` to the end of the run, or through the last sample at or before the
    next learned-velocity epoch ``next_lv_t`` (at least one sample), propagated as
    :func:`propagate_core` does; the free-inertial position and velocity ``inertial_n``
    (north, east, down (m), then (m/s)) advanced by the strapdown's change plus their offset
    from the corrected ones times the time (the arithmetic of the Python it replaces, in its
    order). Returns ``(stop, lv_due, rest_window_done, ok)``: the index after the piece; the
    state reached the learned-velocity epoch; for ``start == 0`` with ``rest_window_s ≥ 0``,
    the stationary-detection window ``rest`` (:func:`accumulate_rest_window`, which takes the
    whole run first) spans ``rest_window_s``; ``ok`` the state guard (:func:`core_ok`) after a
    last piece (else True).

    ``gap_s > 0`` and ``start == 0``: the run is first checked (:func:`imu_clean`: finite,
    after the state time, no gap); not clean, nothing is touched and ``stop`` is −1.

    Why one call: the IMU run is the replay's commonest item; its check, propagation,
    free-inertial bookkeeping, rest window and guard were four compiled calls and ~10 µs of
    Python glue between them."""
    n = t_s.shape[0]
    x, P, acc, clock = core_views(core)
    window_done = False
    if start == 0:
        if gap_s > 0.0 and not imu_clean(t_s, f_b, w_b, clock[0], gap_s):
            return -1, False, False, False
        if rest_window_s >= 0.0 and n > 0:
            if not np.isfinite(rest[0]):
                rest[0] = t_s[0]
            accumulate_rest_window(rest, f_b, w_b)
            window_done = not (t_s[n - 1] - rest[0] < rest_window_s)
    stop = n
    lv_due = False
    if next_lv_t <= t_s[n - 1]:
        stop = 0
        while stop < n and t_s[stop] <= next_lv_t:  # searchsorted(side="right") on rising times
            stop += 1
        if stop < start + 1:
            stop = start + 1
        lv_due = True
    t0 = clock[0]
    q0, q1, q2 = x[_X_POS], x[_X_POS + 1], x[_X_POS + 2]
    u0, u1, u2 = x[_X_VEL], x[_X_VEL + 1], x[_X_VEL + 2]
    _propagate_span(t_s, f_b, w_b, start, stop, core, qdiag, cov_step_s)
    dt = clock[0] - t0
    inertial_n[0] = inertial_n[0] + ((x[_X_POS] - q0) + (inertial_n[3] - u0) * dt)
    inertial_n[1] = inertial_n[1] + ((x[_X_POS + 1] - q1) + (inertial_n[4] - u1) * dt)
    inertial_n[2] = inertial_n[2] + ((x[_X_POS + 2] - q2) + (inertial_n[5] - u2) * dt)
    inertial_n[3] = inertial_n[3] + (x[_X_VEL] - u0)
    inertial_n[4] = inertial_n[4] + (x[_X_VEL + 1] - u1)
    inertial_n[5] = inertial_n[5] + (x[_X_VEL + 2] - u2)
    lv_due = lv_due and clock[0] >= next_lv_t
    ok = True
    if stop >= n and not lv_due:
        ok = core_ok(core, max_speed_m_s)
    return stop, lv_due, window_done, ok


@jit(cache=True)
def inject_error(x, dx, P):
    """x ← x ⊕ δx and the ESKF covariance reset ``P ← G P Gᵀ``."""
    for i in range(3):
        x[_X_POS + i] += dx[_E_POS + i]
        x[_X_VEL + i] += dx[_E_VEL + i]
    rx, ry, rz = dx[_E_ATT], dx[_E_ATT + 1], dx[_E_ATT + 2]
    d0, d1, d2, d3 = rotvec_quat(rx, ry, rz)
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
    # the local error has the opposite sign), the identity elsewhere: G P Gᵀ changes the
    # attitude rows (G_θθ P_θ·) and then columns (P_·θ G_θθᵀ) only — every other entry is
    # what G @ P @ G.T gives exactly, the attitude ones to the last bits (its BLAS sums
    # differ), for 2 × 18 × 9 products instead of 2 × 18³ and two 18 × 18 temporaries (~1.7 µs
    # of every fused update; 2.0 µs → see tests/fusion/test_aid_kernels.py)
    n = P.shape[0]
    th = _E_ATT
    g01, g02, g10, g12, g20, g21 = -0.5 * rz, 0.5 * ry, 0.5 * rz, -0.5 * rx, -0.5 * ry, 0.5 * rx
    for j in range(n):
        p0, p1, p2 = P[th, j], P[th + 1, j], P[th + 2, j]
        P[th, j] = p0 + g01 * p1 + g02 * p2
        P[th + 1, j] = g10 * p0 + p1 + g12 * p2
        P[th + 2, j] = g20 * p0 + g21 * p1 + p2
    for i in range(n):
        p0, p1, p2 = P[i, th], P[i, th + 1], P[i, th + 2]
        P[i, th] = p0 + p1 * g01 + p2 * g02
        P[i, th + 1] = p0 * g10 + p1 + p2 * g12
        P[i, th + 2] = p0 * g20 + p1 * g21 + p2


@jit(cache=True)
def _times_small(A, B):
    """``A @ B`` for A (n×m), B (m×m) with m ≤ 3, as explicit loops (no BLAS call)."""
    n, m = A.shape[0], B.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for b in range(m):
            acc = 0.0
            for a in range(B.shape[0]):
                acc += A[i, a] * B[a, b]
            out[i, b] = acc
    return out


@jit(cache=True)
def gated_update(P, y, H, R, gate, dx_out, s_diag_out):
    """Chi-square gate, then the Joseph-form update (m ≤ 3 measurements, explicit loops).

    ``P ← (I−KH) P (I−KH)ᵀ + K R Kᵀ``, expanded (valid for any gain K) as
    ``P − K (PHᵀ)ᵀ − (PHᵀ) Kᵀ + K S Kᵀ``, which costs O(n² m) instead of O(n³).
    Returns ``(nis, fused)``: ``yᵀ S⁻¹ y`` and whether ``nis ≤ gate`` (NaN ⇒ False);
    ``dx_out`` ← K y (zeros if rejected), ``s_diag_out`` ← diag S.
    """
    return gated_update_gain(P, y, H, R, gate, dx_out, s_diag_out, np.zeros((P.shape[0], y.shape[0])))


@jit(cache=True)
def gated_update_gain(P, y, H, R, gate, dx_out, s_diag_out, k_out):
    """:func:`gated_update`, the gain K (n × m) also into ``k_out`` when fused."""
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
    K = _times_small(PHt, Sinv)
    k_out[:, :] = K
    KS = _times_small(K, S)
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
    """:func:`fuse` on the core array; while clones are tracked, the flush goes into their map
    (:func:`flush_core`) and so does the update: ``M ← G (I − K H) M``."""
    x, P, acc, clock = core_views(core)
    if flush:
        flush_core(core, qdiag)
    n, m = P.shape[0], y.shape[0]
    K = np.zeros((n, m))
    nis, fused = gated_update_gain(P, y, H, R, gate, dx, s_diag_out, K)
    if fused:
        inject_error(x, dx, P)
        if core[_CORE_TRACK] > 0.0:
            M = core[_CORE_M:_CORE_TRACK].reshape((N_ERR, N_ERR))
            HM = np.zeros((m, n))
            for a in range(m):
                for j in range(n):
                    acc_ = 0.0
                    for i in range(n):
                        acc_ += H[a, i] * M[i, j]
                    HM[a, j] = acc_
            for i in range(n):
                for j in range(n):
                    acc_ = M[i, j]
                    for a in range(m):
                        acc_ -= K[i, a] * HM[a, j]
                    M[i, j] = acc_
            # the reset G = I + ½[δθ]× changes the attitude rows only
            rx, ry, rz = 0.5 * dx[_E_ATT], 0.5 * dx[_E_ATT + 1], 0.5 * dx[_E_ATT + 2]
            th = _E_ATT
            for j in range(n):
                m0, m1, m2 = M[th, j], M[th + 1, j], M[th + 2, j]
                M[th, j] = m0 - rz * m1 + ry * m2
                M[th + 1, j] = m1 + rz * m0 - rx * m2
                M[th + 2, j] = m2 - ry * m0 + rx * m1
    return nis, fused


# The estimator's scratch beside the core, one array (``Estimator._work``): the process noise,
# the latest update's correction and outputs, the depth's and the heading's rows, the DVL's
# bottom-track model. The compiled calls of the commonest aid samples take it whole instead of
# three to eight arrays of their own: every array argument is a type, dtype, shape and flags test
# in the kernel's guard (adaptnav.kernels) and an unboxing in the compiled function's wrapper,
# ~0.4 µs each per call; views of it are the estimator's ``_qdiag``, ``_dx``, ... (one memory).
WORK_QDIAG = 0                                # qdiag (N_ERR)
WORK_DX = WORK_QDIAG + N_ERR                  # the error-state correction of the latest update (N_ERR)
WORK_OUT = WORK_DX + N_ERR                    # a scalar update's (y, S, nis); the DVL's innovation (3)
WORK_SDIAG = WORK_OUT + 3                     # diag S of a vector update (3)
WORK_H_DEPTH = WORK_SDIAG + 3                 # the depth's Jacobian row (N_ERR, constant)
WORK_H_HEADING = WORK_H_DEPTH + N_ERR         # the heading's row (N_ERR; its attitude part per sample)
WORK_DVL_H = WORK_H_HEADING + N_ERR           # the DVL's bottom-track model: H (3 × N_ERR), ...
WORK_DVL_SMALL_H = WORK_DVL_H + 3 * N_ERR     # ... h (3), ...
WORK_DVL_R = WORK_DVL_SMALL_H + 3             # ... R (3 × 3, row-major), ...
WORK_DVL_Z = WORK_DVL_R + 9                   # ... z (3) and ...
WORK_DVL_AUX = WORK_DVL_Z + 3                 # ... what the calibration takes (6): _dvl_bottom_track's
WORK_SIZE = WORK_DVL_AUX + 6
# the DVL's installation for :func:`dvl_bottom_track_core`, one array: lever arm (3), R_db and
# R_db [l]× (3 × 3 each, row-major)
DVL_CONST_SIZE = 21


@jit(cache=True)
def fuse_scalar_core(core, work, z, h, row, var, angular, gate, flush, max_speed_m_s):
    """One scalar measurement on the core array, the estimator's whole per-sample numeric path
    in one call: the innovation ``y = z − h`` (``h`` = h(x̂), wrapped to [−π, π) as
    :func:`~adaptnav.fusion.frames.wrap_angle` does when ``angular``), :func:`fuse_core` with
    the row ``H`` (1 × 18) at ``work[row:row + 18]`` and
    variance ``var``, then the guard :func:`core_ok`; the process noise and the correction are
    ``work``'s (:data:`WORK_QDIAG`, :data:`WORK_DX`).

    Why: depth and heading (a sample each every 0.1 s) paid ~20 µs of Python per sample
    around ~1 µs of arithmetic, mostly numpy glue and three guarded kernel calls; the depth's
    model stays its aid module's, the heading has its own kernel (:func:`fuse_heading_core`,
    its model computed inside). ``work[WORK_OUT:WORK_OUT + 3]`` ← ``(y, S, nis)``; returns
    ``(fused, ok)``, ``ok`` as :func:`core_ok`.
    """
    H = work[row:row + N_ERR].reshape((1, N_ERR))
    return _fuse_scalar(core, work[WORK_QDIAG:WORK_QDIAG + N_ERR], z, h, H, var, angular, gate,
                        work[WORK_DX:WORK_DX + N_ERR], work[WORK_OUT:WORK_OUT + 3], flush, max_speed_m_s)


@jit(cache=True)
def _fuse_scalar(core, qdiag, z, h, H, var, angular, gate, dx, out, flush, max_speed_m_s):
    """:func:`fuse_scalar_core`'s body, also :func:`fuse_heading_core`'s: called there with a
    constant ``angular``, numba types it ``Literal[bool]`` — a second signature, which keeps a
    kernel out of the ahead-of-time build (``adaptnav.kernels._widen``); this one is only
    called from compiled code."""
    y = z - h
    if angular:
        y = (y + np.pi) % (2.0 * np.pi) - np.pi
    ys = np.empty(1)
    ys[0] = y
    R = np.empty((1, 1))
    R[0, 0] = var
    s_diag = np.empty(1)
    nis, fused = fuse_core(core, qdiag, ys, H, R, gate, dx, s_diag, flush)
    out[0] = y
    out[1] = s_diag[0]
    out[2] = nis
    return fused, core_ok(core, max_speed_m_s)


@jit(cache=True)
def fuse_vector_core(core, work, z, h, H, R, gate, flush, max_speed_m_s):
    """A measurement of a few rows (at most 3) without angular components (the DVL's three) on
    the core array in one call: ``y = z − h`` (``h`` = h(x̂)) into ``work``'s :data:`WORK_OUT`,
    :func:`fuse_core` with ``H`` (m × 18) and ``R`` (m × m), diag S into :data:`WORK_SDIAG`,
    the process noise and the correction ``work``'s, then the guard :func:`core_ok`.

    Why: the vector sibling of :func:`fuse_scalar_core` for the DVL (a sample every 0.2 s),
    whose general path paid the innovation, the guard and their numpy glue in Python; the
    elementwise subtraction rounds as numpy's. Returns ``(nis, fused, ok)``.
    """
    m = z.shape[0]
    y_out = work[WORK_OUT:WORK_OUT + m]
    for i in range(m):
        y_out[i] = z[i] - h[i]
    nis, fused = fuse_core(core, work[WORK_QDIAG:WORK_QDIAG + N_ERR], y_out, H, R, gate, work[WORK_DX:WORK_DX + N_ERR],
                           work[WORK_SDIAG:WORK_SDIAG + m], flush)
    return nis, fused, core_ok(core, max_speed_m_s)


_X_CUR = X_CUR.start  # the current (north, east) in the nominal state


@jit(cache=True)
def dvl_bottom_track_core(core, consts, work, vel_d0, vel_d1, vel_d2, scale_error, misalignment_rad, sigma_m_s,
                          lever_arm_sigma_m):
    """:func:`_dvl_bottom_track` of the core's state (``x``, and ``ω̂_b`` from its accumulators)
    with the installation packed in ``consts`` (:data:`DVL_CONST_SIZE`: lever arm, ``R_db``,
    ``R_db [l]×``), the model written into ``work``'s ``WORK_DVL_*`` slots; returns the six
    numbers of ``aux`` (the calibration's). Why: the estimator's compiled DVL path
    (:meth:`adaptnav.fusion.eskf.Estimator._fast_dvl`) passes three arrays instead of ten, and
    allocates none (~4 µs of guards, unboxing and arrays per DVL sample)."""
    aux = work[WORK_DVL_AUX:WORK_DVL_AUX + 6]
    _dvl_bottom_track(core[0:N_X], core[_CORE_OMEGA:_CORE_OMEGA + 3], consts[0:3], consts[3:12].reshape((3, 3)),
                      consts[12:21].reshape((3, 3)), vel_d0, vel_d1, vel_d2, scale_error, misalignment_rad,
                      sigma_m_s, lever_arm_sigma_m, work[WORK_DVL_H:WORK_DVL_H + 3 * N_ERR].reshape((3, N_ERR)),
                      work[WORK_DVL_SMALL_H:WORK_DVL_SMALL_H + 3], work[WORK_DVL_R:WORK_DVL_R + 9].reshape((3, 3)),
                      work[WORK_DVL_Z:WORK_DVL_Z + 3], aux)
    return aux[0], aux[1], aux[2], aux[3], aux[4], aux[5]


@jit(cache=True)
def _dvl_bottom_track(x, omega_b, lever_b, R_db, lever_block, vel_d0, vel_d1, vel_d2, scale_error,
                      misalignment_rad, sigma_m_s, lever_arm_sigma_m, H_out, h_out, R_out, z_out, aux_out):
    """The DVL's bottom-track model (:func:`adaptnav.fusion.aiding.dvl.bottom_track`), the body of
    :func:`dvl_bottom_track_core` (only called from compiled code): ``H`` (3 × 18, every entry
    written), ``h`` = h(x̂) and ``R`` of
    :func:`~adaptnav.fusion.aiding.dvl.measure` (``R_nb`` from ``x``'s quaternion as
    :func:`~adaptnav.fusion.aiding.common.dcm`; ``lever_block`` = ``R_db [l]×``) plus the
    lever arm's doubt (:func:`~adaptnav.fusion.aiding.dvl.lever_arm_doubt`, when
    ``lever_arm_sigma_m`` > 0); ``z`` the head velocity corrected with ``(s, ψ)``
    (:func:`~adaptnav.fusion.aiding.dvl.correct_velocity`); ``aux_out`` ← what the calibration
    takes: the uncorrected velocity rotated to n (north, east), and in the heading-aligned
    level frame its forward and lateral parts, the heading and the current along it.

    Why: the same sums as the numpy model (written in its order, without BLAS's fused
    multiply-adds: they differ in the last bits) for ~40 µs less numpy glue per DVL sample
    (a sample every 0.2 s; 62 → see the estimator's ``_fast_dvl``)."""
    R = np.empty((3, 3))
    _dcm(x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3], R)
    v0, v1, v2 = x[_X_VEL], x[_X_VEL + 1], x[_X_VEL + 2]
    # A = R_db R_nbᵀ
    A = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            A[i, j] = R_db[i, 0] * R[j, 0] + R_db[i, 1] * R[j, 1] + R_db[i, 2] * R[j, 2]
    for i in range(3):
        for j in range(N_ERR):
            H_out[i, j] = 0.0
        for j in range(3):
            H_out[i, _E_VEL + j] = A[i, j]
            H_out[i, _E_BG + j] = lever_block[i, j]
        # A [v]×, [v]× = [[0, −v2, v1], [v2, 0, −v0], [−v1, v0, 0]]
        H_out[i, _E_ATT] = A[i, 1] * v2 - A[i, 2] * v1
        H_out[i, _E_ATT + 1] = -A[i, 0] * v2 + A[i, 2] * v0
        H_out[i, _E_ATT + 2] = A[i, 0] * v1 - A[i, 1] * v0
    o0, o1, o2 = omega_b[0], omega_b[1], omega_b[2]
    l0, l1, l2 = lever_b[0], lever_b[1], lever_b[2]
    vb0 = R[0, 0] * v0 + R[1, 0] * v1 + R[2, 0] * v2 + (o1 * l2 - o2 * l1)
    vb1 = R[0, 1] * v0 + R[1, 1] * v1 + R[2, 1] * v2 + (o2 * l0 - o0 * l2)
    vb2 = R[0, 2] * v0 + R[1, 2] * v1 + R[2, 2] * v2 + (o0 * l1 - o1 * l0)
    for i in range(3):
        h_out[i] = R_db[i, 0] * vb0 + R_db[i, 1] * vb1 + R_db[i, 2] * vb2
    s2 = sigma_m_s * sigma_m_s
    for i in range(3):
        for j in range(3):
            R_out[i, j] = s2 if i == j else 0.0
    if lever_arm_sigma_m > 0.0:
        # σ² (R_db [ω]×)(R_db [ω]×)ᵀ
        B = np.empty((3, 3))
        for i in range(3):
            B[i, 0] = R_db[i, 1] * o2 - R_db[i, 2] * o1
            B[i, 1] = -R_db[i, 0] * o2 + R_db[i, 2] * o0
            B[i, 2] = R_db[i, 0] * o1 - R_db[i, 1] * o0
        l2s = lever_arm_sigma_m * lever_arm_sigma_m
        for i in range(3):
            for j in range(3):
                R_out[i, j] += l2s * (B[i, 0] * B[j, 0] + B[i, 1] * B[j, 1] + B[i, 2] * B[j, 2])
    # the uncorrected velocity in n: R_nb (R_dbᵀ v_d)
    t0 = R_db[0, 0] * vel_d0 + R_db[1, 0] * vel_d1 + R_db[2, 0] * vel_d2
    t1 = R_db[0, 1] * vel_d0 + R_db[1, 1] * vel_d1 + R_db[2, 1] * vel_d2
    t2 = R_db[0, 2] * vel_d0 + R_db[1, 2] * vel_d1 + R_db[2, 2] * vel_d2
    vn = R[0, 0] * t0 + R[0, 1] * t1 + R[0, 2] * t2
    ve = R[1, 0] * t0 + R[1, 1] * t1 + R[1, 2] * t2
    c0, s0 = R[0, 0], R[1, 0]
    norm = np.hypot(c0, s0)
    ch, sh = c0 / norm, s0 / norm
    aux_out[0] = vn
    aux_out[1] = ve
    aux_out[2] = ch * vn + sh * ve
    aux_out[3] = -sh * vn + ch * ve
    aux_out[4] = np.arctan2(s0, c0)
    aux_out[5] = ch * x[_X_CUR] + sh * x[_X_CUR + 1]
    # R_z(ψ) v_d / (1 + s)
    k = 1.0 / (1.0 + scale_error)
    cp, sp = np.cos(misalignment_rad) * k, np.sin(misalignment_rad) * k
    z_out[0] = cp * vel_d0 - sp * vel_d1
    z_out[1] = sp * vel_d0 + cp * vel_d1
    z_out[2] = vel_d2 * k


@jit(cache=True)
def _bisect_right(srt, value, lo, hi):
    """``bisect.bisect_right`` of ``value`` in the sorted ``srt[lo:hi]`` (median_window_push's)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if value < srt[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@jit(cache=True)
def median_window_push(window, value):
    """Push ``value`` into a sliding window kept with its values sorted, and return the
    window's count and median (numpy.median's value: the middle one, or the mean of the two
    middle ones). ``window`` (2 + 2W,): the count, the index of the oldest, the W values in
    arrival order (a ring), the same sorted. The oldest leaves a full window from the leftmost
    of its equals (``del s[bisect_left(s, oldest)]``), the new one goes after its equals
    (``bisect.insort``): the same sorted values as :class:`~adaptnav.fusion.aiding.depth.DepthNoise`
    kept in a Python list (~6 µs per depth in a replay, bisections over boxed floats).
    """
    W = (window.shape[0] - 2) // 2
    n = int(window[0])
    ring = window[2:2 + W]
    srt = window[2 + W:2 + 2 * W]
    if n == W:
        head = int(window[1])
        old = ring[head]
        ring[head] = value
        window[1] = float((head + 1) % W)
        lo, hi = 0, n  # bisect_left
        while lo < hi:
            mid = (lo + hi) // 2
            if srt[mid] < old:
                lo = mid + 1
            else:
                hi = mid
        # the new value's place among the others (before the oldest's place when smaller, after
        # it else), and only the values between the two places move, by one (the removal's and
        # the insertion's shifts were each up to W moves: the same sorted values)
        if value < old:
            at = _bisect_right(srt, value, 0, lo)
            for i in range(lo, at, -1):
                srt[i] = srt[i - 1]
            srt[at] = value
        else:
            at = _bisect_right(srt, value, lo + 1, n) - 1
            for i in range(lo, at):
                srt[i] = srt[i + 1]
            srt[at] = value
    else:
        ring[(int(window[1]) + n) % W] = value
        at = _bisect_right(srt, value, 0, n)  # (insort)
        for i in range(n, at, -1):
            srt[i] = srt[i - 1]
        srt[at] = value
        n += 1
        window[0] = float(n)
    med = srt[n // 2] if n % 2 else (srt[n // 2 - 1] + srt[n // 2]) / 2.0
    return n, med


@jit(cache=True)
def heading_row(x):
    """:func:`adaptnav.fusion.aiding.heading.yaw_row` compiled: ``(ψ, ∂ψ/∂δθ_x, ∂ψ/∂δθ_y)`` of
    the nominal state ``x``, the same operations and libm's trigonometry (as its ``math.*``)."""
    w, a, b, c = x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3]
    r00 = 1 - 2 * (b * b + c * c)
    r10 = 2 * (a * b + w * c)
    r20 = 2 * (a * c - w * b)
    yaw = math.atan2(r10, r00)
    pitch = -math.asin(1.0 if r20 > 1.0 else (-1.0 if r20 < -1.0 else r20))
    tp = math.tan(pitch)
    return yaw, math.cos(yaw) * tp, math.sin(yaw) * tp


@jit(cache=True)
def fuse_heading_core(core, work, z, var, gate, flush, max_speed_m_s):
    """:func:`fuse_scalar_core` of a heading ``z`` (rad) with its model computed here from the
    core's state (:func:`heading_row`): ``h`` = ψ and the attitude part of the row ``H``
    (``work``'s :data:`WORK_H_HEADING`, written; its other entries the caller's). Why: the yaw
    row in Python was ~2.5 µs of a heading's ~20 in a replay (a heading every 0.1 s). Returns
    ``(fused, ok)``."""
    H = work[WORK_H_HEADING:WORK_H_HEADING + N_ERR].reshape((1, N_ERR))
    yaw, h_x, h_y = heading_row(core[0:N_X])
    H[0, _E_ATT] = h_x
    H[0, _E_ATT + 1] = h_y
    H[0, _E_ATT + 2] = 1.0
    return _fuse_scalar(core, work[WORK_QDIAG:WORK_QDIAG + N_ERR], z, yaw, H, var, True, gate,
                        work[WORK_DX:WORK_DX + N_ERR], work[WORK_OUT:WORK_OUT + 3], flush, max_speed_m_s)


from .state import ACC_OMEGA, CUR, KS, X_KS  # noqa: E402  (the learned velocity's kernel)

_E_CUR, _E_KS, _X_KS = CUR.start, KS.start, X_KS
_CORE_OMEGA = _CORE_ACC + ACC_OMEGA.start  # the bias-corrected rate ω̂_b in the core array
# the learned velocity's numbers (:func:`lv_epoch`'s ``p``, packed once per release and config by
# :func:`adaptnav.fusion.aiding.learned_velocity.kernel_params`): the motion model's, the
# estimator's additions', the surge variance's adaptation's, and 2.0 (see there)
LV_K_V, LV_TURN_SPEED_LOSS, LV_SWAY_PER_TURN, LV_SWAY_PER_SURGE = 0, 1, 2, 3
LV_VAR_VV, LV_VAR_VW, LV_VAR_V1, LV_VAR_S, LV_HEAVE_PER_SURGE = 4, 5, 6, 7, 8
LV_SIGMA_HEAVE, LV_VARIANCE_SCALE, LV_TRANSIENT_TIME, LV_COAST_MEAN_FRACTION = 9, 10, 11, 12
LV_COAST_SIGMA_PER_GAP, LV_TRANSIENT_SIGMA_PER_GAP, LV_SKID_SIGMA, LV_COAST_SKID_MAX = 13, 14, 15, 16
LV_SKID_MAX, LV_HEAVE_SIGMA_PER_VERTICAL_SPEED = 17, 18
LV_ADAPTIVE, LV_ALPHA, LV_MAX_SCALE, LV_SUSPEND_S, LV_TWO = 19, 20, 21, 22, 23
LV_N_PARAMS = 24
# :func:`lv_epoch`'s scratch ``buf``: z, y, diag S, h (3 each), R (3 × 3), H (3 × 18), row-major
LV_Z, LV_Y, LV_S, LV_H = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
LV_R, LV_JAC = slice(12, 21), slice(21, 21 + 3 * N_ERR)
LV_BUF_SIZE = 21 + 3 * N_ERR


@jit(cache=True)
def lv_epoch(core, qdiag, p, buf, dx, surge, sway, slow_surge, slow_sway, r_hat, has_r_hat, since_release_s, gate,
             flush):
    """The learned velocity's epoch in INS mode in one call: its measurement, the surge
    variance's adaptation and the update — ``Estimator._lv_measure(t, adapt=True)`` and
    ``Estimator._fuse``, whose numpy model (:func:`adaptnav.fusion.aiding.learned_velocity.measure`)
    and adaptation (:meth:`adaptnav.fusion.adaptive_noise.SurgeVariance.adapt`) stay the
    reference the tests compare this with.

    From the core's state and bias-corrected rate, ``p`` (:data:`LV_N_PARAMS`,) and the thrust's
    speeds ``surge``, ``sway``, ``slow_surge``, ``slow_sway`` (m/s; the estimator's ``_rpm[1, 2, 5,
    6]``): ``z``, ``h`` = h(x̂), ``H`` (3 × 18, every entry written) and ``R`` (the transient's,
    the skid's and the heave's variances added as the estimator adds them) into ``buf``
    (:data:`LV_Z`, :data:`LV_H`, :data:`LV_JAC`, :data:`LV_R`; what a velocity reset after a long
    rejection takes). With the adaptation on (``p[LV_ADAPTIVE]``) the covariance is propagated
    (:func:`flush_core`) and the estimate ``r_hat`` (m²/s²; ``has_r_hat`` False: none yet) takes
    this epoch's innovation; the surge variance is scaled to it unless the latest release is
    younger than ``p[LV_SUSPEND_S]`` (``since_release_s``). Then ``y = z − h`` (:data:`LV_Y`) and
    :func:`fuse_core` with ``gate`` (diag S into :data:`LV_S`, the correction into ``dx``; ``flush``
    True in INS mode — an argument: a constant would type :func:`fuse_core`'s ``Literal[bool]``, a
    second signature, which keeps it out of the ahead-of-time build).

    Returns ``(nis, fused, z₀, z₁, z₂, y₀, y₁, y₂, S₀₀, S₁₁, S₂₂, r_hat, has_r_hat)``: the status's
    numbers and the estimate, without a call to read them back.

    Why: the numpy model, its Measurement, the adaptation's ``h P hᵀ`` and the additions' copies
    were ~110 µs of Python steps per epoch in a replay (once a data second). The same operations
    in the same order, without BLAS's fused multiply-adds and sums (the yaw rate's dot, ``Rᵀ v``,
    ``Rᵀ [v]×``, ``h P hᵀ``: they differ in the last bits), squares through libm's ``pow`` as
    Python's ``x ** 2``, ``min``/``max`` as Python's (the first argument unless the second is
    smaller/larger)."""
    r_model, extra0, extra = _lv_model(core, p, buf, surge, sway, slow_surge, slow_sway)
    r00 = r_model
    if p[LV_ADAPTIVE] > 0.0:
        # SurgeVariance.adapt with the prior covariance: the estimate takes the innovation
        # less h P hᵀ and the transient's variance, capped; R₀₀ scaled up to it, never down
        x, P, acc, clock = core_views(core)
        flush_core(core, qdiag)
        hph = 0.0
        for j in range(N_ERR):
            hp = 0.0
            for i in range(N_ERR):
                hp += buf[21 + i] * P[i, j]
            hph += hp * buf[21 + j]
        y0 = buf[0] - buf[9]
        if np.isfinite(y0) and np.isfinite(hph):
            sample = y0 * y0 - hph - extra0
            cap = 100.0 * r_model * p[LV_MAX_SCALE]
            sample = cap if cap < sample else sample
            alpha = p[LV_ALPHA]
            r_hat = (1 - alpha) * r_hat + alpha * sample if has_r_hat else sample
            has_r_hat = True
            scale = r_hat / r_model
            scale = 1.0 if 1.0 > scale else scale
            scale = p[LV_MAX_SCALE] if p[LV_MAX_SCALE] < scale else scale
            if scale != 1.0 and since_release_s >= p[LV_SUSPEND_S]:
                r00 = r_model * scale
    if extra:
        r00 += extra0
    buf[12] = r00
    y = buf[3:6]
    for i in range(3):
        y[i] = buf[i] - buf[9 + i]
    R = buf[12:21].reshape((3, 3))
    H = buf[21:21 + 3 * N_ERR].reshape((3, N_ERR))
    nis, fused = fuse_core(core, qdiag, y, H, R, gate, dx, buf[6:9], flush)
    return (nis, fused, buf[0], buf[1], buf[2], buf[3], buf[4], buf[5], buf[6], buf[7], buf[8],
            r_hat, has_r_hat)


@jit(cache=True)
def _lv_model(core, p, buf, surge, sway, slow_surge, slow_sway):
    """:func:`lv_epoch`'s measurement: ``z``, ``h``, ``H`` and ``R`` into ``buf`` with ``R₀₀`` =
    σ_V² s + e₀ (s the ``variance_scale``, e₀ the transient's surge variance) when an addition
    was made, else σ_V² s. Returns ``(σ_V² s, e₀ or 0, an addition made)``."""
    x = core[0:N_X]
    two = p[LV_TWO]
    R = np.empty((3, 3))
    _dcm(x[_X_Q], x[_X_Q + 1], x[_X_Q + 2], x[_X_Q + 3], R)
    o = _CORE_OMEGA
    w = R[2, 0] * core[o] + R[2, 1] * core[o + 1] + R[2, 2] * core[o + 2]  # the yaw rate
    # a coast (the thrust fell below the slow lag's speed): its speed between the two
    coast = p[LV_TRANSIENT_TIME] > 0 and abs(slow_surge) > abs(surge)
    speed = surge
    if coast:
        speed += p[LV_COAST_MEAN_FRACTION] * (slow_surge - surge)
    k_v = p[LV_K_V]
    w2 = w ** two
    model = k_v * speed * (1.0 - p[LV_TURN_SPEED_LOSS] * w2)
    sway_model = k_v * sway
    skid = p[LV_SWAY_PER_TURN] * speed * w + p[LV_SWAY_PER_SURGE] * model
    var_v = speed ** two * p[LV_VAR_VV] + w2 * p[LV_VAR_VW] + p[LV_VAR_V1]
    vs = p[LV_VARIANCE_SCALE]
    r_model = var_v * vs
    r11 = (p[LV_VAR_S] + sway ** two * p[LV_VAR_VV]) * vs
    r22 = p[LV_SIGMA_HEAVE] ** two * vs
    h_w = p[LV_HEAVE_PER_SURGE]
    r0, r1, r2 = x[_X_VEL] - x[_X_CUR], x[_X_VEL + 1] - x[_X_CUR + 1], x[_X_VEL + 2]
    H = buf[21:21 + 3 * N_ERR].reshape((3, N_ERR))
    for i in range(3):
        for j in range(N_ERR):
            H[i, j] = 0.0
        for j in range(3):
            H[i, _E_VEL + j] = R[j, i]
        # Rᵀ [rel]×, [rel]× = [[0, −r2, r1], [r2, 0, −r0], [−r1, r0, 0]]
        H[i, _E_ATT] = R[1, i] * r2 - R[2, i] * r1
        H[i, _E_ATT + 1] = -R[0, i] * r2 + R[2, i] * r0
        H[i, _E_ATT + 2] = R[0, i] * r1 - R[1, i] * r0
        H[i, _E_CUR] = -R[0, i]
        H[i, _E_CUR + 1] = -R[1, i]
    for j in range(N_ERR):
        H[2, j] -= h_w * H[0, j]
    H[0, _E_KS] = -model
    H[1, _E_KS] = -sway_model
    vb0 = R[0, 0] * r0 + R[1, 0] * r1 + R[2, 0] * r2
    vb1 = R[0, 1] * r0 + R[1, 1] * r1 + R[2, 1] * r2
    vb2 = R[0, 2] * r0 + R[1, 2] * r1 + R[2, 2] * r2
    vb2 -= h_w * vb0
    ks1 = x[_X_KS] - 1.0
    vb0 -= ks1 * model
    vb1 -= ks1 * sway_model
    buf[0], buf[1], buf[2] = model, sway_model + skid, 0.0
    buf[9], buf[10], buf[11] = vb0, vb1, vb2
    # the variance the model leaves unknown on this vehicle: a thrust change settling, a skid
    e0, e1 = 0.0, 0.0
    extra = False
    ks_abs = abs(x[_X_KS])
    if p[LV_TRANSIENT_TIME] > 0:
        scale = ks_abs * k_v
        g_surge = p[LV_COAST_SIGMA_PER_GAP] if coast else p[LV_TRANSIENT_SIGMA_PER_GAP]
        e0 = (scale * g_surge * (surge - slow_surge)) ** two
        e1 = (scale * p[LV_TRANSIENT_SIGMA_PER_GAP] * (sway - slow_sway)) ** two
        extra = not (e0 == 0.0 and e1 == 0.0)
    if p[LV_SKID_SIGMA] > 0:
        u = surge
        if p[LV_TRANSIENT_TIME] > 0:
            a, b = abs(surge), abs(slow_surge)
            u = b if b > a else a  # max(a, b)
        cap = p[LV_COAST_SKID_MAX] if coast else p[LV_SKID_MAX]
        g = p[LV_SKID_SIGMA] * abs(w)
        g = cap if cap < g else g  # min(g, cap)
        s_var = (ks_abs * k_v * u * g) ** two
        if s_var > 0.0:
            if extra:
                e1 = e1 + s_var
            else:
                e0, e1 = 0.0, s_var
            extra = True
    heave = (p[LV_HEAVE_SIGMA_PER_VERTICAL_SPEED] * x[_X_VEL + 2]) ** two
    r00 = r_model
    if extra or heave > 0.0:
        if extra:
            r00 += e0
            r11 += e1
        r22 += heave
    for i in range(9):
        buf[12 + i] = 0.0
    buf[12], buf[16], buf[20] = r00, r11, r22
    return r_model, e0 if extra else 0.0, extra
