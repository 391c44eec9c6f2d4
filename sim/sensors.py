r"""Aiding-sensor models on top of the dense truth (vectorised over sample times).

- heading: ``ψ + N(0, σ²)``, wrapped to [−π, π).
- depth: absolute pressure ``p = p_atm + ρ(t) g d + N(0, (ρ₀ g σ_d)²)`` — the density ρ
  changes with the environment, so a filter that keeps the old ρ sees a small depth bias.
- GNSS: only while the true depth ≤ ``max_depth_m``; horizontal error σ per axis (the σ the
  fix reports), of which ``bias_sigma_m`` is a first-order Gauss–Markov process with
  correlation time ``bias_time_s`` and the rest white: a receiver's error is mostly shared
  by fixes minutes apart (multipath, ionosphere and troposphere residuals; Groves, *Principles
  of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed., §9.4), its
  short-term noise a fraction of its CEP.
- USBL: geodetic position + depth with σ_h per horizontal axis and σ_v, every
  ``period_s`` from ``start_s`` until ``lost_after_s`` (inclusive), none within
  ``outages_s`` intervals ``[start, end)``; of σ_h, ``bias_sigma_m`` is Gauss–Markov as the
  GNSS's (a transducer's residual misalignment and the sound-speed profile bend every fix of a
  leg alike; the ping-to-ping part is white).
- DVL bottom track: ``v_d = R_db (R_bn v_n + ω_b × r_b) + N(0, σ²)`` with lever arm
  ``r_b`` and mounting ``R_bd``; ``valid`` false during outages, random drop-outs, or
  when the altitude exceeds the bottom-lock range.
- range beacons: ``|p − b| + N(0, σ²)``.
- RPM: the commanded propeller speed of the step in force.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from adaptnav.fusion.frames import GRAVITY_M_S2
from adaptnav.fusion.samples import (DepthSample, DvlSample, GnssSample, HeadingSample, RangeSample,
                            RpmSample, TruthSample, UsblSample)
from adaptnav.sim.scenario import Scenario
from adaptnav.sim.vehicle import DenseTruth, MotionSteps


def sample_times(rate_hz: float, duration_s: float, start_s: float = 0.0) -> np.ndarray:
    """Instants ``start + k / rate`` up to and including ``duration_s`` (integer arithmetic)."""
    if rate_hz <= 0:
        return np.empty(0)
    n = int(math.floor((duration_s - start_s) * rate_hz + 1e-9)) + 1
    return start_s + np.arange(max(n, 0)) / rate_hz


def periodic_times(period_s: float, end_s: float, start_s: float = 0.0) -> np.ndarray:
    """Instants ``start + k · period`` up to and including ``end_s``."""
    if period_s <= 0 or end_s < start_s:
        return np.empty(0)
    n = int(math.floor((end_s - start_s) / period_s + 1e-9)) + 1
    return start_s + np.arange(n) * period_s


class TruthInterpolator:
    """Truth at arbitrary times by linear interpolation of the IMU-rate grid."""

    def __init__(self, dense: DenseTruth):
        self.d = dense
        self.dt = dense.t_s[1] - dense.t_s[0]

    def _interp(self, arr: np.ndarray, t: np.ndarray) -> np.ndarray:
        x = np.clip(t / self.dt, 0.0, len(self.d.t_s) - 1.0)
        i0 = np.minimum(np.floor(x + 1e-9).astype(int), len(self.d.t_s) - 2)
        frac = np.clip(x - i0, 0.0, 1.0)
        frac = np.where(frac < 1e-9, 0.0, frac)  # exact grid instants stay exact
        a0, a1 = arr[i0], arr[i0 + 1]
        if arr.ndim == 2:
            frac = frac[:, None]
        return a0 + (a1 - a0) * frac

    def pos(self, t):
        return self._interp(self.d.pos_n_m, t)

    def vel(self, t):
        return self._interp(self.d.vel_n_m_s, t)

    def euler(self, t):
        return self._interp(self.d.euler_rad, t)

    def rotation(self, t) -> Rotation:
        e = self.euler(t)
        return Rotation.from_euler("ZYX", e[:, ::-1])

    def omega_b(self, t):
        """Body rate (rad/s) from finite differences of the attitude around ``t``."""
        h = 0.5 * self.dt
        r0, r1 = self.rotation(np.maximum(t - h, 0.0)), self.rotation(t + h)
        return (r0.inv() * r1).as_rotvec() / (2 * h)


def rpm_samples(scenario: Scenario, steps: MotionSteps) -> list[RpmSample]:
    t = sample_times(scenario.rpm.rate_hz, scenario.duration_s)
    k = np.minimum((t / scenario.motion.step_s + 1e-9).astype(int), len(steps.rpm) - 1)
    return [RpmSample(float(ti), float(r)) for ti, r in zip(t, steps.rpm[k])]


def heading_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[HeadingSample]:
    cfg = scenario.heading
    if not cfg.enabled:
        return []
    t = sample_times(cfg.rate_hz, scenario.duration_s)
    yaw = truth.euler(t)[:, 2] + math.radians(cfg.sigma_deg) * rng.standard_normal(len(t))
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return [HeadingSample(float(a), float(b)) for a, b in zip(t, yaw)]


def depth_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[DepthSample]:
    cfg, env = scenario.depth, scenario.environment
    if not cfg.enabled:
        return []
    t = sample_times(cfg.rate_hz, scenario.duration_s)
    depth = truth.pos(t)[:, 2]
    rho = np.array([scenario.density_at(ti) for ti in t]) if len(t) else np.empty(0)
    p = (env.atmospheric_pressure_pa + rho * GRAVITY_M_S2 * depth
         + env.density_kg_m3 * GRAVITY_M_S2 * cfg.sigma_m * rng.standard_normal(len(t)))
    return [DepthSample(float(a), float(b)) for a, b in zip(t, p)]


def gauss_markov(t_s: np.ndarray, sigma: float, time_constant_s: float, dims: int, rng) -> np.ndarray:
    """A stationary first-order Gauss–Markov process of standard deviation ``sigma`` and
    correlation time ``time_constant_s`` sampled at the increasing times ``t_s``, ``dims``
    independent axes: ``x₀ ~ N(0, σ²)``, ``x_k = a x_{k−1} + σ √(1 − a²) n_k`` with
    ``a = exp(−Δt/τ)`` (exact for any spacing). ``sigma`` 0: zeros, and nothing drawn from
    ``rng`` (the white noise drawn before stays the same stream)."""
    out = np.zeros((len(t_s), dims))
    if sigma <= 0.0 or not len(t_s):
        return out
    n = rng.standard_normal((len(t_s), dims))
    a = np.exp(-np.diff(t_s) / time_constant_s)
    out[0] = sigma * n[0]
    for k in range(1, len(t_s)):
        out[k] = a[k - 1] * out[k - 1] + sigma * math.sqrt(1.0 - a[k - 1] ** 2) * n[k]
    return out


def _white_sigma(cfg) -> float:
    """The white part of a fix's reported σ (``sigma_m``) beside its shared ``bias_sigma_m``."""
    if cfg.bias_sigma_m <= 0.0:
        return cfg.sigma_m  # (not √(σ²): the published scenarios' draws, bit for bit)
    return math.sqrt(max(cfg.sigma_m ** 2 - cfg.bias_sigma_m ** 2, 0.0))


def gnss_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[GnssSample]:
    cfg = scenario.gnss
    listed = [x for x in cfg.fix_times_s if 0.0 <= x <= scenario.duration_s]
    t = np.unique(np.concatenate([np.asarray(listed, dtype=float),
                                  sample_times(cfg.rate_hz, scenario.duration_s)]))
    if not len(t):
        return []
    pos = truth.pos(t)
    noise = _white_sigma(cfg) * rng.standard_normal((len(t), 2))  # drawn for all: stable streams
    noise += gauss_markov(t, cfg.bias_sigma_m, cfg.bias_time_s, 2, rng)
    keep = pos[:, 2] <= cfg.max_depth_m
    pos = pos.copy()
    pos[:, :2] += noise
    lat, lon, _ = scenario.origin.geo().to_geodetic(pos)
    return [GnssSample(float(t[i]), float(lat[i]), float(lon[i]), cfg.sigma_m)
            for i in range(len(t)) if keep[i]]


def usbl_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[UsblSample]:
    cfg = scenario.usbl
    if not cfg.enabled or cfg.period_s <= 0:
        return []
    end = scenario.duration_s if cfg.lost_after_s is None else min(cfg.lost_after_s, scenario.duration_s)
    t = periodic_times(cfg.period_s, end, cfg.start_s)
    if not len(t):
        return []
    pos = truth.pos(t)
    white_h = _white_sigma(cfg)
    noisy = pos + rng.standard_normal((len(t), 3)) * np.array([white_h, white_h, cfg.sigma_depth_m])
    noisy[:, :2] += gauss_markov(t, cfg.bias_sigma_m, cfg.bias_time_s, 2, rng)
    lat, lon, _ = scenario.origin.geo().to_geodetic(noisy)
    # outages drop fixes after the noise is drawn: the other fixes stay the same draws
    keep = np.ones(len(t), dtype=bool)
    for start, stop in cfg.outages_s:
        keep &= ~((t >= start) & (t < stop))
    return [UsblSample(float(t[i]), float(lat[i]), float(lon[i]), float(noisy[i, 2]),
                       cfg.sigma_m, cfg.sigma_depth_m) for i in range(len(t)) if keep[i]]


def janus_beams(beam_angle_rad: float) -> np.ndarray:
    """(4, 3) unit vectors of a 4-beam Janus head in its own frame (z down, beams at
    ``beam_angle_rad`` from z, azimuths forward / aft / starboard / port)."""
    s, c = math.sin(beam_angle_rad), math.cos(beam_angle_rad)
    return np.array([[s, 0.0, c], [-s, 0.0, c], [0.0, s, c], [0.0, -s, c]])


def dvl_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[DvlSample]:
    r"""A 4-beam Janus DVL, beam by beam.

    Per ping: the head's true velocity ``v_d = R_dbᵀ… (R_bnᵀ v_n + ω_b × l_b)`` with the
    *true* head orientation (configured mount ⊗ misalignment), each beam's radial
    velocity ``b_i = (1 + s) n_iᵀ v_d + β_i + ε_i`` (scale error ``s``, bias ``β_i``, white
    ``ε_i``, an outlier with probability ``outlier_prob``), and the velocity the DVL
    reports is the least-squares solution over the four beams (as the instrument does),
    so the white noise projects to ``σ_b/(√2 sin θ)`` horizontally and ``σ_b/(2 cos θ)``
    vertically. Bottom lock needs every beam's slant range ``altitude / (beam's down
    component in n)`` within the range of ``max_altitude_m`` straight down, tilt below
    ``max_tilt_deg`` and altitude above ``min_altitude_m`` — so lock is lost when the
    seabed drops away (a trench) or the vehicle pitches steeply. Without it, water track
    (if enabled) reports the velocity relative to the water, σ ``water_track_sigma_m_s``.

    Figures (public datasheets/manuals): 4 beams at 30° from the vertical — Teledyne RDI
    Workhorse Navigator (rdinstruments.com DVL FAQ) and Pathfinder (Pathfinder DVL Guide,
    P/N 95B-6116-00, 2018: 600 kHz, bottom track and a water-mass layer for water
    tracking); bottom-track range ~75 m for a Nortek DVL1000-class unit; Water Linked
    DVL-A50: 0.05–50 m altitude, 1 MHz, long-term accuracy ±0.1 % (performance) to ±1 %
    (standard edition), water tracking on a layer 1.5–4.5 m below the head at 2 Hz
    (docs.waterlinked.com). Scale factors 0.1–1 % and misalignments of tenths of a degree
    after installation are what in-situ calibration papers report (Kinsey & Whitcomb,
    IEEE JOE 2006, "In situ alignment calibration of attitude and Doppler sensors").
    """
    cfg = scenario.dvl
    if not cfg.enabled:
        return []
    t = sample_times(cfg.rate_hz, scenario.duration_s, cfg.start_s)
    n = len(t)
    rot_nb = truth.rotation(t)
    vel_n = truth.vel(t)
    vel_b = rot_nb.inv().apply(vel_n) + np.cross(truth.omega_b(t), np.asarray(cfg.lever_arm_b_m))
    r, p, y = np.radians(cfg.mount_rpy_deg)
    mr, mp, my = np.radians(cfg.misalignment_rpy_deg)
    rot_bd = Rotation.from_euler("ZYX", [y, p, r]) * Rotation.from_euler("ZYX", [my, mp, mr])
    beams = janus_beams(math.radians(cfg.beam_angle_deg))
    solve = np.linalg.pinv(beams)  # (3, 4): the instrument's least-squares velocity
    # draws in a fixed order (one block each) so that switching a feature keeps the others
    white = cfg.beam_sigma_m_s * rng.standard_normal((n, 4))
    out_mask = rng.random((n, 4)) < cfg.outlier_prob
    out_val = cfg.outlier_sigma_m_s * rng.standard_normal((n, 4))
    dropped = rng.random(n) < cfg.dropout_prob
    wt_noise = cfg.water_track_sigma_m_s * rng.standard_normal((n, 3))

    def through_beams(v_d):
        radial = (1.0 + cfg.scale_factor_error) * v_d @ beams.T + np.asarray(cfg.beam_bias_m_s) + white
        radial = np.where(out_mask, radial + out_val, radial)
        return radial @ solve.T

    vel_d = through_beams(rot_bd.inv().apply(vel_b))
    pos = truth.pos(t)
    altitude = scenario.environment.bottom_depth_at(pos[:, 1]) - pos[:, 2]
    # each beam's down component in n: slant range = altitude / that
    beams_n = np.stack([(rot_nb * rot_bd).apply(np.tile(b, (n, 1)))[:, 2] for b in beams], axis=1)
    max_slant = cfg.max_altitude_m / math.cos(math.radians(cfg.beam_angle_deg))
    with np.errstate(divide="ignore", invalid="ignore"):
        slant = np.where(beams_n > 0.05, altitude[:, None] / beams_n, np.inf)
    euler = truth.euler(t)
    tilt_ok = np.max(np.abs(euler[:, :2]), axis=1) <= math.radians(cfg.max_tilt_deg)
    lock = (slant.max(axis=1) <= max_slant) & (altitude >= cfg.min_altitude_m) & tilt_ok
    for start, stop in cfg.outages_s:
        lock &= ~((t >= start) & (t < stop))
    valid = lock & ~dropped
    water = np.zeros(n, dtype=bool)
    if cfg.water_track:
        water = ~lock & ~dropped & (altitude >= cfg.min_altitude_m + 4.5) & tilt_ok
        cur = np.array(tuple(scenario.current.vel_n_m_s()) + (0.0,))
        water_n = vel_n - cur[None, :]
        if scenario.current.surface_drift_speed_m_s > 0:
            water_n[:, :2] -= scenario.current.surface_drift_n_m_s(pos[:, 2])
        rel_b = rot_nb.inv().apply(water_n)
        wt = rot_bd.inv().apply(rel_b) * (1.0 + cfg.scale_factor_error) + wt_noise
        vel_d = np.where(water[:, None], wt, vel_d)
    return [DvlSample(float(t[i]), tuple(map(float, vel_d[i])), bool(valid[i] or water[i]),
                      float(altitude[i]) if valid[i] else math.nan, bool(water[i])) for i in range(n)]


def beacon_samples(scenario: Scenario, truth: TruthInterpolator, rng) -> list[RangeSample]:
    cfg = scenario.beacons
    if not cfg.enabled or not cfg.positions_n_m:
        return []
    t = periodic_times(cfg.period_s, scenario.duration_s)
    pos = truth.pos(t)
    out = []
    beacons = np.asarray(cfg.positions_n_m, dtype=float)
    ranges = np.linalg.norm(pos[:, None, :] - beacons[None, :, :], axis=2)
    ranges += cfg.sigma_m * rng.standard_normal(ranges.shape)
    for i, ti in enumerate(t):
        for j, b in enumerate(beacons):
            out.append(RangeSample(float(ti), j, tuple(map(float, b)), float(ranges[i, j]), cfg.sigma_m))
    return out


def truth_samples(scenario: Scenario, dense: DenseTruth, steps: MotionSteps,
                  bias_acc: np.ndarray, bias_gyro: np.ndarray) -> list[TruthSample]:
    """Truth at ``truth.rate_hz`` on the IMU grid (nearest IMU instant at or before)."""
    dt = dense.t_s[1] - dense.t_s[0]
    t = sample_times(scenario.truth.rate_hz, scenario.duration_s)
    idx = np.minimum(np.round(t / dt).astype(int), len(dense.t_s) - 1)
    k = np.minimum((dense.t_s[idx] / scenario.motion.step_s + 1e-9).astype(int), len(steps.k_v) - 1)
    cur = tuple(map(float, scenario.current.vel_n_m_s())) + (0.0,)
    drift = (scenario.current.surface_drift_n_m_s(dense.pos_n_m[idx, 2])
             if scenario.current.surface_drift_speed_m_s > 0 else None)
    # biases are per IMU sample (index i−1 for instant i); instant 0 takes the first
    bi = np.maximum(idx - 1, 0)
    out = []
    for j, i in enumerate(idx):
        out.append(TruthSample(
            float(t[j]), tuple(map(float, dense.pos_n_m[i])), tuple(map(float, dense.vel_n_m_s[i])),
            tuple(map(float, dense.q_nb[i])), cur if drift is None else (cur[0] + float(drift[j, 0]), cur[1] + float(drift[j, 1]), 0.0),
            float(steps.k_v[k[j]]),
            tuple(map(float, bias_acc[bi[j]])), tuple(map(float, bias_gyro[bi[j]]))))
    return out
