"""What crosses the process boundary to the calibrator child (service/calibrator/batching.py):
every sample comes out of pack → pickle → unpack as it went in."""
from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np

from adaptnav.fusion.samples import (DepthSample, DvlSample, HeadingSample, ImuBatch, InertialVelocitySample,
                                     RpmSample, UsblSample)
from adaptnav.service.calibrator.batching import _FIELDS, _WHOLE, pack_batch, unpack_batch
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


def _assert_each_came_back(batch, out):
    """``out`` is ``batch`` again, sample by sample in its order: IMU batches' arrays equal,
    sample dataclasses field by field (:func:`_same`), anything else equal."""
    assert len(out) == len(batch)
    for a, b in zip(batch, out):
        if isinstance(a, ImuBatch):
            assert isinstance(b, ImuBatch)
            for name in ("t_s", "specific_force_b_m_s2", "omega_b_rad_s"):
                assert np.array_equal(getattr(a, name), getattr(b, name))
        elif dataclasses.is_dataclass(a):
            assert _same(a, b), (a, b)
        else:
            assert a == b


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
    _assert_each_came_back(batch, out)
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
    codes, groups = packed[0]
    # the DVL sample and the ping in columns, the one with extra state pickled whole, by itself
    assert [g[0] for g in groups] == [_FIELDS, _WHOLE, _FIELDS] and list(codes) == [0, 1, 2]
    assert groups[1][1] == [extra] and len(packed[2]) == 2 and groups[2][3] == (1, 2)
    out = unpack_batch(_trip(packed))
    assert _same(out[0], dvl) and type(out[0].vel_d_m_s) is np.ndarray
    assert _same(out[1], extra) and out[1].note == "kept"
    assert _same(out[2], ping) and np.array_equal(out[2].starboard, np.arange(8) + 1)


def test_batches_of_samples_in_any_order_and_mix_survive_the_trip_in_columns():
    # seeded random interleavings of every kind (columns per type, echoes laid end to end
    # group after group): each sample comes out as it went in, in its place
    rng = np.random.default_rng(11)

    def ping(t):
        n = int(rng.integers(0, 5)) * 8  # (echoes of no samples too)
        return SonarPing(t, rng.random(n).astype(np.float32), rng.random(n).astype(np.float32), 20.0,
                         heading_rad=float(rng.normal()))

    makers = [
        lambda t: ImuBatch(t + np.arange(3) * 0.01, rng.normal(size=(3, 3)), rng.normal(size=(3, 3))),
        ping,
        lambda t: DvlSample(t, tuple(rng.normal(size=3)), valid=bool(rng.integers(2)), altitude_m=float(rng.random())),
        lambda t: RpmSample(t, float(rng.normal(1200.0, 10.0))),
        lambda t: HeadingSample(t, float(rng.normal())),
        lambda t: DepthSample(t, float(rng.normal(120000.0, 100.0))),
        lambda t: ("not a sample", t),
    ]
    for trial in range(20):
        batch = [makers[int(k)](0.1 * i) for i, k in enumerate(rng.integers(0, len(makers), int(rng.integers(1, 60))))]
        if trial % 4 == 1:  # a ping whose echo is no float32 vector (not made by its constructor)
            odd = ping(99.0)
            object.__setattr__(odd, "port", np.zeros(8))
            batch.insert(int(rng.integers(0, len(batch) + 1)), odd)
        if trial % 4 == 2:  # a sample carrying more than its fields
            extra = ping(98.0)
            object.__setattr__(extra, "note", trial)
            batch.insert(int(rng.integers(0, len(batch) + 1)), extra)
        out = unpack_batch(_trip(pack_batch(batch)))
        _assert_each_came_back(batch, out)
        for a, b in zip(batch, out):
            if isinstance(a, (ImuBatch, tuple)):
                continue
            assert getattr(b, "__dict__", {}).keys() == getattr(a, "__dict__", {}).keys()
            if isinstance(a, SonarPing) and a.port.dtype == np.float32 and not hasattr(a, "note"):
                # (as its constructor keeps them; one pickled whole comes out as pickling makes it)
                assert not b.port.flags.writeable and not b.starboard.flags.writeable
