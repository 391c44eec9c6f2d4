"""Estimator.rehearse_epoch (the live daemon's cache warming before an output epoch's IMU
sample, :mod:`adaptnav.service.runtime.rehearsal`) changes nothing of the filter."""
from __future__ import annotations

import numpy as np

from adaptnav.fusion.eskf import Estimator
from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate


def test_a_rehearsed_epoch_leaves_the_filter_as_it_was():
    """``rehearse_epoch`` (the live daemon's cache warming) runs the epoch's compiled steps on a
    scratch copy: the filter's core is the same after it, bit for bit, and the state it
    returns is :meth:`nav_state`'s; before the start and for a step not in (0, 1] s, nothing."""
    sc = load_scenario("short", ["seed=3", "duration_s=120.0", "dvl.enabled=true"])
    cfg = build_config(sc)
    est = Estimator(cfg.filter, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    rehearsed = 0
    for k, item in enumerate(simulate(sc).iter_blocks()):
        if k % 5 == 0:
            if not est.initialized:
                assert est.rehearse_epoch(0.01) is None
            else:
                core, inertial, rest = est._core.copy(), est._inertial_n.copy(), est._st.copy()
                state = est.rehearse_epoch(0.01)
                np.testing.assert_array_equal(est._core, core)
                # (what the epoch sample's compiled call also writes: the free-inertial integral, the rest window)
                assert est._inertial_n.tobytes() == inertial.tobytes() and est._st.tobytes() == rest.tobytes()
                ns = est.nav_state()
                assert state.t_s == ns.t_s and state.valid == ns.valid
                np.testing.assert_array_equal(state.cov, ns.cov)
                np.testing.assert_array_equal(state.pos_n_m, ns.pos_n_m)
                assert est.rehearse_epoch(0.0) is None and est.rehearse_epoch(2.0) is None
                rehearsed += 1
        est.process(item)
    assert rehearsed > 100
