r"""The seed's §3.6 experiment: a robot with a changing motion model, 4 landmarks, ranges.

Simulation (seed §3.6, made reproducible): T steps of δt = 1 s. The true motion follows
:mod:`fusion.motion_model` with σ_Dd ≡ σ_Vv and σ_Tr ≡ σ_Ww set to the *initial* values
for steps < ``change_step`` and to the *changed* values from then on (other terms at their
:class:`MotionParams` defaults, k_V = 1, b_W = 0). Each pose is observed through ranges to
L static landmarks with Gaussian noise ``sensor_noise`` (m).

Controls (our choice — the seed does not give them): both vary so that the three variance
terms of each channel are identifiable (DESIGN.md "Calibration")::

    v_t = 2.5 + 1.2 sin(2π t / 17)           m/s    (1.3 … 3.7)
    w_t = 0.12 + 0.30 sin(2π t / 11 + 0.5)   rad/s  (−0.18 … 0.42)

so the robot loops around the landmark square (landmarks on a circle of radius 40 m
around the loop's centre; L = 4 gives the corners of a square).

Two particle filters localise the robot from the same data: *static* keeps the initial
parameters; *learned* is re-calibrated online by EM (:mod:`calibration.online`'s window
logic: every ``period`` steps, a few EM iterations over the last ``window`` steps, warm
started, with exponential forgetting). The localisation error at step t is the distance
between the filter's weighted mean position and the truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fusion.motion_model import MotionParams, sample_velocities, propagate
from calibration.em import EMOptions, run_em
from calibration.mstep import MStepOptions
from calibration.particle_filter import filter_step, weighted_mean_pose
from calibration.resampling import systematic_resample
from calibration.sensors import RangeObservation


@dataclass(frozen=True)
class ThesisRow:
    sigma_dd_initial: float = 0.05
    sigma_tr_initial: float = 0.05
    sigma_dd_changed: float = 0.2
    sigma_tr_changed: float = 0.05
    sensor_noise: float = 2.0
    change_step: int = 5
    steps: int = 100
    landmarks: int = 4


# the six rows of the seed's table (its numbering skips 3)
LANDMARK_RADIUS_M = 60.0
STEP_S = 10.0

THESIS_ROWS = (
    ThesisRow(0.05, 0.05, 0.2, 0.05, 2.0),
    ThesisRow(0.05, 0.05, 0.2, 0.05, 5.0),
    ThesisRow(0.05, 0.05, 0.5, 0.05, 2.0),
    ThesisRow(0.05, 0.05, 0.5, 0.05, 5.0),
    ThesisRow(0.05, 0.05, 0.05, 0.2, 5.0),
    ThesisRow(0.05, 0.05, 0.05, 0.5, 5.0),
)


@dataclass(frozen=True)
class LearnerSettings:
    n_filter: int = 1000       # particles of the two localisation filters
    n_particles: int = 500     # particles of the EM's E-step
    n_smoothed: int = 50
    period: int = 5            # EM every `period` steps
    window: int = 40           # steps in the EM window
    em_iterations: int = 3
    forgetting: float = 0.97   # λ per step
    first_em_step: int = 10


@dataclass
class ThesisData:
    v: np.ndarray          # (T,)
    w: np.ndarray          # (T,)
    dt: float
    truth: np.ndarray      # (T+1, 3)
    landmarks: np.ndarray  # (L, 2)
    observations: list     # T+1 lists
    params_initial: MotionParams
    params_changed: MotionParams


def controls(steps: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(steps, dtype=float)
    return 4.0 + 1.5 * np.sin(2 * np.pi * t / 17), 0.1 + 0.05 * np.sin(2 * np.pi * t / 11 + 0.5)


def simulate(row: ThesisRow, rng: np.random.Generator, dt: float = STEP_S) -> ThesisData:
    """Truth, controls and range observations for one seed of ``row``."""
    v, w = controls(row.steps)
    p0 = MotionParams().with_sigmas(row.sigma_dd_initial, row.sigma_tr_initial)
    p1 = MotionParams().with_sigmas(row.sigma_dd_changed, row.sigma_tr_changed)
    # loop centre: the nominal path's mean position
    nominal = np.zeros((row.steps + 1, 3))
    for t in range(row.steps):
        nominal[t + 1] = propagate(nominal[t], v[t], w[t], 0.0, dt)
    centre = nominal[:, :2].mean(axis=0)
    ang = np.pi / 4 + 2 * np.pi * np.arange(row.landmarks) / row.landmarks
    landmarks = centre + LANDMARK_RADIUS_M * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    truth = np.zeros((row.steps + 1, 3))
    for t in range(row.steps):
        p = p0 if t < row.change_step else p1
        V, W, S = sample_velocities(p, v[t], w[t], rng)
        truth[t + 1] = propagate(truth[t], V, W, S, dt)
    obs = []
    for t in range(row.steps + 1):
        d = np.hypot(*(truth[t, :2] - landmarks).T)
        r = d + row.sensor_noise * rng.standard_normal(d.size)
        obs.append([RangeObservation(landmarks, r, row.sensor_noise)])
    return ThesisData(v, w, dt, truth, landmarks, obs, p0, p1)


def _init_cloud(n: int, rng: np.random.Generator) -> np.ndarray:
    """Known start (the seed starts at a known pose), with a small spread."""
    return np.column_stack([0.5 * rng.standard_normal(n), 0.5 * rng.standard_normal(n),
                            0.02 * rng.standard_normal(n)])


def run_filter(data: ThesisData, rng: np.random.Generator, settings: LearnerSettings, learn: bool):
    """Localise over the whole run; returns (errors (T+1,), final params, params history)."""
    T = data.v.size
    params = data.params_initial
    poses = _init_cloud(settings.n_filter, rng)
    log_w = np.full(poses.shape[0], -math.log(poses.shape[0]))
    log_w = log_w + data.observations[0][0].log_likelihood(poses)
    log_w -= np.logaddexp.reduce(log_w)
    clouds = [poses[systematic_resample(np.exp(log_w), rng, settings.n_particles)]]
    errors = np.empty(T + 1)
    errors[0] = np.hypot(*(weighted_mean_pose(poses, log_w)[:2] - data.truth[0, :2]))
    history = [(0, params)]
    em_opts = EMOptions(n_particles=settings.n_particles, n_smoothed=settings.n_smoothed,
                        max_iterations=settings.em_iterations,
                        mstep=MStepOptions(fit_k_v=False, fit_b_w=False, fit_var_s=False))
    for t in range(T):
        poses, log_w, _ = filter_step(params, poses, log_w, data.v[t], data.w[t], data.dt,
                                      data.observations[t + 1], rng)
        k = t + 1
        errors[k] = np.hypot(*(weighted_mean_pose(poses, log_w)[:2] - data.truth[k, :2]))
        if learn:
            clouds.append(poses[systematic_resample(np.exp(log_w), rng, settings.n_particles)])
            if k >= settings.first_em_step and k % settings.period == 0:
                s = max(0, k - settings.window)
                lam = settings.forgetting ** np.arange(k - s - 1, -1, -1, dtype=float)
                res = run_em(params, data.v[s:k], data.w[s:k], data.dt, data.observations[s:k + 1],
                             clouds[s], rng, em_opts, step_weights=lam)
                params = res.params
                history.append((k, params))
    return errors, params, history
