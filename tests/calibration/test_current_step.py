"""Sea current in the motion model / M-step / fix regression, and the step-length rescaling."""
import math

import numpy as np
import pytest

from adaptnav.fusion.motion_model import (MotionParams, invert_step, propagate, rescale_step, sample_velocities,
                                 transition_logpdf)
from adaptnav.calibration.fix_regression import fix_regression
from adaptnav.calibration.mstep import MStepOptions, m_step
from adaptnav.calibration.sensors import PositionFix

CURRENT = (0.06, -0.08)


def test_rescale_step_matches_averaging_of_white_per_second_velocities():
    rng = np.random.default_rng(1)
    p1 = MotionParams(var_vv=0.15**2, var_v1=0.02**2, k_v=0.9, b_w=0.01)
    v, n_sub, n = 1.5, 5, 40000
    # V drawn independently every second; a 5 s step moves with their mean
    V, _, _ = sample_velocities(p1, np.full((n, n_sub), v), np.zeros((n, n_sub)), rng)
    p5 = rescale_step(p1, 1.0, 5.0)
    var_model = p5.var_vv * v * v + p5.var_v1
    assert np.var(V.mean(axis=1)) == pytest.approx(var_model, rel=0.03)
    assert (p5.k_v, p5.b_w) == (p1.k_v, p1.b_w)
    back = rescale_step(p5, 5.0, 1.0)
    for name in MotionParams.VARIANCE_NAMES:
        assert getattr(back, name) == pytest.approx(getattr(p1, name), rel=1e-12)
    with pytest.raises(ValueError):
        rescale_step(p1, 0.0, 5.0)


def test_current_moves_the_ground_pose_and_inverts_exactly():
    rng = np.random.default_rng(2)
    pose0 = np.column_stack([rng.normal(0, 10, 50), rng.normal(0, 10, 50), rng.uniform(-3, 3, 50)])
    V, W, S = rng.normal(1.5, 0.1, 50), rng.normal(0, 0.05, 50), rng.normal(0, 0.02, 50)
    still = propagate(pose0, V, W, S, 5.0)
    moved = propagate(pose0, V, W, S, 5.0, CURRENT)
    np.testing.assert_allclose(moved[:, :2] - still[:, :2], np.broadcast_to(np.array(CURRENT) * 5.0, (50, 2)),
                               atol=1e-12)
    V2, W2, S2, _ = invert_step(pose0, moved, 5.0, CURRENT)
    np.testing.assert_allclose(np.column_stack([V2, W2, S2]), np.column_stack([V, W, S]), atol=1e-9)
    p = MotionParams()
    np.testing.assert_allclose(transition_logpdf(p, pose0, moved, 1.5, 0.0, 5.0, CURRENT),
                               transition_logpdf(p, pose0, still, 1.5, 0.0, 5.0), atol=1e-9)


def _lawnmower(rng, params, n_steps=240, dt=5.0, current=CURRENT):
    """Water-relative model steps along N/S legs of 40 steps; ground poses with the current."""
    v = 1.5 + 0.05 * np.sin(np.arange(n_steps) / 7.0)
    w = np.zeros(n_steps)
    leg = (np.arange(n_steps) // 40) % 2
    turn = (np.arange(n_steps) % 40) >= 36
    w[turn] = np.where(leg[turn] == 0, 1, -1) * math.pi / (4 * dt)
    return v, w, _ground_poses(rng, params, v, w, dt, current)


def _ground_poses(rng, params, v, w, dt, current):
    """Poses driven by the motion model from the controls (v, w), moved by the current."""
    poses = np.zeros((v.size + 1, 3))
    for t in range(v.size):
        V, W, S = sample_velocities(params, v[t], w[t], rng)
        poses[t + 1] = propagate(poses[t], V, W, S, dt, current)
    return poses


def test_m_step_recovers_the_current_and_k_v_from_trajectories():
    rng = np.random.default_rng(3)
    truth = MotionParams(var_vv=0.04**2, k_v=0.9, var_s=0.01**2)
    v, w, poses = _lawnmower(rng, truth)
    start = MotionParams(var_vv=0.04**2, var_s=0.01**2)
    res = m_step(poses[None], v, w, 5.0, start, options=MStepOptions(fit_current=True, prior_tau=math.inf))
    assert res.params.k_v == pytest.approx(0.9, abs=0.01)
    np.testing.assert_allclose(res.current_n_m_s, CURRENT, atol=0.005)
    # without the current in the model it leaks into the sway (the bug this fixes)
    res0 = m_step(poses[None], v, w, 5.0, start, options=MStepOptions(fit_current=False, prior_tau=math.inf))
    assert math.sqrt(res0.params.var_s) > 5 * math.sqrt(res.params.var_s)


def test_fix_regression_finds_the_current_from_noisy_fixes():
    rng = np.random.default_rng(4)
    truth = MotionParams(var_vv=0.03**2, k_v=0.95)
    v, w, poses = _lawnmower(rng, truth)
    obs = [[PositionFix(tuple(poses[t, :2] + rng.normal(0, 2.0, 2)), 2.0)] if t % 12 == 0 else []
           for t in range(poses.shape[0])]
    headings = poses[:, 2] + np.radians(0.3) * rng.standard_normal(poses.shape[0])
    k, cur, held = fix_regression(v, 5.0, headings, obs, truth, 1.0, (0.0, 0.0), max_k_v_sigma=0.05)
    assert held == ()  # a survey leg informs k_V well within the calibrator's 0.05
    assert k == pytest.approx(0.95, abs=0.02)
    np.testing.assert_allclose(cur, CURRENT, atol=0.02)
    # one fix: nothing to fit, inputs returned as held
    one = [o if t < 5 else [] for t, o in enumerate(obs)]
    assert fix_regression(v, 5.0, headings, one, truth, 1.0, (0.1, 0.2)) == (1.0, (0.1, 0.2),
                                                                             ("k_v", "current_n", "current_e"))


def _at_rest_with_a_blip(rng, params, n_steps=96, dt=5.0, current=CURRENT):
    """A vehicle holding station (surge 0) but for 15 s of 0.05 m/s: k_V is not informed."""
    v = np.zeros(n_steps)
    v[40:43] = 0.05
    w = np.zeros(n_steps)
    return v, w, _ground_poses(rng, params, v, w, dt, current)


def test_k_v_is_held_when_the_speeds_do_not_inform_it():
    # GIVEN a window at rest with a blip of thrust, moved by a speed scale of 0.6
    rng = np.random.default_rng(8)
    truth = MotionParams(var_vv=0.04**2, k_v=0.6, var_s=0.01**2)
    v, w, poses = _at_rest_with_a_blip(rng, truth)
    start = MotionParams(var_vv=0.04**2, var_s=0.01**2)
    # THEN the M-step holds k_V and says why ...
    res = m_step(poses[None], v, w, 5.0, start, options=MStepOptions(fit_current=True, prior_tau=math.inf))
    assert res.params.k_v == 1.0 and "k_v" in res.held
    assert any("do not inform" in n for n in res.notes), res.notes
    # ... where plain least squares would have taken the blip's noise for a 40 % change
    loose = m_step(poses[None], v, w, 5.0, start,
                   options=MStepOptions(fit_current=True, prior_tau=math.inf, max_k_v_sigma=math.inf))
    assert abs(loose.params.k_v - 1.0) > 0.1
    # AND the fix regression (fixes every minute, σ 2 m) holds it too, while fitting the current
    obs = [[PositionFix(tuple(poses[t, :2] + rng.normal(0, 2.0, 2)), 2.0)] if t % 12 == 0 else []
           for t in range(poses.shape[0])]
    k, cur, held = fix_regression(v, 5.0, poses[:, 2], obs, truth, 1.0, (0.0, 0.0), max_k_v_sigma=0.05)
    assert k == 1.0 and held == ("k_v",)
    np.testing.assert_allclose(cur, CURRENT, atol=0.02)
