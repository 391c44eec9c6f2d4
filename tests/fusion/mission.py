"""A small analytic AUV mission generator for the fusion tests (independent of the filter).

Level vehicle at constant depth, heading ``ψ(t) = ψ₀ + A sin(2π t / T) + ω₀ t``; water-
relative surge ``V(t)`` piecewise linear through knots at the learned-velocity fusion
times, the knot values drawn from the motion model ``N(k_V u, σ_V²(u, ψ̇))``; no sway or
heave; constant sea current. Truth is integrated on a 10× finer grid (trapezoid), the
IMU reports interval averages of the exact specific force and rate (what a real IMU's
Δv/Δθ outputs are), plus white noise and constant biases drawn from the filter's priors.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adaptnav.fusion import imu_grades

from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, euler_to_quat
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable, velocity_variances
from adaptnav.fusion.samples import (DepthSample, DvlSample, HeadingSample, ImuBatch, RpmSample, UsblSample,
                            replay_order_key)

ORIGIN = GeoOrigin(np.radians(43.0), np.radians(5.0), 0.0)
ATM_PA = 101325.0
RHO = 1025.0


@dataclass
class Mission:
    t_imu: np.ndarray
    f_b: np.ndarray
    w_b: np.ndarray
    pos_n: np.ndarray          # truth at IMU times
    vel_n: np.ndarray
    yaw: np.ndarray
    current_n: np.ndarray
    k_speed: float             # true k_V / model k_V
    bias_acc: np.ndarray
    bias_gyro: np.ndarray
    aids: list = field(default_factory=list)

    def truth_at(self, t_s: float) -> dict:
        k = int(np.argmin(np.abs(self.t_imu - t_s)))
        return {"pos": self.pos_n[k], "vel": self.vel_n[k], "yaw": self.yaw[k], "k": k}


def make_mission(rng: np.random.Generator, duration_s: float = 300.0, *, rate_hz: float = 100.0,
                 speed_m_s: float = 1.5, k_v_true: float = 1.0, params: MotionParams = MotionParams(),
                 current_n=(0.1, -0.05), depth_m: float = 10.0, lv_rate_hz: float = 2.0,
                 config: FilterConfig = FilterConfig(), heading_period_s: float = 1.0,
                 depth_period_s: float = 1.0, usbl_period_s: float | None = 10.0, usbl_sigma_m: float = 2.0,
                 usbl_until_s: float = np.inf, dvl_period_s: float | None = None, dvl_sigma_m_s: float = 0.01,
                 dvl_gap=(np.inf, np.inf), static_s: float = 0.0, yaw_rate0: float = 0.0,
                 imu_noise: bool = True, table: RpmSpeedTable = RpmSpeedTable()) -> Mission:
    """Generate IMU, truth and aiding samples (``aids`` sorted by replay order)."""
    sub = 10
    n = int(round(duration_s * rate_hz))
    dt = 1.0 / rate_hz
    tf = np.arange(n * sub + 1) * (dt / sub)
    t_imu = np.arange(1, n + 1) * dt
    A, T = 0.6, 120.0
    moving = tf >= static_s if static_s == 0 else tf > static_s
    tau = np.clip(tf - static_s, 0.0, None)
    psi = 0.3 + A * np.sin(2 * np.pi * tau / T) + yaw_rate0 * tau
    psid = np.where(moving, A * 2 * np.pi / T * np.cos(2 * np.pi * tau / T) + yaw_rate0, 0.0)
    # surge knots at the fusion times, drawn from the motion model
    t_knots = np.arange(0.0, duration_s + 2.0 / lv_rate_hz, 1.0 / lv_rate_hz)
    psid_k = np.interp(t_knots, tf, psid)
    var_V, _, _ = velocity_variances(params, speed_m_s, psid_k)
    V_knots = k_v_true * speed_m_s + np.sqrt(var_V) * rng.standard_normal(t_knots.size)
    V_knots[t_knots <= static_s] = 0.0
    S_knots = np.sqrt(params.var_s) * rng.standard_normal(t_knots.size) * (t_knots > static_s)
    V = np.interp(tf, t_knots, V_knots)
    S = np.interp(tf, t_knots, S_knots)
    seg = np.clip(np.searchsorted(t_knots, tf, side="right") - 1, 0, t_knots.size - 2)
    Vd = (V_knots[seg + 1] - V_knots[seg]) / (t_knots[seg + 1] - t_knots[seg])
    Sd = (S_knots[seg + 1] - S_knots[seg]) / (t_knots[seg + 1] - t_knots[seg])
    # the current carries the vehicle from the start (a vehicle at rest in the water drifts)
    c = np.broadcast_to(np.asarray(current_n, dtype=float), (tf.size, 2))
    cpsi, spsi = np.cos(psi), np.sin(psi)
    vel = np.zeros((tf.size, 3))
    vel[:, 0] = V * cpsi - S * spsi + c[:, 0]
    vel[:, 1] = V * spsi + S * cpsi + c[:, 1]
    acc = np.zeros((tf.size, 3))
    acc[:, 0] = Vd * cpsi - V * psid * spsi - Sd * spsi - S * psid * cpsi
    acc[:, 1] = Vd * spsi + V * psid * cpsi + Sd * cpsi - S * psid * spsi
    pos = np.zeros((tf.size, 3))
    pos[1:] = np.cumsum(0.5 * (vel[1:] + vel[:-1]) * np.diff(tf)[:, None], axis=0)
    pos[:, 2] = depth_m
    # body specific force at sub-interval midpoints, averaged per IMU interval
    mid = 0.5 * (tf[1:] + tf[:-1])
    psi_m = np.interp(mid, tf, psi)
    acc_m = 0.5 * (acc[1:] + acc[:-1])
    f_n = acc_m.copy()
    f_n[:, 2] -= GRAVITY_M_S2
    cm, sm = np.cos(psi_m), np.sin(psi_m)
    f_b_fine = np.stack([cm * f_n[:, 0] + sm * f_n[:, 1], -sm * f_n[:, 0] + cm * f_n[:, 1], f_n[:, 2]], axis=1)
    f_b = f_b_fine.reshape(n, sub, 3).mean(axis=1)
    w_b = np.zeros((n, 3))
    w_b[:, 2] = np.diff(psi[::sub]) / dt
    imu = imu_grades.resolve(config.imu, np.empty((0, 3)), np.empty((0, 3)), 1.0 / rate_hz).figures
    b_a = rng.normal(0.0, imu.acc_bias_sigma_m_s2, 3)
    b_g = rng.normal(0.0, imu.gyro_bias_sigma_rad_s, 3)
    if imu_noise:
        f_b = f_b + b_a + imu.acc_noise_m_s2_rthz * np.sqrt(rate_hz) * rng.standard_normal((n, 3))
        w_b = w_b + b_g + imu.gyro_noise_rad_s_rthz * np.sqrt(rate_hz) * rng.standard_normal((n, 3))
    else:
        b_a[:] = 0.0
        b_g[:] = 0.0
    idx = np.arange(1, n + 1) * sub
    m = Mission(t_imu, f_b, w_b, pos[idx], vel[idx], psi[idx], np.asarray(current_n, float),
                k_v_true / params.k_v, b_a, b_g)
    aids = []
    rpm = float(table.rpm_for_speed(speed_m_s))
    for t in np.arange(0.25, duration_s, 1.0):  # not on a fusion tick: no RPM/LV tie
        aids.append(RpmSample(float(t), rpm if t > static_s else 0.0))
    for t in np.arange(heading_period_s, duration_s, heading_period_s):
        y = np.interp(t, tf, psi) + config.heading.sigma_rad * rng.standard_normal()
        aids.append(HeadingSample(float(t), float((y + np.pi) % (2 * np.pi) - np.pi)))
    for t in np.arange(depth_period_s, duration_s, depth_period_s):
        d = depth_m + config.depth.sigma_m * rng.standard_normal()
        aids.append(DepthSample(float(t), float(ATM_PA + RHO * GRAVITY_M_S2 * d)))
    if usbl_period_s:
        for t in np.arange(usbl_period_s, min(duration_s, usbl_until_s), usbl_period_s):
            p = np.array([np.interp(t, tf, pos[:, i]) for i in range(3)])
            p[:2] += usbl_sigma_m * rng.standard_normal(2)
            lat, lon, _ = ORIGIN.to_geodetic(p)
            aids.append(UsblSample(float(t), float(lat), float(lon), float(depth_m), usbl_sigma_m))
    if dvl_period_s:
        for t in np.arange(dvl_period_s, duration_s, dvl_period_s):
            ps = np.interp(t, tf, psi)
            vn = np.array([np.interp(t, tf, vel[:, 0]), np.interp(t, tf, vel[:, 1]), 0.0])
            vb = np.array([np.cos(ps) * vn[0] + np.sin(ps) * vn[1], -np.sin(ps) * vn[0] + np.cos(ps) * vn[1], 0.0])
            vb += dvl_sigma_m_s * rng.standard_normal(3)
            lost = dvl_gap[0] <= t < dvl_gap[1]
            aids.append(DvlSample(float(t), tuple(map(float, vb)), valid=not lost))
    m.aids = sorted(aids, key=lambda s: replay_order_key(s, 0))
    return m


def true_error(m: Mission, state, k: int) -> np.ndarray:
    """18-dim error truth ⊖ estimate (attitude as a global rotation vector)."""
    from scipy.spatial.transform import Rotation

    from adaptnav.fusion.frames import quat_to_scipy
    e = np.zeros(18)
    e[0:3] = m.pos_n[k] - state.pos_n_m
    e[3:6] = m.vel_n[k] - state.vel_n_m_s
    q_true = euler_to_quat(0.0, 0.0, m.yaw[k])
    r = quat_to_scipy(q_true) * quat_to_scipy(state.q_nb).inv()  # q_true = q(δθ) ⊗ q_est
    e[6:9] = r.as_rotvec()
    e[9:12] = m.bias_acc - state.bias_acc_b_m_s2
    e[12:15] = m.bias_gyro - state.bias_gyro_b_rad_s
    e[15:17] = m.current_n - state.current_n_m_s
    e[17] = m.k_speed - state.k_speed
    return e


def run(est, m: Mission, probe_times=(), drop=lambda s: False, max_batch: int | None = None):
    """Feed the mission in replay order (IMU as batches between aids, of at most ``max_batch``
    samples when given: a live stream's many small inputs); nav states at probes."""
    events = [(s.t_s, 1, s) for s in m.aids if not drop(s)] + [(float(t), 2, None) for t in probe_times]
    events.sort(key=lambda e: (e[0], e[1]))
    states, statuses = [], []

    def imu(k0, k1):
        step = max_batch or k1 - k0
        for k in range(k0, k1, step):
            j = min(k + step, k1)
            statuses.extend(est.process(ImuBatch(m.t_imu[k:j], m.f_b[k:j], m.w_b[k:j])))

    k0 = 0
    for t, kind, s in events:
        k1 = int(np.searchsorted(m.t_imu, t, side="right"))
        if k1 > k0:
            imu(k0, k1)
            k0 = k1
        if kind == 1:
            # a "delayed" stand-in hands its sample over late, as a slow transport would
            if s.KIND == "release":  # a calibrator release applied at this point of the stream
                est.set_motion_params(s.params)
            else:
                statuses += est.process(s.sample if s.KIND == "delayed" else s)
        else:
            states.append((k1 - 1, est.nav_state()))
    if k0 < m.t_imu.size:
        imu(k0, m.t_imu.size)
    return states, statuses
