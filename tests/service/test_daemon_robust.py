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


DROPOUT_S = 7.0


def _sigma_h_m(nav: dict) -> float:
    cov = np.asarray(nav["cov"], dtype=float).reshape(18, 18)
    return float(np.sqrt(cov[0, 0] + cov[1, 1]))


def test_a_link_dropout_is_coasted_through_and_a_step_of_the_clock_re_based(live):
    """Live, both look the same at the door: a stream going on from a time seconds later.
    A link that drops (the autopilot's clock runs on while nothing arrives) is data missing —
    the vehicle moved meanwhile, so the filter coasts through it, its uncertainty growing; it
    was re-based "as if no time had passed". A companion's clock set forward (NTP, GNSS) is a
    step: re-based. The wall clock tells them apart: it ran through the dropout, not the step."""
    daemon, bus, col = live(*SETTINGS)
    key = bus.keys.nav_state
    feeder = Feeder(bus)
    feeder.start()
    kinds = set(feeder.kinds)
    try:
        col.wait_for(key, lambda docs: len(docs) >= 20)
        feeder.kinds = set()          # the link drops; the vehicle's clock runs on
        time.sleep(DROPOUT_S)         # the dropout is wall time passing, not a wait for a result
        before = col.get(key)[-1]
        t_resumed = feeder.t_s
        feeder.kinds = kinds
        gap_health = wait_until(lambda: (h := bus.get("health")) and h["rejected"].get("data_gap") and h,
                                timeout_s=20)
        after = col.wait_for(key, lambda docs: docs[-1]["t_s"] > t_resumed + 0.5, timeout_s=20)
        after = [d for d in after if d["t_s"] > t_resumed][0]
        feeder.t0_s += 1000.0         # the data's clock set 1000 s forward
        step_health = wait_until(lambda: (h := bus.get("health")) and h["rejected"].get("clock_jump") and h,
                                 timeout_s=20)
        stepped = col.wait_for(key, lambda docs: docs[-1]["t_s"] > t_resumed + 1000.0, timeout_s=20)
    finally:
        feeder.stop()
    assert gap_health, f"the dropout was not seen as data missing: {bus.get('health')['rejected']}"
    assert "clock_jump" not in gap_health["rejected"], gap_health["rejected"]
    assert DROPOUT_S - 1.0 < after["t_s"] - before["t_s"] < DROPOUT_S + 2.0
    # coasted: the filter's uncertainty grew with the time it saw nothing (re-based, it did not)
    assert _sigma_h_m(after) > _sigma_h_m(before) + 1.0, (_sigma_h_m(before), _sigma_h_m(after))
    assert step_health, f"the step was not re-based: {bus.get('health')['rejected']}"
    assert step_health["rejected"]["clock_jump"] == 1 and step_health["rejected"]["data_gap"] == 1
    assert stepped[-1]["t_s"] > t_resumed + 1000.0 and np.all(np.isfinite(stepped[-1]["pos_n_m"]))
