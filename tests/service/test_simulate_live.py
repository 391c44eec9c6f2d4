"""``adaptnav simulate --live zenoh`` feeds a running daemon over a real Zenoh session as a
vehicle's drivers would; the daemon's nav states (with latitude/longitude) follow the
simulated mission, and every payload declares its encoding (JSON with a schema name)."""
from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import daemon_config, free_port, peer

pytestmark = pytest.mark.timeout(240)


def test_simulate_live_zenoh_drives_the_daemon(tmp_path):
    from adaptnav.service.cli import main
    from adaptnav.sim.scenario import load_scenario
    from adaptnav.sim.simulator import simulate

    port = free_port()
    cfg = daemon_config(port, tmp_path / "state", "calibrator.enabled=false", "origin.lat_deg=43.0",
                        "origin.lon_deg=5.9")
    daemon = Daemon(cfg)
    daemon.start()
    watcher = peer(port)
    navs: list[dict] = []
    encodings: dict[str, str] = {}
    lock = threading.Lock()

    def on_nav(sample):
        with lock:
            navs.append(json.loads(sample.payload.to_bytes()))
            encodings[str(sample.key_expr)] = str(sample.encoding)

    sub = watcher.session.declare_subscriber(watcher.keys.nav_state, on_nav)
    sensors: dict[str, str] = {}
    sub2 = watcher.session.declare_subscriber(watcher.keys.sensors, lambda s: sensors.setdefault(
        str(s.key_expr).rsplit("/", 1)[-1], str(s.encoding)))
    try:
        rc = main(["simulate", "short", "--set", "duration_s=60", "--live", "zenoh", "--connect",
                   f"tcp/127.0.0.1:{port}", "--vehicle", "testauv", "--speed", "20"])
        assert rc == 0
        # the daemon drains its queue: wait for the states of the mission's last seconds
        import time
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with lock:
                if navs and navs[-1]["t_s"] >= 58.0:
                    break
            time.sleep(0.1)  # polling for the daemon's output, not pacing anything
    finally:
        sub.undeclare()
        sub2.undeclare()
        watcher.close()
        daemon.stop()
    assert navs and navs[-1]["t_s"] >= 58.0, f"last nav state at {navs[-1]['t_s'] if navs else None}"
    # encodings: JSON with the message's schema name, for generic tools
    assert set(encodings.values()) == {"application/json;adaptnav.nav_state"}
    assert sensors["imu"] == "application/json;adaptnav.imu"
    # the daemon followed the simulated vehicle (same scenario, same seed: its truth)
    truth = {round(s.t_s, 3): s for s in simulate(load_scenario("short", ["duration_s=60"])).iter_samples()
             if s.KIND == "truth"}
    errs = []
    for doc in navs:
        tr = truth.get(round(doc["t_s"], 3))
        if tr is not None and doc["valid"]:
            errs.append(math.hypot(doc["pos_n_m"][0] - tr.pos_n_m[0], doc["pos_n_m"][1] - tr.pos_n_m[1]))
            # latitude/longitude beside NED, from the same origin
            lat0 = math.radians(43.0)
            assert doc["lat_deg"] == pytest.approx(43.0 + math.degrees(doc["pos_n_m"][0] / 6_367_000.0), abs=1e-5)
            assert doc["lon_deg"] == pytest.approx(
                5.9 + math.degrees(doc["pos_n_m"][1] / (6_388_000.0 * math.cos(lat0))), abs=1e-5)
    assert len(errs) > 300
    assert np.median(errs) < 10.0
