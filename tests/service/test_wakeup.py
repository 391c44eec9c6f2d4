"""The CPU wake-up latency bound (Linux PM QoS): held by the kernel while the daemon runs,
dropped when it stops, refused cleanly where the device cannot be written."""
from __future__ import annotations

import os

import pytest

from adaptnav.service.config import ConfigError, load_config
from adaptnav.service.runtime.wakeup import PM_QOS_DEVICE, WakeupLatencyRequest, current_bound_us

from .test_daemon_support import wait_until

pytestmark = pytest.mark.timeout(120)

writable = pytest.mark.skipif(not os.access(PM_QOS_DEVICE, os.W_OK),
                              reason=f"{PM_QOS_DEVICE} not writable here (root's, Linux only)")


@writable
def test_the_kernel_applies_the_bound_while_held_and_drops_it_after():
    before = current_bound_us()
    assert before > 7, "another process holds a bound this tight: the test cannot see its own"
    req = WakeupLatencyRequest(7)
    assert req.hold() and req.held
    try:
        assert current_bound_us() == 7  # the kernel's aggregate: the tightest request held
        assert req.hold()  # idempotent: still one request
    finally:
        req.release()
    assert not req.held
    assert current_bound_us() == before
    req.release()  # idempotent


def test_a_refused_request_says_why_and_holds_nothing(tmp_path, caplog):
    req = WakeupLatencyRequest(0, device=str(tmp_path / "no-such-device"))
    with caplog.at_level("WARNING"):
        assert req.hold() is False
    assert not req.held
    rep = req.report()
    assert rep["held"] is False and rep["max_us"] == 0
    assert "FileNotFoundError" in rep["error"]
    assert any("not held" in r.getMessage() for r in caplog.records)
    req.release()  # nothing to drop: no error


@pytest.mark.parametrize("bad", [-1, 2**31, 1.5, True])
def test_a_bound_that_is_not_a_count_of_microseconds_is_refused(bad):
    with pytest.raises(ValueError, match="max_us"):
        WakeupLatencyRequest(bad)


@pytest.mark.parametrize("bad", ["-2", "2000001", "0.5"])
def test_config_refuses_a_bound_out_of_range(bad):
    with pytest.raises(ConfigError, match="cpu_wakeup_latency_us"):
        load_config(None, [f"outputs.cpu_wakeup_latency_us={bad}"])


@writable
def test_the_live_daemon_holds_the_bound_and_reports_it(live):
    before = current_bound_us()
    daemon, bus, _ = live("outputs.cpu_wakeup_latency_us=3")
    assert current_bound_us() == 3
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    assert health["cpu_wakeup_latency"] == {"max_us": 3, "held": True, "error": None}
    daemon.stop()
    assert current_bound_us() == before


def test_the_live_daemon_runs_on_without_a_bound_it_cannot_hold(live, monkeypatch, tmp_path):
    monkeypatch.setattr(WakeupLatencyRequest.__init__, "__defaults__", (str(tmp_path / "none"),))
    daemon, bus, _ = live("outputs.cpu_wakeup_latency_us=0")
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    rep = health["cpu_wakeup_latency"]
    assert rep["held"] is False and rep["max_us"] == 0 and "FileNotFoundError" in rep["error"]
    assert health["runner_alive"] is True


def test_without_a_bound_asked_for_the_daemon_makes_no_request(live):
    daemon, bus, _ = live()
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    assert "cpu_wakeup_latency" not in health
    assert daemon.wakeup is None
