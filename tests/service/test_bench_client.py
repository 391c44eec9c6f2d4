"""The latency bench's outside client publishes what the simulator made, encoded before its
timed loop (:func:`_client_outbox`): every sample on its kind's key, in order, the IMU
samples stamped as a simulated IMU counts its time (``t += 1 / rate``)."""
from __future__ import annotations

import math

from adaptnav.fusion.samples import DepthSample, ImuSample
from adaptnav.service.tools.benchmarks.service import _client_outbox
from adaptnav.service.transport.bus import Keys, decode_sample


def test_the_outbox_is_the_stream_encoded_with_the_imu_counting_its_time():
    rate_hz = 200.0
    # an IMU whose stamps wander off the counted times (jitter): the client re-stamps them
    imu = [ImuSample(10.0 + k * 0.005 + (0.0007 if k % 3 else 0.0), (0.1 * k, 0.2, -9.8), (0.01, 0.02, 0.03 * k))
           for k in range(5)]
    depth = DepthSample(10.011, 301325.0)
    stream = imu[:3] + [depth] + imu[3:]
    keys = Keys("bench")
    out = _client_outbox(stream, keys, rate_hz)

    assert [t for t, *_ in out] == [s.t_s for s in stream]  # paced by the data's own times
    assert [key for _, key, _, _ in out] == [keys.sensor(s.KIND) for s in stream]
    stamps = [stamp for *_, stamp in out]
    assert stamps[3] is None  # only IMU samples are timed
    counted = [10.0 + k / rate_hz for k in range(5)]
    imu_stamps = [s for s in stamps if s is not None]
    assert all(math.isclose(a, b, rel_tol=0.0, abs_tol=1e-12) for a, b in zip(imu_stamps, counted))
    decoded = [decode_sample(payload) for _, _, payload, _ in out]
    assert decoded[3] == depth
    for got, sent, stamp in zip([d for d in decoded if d.KIND == "imu"], imu, imu_stamps):
        assert got.t_s == stamp  # the stamp timed is the one the daemon gets
        assert list(got.specific_force_b_m_s2) == list(sent.specific_force_b_m_s2)
        assert list(got.omega_b_rad_s) == list(sent.omega_b_rad_s)
