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
* :func:`filter_window` — the particle filter over a whole window (resample, move, weigh
  for all T steps in one call) with pre-drawn normals and uniforms and the observations
  packed into arrays; :func:`pf_advance`, :func:`pf_weigh` are its steps, called one by
  one where a per-particle landmark map is updated in Python between them.
* :func:`variance_objective`, :func:`newton_cg_variances` — the M-step's objective and its
  Newton-CG (:mod:`adaptnav.calibration.mstep`).

``pvec`` packs :class:`MotionParams` and the sea current as ``(var_vv, var_vw, var_v1, var_wv,
var_ww, var_w1, var_s, k_v, b_w, u_n, u_e, turn_about_mean)`` (:func:`pack`); the current (m/s) adds
``u δt`` to each step's ground displacement.
"""
from __future__ import annotations

import math

from adaptnav.kernels import jit
import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
# log-weights this far below the largest count as zero weight (pf_weigh)
WEIGHT_FLUSH_LOG = -60.0


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


# sin and cos without libm: Cody–Waite reduction by π/2 in three parts (k·π/2 exact for
# |x| < 2^19·π/2 ≈ 8e5 rad) and fdlibm's minimax polynomials on [−π/4, π/4], quadrant by
# selects. Branch-free, so the particle loops vectorise: 1.5 ns per (sin, cos) pair here
# against 23 ns for libm's sin and cos; error ≤ 1 ulp (tests/calibration/test_filter_smoother.py).
_TWO_OVER_PI = 2.0 / math.pi
_TWO_PI = 2.0 * math.pi
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@jit(cache=True, inline="always")
def sincos(x):
    """``(sin x, cos x)`` (see the comment above; |x| < 8e5 rad)."""
    k = np.floor(x * _TWO_OVER_PI + 0.5)
    r = ((x - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    z = r * r
    s = r + r * z * (_S1 + z * (_S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))))
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + z * z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6))))))
    q = k - 4.0 * np.floor(0.25 * k)
    sn = s if q == 0.0 else (c if q == 1.0 else (-s if q == 2.0 else -c))
    cs = c if q == 0.0 else (-s if q == 1.0 else (-c if q == 2.0 else s))
    return sn, cs


@jit(cache=True, inline="always")
def _chord_of_half_turn(a, dt):
    """``c = δt sin(a) / a`` for the half turn ``a = W δt / 2`` (series near 0)."""
    if abs(a) < 1e-8:
        return dt * (1.0 - a * a / 6.0)
    return dt * sincos(a)[0] / a


@jit(cache=True, inline="always")
def _chord(W, dt):
    return _chord_of_half_turn(0.5 * W * dt, dt)


@jit(cache=True, inline="always")
def _step_constants(v, w, dt, p):
    """Per-step constants of the transition density: the branch centre of the heading
    change, the means and inverse variances of V, W, S and the normalising term (its
    logarithms are the same for every pair of poses of one step)."""
    ref = p[11] * (w + p[8]) * dt if p.shape[0] > 11 else 0.0  # branch centre (pack)
    v2 = v * v
    w2 = w * w
    var_V = v2 * p[0] + w2 * p[1] + p[2]
    var_W = v2 * p[3] + w2 * p[4] + p[5]
    var_S = p[6]
    const = -0.5 * (math.log(var_V) + math.log(var_W) + math.log(var_S) + 3.0 * LOG_2PI) - math.log(dt)
    return ref, p[7] * v, w + p[8], 1.0 / var_V, 1.0 / var_W, 1.0 / var_S, const


@jit(cache=True, inline="always")
def _invert(x0, y0, th0, x1, y1, th1, dt, un, ue, ref):
    """The velocities ``(V, W, S)`` carrying pose 0 to pose 1 in ``dt`` with the chord
    factor ``c`` and the mid-step heading ``φ`` (:func:`adaptnav.fusion.motion_model.invert_step`:
    heading change on the branch nearest ``ref``, current ``(un, ue)`` m/s removed)."""
    # the branch: y mod 2π by floor, not Python's % (a libm fmod call, 7 ns against 0.3)
    y = th1 - th0 - ref + math.pi
    dth = y - _TWO_PI * np.floor(y / _TWO_PI) - math.pi + ref
    W = dth / dt
    phi = th0 + 0.5 * dth
    c = _chord(W, dt)
    dx = x1 - x0 - un * dt
    dy = y1 - y0 - ue * dt
    sp, cp = sincos(phi)
    return (cp * dx + sp * dy) / c, W, (-sp * dx + cp * dy) / c, c, phi


@jit(cache=True, inline="always")
def _transition_core(x0, y0, th0, x1, y1, th1, dt, un, ue, ref, mV, mW, iV, iW, iS, const):
    V, W, S, c, _ = _invert(x0, y0, th0, x1, y1, th1, dt, un, ue, ref)
    eV = V - mV
    eW = W - mW
    return const - 0.5 * (eV * eV * iV + eW * eW * iW + S * S * iS) - 2.0 * math.log(abs(c))


@jit(cache=True)
def mean_design(traj, dt, ref):
    """The M-step's regressors (:func:`adaptnav.calibration.mstep._mean_design`) of
    trajectories ``traj`` (M, T+1, 3), steps ``dt`` (T,), heading-change branch centres
    ``ref`` (T,): zero-current ``V⁰, W, S⁰`` (M, T) and the current's columns ``gv``,
    ``gs`` (M, T, 2)."""
    M = traj.shape[0]
    T = dt.shape[0]
    V0 = np.empty((M, T))
    W = np.empty((M, T))
    S0 = np.empty((M, T))
    gv = np.empty((M, T, 2))
    gs = np.empty((M, T, 2))
    for m in range(M):
        for t in range(T):
            V, Wt, S, c, phi = _invert(traj[m, t, 0], traj[m, t, 1], traj[m, t, 2], traj[m, t + 1, 0],
                                       traj[m, t + 1, 1], traj[m, t + 1, 2], dt[t], 0.0, 0.0, ref[t])
            V0[m, t] = V
            W[m, t] = Wt
            S0[m, t] = S
            g = dt[t] / c
            sp, cp = sincos(phi)
            gv[m, t, 0] = cp * g
            gv[m, t, 1] = sp * g
            gs[m, t, 0] = -sp * g
            gs[m, t, 1] = cp * g
    return V0, W, S0, gv, gs


@jit(cache=True)
def transition_logpdf_scalar(x0, y0, th0, x1, y1, th1, v, w, dt, p):
    ref, mV, mW, iV, iW, iS, const = _step_constants(v, w, dt, p)
    return _transition_core(x0, y0, th0, x1, y1, th1, dt, p[9], p[10], ref, mV, mW, iV, iW, iS, const)


@jit(cache=True)
def _move_into(poses, idx, z, v, w, dt, p, out):
    """``out[i]`` ← ``poses[idx[i]]`` moved with the velocities of the normals ``z[:, i]``.

    Three loops: the gathers, the trigonometry (only two input and three output arrays:
    few enough for LLVM's run-time alias checks, so it vectorises, 2.7× faster than one
    loop doing everything), the positions."""
    n = idx.shape[0]
    v2 = v * v
    w2 = w * w
    sdV = math.sqrt(v2 * p[0] + w2 * p[1] + p[2])
    sdW = math.sqrt(v2 * p[3] + w2 * p[4] + p[5])
    sdS = math.sqrt(p[6])
    mV = p[7] * v
    mW = w + p[8]
    dxc = p[9] * dt
    dyc = p[10] * dt
    th = np.empty(n)
    half_turn = np.empty(n)   # a = W δt / 2
    chord = np.empty(n)
    sin_phi = np.empty(n)
    cos_phi = np.empty(n)
    for i in range(n):
        th[i] = poses[idx[i], 2]
        half_turn[i] = 0.5 * (mW + sdW * z[1, i]) * dt
    for i in range(n):
        a = half_turn[i]
        chord[i] = _chord_of_half_turn(a, dt)
        sin_phi[i], cos_phi[i] = sincos(th[i] + a)   # φ = θ + W δt / 2
    for i in range(n):
        j = idx[i]
        V = mV + sdV * z[0, i]
        S = sdS * z[2, i]
        c = chord[i]
        cp = cos_phi[i]
        sp = sin_phi[i]
        out[i, 0] = poses[j, 0] + c * (cp * V - sp * S) + dxc
        out[i, 1] = poses[j, 1] + c * (sp * V + cp * S) + dyc
        out[i, 2] = th[i] + 2.0 * half_turn[i]


@jit(cache=True)
def move(poses, idx, z, v, w, dt, p):
    out = np.empty((idx.shape[0], 3))
    _move_into(poses, idx, z, v, w, dt, p, out)
    return out


# -- standard normals from a generator's raw bits (calibration.particle_filter.move_normals) --
_UNIT_32 = 2.0 ** -32


@jit(cache=True)
def _box_muller_pairs(radius, angle):
    """``(radius, angle)`` ← ``(r cos a, r sin a)`` with ``r = √(−2 radius)`` (radius holds
    ``ln u₁``): two arrays, so the loop vectorises with :func:`sincos`."""
    for i in range(radius.shape[0]):
        s, c = sincos(angle[i])
        r = math.sqrt(-2.0 * radius[i])
        radius[i] = r * c
        angle[i] = r * s


@jit(cache=True)
def box_muller_into(bits, out):
    """``out`` (2n,) ← standard normals from ``bits`` (n,) uint64 random words, by the
    Box–Muller transform: each word gives two 32-bit uniforms ``u₁, u₂ ∈ (0, 1)`` (the bin
    centres ``(m + ½) 2⁻³²``, never 0), and ``√(−2 ln u₁) (cos 2πu₂, sin 2πu₂)`` two
    independent normals (the cosines fill ``out[:n]``, the sines ``out[n:]``). The largest
    |z| is √(64 ln 2 + 2 ln 2) = 6.76: the 1.4e-11 of the mass beyond is never drawn.
    In loops of one operation each (convert, log, rotate) that vectorise: 1.3 ms for 300k
    normals with the 150k words drawn, against 2.8 ms for ``Generator.standard_normal``."""
    n = bits.shape[0]
    radius = out[:n]
    angle = out[n:]
    for i in range(n):
        word = bits[i]
        radius[i] = (np.float64(word >> np.uint64(32)) + 0.5) * _UNIT_32
        angle[i] = _TWO_PI * ((np.float64(word & np.uint64(0xFFFFFFFF)) + 0.5) * _UNIT_32)
    for i in range(n):
        radius[i] = math.log(radius[i])
    _box_muller_pairs(radius, angle)


@jit(cache=True)
def _add_range_loglik(poses, lm_x, lm_y, ranges, sigma, g):
    """``g += log`` likelihood of ranges to landmarks at (``lm_x``, ``lm_y``) (L,), noise ``sigma``."""
    n = poses.shape[0]
    const = lm_x.shape[0] * (math.log(sigma) + 0.5 * LOG_2PI)
    inv = 1.0 / sigma
    for i in range(n):
        g[i] -= const
    # positions copied out of the (N, 3) rows: unit-stride loops over particles (landmark
    # outside) vectorise, square roots included (4 landmarks, 1000 particles, 100 steps: 1.07 → 0.34 ms)
    px = np.empty(n)
    py = np.empty(n)
    for i in range(n):
        px[i] = poses[i, 0]
        py[i] = poses[i, 1]
    for l in range(lm_x.shape[0]):
        lx = lm_x[l]
        ly = lm_y[l]
        rl = ranges[l]
        for i in range(n):
            dx = px[i] - lx
            dy = py[i] - ly
            r = (math.sqrt(dx * dx + dy * dy) - rl) * inv
            g[i] -= 0.5 * r * r


@jit(cache=True)
def range_loglik(poses, lm, ranges, sigma):
    out = np.zeros(poses.shape[0])
    _add_range_loglik(poses, lm[:, 0], lm[:, 1], ranges, sigma, out)
    return out


@jit(cache=True)
def _add_heading_loglik(poses, yaw, sigma, log_sigma, half_log_2pi, g):
    two_pi = 2.0 * math.pi
    for i in range(poses.shape[0]):
        e = ((poses[i, 2] - yaw + math.pi) % two_pi - math.pi) / sigma
        g[i] += -0.5 * e * e - log_sigma - half_log_2pi


@jit(cache=True)
def heading_loglik(poses, yaw, sigma, log_sigma, half_log_2pi):
    """:meth:`adaptnav.calibration.sensors.HeadingObservation.log_likelihood` (same operations in
    the same order, so the same floats) without numpy's temporaries: the observation of
    almost every pose, evaluated once per particle filter step."""
    out = np.zeros(poses.shape[0])
    _add_heading_loglik(poses, yaw, sigma, log_sigma, half_log_2pi, out)
    return out


@jit(cache=True)
def _cdf_of_weights(W, cdf):
    """``cdf`` ← the cumulative sum of the weights ``W`` normalised, its last element forced
    to 1 (the round-off guard of :func:`adaptnav.calibration.resampling.multinomial_indices`);
    weights below 1e-300 count as zero (no subnormal arithmetic, see :func:`_weigh_into`)."""
    n = W.shape[0]
    acc = 0.0
    for i in range(n):
        if W[i] > 1e-300:
            acc += W[i]
        cdf[i] = acc
    for i in range(n):
        cdf[i] /= acc
    cdf[n - 1] = 1.0


@jit(cache=True, inline="always")
def _search_right(cdf, u):
    """First index i with ``cdf[i] > u`` (``numpy.searchsorted(cdf, u, side="right")``)."""
    lo = 0
    hi = cdf.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] <= u:
            lo = mid + 1
        else:
            hi = mid
    return lo


@jit(cache=True)
def backward_mcmc(poses, W, ancestors, v, w, dt, p, u_last, u_prop, log_u):
    """MCMC-FFBSi over the filter's particles ``poses`` (T+1, N, 3) with weights ``W``
    (T+1, N). Trajectory ends drawn ∝ W_T with the uniforms ``u_last`` (M,);
    ``u_prop`` (T, K, M) uniforms of the proposals drawn ∝ W_t (inverse CDF), ``log_u``
    (T, K, M) log-uniforms of the acceptances."""
    T = v.shape[0]
    N = poses.shape[1]
    M = u_last.shape[0]
    K = u_prop.shape[1]
    out = np.empty((M, T + 1, 3))
    idx = np.empty(M, dtype=np.int64)
    cdf = np.empty(N)
    _cdf_of_weights(W[T], cdf)
    for m in range(M):
        idx[m] = _search_right(cdf, u_last[m])
        out[m, T, :] = poses[T, idx[m], :]
    un = p[9]
    ue = p[10]
    for t in range(T - 1, -1, -1):
        _cdf_of_weights(W[t], cdf)
        ref, mV, mW, iV, iW, iS, const = _step_constants(v[t], w[t], dt[t], p)
        dt_t = dt[t]
        for m in range(M):
            x1 = out[m, t + 1, 0]
            y1 = out[m, t + 1, 1]
            th1 = out[m, t + 1, 2]
            cur = ancestors[t, idx[m]]
            lp_cur = _transition_core(poses[t, cur, 0], poses[t, cur, 1], poses[t, cur, 2], x1, y1, th1,
                                      dt_t, un, ue, ref, mV, mW, iV, iW, iS, const)
            for k in range(K):
                q = _search_right(cdf, u_prop[t, k, m])
                lp = _transition_core(poses[t, q, 0], poses[t, q, 1], poses[t, q, 2], x1, y1, th1,
                                      dt_t, un, ue, ref, mV, mW, iV, iW, iS, const)
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
    un = p[9]
    ue = p[10]
    for t in range(T - 1, -1, -1):
        ref, mV, mW, iV, iW, iS, const = _step_constants(v[t], w[t], dt[t], p)
        dt_t = dt[t]
        for m in range(M):
            x1 = out[m, t + 1, 0]
            y1 = out[m, t + 1, 1]
            th1 = out[m, t + 1, 2]
            mx = -np.inf
            for i in range(N):
                lp[i] = log_w[t, i] + _transition_core(poses[t, i, 0], poses[t, i, 1], poses[t, i, 2],
                                                       x1, y1, th1, dt_t, un, ue, ref, mV, mW, iV, iW, iS, const)
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
def reweight(log_w, g):
    """Normalised ``log_w + g``, the increment ``log Σ exp(log_w + g)`` and the new ESS."""
    out = log_w.copy()
    inc, ess = _weigh_into(out, np.empty(log_w.shape[0]), g)
    return out, inc, ess


@jit(cache=True)
def _systematic_into(W, u, cdf, idx):
    """Systematic resampling indices ``idx`` (N,) from weights ``W`` (N,) and one uniform
    ``u`` ∈ [0, 1); the cumulative sum's last element is forced to 1 (the round-off guard)."""
    n = W.shape[0]
    acc = 0.0
    for i in range(n):
        acc += W[i]
        cdf[i] = acc
    for i in range(n):
        cdf[i] /= acc
    cdf[n - 1] = 1.0
    j = 0
    for i in range(n):
        q = (u + i) / n
        while cdf[j] <= q and j < n - 1:
            j += 1
        idx[i] = j


@jit(cache=True)
def systematic_from_log(log_w, u):
    """:func:`_systematic_into` from normalised ``log_w``."""
    n = log_w.shape[0]
    out = np.empty(n, dtype=np.int64)
    _systematic_into(np.exp(log_w), u, np.empty(n), out)
    return out


# -- the particle filter over a whole window (calibration.particle_filter) ------------------
# observation codes of the packed window (:func:`adaptnav.calibration.particle_filter.pack_observations`);
# ``fdata[off:]`` holds each observation's numbers in the order given
OBS_RANGE = 0           # L, sigma, then L landmark x, L landmark y, L ranges
OBS_FIX = 1             # x, y, sigma
OBS_HEADING = 2         # yaw, sigma
OBS_FIXED_LANDMARK = 3  # along, across, var_along, var_across, mean x, mean y, cov xx, xy, yx, yy


@jit(cache=True)
def _add_observation_loglik(poses, kind, off, fdata, g):
    """``g += log g(poses)`` of one packed observation (same equations as
    :mod:`adaptnav.calibration.sensors`)."""
    n = poses.shape[0]
    if kind == 0:
        n_lm = int(fdata[off])
        k = off + 2
        _add_range_loglik(poses, fdata[k:k + n_lm], fdata[k + n_lm:k + 2 * n_lm],
                          fdata[k + 2 * n_lm:k + 3 * n_lm], fdata[off + 1], g)
    elif kind == 1:
        x = fdata[off]
        y = fdata[off + 1]
        inv = 1.0 / fdata[off + 2]
        const = 2.0 * math.log(fdata[off + 2]) + LOG_2PI
        for i in range(n):
            dx = (poses[i, 0] - x) * inv
            dy = (poses[i, 1] - y) * inv
            g[i] += -0.5 * (dx * dx + dy * dy) - const
    elif kind == 2:
        sigma = fdata[off + 1]
        _add_heading_loglik(poses, fdata[off], sigma, math.log(sigma), 0.5 * LOG_2PI, g)
    else:
        a = fdata[off]
        b = fdata[off + 1]
        va = fdata[off + 2]
        vb = fdata[off + 3]
        mx = fdata[off + 4]
        my = fdata[off + 5]
        c00 = fdata[off + 6]
        c01 = fdata[off + 7]
        c10 = fdata[off + 8]
        c11 = fdata[off + 9]
        for i in range(n):
            s, c = sincos(poses[i, 2])
            ex = poses[i, 0] + c * a - s * b - mx
            ey = poses[i, 1] + s * a + c * b - my
            s00 = c * c * va + s * s * vb + c00
            s11 = s * s * va + c * c * vb + c11
            s01 = c * s * (va - vb) + c01
            s10 = c * s * (va - vb) + c10
            det = s00 * s11 - s01 * s10
            maha = (s11 * ex * ex - 2.0 * s01 * ex * ey + s00 * ey * ey) / det
            g[i] += -0.5 * (maha + math.log(det)) - LOG_2PI


_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10


@jit(cache=True)
def _exp_flushed_into(d, out):
    """``out[i] = exp(d[i])``, 0 where ``d[i] ≤ WEIGHT_FLUSH_LOG`` (or NaN). Branch-free
    like :func:`sincos`, so it vectorises (1.3 against 6.1 µs per 1000): ``d = k ln 2 + r``
    (ln 2 in two parts), ``e^r`` by its Taylor series to r¹²/12! (|r| ≤ ln 2 / 2: below
    1e-17), ``2^k`` built from its exponent bits; ≤ 1 ulp from libm's exp."""
    n = d.shape[0]
    bits = np.empty(n, dtype=np.int64)
    for i in range(n):
        x = max(d[i], WEIGHT_FLUSH_LOG)  # keeps 2^k a normal number
        k = np.floor(x * _LOG2E + 0.5)
        r = (x - k * _LN2_HI) - k * _LN2_LO
        out[i] = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (
            1.0 / 720.0 + r * (1.0 / 5040.0 + r * (1.0 / 40320.0 + r * (1.0 / 362880.0 + r * (
                1.0 / 3628800.0 + r * (1.0 / 39916800.0 + r * (1.0 / 479001600.0))))))))))))
        bits[i] = (np.int64(k) + 1023) << 52
    scale = bits.view(np.float64)
    for i in range(n):
        out[i] = out[i] * scale[i] if d[i] > WEIGHT_FLUSH_LOG else 0.0


@jit(cache=True)
def pf_weigh(LW, W, t, g):
    """``LW[t] += g`` normalised in place, ``W`` = exp(LW[t]); returns the increment
    ``log Σ exp(LW[t] + g)`` (−inf or NaN when every weight vanishes) and the ESS."""
    return _weigh_into(LW[t], W, g)


@jit(cache=True)
def _weigh_into(lw, W, g):
    n = g.shape[0]
    mx = -np.inf
    for i in range(n):
        lw[i] += g[i]
        if lw[i] > mx:
            mx = lw[i]
    if not np.isfinite(mx):
        return mx, 0.0
    d = np.empty(n)
    for i in range(n):
        d[i] = lw[i] - mx
    # below e^-60 a weight cannot change a sum that is ≥ 1 (N e^-60 ≪ 1e-16), and
    # flushing it to zero keeps subnormal numbers (~100× slower arithmetic) out of W
    _exp_flushed_into(d, W)
    total = 0.0
    for i in range(n):
        total += W[i]
    inc = mx + math.log(total)
    s2 = 0.0
    for i in range(n):
        lw[i] -= inc
        W[i] /= total
        s2 += W[i] * W[i]
    return inc, 1.0 / s2


@jit(cache=True)
def pf_advance(X, LW, W, A, resampled, t, resample, u, z, v, w, dt, p, cdf):
    """Step t → t+1: systematic resampling with the uniform ``u`` when ``resample``
    (cumulative sum's last element forced to 1), then the move with standard normals
    ``z`` (3, N); ``LW[t+1]`` gets the weights carried into t+1 (uniform after resampling)."""
    n = W.shape[0]
    idx = A[t]
    if resample:
        _systematic_into(W, u, cdf, idx)
        lw0 = -math.log(n)
        for i in range(n):
            LW[t + 1, i] = lw0
        resampled[t] = True
    else:
        for i in range(n):
            idx[i] = i
            LW[t + 1, i] = LW[t, i]
        resampled[t] = False
    _move_into(X[t], idx, z, v, w, dt, p, X[t + 1])


@jit(cache=True)
def filter_window(X, LW, A, inc, resampled, v, w, dt, p, z, u, threshold, obs_ptr, obs_kind, obs_off, fdata):
    """The whole window of :func:`adaptnav.calibration.particle_filter.run_particle_filter` in one call.

    ``X`` (T+1, N, 3) with ``X[0]`` the prior cloud, ``LW`` (T+1, N) with ``LW[0]`` its
    log-weights; filled in place with ``A`` (T, N), ``inc`` (T+1,), ``resampled`` (T,).
    ``z`` (T, 3, N) standard normals, ``u`` (T,) uniforms; observations of pose t are
    ``obs_ptr[t] .. obs_ptr[t+1]`` of the packed ``obs_kind``, ``obs_off``, ``fdata``.
    Returns −1, or the first pose whose observations no particle can explain."""
    T = v.shape[0]
    n = X.shape[1]
    g = np.empty(n)
    W = np.empty(n)
    cdf = np.empty(n)
    ess = 0.0
    for t in range(T + 1):
        if t > 0:
            pf_advance(X, LW, W, A, resampled, t - 1, ess < threshold, u[t - 1], z[t - 1],
                       v[t - 1], w[t - 1], dt[t - 1], p, cdf)
        g[:] = 0.0
        for k in range(obs_ptr[t], obs_ptr[t + 1]):
            _add_observation_loglik(X[t], obs_kind[k], obs_off[k], fdata, g)
        inc[t], ess = pf_weigh(LW, W, t, g)
        if not np.isfinite(inc[t]):
            return t
    return -1


# -- the M-step's variance objective (calibration.mstep) ------------------------------------
@jit(cache=True)
def variance_objective(x, free, alpha0, design, lam, resid_sq, center, inv_tau2, grad, hess):
    """Negative expected log-likelihood of one channel at the free log-variances ``x``,
    with its gradient and Hessian written into ``grad`` (k,) and ``hess`` (k, k)
    (:class:`adaptnav.calibration.mstep.VarianceObjective`, whose docstring has the equations).

    ``free`` (k,) indices of ``x`` in the full ``alpha0`` (3,); ``design`` (T, 3),
    ``lam`` and ``resid_sq`` (T,); prior ``0.5 inv_tau2 |x − center[free]|²``."""
    n_free = free.shape[0]
    a = alpha0.copy()
    for i in range(n_free):
        a[free[i]] = x[i]
    e = np.empty(3)
    for k in range(3):  # clip: a line search may probe far-off points; exp must not overflow
        e[k] = math.exp(min(max(a[k], -60.0), 20.0))
    val = 0.0
    u = np.empty(n_free)
    for i in range(n_free):
        d = x[i] - center[free[i]]
        val += 0.5 * inv_tau2 * d * d
        grad[i] = inv_tau2 * d
        for j in range(n_free):
            hess[i, j] = inv_tau2 if i == j else 0.0
    for t in range(design.shape[0]):
        s = design[t, 0] * e[0] + design[t, 1] * e[1] + design[t, 2] * e[2]
        r = resid_sq[t]
        val += 0.5 * lam[t] * (math.log(s) + r / s)
        f1 = 0.5 * lam[t] * (1.0 / s - r / (s * s))
        f2 = 0.5 * lam[t] * (-1.0 / (s * s) + 2.0 * r / (s * s * s))
        for i in range(n_free):
            u[i] = design[t, free[i]] * e[free[i]]
        for i in range(n_free):
            grad[i] += f1 * u[i]
            hess[i, i] += f1 * u[i]
            for j in range(n_free):
                hess[i, j] += f2 * u[i] * u[j]
    return val


@jit(cache=True)
def newton_cg_variances(x0, free, alpha0, design, lam, resid_sq, center, inv_tau2, avextol, maxiter):
    """Minimise :func:`variance_objective` from ``x0`` by Newton-CG: the steps of
    ``scipy.optimize.minimize(method="Newton-CG")`` (truncated conjugate gradients on the
    Newton system, stopped at negative curvature; stop when the step's L1 norm is below
    ``k · avextol`` or after ``maxiter`` steps), with a backtracking (Armijo) line search
    instead of scipy's Wolfe search. In one compiled call: scipy's per-iteration Python
    costs ~1.5 ms per fit, four fits per M-step, for a problem of at most 3 unknowns."""
    n = x0.shape[0]
    x = x0.copy()
    g = np.empty(n)
    h = np.empty((n, n))
    g_try = np.empty(n)
    h_try = np.empty((n, n))
    x_try = np.empty(n)
    f = variance_objective(x, free, alpha0, design, lam, resid_sq, center, inv_tau2, g, h)
    xtol = n * avextol
    eps = np.finfo(np.float64).eps
    for _ in range(maxiter):
        # truncated CG on h p = −g
        mag = 0.0
        for i in range(n):
            mag += abs(g[i])
        termcond = min(0.5, math.sqrt(mag)) * mag
        p = np.zeros(n)
        r = g.copy()
        d = -r
        dr0 = r @ r
        for it in range(20 * n):
            if np.sum(np.abs(r)) <= termcond:
                break
            hd = h @ d
            curv = d @ hd
            if 0.0 <= curv <= 3.0 * eps:
                break
            if curv < 0.0:
                if it == 0:
                    p = -(dr0 / -curv) * g
                break
            alpha = dr0 / curv
            p += alpha * d
            r += alpha * hd
            dr1 = r @ r
            d = -r + (dr1 / dr0) * d
            dr0 = dr1
        slope = g @ p
        if not slope < 0.0:  # no descent direction: converged as far as it goes
            break
        step = 1.0
        accepted = False
        for _ in range(40):
            for i in range(n):
                x_try[i] = x[i] + step * p[i]
            f_try = variance_objective(x_try, free, alpha0, design, lam, resid_sq, center, inv_tau2, g_try, h_try)
            if f_try <= f + 1e-4 * step * slope:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        moved = 0.0
        for i in range(n):
            moved += abs(x_try[i] - x[i])
        x[:] = x_try
        g[:] = g_try
        h[:, :] = h_try
        f = f_try
        if moved <= xtol:
            break
    return x
