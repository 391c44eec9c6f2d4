"""The calibrator child process killed → fusion goes on uninterrupted and the
calibrator is restarted (real Zenoh peers on loopback, real spawn child)."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import Collector, Feeder, connected, daemon_config, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(300)


def test_calibrator_killed_restarted_fusion_uninterrupted(tmp_path):
    port = free_port()
    # a restart backoff long enough to see fusion go on while the child is dead (a
    # generous window, not a pace: 5 nav states take 0.5 s of data; the check fails only if
    # a loaded machine stalls the daemon for nearly the whole 15 s)
    cfg = daemon_config(port, tmp_path / "state", "calibrator.enabled=true",
                        'calibrator.location="process"', "calibrator.restart_backoff_s=15.0")
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(port)
    col = Collector(bus)
    feeder = Feeder(bus)

    def calibrator_health():
        h = bus.get("health", timeout_s=0.5)
        return h["calibrator"] if h else None

    try:
        assert connected(bus)
        feeder.start()
        first = wait_until(lambda: (c := calibrator_health()) and c["state"] == "running" and c, timeout_s=120)
        assert first, f"calibrator never came up: {calibrator_health()}"
        pid = first["pid"]
        assert pid and pid != os.getpid()
        # EM runs below the navigation loop's priority (calibrator.nice, default 10)
        background = min(19, os.getpriority(os.PRIO_PROCESS, 0) + 10)
        assert os.getpriority(os.PRIO_PROCESS, pid) == background
        os.kill(pid, signal.SIGKILL)
        # WHILE the child is dead: nav states keep coming (counted from the moment the
        # daemon has seen the death, until it has restarted the child)
        dead = wait_until(lambda: (c := calibrator_health()) and c["state"] == "restarting" and c, timeout_s=120)
        n_dead = len(col.get(col.keys.nav_state))
        during = col.wait_for(col.keys.nav_state, lambda docs: len(docs) >= n_dead + 5)
        still_dead = calibrator_health()  # asked after those arrived: were they made without a child?
        again = wait_until(lambda: (c := calibrator_health()) and c["state"] == "running" and c["pid"] != pid and c,
                           timeout_s=120)
        n_back = len(col.get(col.keys.nav_state))
        restarted_nice = os.getpriority(os.PRIO_PROCESS, again["pid"]) if again else None
        # and after it
        assert col.wait_for(col.keys.nav_state, lambda docs: len(docs) >= n_back + 10)
        health = bus.get("health")
    finally:
        feeder.stop()
        bus.close()
        daemon.stop()
    assert dead, "the daemon never saw the child die"
    assert again, "calibrator was not restarted"
    assert restarted_nice == background, "the restarted child runs at the daemon's priority"
    assert again["restarts"] == 1
    assert health["runner_alive"] is True
    # what came back after its due time is counted in the health report (the rule's own test:
    # test_calibrator_release_rule.py); its numbers depend on the machine's pace, not asserted here
    late = health["calibrator"]["late"]
    assert set(late) == {"releases", "products", "max_s"} and late["releases"] >= 0 and late["max_s"] >= 0.0
    # fusion uninterrupted: nav states in data time without a gap, the whole time (the
    # feeder's data are continuous; the filter's output must be too)
    navs = col.get(col.keys.nav_state)
    ts = np.array([d["t_s"] for d in navs])
    assert np.all(np.diff(ts) > 0) and np.diff(ts).max() < 0.2
    assert len(during) >= n_dead + 5 and still_dead["restarts"] == 0, \
        "no nav states while the calibrator child was dead (or the daemon stalled for the whole backoff)"
