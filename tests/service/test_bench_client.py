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


def test_the_p99_interval_covers_the_true_p99_as_often_as_it_says():
    """Seeded draws from a heavy-tailed latency-like law (log-normal) of the bench's size: the
    95 % interval of :func:`quantile_ci` holds the law's own p99 in ~95 % of the trials (an
    interval one rank too narrow on each side covers ~89 %, the sample p99 itself ~0 %)."""
    import numpy as np

    from adaptnav.service.tools.benchmarks.service import quantile_ci

    rng = np.random.default_rng(17)
    true_p99 = math.exp(0.5 * 2.3263478740408408)  # log-normal(0, 0.5): exp(σ z_0.99)
    trials = 2000
    covered = 0
    for _ in range(trials):
        lo, hi = quantile_ci(rng.lognormal(0.0, 0.5, 600), 0.99)
        assert lo <= hi
        covered += lo <= true_p99 <= hi
    assert 0.93 <= covered / trials <= 0.975, covered / trials


def test_the_p99_interval_is_unknown_with_too_few_samples_and_bounds_the_verdict():
    from adaptnav.service.tools.benchmarks.service import latency_verdict, quantile_ci

    assert all(math.isnan(v) for v in quantile_ci([1.0] * 100, 0.99))  # its top rank is past the 100th
    lo, hi = quantile_ci(list(range(1, 601)), 0.99)
    assert (lo, hi) == (589.0, 599.0)  # the 12th to the 2nd largest of 600
    assert latency_verdict([1.0, 1.1], [1.4, 1.5], 1.5) == "met"
    assert latency_verdict([1.0, 1.1], [1.4, 1.6], 1.5) == "unknown"  # one rate's interval across it
    assert latency_verdict([1.0, 1.6], [1.4, 2.0], 1.5) == "missed"
    assert latency_verdict([math.nan, 1.0], [math.nan, 1.2], 1.5) == "unknown"  # too few at one rate


def test_a_latency_window_that_is_not_a_positive_number_is_refused_before_anything_runs(monkeypatch):
    import argparse

    import pytest

    from adaptnav.service.tools.benchmarks import service

    def ran(*args, **kwargs):
        raise AssertionError("a part ran before the window was checked")

    monkeypatch.setattr(service, "replay_speed", ran)  # the part measured first
    for bad in (0.0, -5.0, math.nan, math.inf):
        args = argparse.Namespace(quick=True, only="replay,latency", latency_s=bad)
        with pytest.raises(ValueError, match="--latency-s"):
            service.run(args)


def test_the_latency_windows_with_and_without_the_wakeup_bound_are_side_by_side_at_each_rate():
    """The bound's comparison is made in the same minutes: at each rate the default window and
    the one without the bound come one right after the other, in the order A B B A across the
    two rates (the host's drift between them cancels to first order); every rate has both."""
    from adaptnav.service.tools.benchmarks.service import LATENCY_WINDOWS

    plain = [(rate, daemon_us) for rate, sonar, _tag, daemon_us, _echo in LATENCY_WINDOWS if not sonar]
    assert plain == [(100.0, None), (100.0, -1), (200.0, -1), (200.0, None)]
    tags = [tag for *_, tag, _d, _e in LATENCY_WINDOWS]
    assert len(set(tags)) == len(tags)
    for rate, _sonar, tag, daemon_us, echo_us in LATENCY_WINDOWS:
        assert tag.startswith(f"{int(rate)}hz")
        assert tag.endswith("_no_wakeup_bound") == (daemon_us == -1) == (echo_us == -1)
