"""Statistical consistency on seeded simulations: NEES and NIS within chi-square bands.

Truth: the analytic missions of :mod:`tests.fusion.mission`, with current and k_V drawn
from the filter's priors. Probes are correlated in time, so the NEES band uses only the
number of independent runs as its sample size (the conservative, wider band).
"""
import numpy as np
from scipy.stats import chi2

from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable

from .mission import ORIGIN, make_mission, run, true_error

RUNS = 3


def _band(dof: int, n: int, p: float = 0.95) -> tuple[float, float]:
    a = (1 - p) / 2
    return chi2.ppf(a, dof * n) / n, chi2.ppf(1 - a, dof * n) / n


def test_nees_and_nis_in_chi_square_bands(matched_config):
    cfg = matched_config
    nees, nis = [], {}
    for seed in range(RUNS):
        rng = np.random.default_rng(100 + seed)
        current = rng.normal(0, cfg.initial.sigma_current_m_s, 2)
        k_v = 1 + rng.normal(0, cfg.initial.sigma_k_speed)
        m = make_mission(rng, 300.0, current_n=current, k_v_true=k_v, static_s=5.0, config=cfg)
        est = Estimator(cfg, MotionParams(), RpmSpeedTable(), ORIGIN)
        states, statuses = run(est, m, probe_times=np.arange(60.0, 300.0, 20.0))
        for k, s in states:
            e = true_error(m, s, k)
            nees.append(e @ np.linalg.solve(s.cov, e))
        for a in statuses:
            if a.t_s > 20.0 and a.innovation:
                nis.setdefault(a.source, []).append(a.test_ratio * cfg.gate_threshold(len(a.innovation)))
    lo, hi = _band(18, RUNS)
    assert lo <= np.mean(nees) <= hi, (np.mean(nees), lo, hi)
    # NIS: consecutive innovations are nearly independent; shrink n 5× for the residual correlation
    for source, dof in (("heading", 1), ("depth", 1), ("usbl", 2)):
        values = np.asarray(nis[source])
        lo, hi = _band(dof, max(len(values) // 5, 1))
        assert lo <= values.mean() <= hi, (source, values.mean(), lo, hi)
    # learned velocity: heave/sway pseudo-measurements are conservative by design (truth has
    # no heave), so only the surge+sway share must not exceed 3 dof and not be vanishing
    lv = np.asarray(nis["learned_velocity"])
    assert 1.0 <= lv.mean() <= _band(3, len(lv) // 5)[1], lv.mean()
