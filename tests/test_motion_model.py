"""Motion model: the errata's arc update, inversion, density and the RPM lookup."""
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from adaptnav.fusion.motion_model import (MotionParams, RpmSpeedTable, invert_step, propagate,
                                 sample_poses, step_errors, transition_logpdf)


def _integrate(pose, V, W, S, dt):
    """Numerical integration of the body-velocity kinematics — independent of the code."""
    def f(_t, s):
        th = s[2]
        return [V * math.cos(th) - S * math.sin(th), V * math.sin(th) + S * math.cos(th), W]
    return solve_ivp(f, (0, dt), pose, rtol=1e-11, atol=1e-12).y[:, -1]


@pytest.mark.parametrize("W", [0.3, -0.7, 1e-9, 0.0])
def test_propagate_matches_numerical_integration(W):
    pose = np.array([3.0, -2.0, 0.4])
    got = propagate(pose, 1.3, W, 0.2, 2.0)
    want = _integrate(pose, 1.3, W, 0.2, 2.0)
    np.testing.assert_allclose(got, want, atol=1e-8)


def test_errata_arc_formula_holds_without_sway():
    x, y, th, V, W, dt = 1.0, 2.0, 0.3, 1.5, 0.2, 1.0
    got = propagate(np.array([x, y, th]), V, W, 0.0, dt)
    assert got[0] == pytest.approx(x - V / W * math.sin(th) + V / W * math.sin(th + W * dt))
    assert got[1] == pytest.approx(y + V / W * math.cos(th) - V / W * math.cos(th + W * dt))


def test_invert_step_recovers_velocities():
    rng = np.random.default_rng(1)
    poses = rng.normal(size=(500, 3))
    V, W, S = rng.normal(1.0, 0.5, 500), rng.normal(0, 0.5, 500), rng.normal(0, 0.1, 500)
    W[:10] = 0.0
    V2, W2, S2, _ = invert_step(poses, propagate(poses, V, W, S, 0.5), 0.5)
    np.testing.assert_allclose(V2, V, atol=1e-9)
    np.testing.assert_allclose(W2, W, atol=1e-9)
    np.testing.assert_allclose(S2, S, atol=1e-9)


def test_step_errors_are_zero_for_the_reported_motion():
    pose0 = np.array([0.0, 0.0, 1.0])
    pose1 = propagate(pose0, 1.2, 0.1, 0.0, 1.0)
    eV, eW, eS = step_errors(pose0, pose1, 1.2, 0.1, 1.0)
    assert abs(eV) < 1e-12 and abs(eW) < 1e-12 and abs(eS) < 1e-12


def test_transition_density_integrates_to_one():
    """Monte-Carlo check of normalisation: E_q[p/q] = 1 for a broad proposal q."""
    params = MotionParams(var_vv=0.1**2, var_ww=0.2**2, var_s=0.05**2)
    rng = np.random.default_rng(2)
    pose0 = np.array([0.0, 0.0, 0.3])
    n = 400_000
    mu = propagate(pose0, 1.0, 0.2, 0.0, 1.0)
    scale = np.array([0.4, 0.4, 0.6])
    prop = mu + scale * rng.standard_normal((n, 3))
    logq = -0.5 * np.sum(((prop - mu) / scale) ** 2, axis=1) - np.sum(np.log(scale)) - 1.5 * math.log(2 * math.pi)
    logp = transition_logpdf(params, pose0, prop, 1.0, 0.2, 1.0)
    assert np.mean(np.exp(logp - logq)) == pytest.approx(1.0, abs=0.03)


def test_sampled_velocities_have_the_model_moments():
    params = MotionParams(var_vv=0.2**2, var_v1=0.05**2, var_ww=0.1**2, k_v=0.9, b_w=0.01)
    rng = np.random.default_rng(3)
    poses = np.zeros((200_000, 3))
    new = sample_poses(params, poses, 1.5, 0.2, 1.0, rng)
    V, W, S, _ = invert_step(poses, new, 1.0)
    assert V.mean() == pytest.approx(0.9 * 1.5, abs=0.003)
    assert V.var() == pytest.approx(1.5**2 * 0.04 + 0.2**2 * params.var_vw + 0.05**2, rel=0.02)
    assert W.mean() == pytest.approx(0.21, abs=0.001)
    assert S.var() == pytest.approx(params.var_s, rel=0.02)


def test_same_seed_same_output():
    p = MotionParams()
    a = sample_poses(p, np.zeros((10, 3)), 1.0, 0.1, 1.0, np.random.default_rng(7))
    b = sample_poses(p, np.zeros((10, 3)), 1.0, 0.1, 1.0, np.random.default_rng(7))
    assert np.array_equal(a, b)


def test_motion_params_reject_bad_values():
    with pytest.raises(ValueError, match="var_vv"):
        MotionParams(var_vv=-1.0)
    with pytest.raises(ValueError, match="finite"):
        MotionParams(k_v=float("nan"))
    with pytest.raises(ValueError, match="unknown"):
        MotionParams.from_dict({"var_vvv": 1.0})


def test_rpm_table_is_monotone_and_invertible():
    table = RpmSpeedTable()
    rpm = np.linspace(0, 1500, 301)
    speed = table.speed(rpm)
    assert np.all(np.diff(speed) >= 0)
    assert table.speed(600.0) == pytest.approx(0.75)
    assert table.speed(1e6) == pytest.approx(1.85)
    assert table.rpm_for_speed(1.5) == pytest.approx(1200.0, abs=1.0)
    with pytest.raises(ValueError, match="increasing"):
        RpmSpeedTable(rpm=(0, 10, 5), speed_m_s=(0, 1, 2))
