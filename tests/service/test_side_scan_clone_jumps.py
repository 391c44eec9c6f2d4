"""The side-scan estimator's jumps at each clone (:meth:`SideScanEstimator._keep_clone_jump`) are
the ones :meth:`~adaptnav.fusion.eskf.Estimator.nav_state`'s position and velocity give, bit for
bit: read from the state itself without an output point, nav_state's with one (the output point's
lever arm moves both), over a simulated survey with USBL fixes (jumps) and clones every period."""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from adaptnav.service.loop_closures import SideScanEstimator
from adaptnav.service.runtime.replay import build_config
from adaptnav.service.runtime.sources import SimSource
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate


class _Checked(SideScanEstimator):
    """Each clone's jumps against the nav_state formulation, taken before the clone's are kept."""

    checked = 0
    extrapolated = 0  # clones after the last ping: their jumps read the position and velocity

    def _keep_clone_jump(self) -> None:
        ns = self.nav_state()
        t = float(self._clones.t_s[-1])
        want = np.array(self._jump_at(t, ns.pos_n_m[:2].tolist(), ns.vel_n_m_s[:2].tolist()))
        self.extrapolated += self._last_vel is not None and t > self._last_vel[0]
        super()._keep_clone_jump()
        assert self._clone_jump[t].tobytes() == want.tobytes(), t
        self.checked += 1


@pytest.fixture(scope="module")
def survey():
    sc = load_scenario("survey", ["seed=2", "duration_s=150.0", "trajectory.leg_length_m=100.0"])
    return sc, simulate(sc)


@pytest.mark.parametrize("output_point_b_m", [(0.0, 0.0, 0.0), (0.6, -0.2, 0.3)])
def test_clone_jumps_are_nav_states(survey, output_point_b_m):
    sc, res = survey
    cfg = build_config(sc)
    fcfg = dataclasses.replace(cfg.filter, output_point_b_m=output_point_b_m)
    est = _Checked(fcfg, cfg.motion.params0, cfg.motion.rpm_table, cfg.origin.geo())
    assert (est._out_arm is None) == (not any(output_point_b_m))
    t_ping = -np.inf
    for item in SimSource(sc, res):
        t = getattr(item, "t_s", None)
        if t is not None and not isinstance(t, float):
            t = float(t[-1])
        est.process(item)
        # a ping a little before the state's time (what the record reads of it: its time), so
        # that each clone comes after the last ping (its jumps extrapolated from the state's)
        if t is not None and t >= t_ping + 0.1:
            t_ping = t
            est._ping(SimpleNamespace(t_s=t - 0.05))
    jumps = np.array(list(est._clone_jump.values()))
    assert est.checked >= 20 and len(jumps) >= 20
    assert est.extrapolated >= 20
    assert np.all(np.isfinite(jumps)) and np.abs(jumps).max() > 0.1  # (fixes made jumps)
