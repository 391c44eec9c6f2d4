"""The CPU wake-up latency bound (Linux PM QoS): held by the kernel while the daemon runs,
dropped when it stops, refused cleanly where the device cannot be written.

The kernel applies the tightest request of any process: other tests' daemons (the default
tightens the bound around their epochs) may hold a tighter one for moments. So a bound of ours
is "applied" when every reading over a while is at most it, and "dropped" when a reading above it
comes; the tests that hold one run in one xdist group (``--dist loadgroup``)."""
from __future__ import annotations

import os

import pytest

from adaptnav.service.config import ConfigError, load_config
import threading
import time

from adaptnav.service.runtime.rehearsal import EpochRehearsal
from adaptnav.service.runtime.wakeup import NO_BOUND_US, PM_QOS_DEVICE, WakeupLatencyRequest, current_bound_us

from .test_daemon_support import wait_until

pytestmark = [pytest.mark.timeout(120), pytest.mark.xdist_group("pm_qos")]


def applied(us: int, readings: int = 40, period_s: float = 0.005) -> bool:
    """Every reading of the kernel's bound over ``readings`` × ``period_s`` at most ``us``."""
    for _ in range(readings):
        if current_bound_us() > us:
            return False
        time.sleep(period_s)
    return True


def dropped(us: int) -> bool:
    """A reading of the kernel's bound above ``us`` within 10 s (no request of ``us`` or tighter)."""
    return bool(wait_until(lambda: current_bound_us() > us, timeout_s=10.0, period_s=0.002))

writable = pytest.mark.skipif(not os.access(PM_QOS_DEVICE, os.W_OK),
                              reason=f"{PM_QOS_DEVICE} not writable here (root's, Linux only)")


@writable
def test_the_kernel_applies_the_bound_while_held_and_drops_it_after():
    req = WakeupLatencyRequest(7)
    assert req.hold() and req.held
    try:
        assert applied(7)  # the kernel's aggregate: the tightest request held
        assert req.hold()  # idempotent: still one request
    finally:
        req.release()
    assert not req.held
    assert dropped(7)
    req.release()  # idempotent


def test_a_refused_request_says_why_and_holds_nothing(tmp_path, caplog):
    req = WakeupLatencyRequest(0, device=str(tmp_path / "no-such-device"))
    with caplog.at_level("INFO"):
        assert req.hold() is False
    assert not req.held
    rep = req.report()
    assert rep["held"] is False and rep["max_us"] == 0
    assert "FileNotFoundError" in rep["error"]
    assert any("not held" in r.getMessage() for r in caplog.records)
    req.release()  # nothing to drop: no error


@pytest.mark.parametrize("bad", [-1, NO_BOUND_US, 1.5, True])
def test_a_bound_that_is_not_a_count_of_microseconds_is_refused(bad):
    with pytest.raises(ValueError, match="max_us"):
        WakeupLatencyRequest(bad)


def test_an_unknown_scope_is_refused():
    with pytest.raises(ValueError, match="scope"):
        WakeupLatencyRequest(0, "sometimes")
    with pytest.raises(ConfigError, match="cpu_wakeup_scope"):
        load_config(None, ['outputs.cpu_wakeup_scope="sometimes"'])
    # the epochs' windows are opened by the rehearsals
    with pytest.raises(ConfigError, match="rehearsal_lead_s"):
        load_config(None, ["outputs.cpu_wakeup_latency_us=0", 'outputs.cpu_wakeup_scope="epochs"',
                           "outputs.rehearsal_lead_s=0"])


@writable
def test_epoch_scope_applies_the_bound_only_between_tighten_and_relax():
    req = WakeupLatencyRequest(7, "epochs")
    assert req.hold()
    try:
        assert dropped(7)  # open, at no bound
        req.tighten()
        assert req.tight and applied(7)
        req.tighten()  # already tight: not counted again
        req.relax()
        assert not req.tight and dropped(7)
        req.relax()
        assert req.report()["tightened"] == 1
    finally:
        req.release()
    always = WakeupLatencyRequest(7, "always")
    assert always.hold()
    try:
        always.relax()  # the scope "always" does not follow the epochs
        assert applied(7)
    finally:
        always.release()


class _Window:
    """A stand-in for the request that keeps when it was tightened and relaxed."""

    def __init__(self):
        self.events = []
        self.tight = False
        self.relaxed = threading.Event()

    def tighten(self):  # (the request's: a change only when not tight)
        if not self.tight:
            self.tight = True
            self.events.append(("tighten", time.monotonic()))

    def relax(self):
        if self.tight:
            self.tight = False
            self.events.append(("relax", time.monotonic()))
            self.relaxed.set()


class _Loop:
    imu_period_s = 0.05
    next_k = 1

    def due_s(self):
        return 1.0


def test_the_rehearsal_opens_each_epochs_window_when_planned_and_closes_it_after_the_sample():
    lead_s, hold_after_s = 0.01, 0.02
    window, rehearsed = _Window(), []
    lock = threading.Lock()
    rehearsal = EpochRehearsal(lock, lambda dt_s: rehearsed.append(time.monotonic()) or True, lead_s,
                               window=window, hold_after_s=hold_after_s)
    rehearsal.start()
    try:
        arrived_s = time.monotonic()
        # the sample before the epoch's came now: the epoch's is expected one IMU period later
        assert rehearsal.plan(arrived_s, 0.97, _Loop())
        expected_s = arrived_s + _Loop.imu_period_s
        assert window.relaxed.wait(10.0), "the window was never closed"
    finally:
        rehearsal.stop()
    (k1, t_tight), (k2, t_relax) = window.events[:2]
    assert (k1, k2) == ("tighten", "relax")
    assert arrived_s <= t_tight <= expected_s - lead_s  # when planned, ahead of the rehearsal's time
    assert rehearsed and t_tight <= rehearsed[0]
    assert t_relax >= expected_s + hold_after_s  # the sample's time and a margin after it covered
    assert not window.tight  # closed again, and so when the rehearsals stop


@pytest.mark.parametrize("bad", ["-2", "2000001", "0.5"])
def test_config_refuses_a_bound_out_of_range(bad):
    with pytest.raises(ConfigError, match="cpu_wakeup_latency_us"):
        load_config(None, [f"outputs.cpu_wakeup_latency_us={bad}"])


@writable
def test_the_live_daemon_holds_the_bound_and_reports_it(live):
    daemon, bus, _ = live("outputs.cpu_wakeup_latency_us=3", 'outputs.cpu_wakeup_scope="always"')
    assert applied(3)
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    assert health["cpu_wakeup_latency"] == {"max_us": 3, "scope": "always", "held": True, "error": None,
                                            "tightened": 0}
    daemon.stop()
    assert dropped(3)


def test_the_live_daemon_runs_on_without_a_bound_it_cannot_hold(live, monkeypatch, tmp_path):
    monkeypatch.setattr("adaptnav.service.runtime.wakeup.PM_QOS_DEVICE", str(tmp_path / "none"))
    daemon, bus, _ = live()  # (the default: 0 µs around the epochs)
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    rep = health["cpu_wakeup_latency"]
    assert rep["held"] is False and rep["max_us"] == 0 and "FileNotFoundError" in rep["error"]
    assert health["runner_alive"] is True


@writable
def test_the_live_daemon_opens_a_window_around_each_output_epoch(live):
    from .test_daemon_support import Feeder

    daemon, bus, col = live("outputs.cpu_wakeup_latency_us=5", 'outputs.cpu_wakeup_scope="epochs"')
    feeder = Feeder(bus)
    feeder.start()
    try:
        col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 10, timeout_s=60)
        health = wait_until(lambda: h if (h := bus.get("health")) and h["cpu_wakeup_latency"]["tightened"] >= 5
                            else None, timeout_s=30)
    finally:
        feeder.stop()
    assert health, f"no epoch windows: {bus.get('health')}"
    rep = health["cpu_wakeup_latency"]
    assert rep["scope"] == "epochs" and rep["held"] is True and rep["error"] is None
    # the windows follow the rehearsals: not more of them than rehearsals that came due, and the
    # one opened at the latest planning, whose rehearsal may not have come due yet
    assert rep["tightened"] <= sum(health["epoch_rehearsal"].values()) + 1
    daemon.stop()
    assert dropped(5)


def test_without_a_bound_asked_for_the_daemon_makes_no_request(live):
    daemon, bus, _ = live("outputs.cpu_wakeup_latency_us=-1")
    health = wait_until(lambda: bus.get("health"), timeout_s=30)
    assert "cpu_wakeup_latency" not in health
    assert daemon.wakeup is None


def test_a_window_opened_for_an_epoch_that_never_comes_closes_when_the_rehearsals_stop():
    class SlowLoop(_Loop):
        imu_period_s = 30.0  # the epoch's sample expected half a minute from now

    window = _Window()
    rehearsal = EpochRehearsal(threading.Lock(), lambda dt_s: True, 0.01, window=window)
    rehearsal.start()
    try:
        assert rehearsal.plan(time.monotonic(), 0.5, SlowLoop())
        assert window.tight
    finally:
        rehearsal.stop()
    assert [k for k, _ in window.events] == ["tighten", "relax"]
