"""The object batches the filter sends back to the calibrator child go without their sightings
(service/calibrator/lagged.py ``for_child``): the calibrator reads only their links and time."""
from __future__ import annotations

import numpy as np

from adaptnav.calibration.sidescan import ObjectBatch
from adaptnav.fusion.samples import RpmSample
from adaptnav.service.calibrator.lagged import for_child
from adaptnav.sonar.objects import ObjectSighting


def _sighting(rng, t_s: float, **kw) -> ObjectSighting:
    args = dict(t_s=t_s, side=str(rng.choice(["port", "starboard"])), ground_range_m=float(rng.uniform(5, 50)),
                height_m=float(rng.uniform(0, 2)), shadow_length_m=float(rng.uniform(0, 5)),
                length_along_m=float(rng.uniform(0, 3)), width_across_m=float(rng.uniform(0, 3)),
                contrast=float(rng.uniform(1, 9)), altitude_m=float(rng.uniform(5, 40)), row=float(rng.uniform(0, 200)),
                pos_n_m=rng.normal(size=2) * 100, nav_cov=np.diag(rng.uniform(0.1, 3, 2)),
                det_cov=rng.normal(size=(2, 2)), heading_rad=float(rng.uniform(-3, 3)),
                weak=bool(rng.random() < 0.5), guided=bool(rng.random() < 0.2))
    args.update(kw)
    return ObjectSighting(**args)


def test_the_child_gets_an_object_batch_without_its_sightings_and_everything_else_as_it_is():
    rng = np.random.default_rng(2)
    links = [((_sighting(rng, 1.0), _sighting(rng, 50.0)),)]
    batch = ObjectBatch(60.0, (_sighting(rng, 1.0), _sighting(rng, 2.0)), links)
    sent = for_child(batch)
    assert sent is not batch and sent.sightings == () and sent.t_s == batch.t_s and sent.links is batch.links
    assert len(batch.sightings) == 2  # the filter's batch untouched
    empty = ObjectBatch(61.0, ())
    assert for_child(empty) is empty
    rpm = RpmSample(1.0, 1200.0)
    assert for_child(rpm) is rpm
