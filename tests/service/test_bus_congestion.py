"""A sensor sample on the bus is not lost to a congested link (real Zenoh peers on loopback).

Zenoh drops a publication whose transmission queue is full unless its publisher blocks
(``CongestionControl``, default DROP), and neither side hears of it. On a loaded machine the
demo's sonar driver lost 2 of 721 side-scan pings that way (`test_demo`, under load). A driver's
samples and a calibration release now wait for room (:meth:`Keys.lossless`); the daemon's own
nav states, aid status and health stay droppable (the next replaces them, and the runner must
not wait for a slow subscriber)."""
from __future__ import annotations

import threading
import time

import pytest

from adaptnav.service.config import ZenohConfig
from adaptnav.service.transport.bus import Bus, Keys

from .test_daemon_support import free_port

pytestmark = pytest.mark.timeout(120)


def test_a_slow_subscriber_gets_every_ping_a_driver_publishes():
    port = free_port()
    daemon_side = Bus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "congested")
    driver = Bus(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=(), scouting=False), "congested")
    n, got, all_in = 1500, [0], threading.Event()

    def slow(_sample) -> None:  # a consumer slower than the link: the sender's queue fills
        got[0] += 1
        time.sleep(0.0005)
        if got[0] == n:
            all_in.set()

    key = driver.keys.sensor("sonar")
    try:
        daemon_side.session.declare_subscriber(key, slow)
        assert driver.wait_subscribed(key)
        ping = b"x" * 32768  # a side-scan ping's size: 48 MB in all, sent as fast as possible
        for _ in range(n):
            driver.put(key, ping)
        all_in.wait(60.0)
        assert got[0] == n  # with Zenoh's default (drop) 176 of 1500 arrived
    finally:
        driver.close()
        daemon_side.close()


def test_what_the_next_message_replaces_stays_droppable():
    k = Keys("v")
    assert k.lossless(k.sensor("imu")) and k.lossless(k.sensor("sonar")) and k.lossless(k.params)
    assert not any(k.lossless(x) for x in (k.nav_state, k.nav_inertial, k.health, k.aid("dvl")))


def test_imu_samples_are_sent_at_once_and_droppable_messages_batched():
    """The IMU samples are never held for a batch (:meth:`Keys.express`); nothing droppable
    is express (a message of its own is what a starved link drops), nor a ping."""
    k = Keys("v")
    assert k.express(k.sensor("imu"))
    assert not any(k.express(x) for x in (k.nav_state, k.sensor("sonar"), k.sensor("dvl"), k.nav_inertial,
                                          k.health, k.aid("dvl"), k.params))
