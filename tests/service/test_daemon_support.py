"""Helpers for the live-service tests: free ports, configs, a real Zenoh peer feeding
sensor data in real time, and a collector of what the daemon publishes."""
from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections import defaultdict

from adaptnav.fusion.samples import DepthSample, HeadingSample, ImuSample, RpmSample
from adaptnav.service.transport.bus import Bus
from adaptnav.service.config import ZenohConfig, load_config

G_M_S2 = 9.80665


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def service_overrides(port: int, state_dir, *extra: str) -> list[str]:
    """Overrides for a daemon listening on loopback ``port``, scouting off."""
    return [f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "zenoh.scouting=false",
            f'state_dir="{state_dir}"', "vehicle.name=testauv", *extra]


def daemon_config(port: int, state_dir, *extra: str):
    return load_config(None, service_overrides(port, state_dir, *extra))


def peer(port: int, vehicle: str = "testauv") -> Bus:
    """A program attached to the daemon: a Zenoh client of its peer (no listen, no scouting)."""
    return Bus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=(), scouting=False),
               vehicle)


class Feeder(threading.Thread):
    """Publishes a vehicle at rest in real time: IMU 200 Hz, heading/depth/rpm 5 Hz.

    ``kinds`` may be changed while running (e.g. drop "depth" to silence it).
    Data time starts at ``t0_s`` and advances with the wall clock.
    """

    def __init__(self, bus: Bus, imu_hz: float = 200.0, t0_s: float = 0.0) -> None:
        super().__init__(daemon=True)
        self.bus = bus
        self.dt = 1.0 / imu_hz
        self.t0_s = t0_s
        self.kinds = {"imu", "heading", "depth", "rpm"}
        self.stop_event = threading.Event()
        self.published: dict[str, int] = defaultdict(int)
        self.t_s = t0_s
        self.publish_wall: dict[float, float] = {}

    def run(self) -> None:
        wall0 = time.monotonic()
        k = 0
        while not self.stop_event.is_set():
            t = self.t0_s + k * self.dt
            due = wall0 + k * self.dt
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            kinds = set(self.kinds)
            if "imu" in kinds:
                self.bus.publish_sample(ImuSample(t, (0.0, 0.0, -G_M_S2), (0.0, 0.0, 0.0)))
                self.publish_wall[round(t, 6)] = time.monotonic()
                self.published["imu"] += 1
            if k % 40 == 0:
                if "heading" in kinds:
                    self.bus.publish_sample(HeadingSample(t, 0.3))
                    self.published["heading"] += 1
                if "depth" in kinds:
                    self.bus.publish_sample(DepthSample(t, 101325.0 + 1025.0 * G_M_S2 * 5.0))
                    self.published["depth"] += 1
                if "rpm" in kinds:
                    self.bus.publish_sample(RpmSample(t, 0.0))
                    self.published["rpm"] += 1
            self.t_s = t
            k += 1

    def stop(self) -> None:
        self.stop_event.set()
        self.join(2.0)


class Collector:
    """Subscribes to ``adaptnav/<v>/**`` and keeps every JSON message by key."""

    def __init__(self, bus: Bus) -> None:
        self.by_key: dict[str, list[dict]] = defaultdict(list)
        self.recv_wall: list[tuple[float, float]] = []  # (nav t_s, wall time received)
        self._lock = threading.Lock()
        bus.subscribe_raw(bus.keys.all, self._on)
        self.keys = bus.keys

    def _on(self, key: str, payload: bytes) -> None:
        doc = json.loads(payload)
        with self._lock:
            self.by_key[key].append(doc)
            if key == self.keys.nav_state:
                self.recv_wall.append((doc["t_s"], time.monotonic()))

    def get(self, key: str) -> list[dict]:
        with self._lock:
            return list(self.by_key.get(key, []))

    def wait_for(self, key: str, pred=lambda docs: bool(docs), timeout_s: float = 60.0) -> list[dict]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            docs = self.get(key)
            if pred(docs):
                return docs
            time.sleep(0.05)
        return self.get(key)


def connected(bus: Bus, kinds=("imu", "heading", "depth", "rpm"), timeout_s: float = 60.0) -> bool:
    """The daemon's subscriptions to the sensor topics ``kinds`` have reached ``bus``: what
    is published from now on is not lost to a declaration still propagating."""
    return all(bus.wait_subscribed(bus.keys.sensor(k), timeout_s) for k in kinds)


def wait_until(pred, timeout_s: float = 60.0, period_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(period_s)
    return pred()


def finite(x) -> bool:
    return x is not None and math.isfinite(x)
