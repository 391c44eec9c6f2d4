"""Estimator.horizontal_nav is nav_state's horizontal numbers without building the state
(the side-scan ping's record): both must stay the same numbers, the considered DVL terms of
the published covariance included, as either of them changes."""
from __future__ import annotations

import numpy as np

from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.state import POS_NE, VEL
from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate


def test_horizontal_nav_is_nav_states_numbers_with_the_dvl_terms():
    sc = load_scenario("short", ["seed=3", "duration_s=200.0", "dvl.enabled=true", "usbl.lost_after_s=60.0"])
    res = simulate(sc)
    cfg = build_config(sc)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    vel_ne = slice(VEL.start, VEL.start + 2)
    compared = with_dvl_terms = 0
    for k, item in enumerate(res.iter_blocks()):
        est.process(item)
        if k % 7:
            continue
        ns, hn = est.nav_state(), est.horizontal_nav()
        if not ns.valid:
            assert hn is None
            continue
        t, pos, vel, yaw, cov_pos, cov_vel = hn
        assert t == ns.t_s and yaw == ns.euler_rad()[2]
        np.testing.assert_array_equal(pos, ns.pos_n_m[:2])
        np.testing.assert_array_equal(vel, ns.vel_n_m_s[:2])
        np.testing.assert_array_equal(cov_pos, ns.cov[POS_NE, POS_NE])
        np.testing.assert_array_equal(cov_vel, ns.cov[vel_ne, vel_ne])
        compared += 1
        cal = est.dvl_calibration
        with_dvl_terms += cal is not None and bool(np.any(cal.position_cov_ne() > 0.0))
    assert compared > 100 and with_dvl_terms > 50, (compared, with_dvl_terms)
