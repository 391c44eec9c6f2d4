"""M-step recovery, identifiability, EM on the thesis simulation."""
import math
from dataclasses import replace

import numpy as np

from adaptnav.fusion.motion_model import MotionParams, propagate, sample_velocities
from adaptnav.calibration.em import EMOptions, run_em
from adaptnav.calibration.mstep import MStepOptions, m_step, identifiable_terms, V_PRIORITY
from adaptnav.calibration.thesis import ThesisRow, _init_cloud, simulate


def _exact_trajectories(params, v, w, dt, n_traj, rng, pin_sway=False):
    """Trajectories drawn from the motion model itself (a perfect E-step).

    ``pin_sway``: one sway per step shared by every trajectory (data that pin it), and V, W
    of that one draw with a small scatter.
    """
    T = v.size
    traj = np.zeros((n_traj, T + 1, 3))
    for t in range(T):
        V, W, S = sample_velocities(params, v[t], w[t], rng, size=1 if pin_sway else n_traj)
        if pin_sway:
            V = V + 0.01 * rng.standard_normal(n_traj)
            W = W + 0.001 * rng.standard_normal(n_traj)
            S = np.full(n_traj, S[0])
        traj[:, t + 1] = propagate(traj[:, t], V, W, S, dt)
    return traj


def test_m_step_recovers_known_parameters():
    rng = np.random.default_rng(0)
    T = 400
    t = np.arange(T)
    v = 1.0 + 0.8 * np.sin(t / 7.0)
    w = 0.3 * np.sin(t / 5.0 + 1.0)
    truth = MotionParams(var_vv=0.2**2, var_vw=0.3**2, var_v1=0.05**2, var_wv=0.02**2, var_ww=0.15**2,
                         var_w1=0.01**2, var_s=0.03**2, k_v=0.9, b_w=0.01)
    traj = _exact_trajectories(truth, v, w, 1.0, 50, rng)
    start = MotionParams()  # defaults far from the truth
    # independent draws of the complete data: the sway's missing-information hold is off here
    res = m_step(traj, v, w, 1.0, start, options=MStepOptions(prior_tau=math.inf, max_condition=100,
                                                              max_missing_information_s=math.inf))
    assert res.held == ()
    got = res.params
    assert abs(got.k_v - 0.9) < 0.01
    assert abs(got.b_w - 0.01) < 0.003
    for name in ("var_vv", "var_ww", "var_s"):
        assert abs(math.sqrt(getattr(got, name)) / math.sqrt(getattr(truth, name)) - 1) < 0.1, name
    for name in ("var_vw", "var_wv", "var_v1", "var_w1"):  # weaker terms
        assert abs(math.sqrt(getattr(got, name)) / math.sqrt(getattr(truth, name)) - 1) < 0.35, name


def test_m_step_holds_terms_the_controls_cannot_separate():
    rng = np.random.default_rng(1)
    T = 200
    v = np.full(T, 1.5)  # constant speed: v² and 1 are the same column
    w = np.zeros(T)      # no turning: the w² column is zero
    truth = MotionParams(var_vv=0.1**2)
    traj = _exact_trajectories(truth, v, w, 1.0, 30, rng)
    start = MotionParams(var_vv=0.05**2)
    res = m_step(traj, v, w, 1.0, start, options=MStepOptions(max_missing_information_s=math.inf))
    assert set(res.held) == {"var_vw", "var_v1", "var_ww", "var_wv"}
    for name in res.held:
        assert getattr(res.params, name) == getattr(start, name)
    # the admitted V term absorbs the whole channel variance: v² σ_Vv² + σ_V1²(held)
    total = 1.5**2 * res.params.var_vv + start.var_v1 + 0.0
    expect = 1.5**2 * truth.var_vv + truth.var_v1
    assert abs(total / expect - 1) < 0.2
    # and the design check itself
    design = np.stack([v * v, w * w, np.ones(T)], axis=1)
    kept, _ = identifiable_terms(design, V_PRIORITY, 30.0)
    assert kept == [0]


def test_m_step_holds_the_sway_variance_when_the_data_do_not_inform_it():
    rng = np.random.default_rng(5)
    T = 300
    t = np.arange(T)
    v = 1.0 + 0.5 * np.sin(t / 9.0)
    w = 0.2 * np.sin(t / 4.0)
    start = MotionParams(var_s=0.01**2)
    truth = replace(start, var_s=0.03**2)
    # sway drawn independently per trajectory, as the prior does: the data said nothing
    prior_like = _exact_trajectories(truth, v, w, 1.0, 40, rng)
    res = m_step(prior_like, v, w, 1.0, start)
    assert res.missing_information_s > 0.9
    assert "var_s" in res.held and res.params.var_s == start.var_s
    assert any("var_s" in note and "missing-information" in note for note in res.notes)
    # the same sway on every trajectory: the data pinned it, so σ_S² is learned
    pinned = _exact_trajectories(truth, v, w, 1.0, 40, rng, pin_sway=True)
    res = m_step(pinned, v, w, 1.0, start)
    assert res.missing_information_s < 0.05
    assert "var_s" not in res.held
    assert abs(math.sqrt(res.params.var_s) / 0.03 - 1) < 0.15


def test_em_recovers_changed_sigma_dd_on_thesis_simulation():
    row = ThesisRow(0.3, 0.05, 0.3, 0.05, 2.0, change_step=0, steps=60)
    data = simulate(row, np.random.default_rng(5))
    start = MotionParams().with_sigmas(0.1, 0.05)
    rng = np.random.default_rng(6)
    opts = EMOptions(n_particles=800, n_smoothed=60, max_iterations=12,
                     mstep=MStepOptions(fit_k_v=False, fit_b_w=False, fit_var_s=False, prior_tau=math.inf))
    res = run_em(start, data.v, data.w, data.dt, data.observations, _init_cloud(800, rng), rng, opts)
    assert abs(res.params.sigma_dd / 0.3 - 1) < 0.25, res.params
    # the log-likelihood improved from the wrong start
    assert res.log_likelihoods[-1] > res.log_likelihoods[0] + 5


def test_variance_objective_gradient_and_hessian_match_finite_differences():
    from scipy.optimize import approx_fprime
    from adaptnav.calibration.mstep import VarianceObjective

    rng = np.random.default_rng(3)
    T = 50
    v, w = 1 + rng.random(T), rng.normal(scale=0.3, size=T)
    design = np.stack([v * v, w * w, np.ones(T)], axis=1)
    resid_sq = rng.gamma(2.0, 0.01, T)
    obj = VarianceObjective(design, rng.random(T), resid_sq, np.log([0.01, 0.02, 0.003]), [0, 1, 2], 1.5)
    for a in (np.log([0.01, 0.02, 0.003]), np.log([0.1, 0.001, 0.05])):
        np.testing.assert_allclose(obj.jac(a), approx_fprime(a, obj.fun, 1e-7), rtol=1e-4, atol=1e-6)
        num_h = np.array([approx_fprime(a, lambda x, i=i: obj.jac(x)[i], 1e-7) for i in range(3)])
        np.testing.assert_allclose(obj.hess(a), num_h, rtol=1e-4, atol=1e-5)


def test_compiled_newton_cg_finds_scipys_minimum():
    """The compiled Newton-CG of the M-step against scipy's Newton-CG on the same objective."""
    from scipy.optimize import minimize
    from adaptnav.calibration.mstep import VarianceObjective

    rng = np.random.default_rng(8)
    for rep in range(12):
        T = 60
        v, w = 1 + 3 * rng.random(T), rng.normal(scale=0.3, size=T)
        design = np.stack([v * v, w * w, np.ones(T)], axis=1)
        true = np.exp(rng.uniform(-8, -2, 3))
        resid_sq = design @ true * rng.chisquare(20, T) / 20
        free = [[0, 1, 2], [0, 2], [1]][rep % 3]
        alpha0 = np.log(rng.uniform(0.2, 5, 3) * true)
        obj = VarianceObjective(design, rng.uniform(0.5, 1, T), resid_sq, alpha0, free, [3.0, np.inf][rep % 2])
        ref = minimize(obj.fun, alpha0[free], method="Newton-CG", jac=obj.jac, hess=obj.hess,
                       options={"xtol": 1e-8, "maxiter": 200})
        got = obj.minimise(alpha0[free], xtol=1e-8, maxiter=200)
        assert obj.fun(got) <= ref.fun + 1e-7 * abs(ref.fun)
        if rep % 2 == 0:  # with the prior the minimum is unique (without, a term may be flat)
            np.testing.assert_allclose(got, ref.x, atol=1e-4)
