"""IMU surge increments (calibration.inertial): σ_Vv from a free-inertial velocity track."""
import math
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.calibration.inertial import InertialTrack, surge_increments
from adaptnav.calibration.mstep import MStepOptions, m_step
from adaptnav.fusion.motion_model import MotionParams, rescale_step, sample_poses

STEP_S, T, SPEED = 5.0, 96, 1.5
TRUE = replace(MotionParams(), var_vv=0.15 ** 2, var_v1=1e-4, k_v=0.9)


def _track(rng, params=TRUE, t0=1000.0, lag_s=0.005, offset=(0.3, -0.2), drift=(1e-3, -5e-4),
           current=(0.07, 0.07)):
    """A free-inertial track as the runner hands it over (once a second, an IMU period after
    the second): the integral of per-second surge draws along a slowly turning heading, plus
    the current, an unknown velocity offset and a slow drift."""
    n_sub = int(T * STEP_S)
    V = params.k_v * SPEED + math.sqrt(params.var_vv * SPEED ** 2 + params.var_v1) * rng.standard_normal(n_sub)
    fine = t0 + np.arange(0.0, n_sub + 1e-9, 0.001)  # integrate on a fine grid
    j = np.minimum(np.floor(fine - t0 + 1e-9).astype(int), n_sub - 1)
    yaw_f = 0.3 + 0.002 * (fine - t0)
    vel = (V[j][:, None] * np.column_stack([np.cos(yaw_f), np.sin(yaw_f)]) + np.asarray(current)
           + np.asarray(offset) + np.outer(fine - t0, drift))
    pos = np.concatenate([np.zeros((1, 2)), np.cumsum(0.5 * (vel[1:] + vel[:-1]) * 0.001, axis=0)])
    t = t0 + np.arange(0, n_sub) + lag_s
    idx = np.round((t - t0) / 0.001).astype(int)
    return InertialTrack(t, pos[idx], yaw_f[idx], np.zeros(t.size, dtype=int)), V


def _window_ll(inc, sigma_vv):
    return inc.log_likelihood(rescale_step(replace(TRUE, var_vv=sigma_vv ** 2), 1.0, STEP_S))


def test_the_increments_likelihood_peaks_at_the_true_surge_noise():
    rng = np.random.default_rng(3)
    track, _ = _track(rng)
    v, w = np.full(T, SPEED), np.zeros(T)
    inc = surge_increments(track, 1000.0, STEP_S, v, w, current_n_m_s=(0.07, 0.07))
    # every pair of consecutive 1 s sub-steps inside the window (the last edges need samples after them)
    assert len(inc) >= T * STEP_S - 3
    grid = np.linspace(0.05, 0.3, 51)
    best = grid[np.argmax([_window_ll(inc, s) for s in grid])]
    assert abs(best / 0.15 - 1) < 0.1, best


def test_gaps_and_resets_remove_the_sub_steps_they_touch():
    rng = np.random.default_rng(4)
    track, _ = _track(rng)
    v, w = np.full(T, SPEED), np.zeros(T)
    full = len(surge_increments(track, 1000.0, STEP_S, v, w))
    # two samples missing (a 3 s hole) and a filter reset (IMU gap) 100 s later
    keep = ~((track.t_s > 1101.0) & (track.t_s < 1103.0))
    reset = np.where(track.t_s >= 1200.5, 1, 0)
    holed = InertialTrack(track.t_s[keep], track.pos_ne_m[keep], track.yaw_rad[keep], reset[keep])
    inc = surge_increments(holed, 1000.0, STEP_S, v, w)
    # the hole spoils sub-steps 1100..1103 (4 sub-steps → 5 pairs); the reset at 1200.5 s spoils
    # sub-steps 1200 and 1201 (the edge at 1201 s is interpolated across it: 3 pairs)
    assert full - len(inc) == 8
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
