"""The live daemon over REAL Zenoh sessions on loopback (two peers, explicit endpoints,
multicast scouting off): samples in, nav states out, queryables, bad input counted,
silent sensors reported."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from adaptnav import kernels

from .test_daemon_support import Feeder, wait_until

pytestmark = pytest.mark.timeout(120)


# sensors silent after 1 s of data time; state saved every 0.5 s
SETTINGS = ("health.sensor_timeout_s=1.0", "persistence.period_s=0.5")


def test_sample_in_nav_state_out_and_queryables(live):
    daemon, bus, col = live(*SETTINGS)
    feeder = Feeder(bus)
    feeder.start()
    try:
        navs = col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 10, timeout_s=60)
    finally:
        feeder.stop()
    assert len(navs) >= 10, "no nav states came back over Zenoh"
    last = navs[-1]
    assert last["type"] == "nav_state" and last["schema_version"] == 1
    assert len(last["cov"]) == 18 * 18
    # at rest at 5 m depth (the depth sample we sent), heading 0.3 rad (the heading we sent)
    assert abs(last["pos_n_m"][2] - 5.0) < 0.5
    assert abs(last["euler_rad"][2] - 0.3) < 0.05
    # nav states at 10 Hz of data time: epochs are multiples of 0.1 s (± one IMU period)
    ts = np.array([d["t_s"] for d in navs])
    assert np.all(np.diff(ts) > 0)
    assert np.median(np.diff(ts)) == pytest.approx(0.1, abs=0.006)

    params = bus.get("params")
    assert params["type"] == "motion_params"
    assert params["params"]["k_v"] == 1.0 and params["params"]["var_vv"] == pytest.approx(0.05**2)
    config = bus.get("config")
    assert config["vehicle"]["name"] == "testauv"
    assert config["zenoh"]["scouting"] is False
    state = bus.get("state")
    assert state["type"] == "nav_state" and state["t_s"] >= navs[0]["t_s"]
    # reliable transport, no overflow: every sample published reaches the runner
    health = wait_until(lambda: (h := bus.get("health")) and h["queue_depth"] == 0
                        and h["sensors"]["imu"]["count"] == feeder.published["imu"] and h, timeout_s=60)
    assert health, f"imu count {bus.get('health')['sensors']['imu']} != published {feeder.published['imu']}"
    assert health["sensors"]["heading"]["count"] == feeder.published["heading"]
    assert health["runner_alive"] is True
    # what start-up made is frozen out of the collector's passes (service/runtime/collector.py)
    assert health["gc"]["frozen_objects"] > 1000
    assert set(health["gc"]) == {"frozen_objects"} | {f"{how}_{g}" for how in ("paced", "automatic") for g in range(3)}
    # the kernels' build as this process found it (a damaged one: tests/test_kernels.py)
    assert health["kernels"] == {"ahead_of_time": kernels.using_aot(), "build": kernels.loaded_build(), "problem": None}
    # the integrity monitor's window per aid: the vehicle at rest, its heading and depth exact
    integrity = health["integrity"]
    for source in ("heading", "depth"):
        w = integrity[source]
        assert 1 <= w["attempts"] <= min(feeder.published[source], 20)
        assert 0.0 <= w["nis_per_dof"] < w["bound_per_dof"] and w["failing"] is False


def test_malformed_and_nan_counted_service_alive(live):
    daemon, bus, col = live(*SETTINGS)
    feeder = Feeder(bus)
    feeder.start()
    try:
        col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 3)
        bad = [b"\xff\xfe not utf8", b"{not json", b"[1, 2, 3]",
               json.dumps({"type": "imu", "schema_version": 1, "t_s": 1.0}).encode(),  # missing fields
               json.dumps({"type": "warp_drive", "schema_version": 1, "t_s": 1.0}).encode()]
        for payload in bad:
            bus.put(bus.keys.sensor("imu"), payload)
        n_nan = 7
        for i in range(n_nan):
            # a NaN depth sample is well-formed JSON (null) but not finite
            bus.put(bus.keys.sensor("depth"), json.dumps(
                {"type": "depth", "schema_version": 1, "t_s": feeder.t_s, "pressure_pa": None}).encode())
        n_before = len(col.get(bus.keys.nav_state))
        health = wait_until(lambda: (h := col.get(bus.keys.health)) and
                            sum(v for k, v in h[-1]["rejected"].items() if k.startswith("malformed")) >= len(bad)
                            and h[-1]["rejected"].get("non_finite", 0) >= n_nan and h[-1], timeout_s=60)
        navs = col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= n_before + 5)
    finally:
        feeder.stop()
    assert health, f"health never counted the bad input: {col.get(bus.keys.health)[-1:]}"
    malformed = sum(v for k, v in health["rejected"].items() if k.startswith("malformed"))
    assert malformed == len(bad)
    assert health["rejected"]["non_finite"] == n_nan
    assert len(navs) >= n_before + 5, "the daemon stopped producing nav states after bad input"
    assert daemon._threads[0].is_alive()


def test_silent_sensor_reported_with_reason(live):
    daemon, bus, col = live(*SETTINGS)  # sensor_timeout_s = 1.0 s of data time
    feeder = Feeder(bus)
    feeder.start()
    try:
        col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 3)
        feeder.kinds.discard("depth")
        # the feeder's iteration in flight may have copied its kinds before the discard
        t_silenced = feeder.t_s + feeder.dt
        health = wait_until(lambda: (h := col.get(bus.keys.health)) and "depth" in h[-1]["silent"] and h[-1],
                            timeout_s=60)
        aid = col.wait_for(bus.keys.aid("depth"), lambda docs: any(d["reason"] == "stale" for d in docs),
                           timeout_s=60)
    finally:
        feeder.stop()
    assert health, "health never reported depth silent"
    assert health["sensors"]["depth"]["silent"] is True
    assert health["sensors"]["depth"]["age_s"] > 1.0
    assert health["sensors"]["depth"]["last_seen_t_s"] <= t_silenced + 1e-6
    assert "imu" not in health["silent"] and "heading" not in health["silent"]
    stale = [d for d in aid if d["reason"] == "stale"]
    assert stale, f"no stale aid status for depth: {aid[-3:]}"
    assert stale[-1]["fused"] is False and "depth" in stale[-1]["detail"]
    assert math.isnan(stale[-1]["test_ratio"] or math.nan)
