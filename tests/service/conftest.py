"""Fixtures shared by the live-service tests."""
from __future__ import annotations

import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import Collector, connected, daemon_config, free_port, peer


@pytest.fixture
def live(tmp_path):
    """Start daemons (calibrator off) on loopback, each with a client peer and a collector.

    ``live(*overrides)`` returns ``(daemon, peer, collector)`` once the daemon's sensor
    subscriptions have reached the peer, so nothing the test publishes is lost to a race.
    """
    made = []

    def make(*overrides: str):
        port = free_port()
        daemon = Daemon(daemon_config(port, tmp_path / "state", "calibrator.enabled=false", *overrides))
        daemon.start()
        bus = peer(port)
        made.append((daemon, bus))
        assert connected(bus)
        return daemon, bus, Collector(bus)

    yield make
    for daemon, bus in made:
        bus.close()
        daemon.stop()
