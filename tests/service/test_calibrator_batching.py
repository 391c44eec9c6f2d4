"""What crosses the process boundary to the calibrator child (service/calibrator/batching.py):
every sample comes out of pack → pickle → unpack as it went in."""
from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np

from adaptnav.fusion.samples import (DepthSample, DvlSample, HeadingSample, ImuBatch, InertialVelocitySample,
                                     RpmSample, UsblSample)
from adaptnav.service.calibrator.batching import pack_batch, unpack_batch
from adaptnav.sonar.ping import SonarPing


def _same(a, b) -> bool:
    if type(a) is not type(b):
        return False
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if not (isinstance(y, np.ndarray) and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)):
                return False
        elif not (x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))):
            return False
    return True


def _trip(packed):
    """What ProcessBackend does: the items pickled, the echoes as raw bytes beside them."""
    items, imu, echoes = pickle.loads(pickle.dumps(packed[:2] + (None,)))
    raw = b"".join(e.tobytes() for e in packed[2])
    return items, imu, (np.frombuffer(raw, dtype=np.float32).copy() if packed[2] else None)


def test_every_sample_survives_the_trip_to_the_child_with_its_values_and_order():
    rng = np.random.default_rng(3)
    n = 7
    batch = [
        ImuBatch(np.arange(n) * 0.01, rng.normal(size=(n, 3)), rng.normal(size=(n, 3))),
        SonarPing(0.05, rng.random(64).astype(np.float32), rng.random(64).astype(np.float32), 30.0,
                  altitude_m=4.5, heading_rad=0.3),
        DvlSample(0.06, (0.5, -0.1, 0.02), valid=True, altitude_m=math.nan),
        RpmSample(0.07, 1200.0),
        ImuBatch(0.07 + np.arange(3) * 0.01, rng.normal(size=(3, 3)), rng.normal(size=(3, 3))),
        SonarPing(0.1, rng.random(32).astype(np.float32), rng.random(32).astype(np.float32), 15.0),
        DepthSample(0.1, 120000.0),
        HeadingSample(0.1, 1.2),
        UsblSample(0.2, 0.1, 0.2, 3.0, 2.0, 1.0),
        InertialVelocitySample(1.0, (0.1, 0.2, 0.0), (1.0, 2.0, 0.0), 0.5, 3, (0.0, 0.1, 0.0)),
        "not a dataclass",
    ]
    out = unpack_batch(_trip(pack_batch(batch)))
    assert len(out) == len(batch)
    for a, b in zip(batch, out):
        if isinstance(a, ImuBatch):
            assert isinstance(b, ImuBatch)
            for name in ("t_s", "specific_force_b_m_s2", "omega_b_rad_s"):
                assert np.array_equal(getattr(a, name), getattr(b, name))
        elif isinstance(a, str):
            assert a == b
        else:
            assert _same(a, b), (a, b)
    # the echoes stay read-only, as a SonarPing keeps them
    assert not out[1].port.flags.writeable and out[1].port.size == 64 and out[5].starboard.size == 32


def test_a_sample_with_a_non_echo_array_or_extra_state_survives_the_trip_too():
    # a float64 array field is no echo (it stays in place); a sample carrying more than its
    # fields goes pickled whole — both must come out as they went in
    dvl = DvlSample(0.06, np.array([0.5, -0.1, 0.02]), valid=True, altitude_m=3.0)
    extra = SonarPing(0.1, np.zeros(4, dtype=np.float32), np.ones(4, dtype=np.float32), 5.0)
    object.__setattr__(extra, "note", "kept")
    ping = SonarPing(0.2, np.arange(8, dtype=np.float32), np.arange(8, dtype=np.float32) + 1, 10.0)
    packed = pack_batch([dvl, extra, ping])
    items = packed[0]
    assert items[1] is extra and type(items[0]) is tuple and type(items[2]) is list and len(packed[2]) == 2
    out = unpack_batch(_trip(packed))
    assert _same(out[0], dvl) and type(out[0].vel_d_m_s) is np.ndarray
    assert _same(out[1], extra) and out[1].note == "kept"
    assert _same(out[2], ping) and np.array_equal(out[2].starboard, np.arange(8) + 1)
