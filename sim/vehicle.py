r"""Vehicle truth: guidance along a pattern, velocities drawn from the motion model.

Per motion step ``k`` (length ``T = motion.step_s``), from the *water-relative* pose
``(x_k, y_k, θ_k)`` (DESIGN.md "Motion model"):

1. guidance: line-of-sight steering along the pattern's waypoints gives the yaw-rate
   command ``w_k``; the commanded speed gives the propeller RPM ``n_k``
   (:meth:`RpmSpeedTable.rpm_for_speed`) and the reported surge ``v_k = f(n_k)``;
2. truth: ``(V_k, W_k, S_k)`` ~ the motion model with the parameters in force at
   ``t_k`` (:func:`adaptnav.fusion.motion_model.sample_velocities`), and
   ``pose_{k+1} = propagate(pose_k, V_k, W_k, S_k, T)`` — so the water-relative poses at
   the step instants follow the model *exactly* and :func:`invert_step` recovers
   ``(V_k, W_k, S_k)``;
3. ground position = water-relative position + current · t (constant current).

Inside a step the yaw rate is ``W_k`` (yaw is continuous) and the body velocity blends
linearly over ``ramp_s`` from the previous step's value to a constant ``u'_k`` (no
velocity jumps, so accelerations stay physical). ``u'_k`` solves the 2×2 system that
makes the trapezoid-integrated displacement over the step equal to the model's
``propagate`` displacement:  ``(A_k − B_k) u'_k = D_k − B_k u'_{k−1}`` with
``A_k = Σ_j w_j R(θ_j) Δt``, ``B_k = Σ_j w_j h_j R(θ_j) Δt`` (trapezoid weights ``w_j``,
ramp ``h_j = max(0, 1 − τ_j/ramp_s)``). The forward recursion contracts by
``ramp_s/(2T − ramp_s) ≤ 1/3``.

Depth follows a smooth (raised-cosine) descent from ``start_depth_m`` to ``depth_m``;
roll and pitch are small sinusoids, pitch also follows the flight-path angle.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from adaptnav.fusion.motion_model import propagate, sample_velocities
from adaptnav.sim.scenario import Scenario


@dataclass(frozen=True)
class MotionSteps:
    """The motion-model view of the truth: one row per step (what the calibrator sees).

    ``t_s`` (K+1,) step instants; ``pose_water`` (K+1, 3) water-relative (x north m,
    y east m, θ yaw rad, unwrapped); ``rpm``, ``v_m_s``, ``w_rad_s`` (K,) the reported
    controls; ``V_m_s``, ``W_rad_s``, ``S_m_s`` (K,) the true velocities drawn;
    ``k_v`` (K,) the true k_V in force.
    """

    t_s: np.ndarray
    pose_water: np.ndarray
    rpm: np.ndarray
    v_m_s: np.ndarray
    w_rad_s: np.ndarray
    V_m_s: np.ndarray
    W_rad_s: np.ndarray
    S_m_s: np.ndarray
    k_v: np.ndarray


@dataclass(frozen=True)
class DenseTruth:
    """Truth at every IMU instant ``t_i = i Δt``, ``i = 0 … N``.

    ``pos_n_m``, ``vel_n_m_s`` (N+1, 3) NED; ``euler_rad`` (N+1, 3) roll, pitch, yaw
    (yaw unwrapped); ``q_nb`` (N+1, 4) (w, x, y, z).
    """

    t_s: np.ndarray
    pos_n_m: np.ndarray
    vel_n_m_s: np.ndarray
    euler_rad: np.ndarray
    q_nb: np.ndarray


def waypoints(scenario: Scenario) -> np.ndarray:
    """(M, 2) north/east waypoints of the pattern, long enough for the whole run."""
    tr = scenario.trajectory
    length_needed = max(tr.speed_m_s, 0.1) * scenario.duration_s * 1.5 + 100.0
    h = math.radians(tr.heading_deg)
    along = np.array([math.cos(h), math.sin(h)])
    across = np.array([-math.sin(h), math.cos(h)])  # to starboard of the first leg
    if tr.pattern == "straight":
        return np.array([[0.0, 0.0], along * length_needed])
    if tr.pattern == "circle":
        # polygon approximation; the vehicle starts on the circle heading along it
        n_turns = int(length_needed / (2 * math.pi * tr.circle_radius_m)) + 2
        ang = np.linspace(0.0, 2 * math.pi * n_turns, 72 * n_turns + 1)
        centre = across * tr.circle_radius_m
        pts = centre[None, :] + tr.circle_radius_m * (
            np.cos(ang)[:, None] * -across[None, :] + np.sin(ang)[:, None] * along[None, :])
        return pts
    n_legs = int(length_needed / (tr.leg_length_m + tr.leg_spacing_m)) + 2
    pts = []
    for i in range(n_legs):
        start = across * i * tr.leg_spacing_m + (along * tr.leg_length_m if i % 2 else 0.0)
        end = across * i * tr.leg_spacing_m + (0.0 if i % 2 else along * tr.leg_length_m)
        pts.extend([start, end])
    return np.array(pts)


class LosGuidance:
    """Line-of-sight steering along a polyline; yields a yaw-rate command (rad/s)."""

    def __init__(self, wps: np.ndarray, lookahead_m: float, gain_per_s: float, max_rate_rad_s: float):
        self.wps = wps
        self.seg = 0
        self.lookahead = lookahead_m
        self.gain = gain_per_s
        self.max_rate = max_rate_rad_s

    def command(self, north_m: float, east_m: float, yaw_rad: float) -> float:
        while True:
            a, b = self.wps[self.seg], self.wps[self.seg + 1]
            d = b - a
            length = math.hypot(d[0], d[1])
            ux, uy = d[0] / length, d[1] / length
            along = (north_m - a[0]) * ux + (east_m - a[1]) * uy
            if along >= length and self.seg + 2 < len(self.wps):
                self.seg += 1
                continue
            break
        cross = -(north_m - a[0]) * uy + (east_m - a[1]) * ux  # + = to the right of the path
        desired = math.atan2(uy, ux) - math.atan(cross / self.lookahead)
        err = (desired - yaw_rad + math.pi) % (2 * math.pi) - math.pi
        return max(-self.max_rate, min(self.max_rate, self.gain * err))


def simulate_steps(scenario: Scenario, rng: np.random.Generator) -> MotionSteps:
    """Run guidance and draw the true velocities step by step (sequential: feedback)."""
    tr, T = scenario.trajectory, scenario.motion.step_s
    K = int(round(scenario.duration_s / T))
    table = scenario.rpm.table()
    rpm_cmd = float(table.rpm_for_speed(tr.speed_m_s))
    v_rep = float(table.speed(rpm_cmd))
    cur = np.array(scenario.current.vel_n_m_s())
    guide = LosGuidance(waypoints(scenario), tr.lookahead_m, tr.yaw_gain_per_s,
                        math.radians(tr.turn_rate_max_deg_s))
    t = np.arange(K + 1) * T
    pose = np.empty((K + 1, 3))
    pose[0] = (0.0, 0.0, math.radians(tr.heading_deg))
    out = {name: np.empty(K) for name in ("w", "V", "W", "S", "k_v")}
    rpm = np.full(K, rpm_cmd)
    v_steps = np.full(K, v_rep)
    for k in range(K):
        params = scenario.params_at(t[k])
        if t[k] < tr.start_delay_s:
            # stopped: the model still applies (V ~ N(0, σ_V1²), W ~ N(b_W, σ_W1²))
            rpm[k], v_steps[k], w = 0.0, float(table.speed(0.0)), 0.0
        else:
            ground_n = pose[k, 0] + cur[0] * t[k]
            ground_e = pose[k, 1] + cur[1] * t[k]
            w = guide.command(ground_n, ground_e, pose[k, 2])
        V, W, S = sample_velocities(params, v_steps[k], w, rng)
        pose[k + 1] = propagate(pose[k], V, W, S, T)
        out["w"][k], out["V"][k], out["W"][k], out["S"][k] = w, V, W, S
        out["k_v"][k] = params.k_v
    return MotionSteps(t_s=t, pose_water=pose, rpm=rpm, v_m_s=v_steps,
                       w_rad_s=out["w"], V_m_s=out["V"], W_rad_s=out["W"], S_m_s=out["S"],
                       k_v=out["k_v"])


def _depth_profile(scenario: Scenario, t: np.ndarray):
    """Smooth descent: depth (m) and down-velocity (m/s) at times ``t``."""
    tr = scenario.trajectory
    dd = tr.depth_m - tr.start_depth_m
    if dd == 0.0:
        return np.full_like(t, tr.depth_m), np.zeros_like(t)
    dur = 0.5 * math.pi * abs(dd) / tr.dive_rate_m_s
    ts = t - tr.start_delay_s
    phase = np.clip(ts / dur, 0.0, 1.0)
    vel = np.where((ts > 0) & (ts < dur), 0.5 * dd * math.pi / dur * np.sin(math.pi * phase), 0.0)
    return tr.start_depth_m + 0.5 * dd * (1.0 - np.cos(math.pi * phase)), vel


def _trapezoid_cumsum(vel: np.ndarray, dt: float) -> np.ndarray:
    out = np.zeros_like(vel)
    out[1:] = np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, axis=0)
    return out


def dense_truth(scenario: Scenario, steps: MotionSteps) -> DenseTruth:
    """Truth at every IMU instant, exactly consistent with ``steps`` (module docstring)."""
    T = scenario.motion.step_s
    M = int(round(T * scenario.imu.rate_hz))
    dt = 1.0 / scenario.imu.rate_hz
    K = len(steps.V_m_s)
    N = K * M
    # (K, M+1) grid of each step's instants, both ends included
    tau = np.arange(M + 1) * dt
    theta = steps.pose_water[:-1, 2:3] + steps.W_rad_s[:, None] * tau[None, :]
    c, s = np.cos(theta), np.sin(theta)
    wts = np.full(M + 1, dt)
    wts[0] = wts[-1] = 0.5 * dt
    h = np.clip(1.0 - tau / scenario.motion.ramp_s, 0.0, 1.0)
    a_c, a_s = c @ wts, s @ wts
    b_c, b_s = c @ (wts * h), s @ (wts * h)
    disp = steps.pose_water[1:, :2] - steps.pose_water[:-1, :2]
    u = np.empty((K, 2))
    prev = np.array([steps.V_m_s[0], steps.S_m_s[0]])
    for k in range(K):
        # (A − B) u = D − B prev, with A, B of the form [[p, −q], [q, p]]
        bx = b_c[k] * prev[0] - b_s[k] * prev[1]
        by = b_s[k] * prev[0] + b_c[k] * prev[1]
        rx, ry = disp[k, 0] - bx, disp[k, 1] - by
        p, q = a_c[k] - b_c[k], a_s[k] - b_s[k]
        det = p * p + q * q
        prev = np.array([(p * rx + q * ry) / det, (-q * rx + p * ry) / det])
        u[k] = prev
    u_prev = np.vstack([[steps.V_m_s[0], steps.S_m_s[0]], u[:-1]])
    # body velocity on the (K, M+1) grid → water velocity in n
    ub = u[:, None, :] + (u_prev - u)[:, None, :] * h[None, :, None]
    vn = c * ub[..., 0] - s * ub[..., 1]
    ve = s * ub[..., 0] + c * ub[..., 1]
    # flatten to the global grid: step k owns instants kM … kM+M−1, the last instant is N
    def flat(a):
        return np.concatenate([a[:, :-1].reshape(-1), a[-1:, -1]])
    t = np.arange(N + 1) / scenario.imu.rate_hz  # i/rate: equal to other sensors' k/rate
    yaw = flat(theta)
    cur = np.array(scenario.current.vel_n_m_s())
    down, vd = _depth_profile(scenario, t)
    vel = np.stack([flat(vn) + cur[0], flat(ve) + cur[1], vd], axis=1)
    vel_water = np.stack([flat(vn), flat(ve)], axis=1)
    pos = np.empty((N + 1, 3))
    # positions by the trapezoid rule (what the IMU is made consistent with); the water
    # part starts from the model pose so step instants land on the model poses.
    pos[:, :2] = _trapezoid_cumsum(vel_water, dt) + steps.pose_water[0, :2] + cur[None, :] * t[:, None]
    pos[:, 2] = _trapezoid_cumsum(vd[:, None], dt)[:, 0] + down[0]
    tr = scenario.trajectory
    surge = np.hypot(vel_water[:, 0], vel_water[:, 1])
    pitch = (math.radians(tr.pitch_trim_deg)
             + math.radians(tr.pitch_amp_deg) * np.sin(2 * math.pi * t / tr.pitch_period_s)
             - np.arctan2(vd, np.maximum(surge, 0.2)))
    roll = math.radians(tr.roll_amp_deg) * np.sin(2 * math.pi * t / tr.roll_period_s)
    euler = np.stack([roll, pitch, yaw], axis=1)
    xyzw = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_quat()
    q = xyzw[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return DenseTruth(t_s=t, pos_n_m=pos, vel_n_m_s=vel, euler_rad=euler, q_nb=q)
