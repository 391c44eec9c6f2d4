"""The live daemon (real Zenoh sessions on loopback) against absurd input: it keeps
producing finite nav states, counts every refused sample by reason, never calls flowing
sensors silent, and feeds the systemd watchdog only while its runner is sound."""
from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest

from adaptnav.fusion.samples import DepthSample, ImuSample

from .test_daemon_support import Feeder, wait_until

pytestmark = pytest.mark.timeout(120)


SETTINGS = ("health.sensor_timeout_s=2.0",)


def test_absurd_samples_on_the_bus_are_refused_and_navigation_goes_on(live):
    daemon, bus, col = live(*SETTINGS)
    feeder = Feeder(bus)
    feeder.start()
    try:
        col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 5)
        t = feeder.t_s
        absurd = [ImuSample(t, (1e308, 0.0, 0.0), (0.0, 0.0, 0.0)),      # killed the filter for good
                  ImuSample(t, (0.0, 0.0, -9.8), (1e4, 0.0, 0.0)),       # depth at 244 m
                  ImuSample(4.1e9, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)),   # 2100: hung the runner
                  ImuSample(t + 20.0, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)),  # blanked output for 20 s
                  DepthSample(1e17, 2e5)]
        for s in absurd:
            bus.publish_sample(s)
        n_before = len(col.get(bus.keys.nav_state))
        health = wait_until(lambda: (h := bus.get("health")) and sum(
            h["rejected"].get(k, 0) for k in ("imu_acc_range", "imu_rate_range", "time_ahead")) >= len(absurd)
            and h, timeout_s=10)
        # output goes on for 3 s of data after the absurd samples (not blanked for 20 s)
        navs = col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= n_before + 30, timeout_s=15)
        late_health = wait_until(lambda: (h := bus.get("health")) and h["t_s"] is not None
                                 and h["t_s"] > t + 3.0 and h, timeout_s=10)
    finally:
        feeder.stop()
    assert health, f"absurd samples not counted: {bus.get('health')['rejected']}"
    assert health["rejected"]["imu_acc_range"] == 1 and health["rejected"]["imu_rate_range"] == 1
    assert health["rejected"]["time_ahead"] == 3
    assert len(navs) >= n_before + 30, "nav output stopped or blanked after absurd input"
    last = navs[-1]
    assert np.all(np.isfinite(last["pos_n_m"])) and abs(last["pos_n_m"][2] - 5.0) < 0.5
    assert np.linalg.norm(last["pos_n_m"][:2]) < 1.0  # at rest: the spikes moved nothing
    assert last["t_s"] < t + 10.0
    assert late_health["silent"] == [], late_health["silent"]
    assert late_health["runner_alive"] and late_health["state_finite"] and late_health["status"] == "navigating"


class _Wedge:
    """An item whose time blocks the runner until released (a stand-in for a hang)."""

    KIND = "altitude"

    def __init__(self):
        self.entered = threading.Event()
        self.release = threading.Event()

    @property
    def t_s(self):
        self.entered.set()
        self.release.wait(30.0)
        return float("nan")


def test_watchdog_fed_only_while_the_runner_is_sound(live, tmp_path, monkeypatch):
    sock_path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(sock_path)
    srv.settimeout(0.05)
    got: list[tuple[float, str]] = []
    stop = threading.Event()

    def listen():
        while not stop.is_set():
            try:
                got.append((time.monotonic(), srv.recv(4096).decode()))
            except socket.timeout:
                continue

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    monkeypatch.setenv("NOTIFY_SOCKET", sock_path)
    monkeypatch.setenv("WATCHDOG_USEC", "1000000")  # fed every ≤ 0.25 s; wedged after 0.5 s
    daemon, bus, col = live(*SETTINGS)
    feeder = Feeder(bus)
    feeder.start()
    wedge = _Wedge()
    try:
        assert wait_until(lambda: sum("WATCHDOG=1" in m for _, m in got) >= 3, timeout_s=10)
        daemon.enqueue(wedge)
        assert wedge.entered.wait(10.0)
        t_wedged = time.monotonic()
        time.sleep(3.0)  # the interval observed: no feeding once 0.5 s (+ one tick) have passed
        # stamps are the listener's receive times: a ping sent just before the limit may be read
        # late on a loaded machine, so only pings received a full second past the limit count
        fed_while_wedged = [t for t, m in got if "WATCHDOG=1" in m and t > t_wedged + 0.5 + 1.0]
        assert not daemon.runner_sound(0.5)
        wedge.release.set()
        n = sum("WATCHDOG=1" in m for _, m in got)
        assert wait_until(lambda: sum("WATCHDOG=1" in m for _, m in got) >= n + 2, timeout_s=10)
    finally:
        wedge.release.set()
        feeder.stop()
        stop.set()
        listener.join(1.0)
        srv.close()
    assert fed_while_wedged == [], "the watchdog was fed while the runner was wedged"
    assert daemon.runner_sound(5.0)
    assert os.environ["NOTIFY_SOCKET"] == sock_path
