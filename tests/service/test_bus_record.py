"""Bus and recorder over REAL Zenoh peers on loopback (explicit endpoints, scouting off)."""
from __future__ import annotations

import json
import threading
import time
from collections import Counter

import pytest

from adaptnav.fusion.samples import DepthSample, ImuSample, RpmSample
from adaptnav.service.transport.bus import Bus, message
from adaptnav.service.commands.record import record
from adaptnav.service.config import ZenohConfig
from adaptnav.service.transport.logs import LOG_CLOCK_KEY, RECEPTION_WALL_CLOCK, ReadStats, read_mcap

from .test_daemon_support import free_port, wait_until

pytestmark = pytest.mark.timeout(60)


def _pair(vehicle="busauv"):
    port = free_port()
    a = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), vehicle)
    b = Bus(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=(), scouting=False), vehicle)
    return a, b


def test_samples_cross_and_malformed_counted():
    a, b = _pair()
    got = []
    try:
        a.subscribe_samples(got.append)
        for kind in ("imu", "depth"):  # the subscription has reached b (no sample lost to its propagation)
            assert b.wait_subscribed(b.keys.sensor(kind))
        sent = [ImuSample(0.005 * k, (0.1, 0.2, -9.8), (0.0, 0.01, 0.0)) for k in range(20)]
        for s in sent:
            b.publish_sample(s)
        b.publish_sample(RpmSample(0.1, 900.0))
        b.put(b.keys.sensor("imu"), b"{broken")
        b.put(b.keys.sensor("depth"), json.dumps({"type": "depth", "schema_version": 7,
                                                  "t_s": 1.0, "pressure_pa": 1e5}).encode())
        assert wait_until(lambda: len(got) == 21 and sum(a.malformed.values()) == 2, 5)
    finally:
        a.close()
        b.close()
    assert got[:20] == sent  # exact round trip through JSON and Zenoh, in order
    assert got[20] == RpmSample(0.1, 900.0)
    assert a.malformed == Counter({"imu": 1, "depth": 1})


def test_queryable_answers_and_survives_errors():
    a, b = _pair()
    try:
        a.queryable("params", lambda: message("motion_params", {"params": {"k_v": 1.25}}))
        a.queryable("health", lambda: 1 / 0)  # a failing answer must not break the session
        assert b.wait_queryable("params") and b.wait_queryable("health")
        assert b.get("params")["params"]["k_v"] == 1.25
        assert b.get("health", timeout_s=1.0) is None
        assert b.get("params")["type"] == "motion_params"  # still answering
    finally:
        a.close()
        b.close()


def test_record_writes_every_message(tmp_path):
    a, b = _pair()
    out = tmp_path / "rec.mcap"
    stop = threading.Event()
    result = {}
    t = threading.Thread(target=lambda: result.update(zip(("counts", "malformed"),
                                                           record(b, out, stop, duration_s=30))))
    try:
        t.start()
        keys = (a.keys.sensor("imu"), a.keys.sensor("depth"), a.keys.nav_state, a.keys.health)
        assert wait_until(lambda: all(a.wait_subscribed(k, 0.1) for k in keys), 30), "recorder not subscribed"
        # a second subscriber in the recorder's session, declared after the recorder's: Zenoh
        # runs a session's callbacks for a message in declaration order, so once this one has
        # seen everything, the recorder's inbox holds everything
        seen = []
        b.subscribe_raw(b.keys.all, lambda key, payload: seen.append(key))
        samples = [ImuSample(0.01 * k, (0.0, 0.0, -9.8), (0.0, 0.0, 0.001 * k)) for k in range(50)]
        samples += [DepthSample(0.1 * k, 1.2e5 + k) for k in range(5)]
        for s in samples:
            a.publish_sample(s)
        a.publish(a.keys.nav_state, "nav_state", {"t_s": 0.5, "pos_n_m": [1.0, 2.0, 3.0]})
        a.publish(a.keys.health, "health", {"t_s": 0.5, "queue_depth": 0})
        a.put(a.keys.sensor("imu"), b"garbage")
        assert wait_until(lambda: len(seen) == 58, 30), len(seen)  # 55 samples, 2 messages, 1 garbage
    finally:
        stop.set()
        t.join(10)
        a.close()
        b.close()
    assert result["counts"] == {"imu": 50, "depth": 5, "nav_state": 1, "health": 1}
    assert result["malformed"] == 1
    stats = ReadStats()
    back = list(read_mcap(out, stats))
    assert not stats.truncated and stats.bad_messages == 0
    imu_back = [m for m in back if m.KIND == "imu"]
    assert imu_back == samples[:50]
    nav = [m for m in back if m.KIND == "nav_state"]
    assert nav[0].body["pos_n_m"] == [1.0, 2.0, 3.0] and nav[0].t_s == 0.5
    # the log times are the recorder's wall clock, and the file says so (replay tells a dropout
    # from a step of the data's clock by it: McapSource.forward_jump_is_gap)
    log = read_mcap(out)
    assert log.metadata[LOG_CLOCK_KEY] == RECEPTION_WALL_CLOCK
    times = [(getattr(m, "t_s", None), log.log_time_ns) for m in log if getattr(m, "KIND", "") == "imu"]
    assert all(abs(ns * 1e-9 - time.time()) < 600.0 for _, ns in times)  # wall time, not the data's 0–0.5 s
