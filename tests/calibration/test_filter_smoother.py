"""Particle filter and FFBSi against exact answers (Kalman / RTS) and against each other."""
import math

import numpy as np
import pytest

from adaptnav.fusion.motion_model import MotionParams, propagate, transition_logpdf
from adaptnav.calibration._kernels import move, pack, transition_logpdf_scalar
from adaptnav.calibration.particle_filter import run_particle_filter
from adaptnav.calibration.resampling import ess, systematic_resample
from adaptnav.calibration.sensors import PositionFix, RangeObservation
from adaptnav.calibration.smoother import ffbsi_exact, ffbsi_exact_numpy, ffbsi_mcmc
from adaptnav.calibration.thesis import ThesisRow, _init_cloud, simulate


def test_systematic_resample_round_off_guard():
    # weights whose float cumsum ends below 1: an unguarded inverse CDF can return N
    rng = np.random.default_rng(0)
    w = np.full(10, 0.1)
    w[-1] = 0.1 - 1e-16
    for _ in range(200):
        idx = systematic_resample(w, rng)
        assert idx.max() < w.size
    # systematic: every index appears floor(N w_i) or ceil(N w_i) times
    w = rng.random(50)
    w /= w.sum()
    counts = np.bincount(systematic_resample(w, rng), minlength=50)
    assert np.all(np.abs(counts - 50 * w) < 1.0 + 1e-9)


def test_ess_of_uniform_and_degenerate_weights():
    assert ess(np.zeros(100)) == pytest.approx(100.0)
    lw = np.full(100, -1e3)
    lw[3] = 0.0
    assert ess(lw) == pytest.approx(1.0)


def test_kernels_match_motion_model():
    rng = np.random.default_rng(1)
    p = MotionParams(var_vv=0.03, var_vw=0.01, var_v1=0.02, var_wv=0.001, var_ww=0.04, var_w1=0.002,
                     var_s=0.01, k_v=1.1, b_w=0.02)
    x0 = rng.normal(size=(50, 3))
    z = rng.standard_normal((3, 50))
    out = move(x0, np.arange(50), z, 1.3, 0.4, 2.0, pack(p))
    var_V = 1.3**2 * p.var_vv + 0.4**2 * p.var_vw + p.var_v1
    var_W = 1.3**2 * p.var_wv + 0.4**2 * p.var_ww + p.var_w1
    V = p.k_v * 1.3 + math.sqrt(var_V) * z[0]
    W = 0.4 + p.b_w + math.sqrt(var_W) * z[1]
    S = math.sqrt(p.var_s) * z[2]
    np.testing.assert_allclose(out, propagate(x0, V, W, S, 2.0), atol=1e-12)
    ref = transition_logpdf(p, x0, out, 1.3, 0.4, 2.0)
    got = [transition_logpdf_scalar(*x0[i], *out[i], 1.3, 0.4, 2.0, pack(p)) for i in range(50)]
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)
    lm = rng.normal(scale=20, size=(4, 2))
    ob = RangeObservation(lm, rng.uniform(5, 30, 4), 2.0)
    np.testing.assert_allclose(ob.log_likelihood(x0), ob.log_likelihood_numpy(x0), rtol=1e-12)


def _linear_gaussian_problem(rng, T=30):
    """Heading fixed at 0 (yaw-rate noise ~0): x' = x + δt V, y' = y + δt S — linear Gaussian."""
    p = MotionParams(var_vv=0.0, var_vw=0.0, var_v1=0.25, var_wv=0.0, var_ww=0.0, var_w1=1e-14,
                     var_s=0.09, k_v=1.0, b_w=0.0) if False else None
    p = MotionParams(var_vv=1e-14, var_vw=1e-14, var_v1=0.25, var_wv=1e-14, var_ww=1e-14, var_w1=1e-14,
                     var_s=0.09)
    v = 1.0 + 0.5 * np.sin(np.arange(T) / 3.0)
    w = np.zeros(T)
    dt = 1.0
    truth = np.zeros((T + 1, 2))
    for t in range(T):
        truth[t + 1] = truth[t] + dt * np.array([v[t] + 0.5 * rng.standard_normal(), 0.3 * rng.standard_normal()])
    sig = 1.0
    fixes = truth + sig * rng.standard_normal(truth.shape)
    obs = [[PositionFix(tuple(fixes[t]), sig)] for t in range(T + 1)]
    prior_sd = 2.0
    return p, v, w, dt, fixes, sig, prior_sd, obs


def _kalman_rts_1d(u, q, z, r, m0, p0):
    """Random walk x' = x + u + N(0, q), z = x + N(0, r): filter log-lik, RTS means/vars."""
    T = len(u)
    mf, pf = np.empty(T + 1), np.empty(T + 1)
    mp, pp = np.empty(T + 1), np.empty(T + 1)
    ll = 0.0
    mp[0], pp[0] = m0, p0
    for t in range(T + 1):
        if t > 0:
            mp[t], pp[t] = mf[t - 1] + u[t - 1], pf[t - 1] + q
        s = pp[t] + r
        ll += -0.5 * (math.log(2 * math.pi * s) + (z[t] - mp[t]) ** 2 / s)
        k = pp[t] / s
        mf[t], pf[t] = mp[t] + k * (z[t] - mp[t]), (1 - k) * pp[t]
    ms, ps = mf.copy(), pf.copy()
    for t in range(T - 1, -1, -1):
        c = pf[t] / pp[t + 1]
        ms[t] = mf[t] + c * (ms[t + 1] - mp[t + 1])
        ps[t] = pf[t] + c * c * (ps[t + 1] - pp[t + 1])
    return ll, ms, ps


def test_pf_and_smoothers_match_kalman_rts_on_linear_gaussian_model():
    rng = np.random.default_rng(42)
    p, v, w, dt, fixes, sig, prior_sd, obs = _linear_gaussian_problem(rng)
    T = v.size
    ll_x, ms_x, ps_x = _kalman_rts_1d(v * dt, 0.25 * dt**2, fixes[:, 0], sig**2, 0.0, prior_sd**2)
    ll_y, ms_y, ps_y = _kalman_rts_1d(np.zeros(T), 0.09 * dt**2, fixes[:, 1], sig**2, 0.0, prior_sd**2)
    N = 3000
    init = np.column_stack([prior_sd * rng.standard_normal((N, 2)), np.zeros(N)])
    lls = []
    for rep in range(4):
        fr = run_particle_filter(p, v, w, dt, obs, init, np.random.default_rng(100 + rep), N)
        lls.append(fr.log_likelihood)
    assert fr.resampled.any() and not fr.resampled.all()  # the adaptive path is exercised
    # the PF likelihood is unbiased in p, slightly biased low in log p; MC sd ~0.1 here
    assert abs(np.mean(lls) - (ll_x + ll_y)) < 0.5
    M = 400
    for smoother in (ffbsi_exact, ffbsi_mcmc):
        traj = smoother(fr, p, v, w, dt, M, np.random.default_rng(7))
        for got, ms, ps in ((traj[:, :, 0], ms_x, ps_x), (traj[:, :, 1], ms_y, ps_y)):
            # means: within 5 standard errors (correlation between trajectories inflates
            # the error; allow a factor 2 on M)
            se = np.sqrt(ps / (M / 2))
            assert np.all(np.abs(got.mean(axis=0) - ms) < 5 * se), smoother.__name__
            ratio = got.var(axis=0).mean() / ps.mean()
            assert 0.75 < ratio < 1.25, (smoother.__name__, ratio)


def test_exact_and_mcmc_smoothers_give_the_same_moments():
    """Over independent particle systems, the mean smoothed pose and its spread from the
    MCMC backward kernel match the exact FFBSi (both numba), and the numba exact matches
    the numpy reference. Differences are tested against their spread across replicates
    (trajectories from one particle system share genealogy, so within-system standard
    errors would be wrong)."""
    row = ThesisRow(0.05, 0.05, 0.3, 0.1, 2.0, steps=30)
    data = simulate(row, np.random.default_rng(3))
    p = data.params_changed
    times = [0, 8, 15, 22, 30]
    diffs = {"mcmc": [], "numpy": []}
    spread = {"mcmc": [], "numpy": []}
    M = 200
    for rep in range(8):
        rng = np.random.default_rng(100 + rep)
        fr = run_particle_filter(p, data.v, data.w, data.dt, data.observations, _init_cloud(500, rng), rng, 500)
        a = ffbsi_exact(fr, p, data.v, data.w, data.dt, M, rng)
        for name, other in (("mcmc", ffbsi_mcmc(fr, p, data.v, data.w, data.dt, M, rng)),
                            ("numpy", ffbsi_exact_numpy(fr, p, data.v, data.w, data.dt, M, rng))):
            diffs[name].append(other[:, times, :2].mean(0) - a[:, times, :2].mean(0))
            spread[name].append(other[:, times, :2].std(0).mean() / a[:, times, :2].std(0).mean())
    for name in diffs:
        d = np.array(diffs[name])  # (reps, times, 2)
        t_stat = d.mean(0) / (d.std(0, ddof=1) / math.sqrt(d.shape[0]))
        assert np.max(np.abs(t_stat)) < 5.4, (name, t_stat)  # t(7): P(|t| > 5.4) ≈ 0.001
        assert 0.75 < np.mean(spread[name]) < 1.33, (name, spread[name])


def test_filter_is_deterministic_given_the_seed():
    data = simulate(ThesisRow(steps=10), np.random.default_rng(9))
    outs = []
    for _ in range(2):
        rng = np.random.default_rng(10)
        fr = run_particle_filter(data.params_initial, data.v, data.w, data.dt, data.observations,
                                 _init_cloud(200, rng), rng, 200)
        outs.append((fr.poses.copy(), ffbsi_mcmc(fr, data.params_initial, data.v, data.w, data.dt, 20, rng)))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


def test_numba_systematic_resampling_matches_the_reference():
    from adaptnav.calibration._kernels import systematic_from_log

    rng = np.random.default_rng(12)
    for _ in range(20):
        w = rng.random(300) ** 4
        w /= w.sum()
        u = rng.random()
        ref = np.searchsorted(np.concatenate([np.cumsum(w)[:-1], [1.0]]), (u + np.arange(300)) / 300, side="right")
        np.testing.assert_array_equal(systematic_from_log(np.log(w), u), ref)


def test_window_kernel_matches_the_step_by_step_filter():
    """The one-call window (packed observations) and the step-by-step path the landmark
    map needs draw the same numbers and must give the same particles, weights and
    log-likelihood, for every observation type the window packs."""
    from adaptnav.calibration.sensors import FixedLandmarkObservation, HeadingObservation, LandmarkSighting

    data = simulate(ThesisRow(steps=25), np.random.default_rng(21))
    rng = np.random.default_rng(22)
    obs = [list(o) for o in data.observations]
    for t in range(0, 26, 3):
        obs[t].append(HeadingObservation(float(rng.normal(0, 3)), 0.4))
    for t in range(1, 26, 4):
        obs[t].append(PositionFix((float(rng.normal(0, 50)), float(rng.normal(0, 50))), 60.0))
    for t in range(2, 26, 5):
        obs[t].append(FixedLandmarkObservation(LandmarkSighting(1, 5.0, -20.0), np.array([0.0, 50.0]),
                                               np.array([[900.0, 50.0], [50.0, 800.0]])))
    obs[7] = []
    outs = []
    for map_landmarks in (False, True):
        r = np.random.default_rng(5)
        fr = run_particle_filter(data.params_initial, data.v, data.w, data.dt, obs, _init_cloud(300, r), r, 300,
                                 map_landmarks=map_landmarks, current_n_m_s=(0.1, -0.05))
        outs.append(fr)
    a, b = outs
    assert a.landmark_map is None and b.landmark_map is not None  # the two paths really ran
    assert a.resampled.any() and not a.resampled.all()
    np.testing.assert_array_equal(a.ancestors, b.ancestors)
    np.testing.assert_array_equal(a.resampled, b.resampled)
    np.testing.assert_allclose(a.poses, b.poses, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.log_w, b.log_w, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(a.log_lik_increments, b.log_lik_increments, rtol=1e-10)


def test_window_kernel_reports_the_pose_no_particle_explains():
    data = simulate(ThesisRow(steps=6), np.random.default_rng(2))
    obs = [list(o) for o in data.observations]
    obs[4] = [PositionFix((1e6, 0.0), 1e-160)]  # likelihood underflows to 0 for every particle
    rng = np.random.default_rng(3)
    with pytest.raises(FloatingPointError, match="pose 4"):
        run_particle_filter(data.params_initial, data.v, data.w, data.dt, obs, _init_cloud(100, rng), rng, 100)


def test_compiled_exp_and_sincos_match_libm():
    """The branch-free exp of the weights and sin/cos of the moves, against numpy (libm)."""
    from adaptnav.calibration._kernels import WEIGHT_FLUSH_LOG, _exp_flushed_into, sincos

    rng = np.random.default_rng(4)
    d = np.concatenate([rng.uniform(-70.0, 0.0, 5000), [0.0, -1e-300, WEIGHT_FLUSH_LOG, -800.0, np.nan]])
    out = np.empty_like(d)
    _exp_flushed_into(d, out)
    ref = np.where(d > WEIGHT_FLUSH_LOG, np.exp(d), 0.0)
    np.testing.assert_allclose(out, ref, rtol=4.5e-16, atol=0.0)
    assert np.array_equal(out == 0.0, ~(d > WEIGHT_FLUSH_LOG))
    for x in np.concatenate([rng.uniform(-4.0, 4.0, 2000), rng.uniform(-1e5, 1e5, 2000), [0.0, np.pi / 2, -np.pi]]):
        s, c = sincos(x)
        assert abs(s - math.sin(x)) <= 2.3e-16 and abs(c - math.cos(x)) <= 2.3e-16, x


def test_move_normals_are_box_muller_of_the_generators_words_and_standard_normal():
    """The moves' normals: the Box–Muller pairs of the generator's raw words (written out
    in numpy here), standard normal by the Kolmogorov–Smirnov test, the two of a pair
    uncorrelated, an odd count served, the generator advanced by the words used."""
    from scipy import stats

    from adaptnav.calibration.particle_filter import move_normals

    n_words = 100_001
    words = np.random.default_rng(7).bit_generator.random_raw(n_words)
    u1 = ((words >> np.uint64(32)).astype(float) + 0.5) * 2.0 ** -32
    u2 = ((words & np.uint64(0xFFFFFFFF)).astype(float) + 0.5) * 2.0 ** -32
    r = np.sqrt(-2.0 * np.log(u1))
    expected = np.concatenate([r * np.cos(2.0 * np.pi * u2), r * np.sin(2.0 * np.pi * u2)])

    rng = np.random.default_rng(7)
    z = move_normals(rng, (2 * n_words - 1,))  # odd: the last word's sine is not used
    np.testing.assert_allclose(z, expected[:z.size], rtol=0.0, atol=2e-15)
    after = np.random.default_rng(7)
    after.bit_generator.random_raw(n_words)
    assert rng.random() == after.random()

    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert abs(z.mean()) < 5.0 / math.sqrt(z.size) and abs(z.var() - 1.0) < 0.02
    assert abs(np.corrcoef(z[:n_words - 1], z[n_words:])[0, 1]) < 0.02  # cosine with its sine
    shaped = move_normals(np.random.default_rng(3), (5, 3, 7))
    assert shaped.shape == (5, 3, 7) and np.isfinite(shaped).all()
    assert np.array_equal(shaped, move_normals(np.random.default_rng(3), (5, 3, 7)))
