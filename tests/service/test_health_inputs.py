"""Health stays truthful under odd input and failing disks (live daemon on loopback):

- a nav state or a calibrator release published on a *sensor* key is counted
  (``malformed:<key>:<kind>``), neither fused nor applied, and no sensor turns "silent";
- a learned-state save that fails is counted in health (``persistence.failures`` with why)
  while navigation goes on.
"""
from __future__ import annotations

import pytest

from adaptnav.calibration.online import Release
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.transport import codec
from adaptnav.service.transport.bus import message

from .test_daemon_support import Feeder, wait_until

pytestmark = pytest.mark.timeout(120)

SETTINGS = ("health.sensor_timeout_s=1.0",)


def test_nav_state_and_release_on_a_sensor_key_are_counted_not_taken(live):
    daemon, bus, col = live(*SETTINGS)
    feeder = Feeder(bus)
    feeder.start()
    try:
        navs = col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= 3)
        t_s = feeder.t_s
        bus.put(bus.keys.sensor("imu"), message("nav_state", {**navs[-1], "t_s": t_s}))
        bus.put(bus.keys.sensor("depth"), codec.encode(Release(
            t_s=t_s, params=MotionParams(k_v=1.3), log_likelihood=0.0, accepted=True, reason="", iterations=1)))
        # well past the silence limit (1 s of data) after the odd messages
        health = wait_until(lambda: (h := col.get(bus.keys.health)) and h[-1]["t_s"] is not None
                            and h[-1]["t_s"] > t_s + 3.0 and h[-1], timeout_s=60)
    finally:
        feeder.stop()
    assert health, "no health report"
    rejected = health["rejected"]
    assert rejected.get("malformed:imu:nav_state") == 1, rejected
    assert rejected.get("malformed:depth:calibration_release") == 1, rejected
    assert health["silent"] == [], health["silent"]
    assert set(health["sensors"]) == {"imu", "heading", "depth", "rpm"}
    assert health["calibrator"]["releases"] == 0 and daemon.params.k_v == 1.0


def _with_a_file_for_a_state_dir(live, tmp_path, period_s: float, health_ready):
    """A live daemon whose state dir lies under a file (unwritable for root too), fed until a
    health report passes ``health_ready`` and 5 more nav states came: (health, nav states before,
    nav states after)."""
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the state directory should be\n")
    daemon, bus, col = live(*SETTINGS, f'state_dir="{blocker}/state"', f"persistence.period_s={period_s}")
    feeder = Feeder(bus)
    feeder.start()
    try:
        health = wait_until(lambda: (h := col.get(bus.keys.health)) and health_ready(h[-1]) and h[-1], timeout_s=60)
        n_before = len(col.get(bus.keys.nav_state))
        navs = col.wait_for(bus.keys.nav_state, lambda docs: len(docs) >= n_before + 5)
    finally:
        feeder.stop()
    assert health, f"no health report as awaited: {col.get(bus.keys.health)[-1:]}"
    return health, n_before, navs


def test_a_failing_state_save_is_counted_in_health(live, tmp_path):
    health, n_before, navs = _with_a_file_for_a_state_dir(live, tmp_path, 0.2,
                                                          lambda h: h["persistence"]["failures"] >= 2)
    persistence = health["persistence"]
    assert persistence["saves"] == 0
    assert "NotADirectoryError" in persistence["last_error"] or "FileExistsError" in persistence["last_error"]
    assert len(navs) >= n_before + 5, "navigation stopped with the failing saves"


def test_the_heap_is_given_back_once_a_burst_has_drained():
    from adaptnav.service.runtime.memory import BurstTrimmer

    trimmer = BurstTrimmer(burst_items=100)
    # ordinary traffic never trims; a burst trims once, when its queue is empty again
    assert [trimmer.check(d) for d in (0, 3, 0, 50, 0)] == [False] * 5
    assert [trimmer.check(d) for d in (40, 150, 90, 1)] == [False] * 4
    assert trimmer.check(0) is True
    assert trimmer.check(0) is False


def test_a_state_dir_it_cannot_write_is_said_at_start(live, tmp_path):
    """The learned state's folder unwritable (here a file stands where it should be: so for root
    too) was found only at the first save, minutes later, or at shutdown: now health's
    ``persistence.last_error`` says it from the first report, before any save was tried, and
    navigation goes on."""
    health, n_before, navs = _with_a_file_for_a_state_dir(live, tmp_path, 3600, lambda h: True)
    persistence = health["persistence"]
    assert persistence["saves"] == 0 and persistence["failures"] == 0, persistence  # nothing saved yet
    assert persistence["last_error"].startswith("state dir not writable at start: "), persistence
    assert "NotADirectoryError" in persistence["last_error"] or "FileExistsError" in persistence["last_error"]
    assert len(navs) >= n_before + 5
