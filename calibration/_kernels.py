r"""numba kernels for the calibrator's hot loops (same equations as :mod:`adaptnav.fusion.motion_model`).

* :func:`transition_logpdf_scalar` — ``log p(x' | x)`` of the motion model with the lateral
  term and the Jacobian ``log(c² δt)`` (see :func:`adaptnav.fusion.motion_model.transition_logpdf`).
* :func:`move` — :func:`adaptnav.fusion.motion_model.propagate` of resampled particles with
  velocities built from given standard normals (the normals come from the caller's
  ``numpy.random.Generator``, so results stay reproducible and generator-driven).
* :func:`range_loglik` — :class:`adaptnav.calibration.sensors.RangeObservation`.
* :func:`heading_loglik` — :class:`adaptnav.calibration.sensors.HeadingObservation`.
* :func:`backward_mcmc`, :func:`backward_exact` — the FFBSi backward passes of
  :mod:`adaptnav.calibration.smoother` given pre-drawn random numbers.

``pvec`` packs :class:`MotionParams` and the sea current as ``(var_vv, var_vw, var_v1, var_wv,
var_ww, var_w1, var_s, k_v, b_w, u_n, u_e, turn_about_mean)`` (:func:`pack`); the current (m/s) adds
``u δt`` to each step's ground displacement.
"""
from __future__ import annotations

import math

from adaptnav.kernels import jit
import numpy as np

LOG_2PI = math.log(2.0 * math.pi)


def pack(params, current_n_m_s=None, turn_about_mean: bool = False) -> np.ndarray:
    """(12,) parameter vector of the kernels; ``current_n_m_s`` (2,) m/s, default zero.

    ``turn_about_mean``: the transition density takes the heading change on the branch
    nearest the expected turn ``(w + b_W) δt`` instead of (−π, π] (see
    :func:`adaptnav.fusion.motion_model.invert_step`'s ``turn_ref_rad``); element 11 is the flag.
    """
    un, ue = (0.0, 0.0) if current_n_m_s is None else (float(current_n_m_s[0]), float(current_n_m_s[1]))
    return np.array([params.var_vv, params.var_vw, params.var_v1, params.var_wv, params.var_ww,
                     params.var_w1, params.var_s, params.k_v, params.b_w, un, ue,
                     1.0 if turn_about_mean else 0.0])


@jit(cache=True, inline="always")
def _chord(W, dt):
    a = 0.5 * W * dt
    if abs(a) < 1e-8:
        return dt * (1.0 - a * a / 6.0)
    return dt * math.sin(a) / a


@jit(cache=True)
def transition_logpdf_scalar(x0, y0, th0, x1, y1, th1, v, w, dt, p):
    ref = p[11] * (w + p[8]) * dt if p.shape[0] > 11 else 0.0  # branch centre (pack)
    dth = (th1 - th0 - ref + math.pi) % (2.0 * math.pi) - math.pi + ref
    W = dth / dt
    phi = th0 + 0.5 * dth
    c = _chord(W, dt)
    dx = x1 - x0 - p[9] * dt
    dy = y1 - y0 - p[10] * dt
    cp = math.cos(phi)
    sp = math.sin(phi)
    V = (cp * dx + sp * dy) / c
    S = (-sp * dx + cp * dy) / c
    v2 = v * v
    w2 = w * w
    var_V = v2 * p[0] + w2 * p[1] + p[2]
    var_W = v2 * p[3] + w2 * p[4] + p[5]
    var_S = p[6]
    eV = V - p[7] * v
    eW = W - (w + p[8])
    ll = -0.5 * (eV * eV / var_V + math.log(var_V) + eW * eW / var_W + math.log(var_W)
                 + S * S / var_S + math.log(var_S) + 3.0 * LOG_2PI)
    return ll - math.log(c * c * dt)


@jit(cache=True)
def move(poses, idx, z, v, w, dt, p):
    n = idx.shape[0]
    out = np.empty((n, 3))
    v2 = v * v
    w2 = w * w
    sdV = math.sqrt(v2 * p[0] + w2 * p[1] + p[2])
    sdW = math.sqrt(v2 * p[3] + w2 * p[4] + p[5])
    sdS = math.sqrt(p[6])
    mV = p[7] * v
    mW = w + p[8]
    dxc = p[9] * dt
    dyc = p[10] * dt
    for i in range(n):
        j = idx[i]
        V = mV + sdV * z[0, i]
        W = mW + sdW * z[1, i]
        S = sdS * z[2, i]
        th = poses[j, 2]
        phi = th + 0.5 * W * dt
        c = _chord(W, dt)
        cp = math.cos(phi)
        sp = math.sin(phi)
        out[i, 0] = poses[j, 0] + c * (cp * V - sp * S) + dxc
        out[i, 1] = poses[j, 1] + c * (sp * V + cp * S) + dyc
        out[i, 2] = th + W * dt
    return out


@jit(cache=True)
def range_loglik(poses, lm, ranges, sigma):
    n = poses.shape[0]
    out = np.empty(n)
    const = lm.shape[0] * (math.log(sigma) + 0.5 * LOG_2PI)
    inv = 1.0 / sigma
    for i in range(n):
        acc = 0.0
        for l in range(lm.shape[0]):
            d = math.hypot(poses[i, 0] - lm[l, 0], poses[i, 1] - lm[l, 1])
            r = (d - ranges[l]) * inv
            acc += r * r
        out[i] = -0.5 * acc - const
    return out


@jit(cache=True)
def backward_mcmc(poses, ancestors, v, w, dt, p, idx_T, props, log_u):
    """MCMC-FFBSi. ``props`` (T, K, M) proposals drawn ∝ W_t, ``log_u`` (T, K, M)."""
    T = v.shape[0]
    M = idx_T.shape[0]
    K = props.shape[1]
    out = np.empty((M, T + 1, 3))
    idx = idx_T.copy()
    for m in range(M):
        out[m, T, :] = poses[T, idx[m], :]
    for t in range(T - 1, -1, -1):
        for m in range(M):
            x1 = out[m, t + 1, 0]
            y1 = out[m, t + 1, 1]
            th1 = out[m, t + 1, 2]
            cur = ancestors[t, idx[m]]
            lp_cur = transition_logpdf_scalar(poses[t, cur, 0], poses[t, cur, 1], poses[t, cur, 2],
                                              x1, y1, th1, v[t], w[t], dt[t], p)
            for k in range(K):
                q = props[t, k, m]
                lp = transition_logpdf_scalar(poses[t, q, 0], poses[t, q, 1], poses[t, q, 2],
                                              x1, y1, th1, v[t], w[t], dt[t], p)
                if log_u[t, k, m] < lp - lp_cur:
                    cur = q
                    lp_cur = lp
            idx[m] = cur
            out[m, t, 0] = poses[t, cur, 0]
            out[m, t, 1] = poses[t, cur, 1]
            out[m, t, 2] = poses[t, cur, 2]
    return out


@jit(cache=True)
def backward_exact(poses, log_w, v, w, dt, p, idx_T, u):
    """Exact FFBSi, O(N·M·T). ``u`` (T, M) uniforms."""
    T = v.shape[0]
    M = idx_T.shape[0]
    N = poses.shape[1]
    out = np.empty((M, T + 1, 3))
    lp = np.empty(N)
    for m in range(M):
        out[m, T, :] = poses[T, idx_T[m], :]
    for t in range(T - 1, -1, -1):
        for m in range(M):
            x1 = out[m, t + 1, 0]
            y1 = out[m, t + 1, 1]
            th1 = out[m, t + 1, 2]
            mx = -np.inf
            for i in range(N):
                lp[i] = log_w[t, i] + transition_logpdf_scalar(poses[t, i, 0], poses[t, i, 1], poses[t, i, 2],
                                                               x1, y1, th1, v[t], w[t], dt[t], p)
                if lp[i] > mx:
                    mx = lp[i]
            total = 0.0
            for i in range(N):
                lp[i] = math.exp(lp[i] - mx)
                total += lp[i]
            target = u[t, m] * total
            acc = 0.0
            j = N - 1
            for i in range(N):
                acc += lp[i]
                if acc >= target:
                    j = i
                    break
            out[m, t, 0] = poses[t, j, 0]
            out[m, t, 1] = poses[t, j, 1]
            out[m, t, 2] = poses[t, j, 2]
    return out


@jit(cache=True)
def heading_loglik(poses, yaw, sigma, log_sigma, half_log_2pi):
    """:meth:`adaptnav.calibration.sensors.HeadingObservation.log_likelihood` (same operations in
    the same order, so the same floats) without numpy's temporaries: the observation of
    almost every pose, evaluated once per particle filter step."""
    n = poses.shape[0]
    out = np.empty(n)
    two_pi = 2.0 * math.pi
    for i in range(n):
        e = ((poses[i, 2] - yaw + math.pi) % two_pi - math.pi) / sigma
        out[i] = -0.5 * e * e - log_sigma - half_log_2pi
    return out


@jit(cache=True)
def reweight(log_w, g):
    """Normalised ``log_w + g``, the increment ``log Σ exp(log_w + g)`` and the new ESS."""
    n = log_w.shape[0]
    out = np.empty(n)
    mx = -np.inf
    for i in range(n):
        out[i] = log_w[i] + g[i]
        if out[i] > mx:
            mx = out[i]
    if not np.isfinite(mx):
        return out, mx, 0.0
    total = 0.0
    for i in range(n):
        total += math.exp(out[i] - mx)
    inc = mx + math.log(total)
    s2 = 0.0
    for i in range(n):
        out[i] -= inc
        e = math.exp(out[i])
        s2 += e * e
    return out, inc, 1.0 / s2


@jit(cache=True)
def systematic_from_log(log_w, u):
    """Systematic resampling indices from normalised ``log_w`` and one uniform ``u`` ∈ [0, 1);
    the cumulative sum's last element is forced to 1 (the round-off guard)."""
    n = log_w.shape[0]
    cdf = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc += math.exp(log_w[i])
        cdf[i] = acc
    for i in range(n):
        cdf[i] /= acc
    cdf[n - 1] = 1.0
    out = np.empty(n, dtype=np.int64)
    j = 0
    for i in range(n):
        p = (u + i) / n
        while cdf[j] <= p and j < n - 1:
            j += 1
        out[i] = j
    return out
