import functools
import math

import numpy as np
import pytest

from adaptnav.sim.seabed import Seabed
from adaptnav.sim.sidescan import SidescanRenderer
from adaptnav.sonar.landmarks import LandmarkTracker, extract_landmarks
from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall
from tests.sonar.conftest import straight_pass

CFG = WaterfallConfig(ground_res_m=0.1, along_res_m=0.1)


@functools.lru_cache(maxsize=None)  # the two tests share their surveys
def _survey(seed):
    """Two passes over one seabed; observations with true and (noisy) estimated positions."""
    rng = np.random.default_rng(seed)
    seabed = Seabed.random((120.0, 70.0), rng, n_objects=60, radius_m=(0.15, 0.3))
    ren = SidescanRenderer(seabed, 25.0, 512)
    tracker = LandmarkTracker()
    passes = []
    yaw2 = math.radians(rng.uniform(-3, 3))
    for start, yaw in [((10.0, 35.0), 0.0), ((12.0, 35.0 + rng.uniform(-2, 2)), yaw2)]:
        pings, pos = straight_pass(ren, rng, start, yaw, 400)
        wf = build_waterfall(pings, CFG)
        obs = extract_landmarks(wf, max_landmarks=60)
        fwd = np.array([math.cos(yaw), math.sin(yaw)])
        true_pos = np.array([o.position_n_m(pos[0] + o.along_track_m * fwd, yaw) for o in obs])
        est_pos = true_pos + rng.normal(0.0, 0.5, 2)  # navigation error of the pass
        passes.append((tracker.update(obs, est_pos), true_pos, np.asarray(start), yaw))
    return seabed, passes


@pytest.mark.parametrize("seed", [3, 5, 8])
def test_ground_ranges_of_object_landmarks(seed):
    seabed, passes = _survey(seed)
    errors = []
    for obs, true_pos, start, yaw in passes:
        d = np.linalg.norm(true_pos[:, None, :] - seabed.objects_n_m[None], axis=2)
        near = d.min(axis=1) < 0.8
        j = d.argmin(axis=1)
        stbd = np.array([-math.sin(yaw), math.cos(yaw)])
        true_range = np.abs((seabed.objects_n_m[j] - start) @ stbd)
        gr = np.array([o.ground_range_m for o in obs])
        errors.extend(np.abs(gr - true_range)[near])
    errors = np.array(errors)
    assert errors.size >= 20  # objects are found at all
    assert np.mean(errors < 0.3) >= 0.9


def _identity(true_pos, seabed):
    """Truth label of each observation: its object's index, or −1 for seabed texture."""
    d = np.linalg.norm(true_pos[:, None, :] - seabed.objects_n_m[None], axis=2)
    return np.where(d.min(axis=1) < 0.8, d.argmin(axis=1), -1)


@pytest.mark.parametrize("seed", [3, 5, 8, 11])
def test_reobserved_landmarks_get_their_track_id(seed):
    seabed, passes = _survey(seed)
    (obs1, true1, *_), (obs2, true2, *_) = passes
    id1, id2 = _identity(true1, seabed), _identity(true2, seabed)
    first = {o.track_id: (k, p) for o, k, p in zip(obs1, id1, true1)}
    assert len(first) == len(obs1)  # every first-pass landmark starts its own track
    reobserved = correct = false_links = 0
    for o, k, p in zip(obs2, id2, true2):
        # same object, or (texture) the same spot seen on the first pass
        seen_before = (k in id1) if k >= 0 else np.min(np.linalg.norm(true1 - p, axis=1)) < 0.5
        linked = o.track_id in first
        if seen_before:
            reobserved += 1
            if linked:
                k1, p1 = first[o.track_id]
                correct += (k1 == k) if k >= 0 else np.linalg.norm(p1 - p) < 0.5
        elif linked:
            false_links += 1
    assert reobserved >= 8
    assert correct / reobserved >= 0.9
    assert false_links <= 0.2 * len(obs2)


def test_observation_fields_and_sides():
    rng = np.random.default_rng(2)
    seabed = Seabed.random((60.0, 60.0), rng, n_objects=30, radius_m=(0.15, 0.3))
    ren = SidescanRenderer(seabed, 25.0, 512)
    pings, _ = straight_pass(ren, rng, (10.0, 30.0), 0.0, 200)
    obs = extract_landmarks(build_waterfall(pings, CFG), max_landmarks=4)
    assert 1 <= len(obs) <= 4
    for o in obs:
        assert o.side in ("port", "starboard") and o.ground_range_m >= 1.0
        assert o.track_id is None and o.descriptor.shape == (128,)
        assert 0.0 <= o.t_s <= pings[-1].t_s and 0.0 <= o.along_track_m <= 40.0
    assert [o.response for o in obs] == sorted((o.response for o in obs), reverse=True)
