"""IMU surge increments (calibration.inertial): σ_Vv from a free-inertial velocity track."""
import math
from dataclasses import replace

import numpy as np
import pytest

from calibration.inertial import InertialTrack, surge_increments
from calibration.mstep import MStepOptions, m_step
from fusion.motion_model import MotionParams, rescale_step, sample_poses

STEP_S, T, SPEED = 5.0, 96, 1.5
TRUE = replace(MotionParams(), var_vv=0.15 ** 2, var_v1=1e-4, k_v=0.9)


def _track(rng, params=TRUE, t0=1000.0, rate_hz=10.0, offset=(0.3, -0.2), drift=(1e-3, -5e-4),
           current=(0.07, 0.07)):
    """A free-inertial track: per-second surge draws along a slowly turning heading, plus the
    current, an unknown offset and a slow drift (what the filter hands over)."""
    n_sub = int(T * STEP_S)
    V = params.k_v * SPEED + math.sqrt(params.var_vv * SPEED ** 2 + params.var_v1) * rng.standard_normal(n_sub)
    t = t0 + np.arange(0.0, n_sub, 1.0 / rate_hz)
    j = np.floor(t - t0 + 1e-9).astype(int)
    yaw = 0.3 + 0.002 * (t - t0)
    vel = (V[j][:, None] * np.column_stack([np.cos(yaw), np.sin(yaw)]) + np.asarray(current)
           + np.asarray(offset) + np.outer(t - t0, drift))
    return InertialTrack(t, vel, yaw, np.zeros(t.size, dtype=int)), V


def _window_ll(inc, sigma_vv):
    return inc.log_likelihood(rescale_step(replace(TRUE, var_vv=sigma_vv ** 2), 1.0, STEP_S))


def test_the_increments_likelihood_peaks_at_the_true_surge_noise():
    rng = np.random.default_rng(3)
    track, _ = _track(rng)
    v, w = np.full(T, SPEED), np.zeros(T)
    inc = surge_increments(track, 1000.0, STEP_S, v, w, current_n_m_s=(0.07, 0.07))
    # every pair of consecutive 1 s sub-steps inside the window (the last edge needs a sample after it)
    assert len(inc) >= T * STEP_S - 3
    grid = np.linspace(0.05, 0.3, 51)
    best = grid[np.argmax([_window_ll(inc, s) for s in grid])]
    assert abs(best / 0.15 - 1) < 0.1, best


def test_gaps_and_resets_remove_the_sub_steps_they_touch():
    rng = np.random.default_rng(4)
    track, _ = _track(rng)
    v, w = np.full(T, SPEED), np.zeros(T)
    full = len(surge_increments(track, 1000.0, STEP_S, v, w))
    # a 2 s hole in the samples and a filter reset (IMU gap) 100 s later
    keep = ~((track.t_s > 1100.2) & (track.t_s < 1102.2))
    reset = np.where(track.t_s >= 1200.05, 1, 0)
    holed = InertialTrack(track.t_s[keep], track.vel_ne_m_s[keep], track.yaw_rad[keep], reset[keep])
    inc = surge_increments(holed, 1000.0, STEP_S, v, w)
    # the hole spoils sub-steps 100..102 (3 sub-steps → 4 pairs), the reset one sub-step (2 pairs)
    assert full - len(inc) == 6
    assert np.all(np.isfinite(inc.dv_obs))


def test_em_with_increments_moves_to_the_changed_surge_noise_that_trajectories_alone_do_not():
    # GIVEN a smoother that carries no information on σ_Vv (sparse fixes: its trajectories are
    # draws from the model it is given — the prior) and IMU increments of water whose σ_Vv is
    # 0.15 while the calibration says 0.05
    rng = np.random.default_rng(5)
    track, _ = _track(rng)
    v, w, dt = np.full(T, SPEED), np.zeros(T), np.full(T, STEP_S)
    opts = MStepOptions(fit_k_v=False, fit_b_w=False, fit_var_s=False, prior_tau=math.inf)
    inc = surge_increments(track, 1000.0, STEP_S, v, w, current_n_m_s=(0.07, 0.07))
    sigma = lambda p: math.sqrt(rescale_step(p, STEP_S, 1.0).var_vv)  # noqa: E731

    def em(params, increments, iterations=8):
        for _ in range(iterations):
            traj = np.zeros((20, T + 1, 3))
            for k in range(T):
                traj[:, k + 1] = sample_poses(params, traj[:, k], v[k], w[k], STEP_S, rng)
            params = m_step(traj, v, w, dt, params, options=opts, surge_increments=increments).params
        return params

    old = rescale_step(replace(TRUE, var_vv=0.05 ** 2), 1.0, STEP_S)
    # THEN without the increments σ_Vv stays where it was; with them EM climbs to the truth
    # (each M-step weighs the prior-like smoothed rows against ~480 increments)
    assert abs(sigma(em(old, None)) / 0.05 - 1) < 0.3
    assert sigma(em(old, inc)) == pytest.approx(0.15, rel=0.15)
