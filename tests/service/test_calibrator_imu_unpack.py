"""IMU batches rebuilt in the calibrator child field by field (service/calibrator/batching.py
``unpack_batch``, without ``ImuBatch.__post_init__``): each is the batch its constructor makes of
the same rows — same fields in the same order, same arrays, no source — among other samples."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from adaptnav.fusion.samples import HeadingSample, ImuBatch, RpmSample
from adaptnav.service.calibrator.batching import pack_batch, unpack_batch


def _trip(batch):
    items, imu, _ = pack_batch(batch)
    return unpack_batch(pickle.loads(pickle.dumps((items, imu, None))))


@pytest.mark.parametrize("seed", range(6))
def test_imu_batches_come_back_as_their_constructor_makes_them(seed):
    rng = np.random.default_rng(seed)
    batch, t = [], 0.0
    for _ in range(int(rng.integers(1, 40))):
        if rng.random() < 0.6:
            n = int(rng.integers(0, 25))  # empty and single-row runs too
            ts = t + 0.01 * np.arange(n)
            f, w = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
            if n and rng.random() < 0.2:
                f[rng.integers(n), rng.integers(3)] = np.nan
                ts[rng.integers(n)] = np.inf
            batch.append(ImuBatch(ts, f, w, source=str(rng.choice(["", "imu0"]))))
            t += 0.01 * n
        else:
            batch.append(RpmSample(t, 1200.0) if rng.random() < 0.5 else HeadingSample(t, 0.1))
    out = _trip(batch)
    assert len(out) == len(batch)
    for a, b in zip(batch, out):
        if not isinstance(a, ImuBatch):
            continue
        ref = ImuBatch(np.asarray(a.t_s, float), np.asarray(a.specific_force_b_m_s2, float),
                       np.asarray(a.omega_b_rad_s, float))  # (the child is sent no source)
        assert type(b) is ImuBatch and list(vars(b)) == list(vars(ref))
        assert b.source == ""
        for name in ("t_s", "specific_force_b_m_s2", "omega_b_rad_s"):
            x, y = getattr(ref, name), getattr(b, name)
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
        ImuBatch(b.t_s, b.specific_force_b_m_s2, b.omega_b_rad_s)  # what __post_init__ would say: valid
        assert len(b) == len(a)
