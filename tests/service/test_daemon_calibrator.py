"""The calibrator child process killed → fusion goes on uninterrupted and the
calibrator is restarted (real Zenoh peers on loopback, real spawn child)."""
from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import Collector, Feeder, daemon_config, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(150)


def test_calibrator_killed_restarted_fusion_uninterrupted(tmp_path):
    port = free_port()
    cfg = daemon_config(port, tmp_path / "state", "calibrator.enabled=true",
                        'calibrator.location="process"', "calibrator.restart_backoff_s=0.2")
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(port)
    col = Collector(bus)
    feeder = Feeder(bus)
    try:
        time.sleep(0.3)
        feeder.start()
        first = wait_until(lambda: (h := bus.get("health", timeout_s=0.5)) and
                           h["calibrator"]["state"] == "running" and h, timeout_s=60)
        assert first, f"calibrator never came up: {bus.get('health')['calibrator']}"
        pid = first["calibrator"]["pid"]
        assert pid and pid != os.getpid()
        n_nav_before = len(col.get(bus.keys.nav_state))
        t_kill = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        again = wait_until(lambda: (h := bus.get("health", timeout_s=0.5)) and
                           h["calibrator"]["state"] == "running" and h["calibrator"]["pid"] != pid and h,
                           timeout_s=60)
        t_back = time.monotonic()
        time.sleep(0.5)
    finally:
        feeder.stop()
        bus.close()
        daemon.stop()
    assert again, "calibrator was not restarted"
    assert again["calibrator"]["restarts"] == 1
    assert again["runner_alive"] is True
    # fusion uninterrupted: nav states kept arriving at 10 Hz of data time, in real time,
    # while the child was dead and restarting
    navs = col.get(col.keys.nav_state)
    recv = np.array([w for _, w in col.recv_wall])
    during = (recv > t_kill) & (recv < t_back)
    assert len(navs) > n_nav_before
    assert during.sum() >= 0.8 * 10 * (t_back - t_kill) - 2
    gaps_wall = np.diff(recv[(recv > t_kill - 1) & (recv < t_back + 0.5)])
    assert gaps_wall.max() < 0.5, f"nav output stalled {gaps_wall.max():.2f} s"
    ts = np.array([d["t_s"] for d in navs])
    assert np.diff(ts).max() < 0.2
