"""The side-scan path stays bounded in memory (service/loop_closures.py): the associator's
sighting store has a cap and forgets what the filter's clones could no longer fuse."""
from __future__ import annotations

import numpy as np

from adaptnav.service.runtime.replay import build_config
from adaptnav.sim.scenario import load_scenario
from adaptnav.sonar.association import AssociationConfig, LegAssociator
from adaptnav.sonar.objects import ObjectSighting


def _sighting(t_s: float, north: float) -> ObjectSighting:
    return ObjectSighting(t_s=t_s, side="port", ground_range_m=20.0, height_m=0.5, shadow_length_m=1.0,
                          length_along_m=1.0, width_across_m=0.5, contrast=10.0, altitude_m=10.0,
                          pos_n_m=np.array([north, 0.0]), nav_cov=np.eye(2), det_cov=0.04 * np.eye(2),
                          heading_rad=0.0)


def test_sighting_store_is_capped():
    assoc = LegAssociator(AssociationConfig(max_sightings=25))
    for b in range(20):
        assoc.add([_sighting(10.0 * b + 0.1 * i, 1000.0 * b + 10.0 * i) for i in range(5)])
        assert len(assoc.sightings) <= 25
    assert max(o.t_s for o in assoc.sightings) >= 190.0  # the newest kept


def test_estimator_forgets_sightings_beyond_its_clones():
    from adaptnav.service.compose import make_estimator

    cfg = build_config(load_scenario("short", []))
    est = make_estimator(cfg)
    assoc = est.associator
    assert assoc.config.memory_s <= cfg.filter.loop_closure.clone_horizon_s
    assert assoc.config.max_sightings > 0
