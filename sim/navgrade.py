r"""A navigation-grade AUV on the real (rotating, ellipsoidal) earth: what its IMU and its
autopilot's attitude really report along a simulated trajectory.

The simulator's truth (:mod:`adaptnav.sim.vehicle`) is flat: ``pos_n`` are north/east arc
lengths and depth from the origin (the mapping of :class:`adaptnav.fusion.frames.GeoOrigin`),
``vel_n`` their rates, the attitude relative to the local level, and its IMU
(:func:`adaptnav.sim.imu.exact_imu`) is ``f = R_bnᵀ(v̇ − g₀ e_z)``, ``ω = ω_nb``.  On the earth the
same trajectory is sensed as (local-level NED mechanisation, Groves 2013 §5.4, eqs. 5.44–5.54)::

    ω_ib^b = ω_nb^b + R_bn (ω_ie^n + ω_en^n)
    f^b    = R_bn (v̇^n + (2 ω_ie^n + ω_en^n) × v^n − γ(L, h) e_z)

with the earth rate ``ω_ie^n = Ω (cos L, 0, −sin L)`` and the transport rate
``ω_en^n = (v_E/(R_E+h), −v_N/(R_N+h), −v_E tan L/(R_E+h))`` at the vehicle's own latitude
``L`` and height ``h`` (``R_N`` meridian, ``R_E`` transverse radius of curvature), and the normal
gravity of Somigliana with the free-air gradient ``γ(L, h) ≈ γ(L)(1 − 2h/a)``.  A fibre-optic
gyro sees all of it: the earth rate is 15 °/h, the transport rate of a 1.5 m/s vehicle
0.05 °/h, against a navigation-grade bias of 0.003–0.01 °/h.

The autopilot's attitude (``ATTITUDE``) comes from one of two classes of source
(:class:`AhrsErrors`, the same error model with the class's figures):

- a **compass-grade AHRS** (:data:`COMPASS_AHRS`, ArduSub's EKF3 on a consumer IMU and a
  magnetometer): roll and pitch within a few tenths of a degree, and a magnetic heading whose
  error is a constant offset (declination and calibration residue), a heading-dependent
  deviation ``A sin ψ + B cos ψ`` (hard iron: thrusters, batteries), a slow wander
  (Gauss–Markov) and noise.  Marine magnetic compasses after a deviation swing keep 1–2°
  (IMO A.382); a small vehicle's compass near its thrusters does worse (Kinsey, Eustice &
  Whitcomb, "A survey of underwater vehicle navigation", IFAC 2006: 1–10° for magnetic heading
  sensors on vehicles);
- the vehicle's own **navigation-grade INS** (:func:`ins_ahrs_errors`, iXblue PHINS / Sonardyne
  SPRINT class, its attitude forwarded as ``ATTITUDE``): a gyrocompass, no magnetic terms;
  heading 0.01–0.1° sec L (PHINS: 0.01° sec L with DVL aiding, 0.05° sec L without;
  roll/pitch 0.01°), its error a slow oscillation (Schuler 84 min, earth period) modelled as
  an offset plus a Gauss–Markov wander of half-hour correlation, and a milli-degree noise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from adaptnav.fusion.frames import GRAVITY_M_S2, WGS84_A_M, WGS84_E2, GeoOrigin
from adaptnav.fusion.strapdown import EARTH_RATE_RAD_S, normal_gravity_m_s2


def gravity_at_m_s2(lat_rad: np.ndarray, height_m: np.ndarray) -> np.ndarray:
    """Normal gravity (Somigliana, WGS-84) with the free-air gradient ``1 − 2h/a``, m/s²."""
    g0 = np.array([normal_gravity_m_s2(float(x)) for x in np.ravel(lat_rad)]).reshape(np.shape(lat_rad))
    return g0 * (1.0 - 2.0 * np.asarray(height_m) / WGS84_A_M)


def rotating_earth_imu(pos_n_m: np.ndarray, vel_n_m_s: np.ndarray, q_nb: np.ndarray, origin: GeoOrigin,
                       f_b_m_s2: np.ndarray, w_b_rad_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Add what the earth adds to a flat IMU (module docstring).

    Parameters
    ----------
    pos_n_m, vel_n_m_s : (N+1, 3) truth at the IMU instants ``t_0 … t_N`` (NED arc lengths, m; m/s)
    q_nb : (N+1, 4) truth attitude (w, x, y, z) relative to the local level
    origin : the geodetic origin of ``pos_n_m``
    f_b_m_s2, w_b_rad_s : (N, 3) the flat IMU's samples for the intervals ending at ``t_1 … t_N``
        (errors included: the earth terms are added, not the errors re-drawn)

    Returns
    -------
    (f_b, w_b) : (N, 3) each, m/s² and rad/s
    """
    pos = 0.5 * (pos_n_m[1:] + pos_n_m[:-1])  # mid-interval
    vel = 0.5 * (vel_n_m_s[1:] + vel_n_m_s[:-1])
    lat, _, h = origin.to_geodetic(pos)
    s2 = np.sin(lat) ** 2
    denom = np.sqrt(1.0 - WGS84_E2 * s2)
    r_n = WGS84_A_M * (1.0 - WGS84_E2) / denom**3 + h  # meridian
    r_e = WGS84_A_M / denom + h  # transverse
    w_ie = EARTH_RATE_RAD_S * np.stack([np.cos(lat), np.zeros_like(lat), -np.sin(lat)], axis=1)
    w_en = np.stack([vel[:, 1] / r_e, -vel[:, 0] / r_n, -vel[:, 1] * np.tan(lat) / r_e], axis=1)
    rot = Rotation.from_quat(np.asarray(q_nb)[1:, [1, 2, 3, 0]])  # b → n at the interval's end
    extra_f_n = np.cross(2.0 * w_ie + w_en, vel)
    extra_f_n[:, 2] -= gravity_at_m_s2(lat, h) - GRAVITY_M_S2
    return f_b_m_s2 + rot.inv().apply(extra_f_n), w_b_rad_s + rot.inv().apply(w_ie + w_en)


@dataclass(frozen=True)
class AhrsErrors:
    """An autopilot AHRS's attitude errors (degrees; module docstring for the figures)."""

    level_bias_deg: float = 0.3          # roll/pitch offset 1-σ (mounting, accelerometer offsets)
    level_noise_deg: float = 0.05
    heading_offset_deg: float = 2.0      # constant heading offset 1-σ
    deviation_deg: float = 1.5           # 1-σ of each of A, B in A sin ψ + B cos ψ
    wander_deg: float = 0.5              # Gauss–Markov wander, stationary 1-σ ...
    wander_time_s: float = 300.0         # ... and correlation time
    heading_noise_deg: float = 0.1


COMPASS_AHRS = AhrsErrors()


def ins_ahrs_errors(lat_deg: float, heading_sec_lat_deg: float = 0.05) -> AhrsErrors:
    """A navigation-grade INS's attitude errors (module docstring) at latitude ``lat_deg``:
    heading 1-σ ``heading_sec_lat_deg · sec L`` (split evenly between an offset and a
    half-hour wander), roll/pitch 0.01°."""
    h = heading_sec_lat_deg / math.cos(math.radians(lat_deg)) / math.sqrt(2.0)
    return AhrsErrors(level_bias_deg=0.01, level_noise_deg=0.002, heading_offset_deg=h, deviation_deg=0.0,
                      wander_deg=h, wander_time_s=1800.0, heading_noise_deg=0.003)


def ahrs_attitude(t_s: np.ndarray, euler_rad: np.ndarray, errors: AhrsErrors,
                  rng: np.random.Generator) -> np.ndarray:
    """The attitude an autopilot reports: truth (K, 3) roll, pitch, yaw (rad) at ``t_s`` (K,)
    plus :class:`AhrsErrors`; yaw wrapped to [−π, π)."""
    d = math.radians
    k = len(t_s)
    level_bias = d(errors.level_bias_deg) * rng.standard_normal(2)
    offset = d(errors.heading_offset_deg) * rng.standard_normal()
    a, b = d(errors.deviation_deg) * rng.standard_normal(2)
    dt = float(np.median(np.diff(t_s))) if k > 1 else 1.0
    phi = math.exp(-dt / errors.wander_time_s)
    drive = d(errors.wander_deg) * math.sqrt(1.0 - phi * phi) * rng.standard_normal(k)
    wander, _ = lfilter([1.0], [1.0, -phi], drive, zi=[phi * d(errors.wander_deg) * rng.standard_normal()])
    out = np.array(euler_rad, dtype=float, copy=True)
    out[:, :2] += level_bias + d(errors.level_noise_deg) * rng.standard_normal((k, 2))
    yaw = out[:, 2]
    out[:, 2] = yaw + offset + a * np.sin(yaw) + b * np.cos(yaw) + wander \
        + d(errors.heading_noise_deg) * rng.standard_normal(k)
    out[:, 2] = (out[:, 2] + math.pi) % (2 * math.pi) - math.pi
    return out
