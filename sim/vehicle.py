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
3. ground position = water-relative position + current · t (constant current), plus the
   integral of the surface drift while the vehicle is in the surface layer.

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

With ``vehicle.model = "fossen3dof"`` step 2 is physics instead of the motion model: the
surge–sway–yaw body of :class:`Fossen3Dof` is integrated through the step and the step's
``(V_k, W_k, S_k)`` are read off the poses it reaches (:func:`invert_step`); the true k_V is
then whatever the water, trim, payload and fouling make of the thrust (:meth:`Fossen3Dof.k_v`)
and the body pitches by the angle of attack that holds depth (``MotionSteps.pitch_rad``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from adaptnav.fusion.motion_model import invert_step, propagate, sample_velocities
from adaptnav.sim.scenario import Scenario


@dataclass(frozen=True)
class MotionSteps:
    """The motion-model view of the truth: one row per step (what the calibrator sees).

    ``t_s`` (K+1,) step instants; ``pose_water`` (K+1, 3) water-relative (x north m,
    y east m, θ yaw rad, unwrapped); ``rpm``, ``v_m_s``, ``w_rad_s`` (K,) the reported
    controls; ``V_m_s``, ``W_rad_s``, ``S_m_s`` (K,) the true velocities drawn;
    ``k_v`` (K,) the true k_V in force; ``pitch_rad`` (K,) or None, a pitch the vehicle
    physics adds to the trajectory's (angle of attack holding depth; fossen3dof only).
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
    pitch_rad: np.ndarray | None = None


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


# REMUS 100 (Prestero 2001, "Verification of a six-degree of freedom simulation model for the
# REMUS autonomous underwater vehicle", MIT/WHOI MSc thesis, tables of hydrodynamic
# coefficients; values rounded): mass, yaw inertia, added mass, quadratic and cross-flow
# drag, body lift and rudder derivatives. A linear surge drag (Fossen 2011, "Handbook of
# Marine Craft Hydrodynamics and Motion Control", §6.4: linear + quadratic damping) is added.
REMUS100 = dict(
    mass_kg=30.5, izz_kg_m2=3.45, reference_density_kg_m3=1025.0,
    x_udot=-0.93, y_vdot=-35.5, n_rdot=-4.88,
    x_uu=-1.62, x_u=-1.0, x_vr=35.5, x_rr=-1.93,
    y_vv=-1310.0, y_rr=0.632, y_uv=-28.6, y_ur=5.22, y_uudr=9.64,
    n_vv=-3.18, n_rr=-94.0, n_uv=-24.0, n_ur=-2.0, n_uudr=-6.15,
    z_uw=-28.6, rudder_max_rad=math.radians(15.0),
)


@dataclass(frozen=True)
class Condition:
    """What acts on the vehicle's dynamics: water density (kg/m³), trim (rad), payload (kg)
    and fouling (fractional drag increase)."""

    density_kg_m3: float
    trim_rad: float
    payload_kg: float
    fouling: float


class Fossen3Dof:
    r"""Surge–sway–yaw rigid body in Fossen's form ``M ν̇ + C(ν) ν + D(ν) ν = τ``, ν = (u, v, r).

    ::

        (m − X_u̇) u̇ = ρ̃ [X_u u + X_uu u|u| (1+f)] − L(u) α + (m + ρ̃X_vr) v r + ρ̃X_rr r² + T(n) + w_u
        (m − Y_v̇) v̇ = ρ̃ [Y_vv v|v| + Y_uv u v + Y_rr r|r| + Y_uuδ u² δ] + (ρ̃Y_ur − m) u r + w_v
        (I_z − N_ṙ) ṙ = ρ̃ [N_vv v|v| + N_uv u v + N_ur u r + N_rr r|r| + N_uuδ u² δ] + w_r

    with ``ρ̃ = ρ/ρ_ref`` (every hydrodynamic force and added mass scales with density) and
    ``m`` the dry mass plus payload. Thrust ``T(n) = ρ̃ · (−X_u f − X_uu f|f|)``, ``f = f(n)``
    the RPM table: the nominal vehicle (reference density, neutral, clean) cruises at
    exactly ``f(n)`` — the table is its steady state. Depth is held with lift: the net
    weight ``F_z = m g − ρ ∇ g`` (∇ makes the clean vehicle neutral at ρ_ref) needs an angle
    of attack ``α = trim + F_z / (ρ̃|Z_uw| u²)`` whose lift ``L = ρ̃|Z_uw| u² α`` tilts
    back as induced drag ``L α``. So density barely changes speed per RPM directly
    (thrust and drag both ∝ ρ); it does through buoyancy → angle of attack → drag, as
    trim, payload and fouling do (DESIGN.md "Physics of a change of water"). The rudder
    follows the guidance's yaw-rate command by inverting the yaw equation (saturated).
    """

    GRAVITY = 9.81

    def __init__(self, coeffs: dict | None = None):
        self.c = dict(REMUS100 if coeffs is None else coeffs)
        self.volume_m3 = self.c["mass_kg"] / self.c["reference_density_kg_m3"]

    def _rho(self, cond: Condition) -> float:
        return cond.density_kg_m3 / self.c["reference_density_kg_m3"]

    def angle_of_attack(self, u: float, cond: Condition) -> float:
        c, rho = self.c, self._rho(cond)
        fz = (c["mass_kg"] + cond.payload_kg - cond.density_kg_m3 * self.volume_m3) * self.GRAVITY
        return max(-0.35, min(0.35, cond.trim_rad + fz / (rho * abs(c["z_uw"]) * max(u, 0.3) ** 2)))

    def thrust(self, speed_table_m_s: float, cond: Condition) -> float:
        c, f = self.c, speed_table_m_s
        return self._rho(cond) * (-c["x_u"] * f - c["x_uu"] * f * abs(f))

    def surge_drag(self, u: float, cond: Condition) -> float:
        """Hydrodynamic surge force at surge ``u`` (N, negative), induced drag included."""
        c, rho = self.c, self._rho(cond)
        a = self.angle_of_attack(u, cond)
        return rho * (c["x_u"] * u + c["x_uu"] * u * abs(u) * (1.0 + cond.fouling)) - rho * abs(c["z_uw"]) * u * u * a * a

    def steady_surge(self, speed_table_m_s: float, cond: Condition) -> float:
        """Surge where thrust balances drag (bisection; m/s)."""
        thrust = self.thrust(speed_table_m_s, cond)
        if thrust <= 0.0:
            return 0.0
        lo, hi = 0.0, 3.0 * max(speed_table_m_s, 0.1)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if thrust + self.surge_drag(mid, cond) > 0 else (lo, mid)
        return 0.5 * (lo + hi)

    def k_v(self, speed_table_m_s: float, cond: Condition) -> float:
        """Speed per RPM relative to the table: the motion model's k_V under ``cond``."""
        if speed_table_m_s <= 0.05:
            return 1.0
        return self.steady_surge(speed_table_m_s, cond) / speed_table_m_s

    def step(self, nu: np.ndarray, speed_table_m_s: float, r_cmd: float, cond: Condition,
             dt: float, force_noise: np.ndarray) -> np.ndarray:
        """One explicit-Euler step of ν = (u, v, r); ``force_noise`` (3,) N, N, N m, the
        turbulent fluctuation over this step (white: its density × 1/√dt)."""
        c, rho = self.c, self._rho(cond)
        u, v, r = float(nu[0]), float(nu[1]), float(nu[2])
        m = c["mass_kg"] + cond.payload_kg
        m_u = m - rho * c["x_udot"]
        m_v = m - rho * c["y_vdot"]
        i_r = c["izz_kg_m2"] - rho * c["n_rdot"]
        # yaw: the rudder that gives ṙ = (r_cmd − r)/τ (τ = 1 s), within its travel
        n_other = rho * (c["n_vv"] * v * abs(v) + c["n_uv"] * u * v + c["n_ur"] * u * r + c["n_rr"] * r * abs(r))
        n_per_rad = rho * c["n_uudr"] * u * u
        delta = 0.0
        if abs(n_per_rad) > 1e-6:
            delta = (i_r * (r_cmd - r) / 1.0 - n_other) / n_per_rad
            delta = max(-c["rudder_max_rad"], min(c["rudder_max_rad"], delta))
        du = (self.thrust(speed_table_m_s, cond) + self.surge_drag(u, cond)
              + (m + rho * c["x_vr"]) * v * r + rho * c["x_rr"] * r * r + force_noise[0]) / m_u
        dv = (rho * (c["y_vv"] * v * abs(v) + c["y_uv"] * u * v + c["y_rr"] * r * abs(r) + c["y_uudr"] * u * u * delta)
              + (rho * c["y_ur"] - m) * u * r + force_noise[1]) / m_v
        dr = (n_other + n_per_rad * delta + force_noise[2]) / i_r
        return np.array([u + du * dt, v + dv * dt, r + dr * dt])


def condition_at(scenario: Scenario, t_s: float) -> Condition:
    """The vehicle's condition in force at ``t_s`` (``*_after`` from the change on)."""
    veh, after = scenario.vehicle, t_s >= scenario.change_at_s

    def pick(before, later):
        return later if (after and later is not None) else before

    return Condition(scenario.density_at(t_s), math.radians(pick(veh.trim_deg, veh.trim_after_deg)),
                     pick(veh.payload_kg, veh.payload_after_kg), pick(veh.fouling, veh.fouling_after))


def _fossen_steps(scenario: Scenario, rng: np.random.Generator) -> MotionSteps:
    """Guidance + the physical vehicle (:class:`Fossen3Dof`), read out per motion step."""
    tr, T, veh = scenario.trajectory, scenario.motion.step_s, scenario.vehicle
    K = int(round(scenario.duration_s / T))
    n_sub = max(1, int(round(T / veh.integration_step_s)))
    dt = T / n_sub
    table = scenario.rpm.table()
    rpm_cmd = float(table.rpm_for_speed(tr.speed_m_s))
    v_rep = float(table.speed(rpm_cmd))
    cur = np.array(scenario.current.vel_n_m_s())
    guide = LosGuidance(waypoints(scenario), tr.lookahead_m, tr.yaw_gain_per_s,
                        math.radians(tr.turn_rate_max_deg_s))
    body = Fossen3Dof()
    t = np.arange(K + 1) * T
    pose = np.empty((K + 1, 3))
    pose[0] = (0.0, 0.0, math.radians(tr.heading_deg))
    nu = np.array([v_rep if tr.start_delay_s <= 0 else 0.0, 0.0, 0.0])
    rpm = np.full(K, rpm_cmd)
    v_steps = np.full(K, v_rep)
    w_cmd, k_v, pitch = np.empty(K), np.empty(K), np.empty(K)
    c = body.c
    sig = np.array([veh.surge_force_rel_rthz * abs(c["x_uu"]), veh.sway_force_rel_rthz * abs(c["x_uu"]),
                    veh.yaw_moment_rel_rthz * abs(c["n_uv"])]) / math.sqrt(dt)
    for k in range(K):
        cond = condition_at(scenario, t[k])
        if t[k] < tr.start_delay_s:
            rpm[k], v_steps[k], w = 0.0, float(table.speed(0.0)), 0.0
        else:
            w = guide.command(pose[k, 0] + cur[0] * t[k], pose[k, 1] + cur[1] * t[k], pose[k, 2])
        x, y, psi = pose[k]
        noise = sig[None, :] * rng.standard_normal((n_sub, 3))
        for j in range(n_sub):
            nu_next = body.step(nu, v_steps[k], w, cond, dt, noise[j] * nu[0] * abs(nu[0]))
            # trapezoid on the body velocity rotated by the mid-step heading
            psi_mid = psi + 0.5 * (nu[2] + nu_next[2]) * 0.5 * dt
            ub, vb = 0.5 * (nu[0] + nu_next[0]), 0.5 * (nu[1] + nu_next[1])
            x += (ub * math.cos(psi_mid) - vb * math.sin(psi_mid)) * dt
            y += (ub * math.sin(psi_mid) + vb * math.cos(psi_mid)) * dt
            psi += 0.5 * (nu[2] + nu_next[2]) * dt
            nu = nu_next
        pose[k + 1] = (x, y, psi)
        w_cmd[k] = w
        k_v[k] = body.k_v(v_steps[k], cond)
        pitch[k] = body.angle_of_attack(max(nu[0], 0.3), cond) if v_steps[k] > 0.05 else cond.trim_rad
    V, W, S, _ = invert_step(pose[:-1], pose[1:], T, turn_ref_rad=w_cmd * T)
    return MotionSteps(t_s=t, pose_water=pose, rpm=rpm, v_m_s=v_steps, w_rad_s=w_cmd,
                       V_m_s=np.asarray(V), W_rad_s=np.asarray(W), S_m_s=np.asarray(S), k_v=k_v,
                       pitch_rad=pitch)


def simulate_steps(scenario: Scenario, rng: np.random.Generator) -> MotionSteps:
    """Run guidance and draw the true velocities step by step (sequential: feedback).

    ``vehicle.model = "fossen3dof"``: the physical vehicle instead (:func:`_fossen_steps`).
    """
    if scenario.vehicle.model == "fossen3dof":
        return _fossen_steps(scenario, rng)
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
    if scenario.current.surface_drift_speed_m_s > 0:
        # the surface layer's drift carries the vehicle while it is in it (not the guidance:
        # it steers the water-relative pose plus the current at depth, as an unaided vehicle)
        drift = scenario.current.surface_drift_n_m_s(pos[:, 2])
        vel[:, :2] += drift
        pos[:, :2] += _trapezoid_cumsum(drift, dt)
    tr = scenario.trajectory
    surge = np.hypot(vel_water[:, 0], vel_water[:, 1])
    extra = 0.0
    if steps.pitch_rad is not None:  # the physics' angle of attack, smooth between step midpoints
        extra = np.interp(t, steps.t_s[:-1] + 0.5 * T, steps.pitch_rad)
    pitch = (math.radians(tr.pitch_trim_deg) + extra
             + math.radians(tr.pitch_amp_deg) * np.sin(2 * math.pi * t / tr.pitch_period_s)
             - np.arctan2(vd, np.maximum(surge, 0.2)))
    roll = math.radians(tr.roll_amp_deg) * np.sin(2 * math.pi * t / tr.roll_period_s)
    euler = np.stack([roll, pitch, yaw], axis=1)
    xyzw = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_quat()
    q = xyzw[:, [3, 0, 1, 2]]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return DenseTruth(t_s=t, pos_n_m=pos, vel_n_m_s=vel, euler_rad=euler, q_nb=q)
