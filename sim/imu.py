r"""IMU simulation: exact increments from the truth, then grade-dependent errors.

Exact signals
-------------
The truth is sampled at the IMU instants ``t_i = i Δt``. Sample ``i`` describes the
interval ``(t_{i-1}, t_i]``:

    ω_i = log(R_{i-1}ᵀ R_i) / Δt                         (constant-rate rotation, rad/s)
    f_i = R_mid,iᵀ ((v_i − v_{i-1}) / Δt − g_n)          (m/s², body FRD)

with ``R_mid,i = R_{i-1} exp(½ ω_i Δt)`` and ``g_n = (0, 0, g)``. A strapdown
integrator ``q_i = q_{i-1} ⊗ exp(ω_i Δt)``, ``v_i = v_{i-1} + R_mid f_i Δt + g_n Δt``,
``p_i = p_{i-1} + ½ (v_{i-1} + v_i) Δt`` reproduces the truth to rounding error
(the simulator builds positions with that trapezoid rule). Integrators that use
``R_{i-1}(I + ½[ω Δt]×)`` instead of ``R_mid`` differ by O((ω Δt)²) ≈ 1e-7 relative.
Earth rate and gravity variation are not modelled (flat, non-rotating NED; gravity
:data:`adaptnav.fusion.frames.GRAVITY_M_S2`).

Errors (per axis, independent)
------------------------------
    y = x + b_0 + b_GM(t) + b_RW(t) + n

``b_0`` turn-on bias ~ N(0, σ_0²); ``b_GM`` first-order Gauss–Markov bias instability
with stationary σ_BI and correlation time τ (``b_{k+1} = a b_k + σ_BI √(1−a²) ξ``,
``a = e^{−Δt/τ}``); ``b_RW`` random walk with density ``q_RW`` (σ grows as
``q_RW √t``); ``n`` white noise with density ``N`` (ARW / VRW), σ = N / √Δt.

Grades — per-axis 1-σ values from the datasheet classes (rounded, typical figures):

- ``consumer``: MEMS, Bosch BMI088 / InvenSense ICM-20948 class: gyro offset after
  trimming ~0.5 °/s, bias instability ~5 °/h, noise 0.014 °/s/√Hz; accel offset ~20 mg,
  bias instability ~40 µg, noise ~175 µg/√Hz.
- ``tactical``: Honeywell HG1700 / KVH 1750 / Safran STIM300 class: gyro bias 1 °/h,
  instability 0.3 °/h, ARW 0.15 °/√h; accel bias 1 mg, instability 0.05 mg,
  VRW 0.06 m/s/√h.
- ``navigation``: Honeywell HG9900 / iXblue PHINS class: gyro bias 0.003 °/h,
  instability 0.002 °/h, ARW 0.002 °/√h; accel bias 25 µg, instability 10 µg,
  VRW 0.005 m/s/√h.
- ``perfect``: no errors (tests).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from adaptnav.fusion.frames import GRAVITY_M_S2

DEG = math.pi / 180.0
HOUR = 3600.0
MG = 1e-3 * GRAVITY_M_S2
UG = 1e-6 * GRAVITY_M_S2


@dataclass(frozen=True)
class SensorErrorModel:
    """Per-axis error terms of one triad (SI units; densities per √Hz)."""

    turn_on_sigma: float          # b_0 1-σ (rad/s or m/s²)
    instability_sigma: float      # Gauss–Markov stationary 1-σ
    correlation_time_s: float     # Gauss–Markov τ
    white_density: float          # ARW (rad/s/√Hz) or VRW (m/s²/√Hz)
    random_walk_density: float    # rate / acceleration random walk (unit/s/√Hz)


@dataclass(frozen=True)
class ImuGrade:
    gyro: SensorErrorModel
    accel: SensorErrorModel


_ZERO = SensorErrorModel(0.0, 0.0, 1.0, 0.0, 0.0)

IMU_GRADES: dict[str, ImuGrade] = {
    "consumer": ImuGrade(
        gyro=SensorErrorModel(0.5 * DEG, 5.0 * DEG / HOUR, 300.0, 0.014 * DEG, 1e-5 * DEG),
        accel=SensorErrorModel(20 * MG, 40 * UG, 300.0, 175 * UG, 1e-5),
    ),
    "tactical": ImuGrade(
        gyro=SensorErrorModel(1.0 * DEG / HOUR, 0.3 * DEG / HOUR, 600.0,
                              0.15 * DEG / math.sqrt(HOUR), 0.01 * DEG / HOUR / math.sqrt(HOUR)),
        accel=SensorErrorModel(1 * MG, 0.05 * MG, 600.0, 0.06 / math.sqrt(HOUR), 1e-6),
    ),
    "navigation": ImuGrade(
        gyro=SensorErrorModel(0.003 * DEG / HOUR, 0.002 * DEG / HOUR, 3600.0,
                              0.002 * DEG / math.sqrt(HOUR), 1e-4 * DEG / HOUR / math.sqrt(HOUR)),
        accel=SensorErrorModel(25 * UG, 10 * UG, 3600.0, 0.005 / math.sqrt(HOUR), 1e-7),
    ),
    "perfect": ImuGrade(gyro=_ZERO, accel=_ZERO),
}


def exact_imu(q_nb: np.ndarray, vel_n_m_s: np.ndarray, dt_s: float):
    """Exact IMU increments between consecutive truth samples (see module docstring).

    Parameters
    ----------
    q_nb : (N+1, 4) truth attitudes (w, x, y, z) at ``t_0 … t_N``
    vel_n_m_s : (N+1, 3) truth NED velocities at the same instants
    dt_s : IMU interval (s)

    Returns
    -------
    specific_force_b_m_s2, omega_b_rad_s : (N, 3) arrays for the samples at ``t_1 … t_N``
    """
    rot = Rotation.from_quat(np.asarray(q_nb)[:, [1, 2, 3, 0]])
    prev, curr = rot[:-1], rot[1:]
    dtheta = (prev.inv() * curr).as_rotvec()
    mid = prev * Rotation.from_rotvec(0.5 * dtheta)
    accel_n = np.diff(vel_n_m_s, axis=0) / dt_s
    accel_n[:, 2] -= GRAVITY_M_S2
    return mid.inv().apply(accel_n), dtheta / dt_s


def triad_errors(model: SensorErrorModel, n: int, dt_s: float, rng: np.random.Generator):
    """Error time series of one 3-axis sensor.

    Returns
    -------
    slow_bias : (n, 3) turn-on + Gauss–Markov + random walk (what a filter estimates)
    white : (n, 3) white noise
    """
    b0 = model.turn_on_sigma * rng.standard_normal(3)
    a = math.exp(-dt_s / model.correlation_time_s)
    drive = rng.standard_normal((n, 3)) * (model.instability_sigma * math.sqrt(1.0 - a * a))
    gm0 = model.instability_sigma * rng.standard_normal(3)  # start in the stationary law
    gm, _ = lfilter([1.0], [1.0, -a], drive, axis=0, zi=(a * gm0)[None, :])
    rw = np.cumsum(rng.standard_normal((n, 3)) * (model.random_walk_density * math.sqrt(dt_s)), axis=0)
    white = rng.standard_normal((n, 3)) * (model.white_density / math.sqrt(dt_s))
    return b0 + gm + rw, white


def corrupt_imu(specific_force_b_m_s2, omega_b_rad_s, grade: str, dt_s: float,
                rng: np.random.Generator):
    """Add a grade's errors to exact IMU signals.

    Returns
    -------
    (f_meas, omega_meas, bias_acc, bias_gyro) : four (N, 3) arrays; the biases exclude
    the white noise (they are what the truth reports as the current bias).
    """
    g = IMU_GRADES[grade]
    n = len(omega_b_rad_s)
    acc_rng, gyro_rng = rng.spawn(2)
    bias_gyro, white_gyro = triad_errors(g.gyro, n, dt_s, gyro_rng)
    bias_acc, white_acc = triad_errors(g.accel, n, dt_s, acc_rng)
    return (specific_force_b_m_s2 + bias_acc + white_acc, omega_b_rad_s + bias_gyro + white_gyro,
            bias_acc, bias_gyro)
