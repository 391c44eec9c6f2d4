"""What the daemon is told to trust (issue 12 item 4): releases from a remote calibrator
node and the persisted state file are held to the calibrator's own bounds; a refused one
is counted with why, never applied, persisted or restored."""
from __future__ import annotations

import json
from dataclasses import replace

import pytest

from adaptnav.calibration.online import Release
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.transport.release import release_to_dict
from adaptnav.service.daemon import Daemon
from adaptnav.service.runtime.persistence import load_state, save_state

from .test_daemon_support import Feeder, connected, daemon_config, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(120)


def test_a_hostile_remote_release_is_refused_counted_and_not_persisted(tmp_path):
    port = free_port()
    cfg = daemon_config(port, tmp_path / "state", 'calibrator.location="remote"', "persistence.period_s=0.5")
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(port)
    feeder = Feeder(bus)
    try:
        assert connected(bus)
        feeder.start()
        assert wait_until(lambda: daemon.sink.nav_count > 5, timeout_s=20)
        p0 = MotionParams()
        hostile = Release(feeder.t_s, replace(p0, k_v=100.0, **{n: 1e-30 for n in p0.VARIANCE_NAMES}),
                          0.0, True, "", 1)
        assert bus.wait_subscribed(bus.keys.params)  # the daemon's release subscription reached us
        bus.put(bus.keys.params, json.dumps(release_to_dict(hostile)).encode())
        health = wait_until(lambda: (h := bus.get("health")) and h["calibrator"]["releases"] >= 1 and h,
                            timeout_s=20)
        params = bus.get("params")
    finally:
        feeder.stop()
        bus.close()
        daemon.stop()
    assert health, "the release never reached the runner"
    assert health["rejected"].get("release_refused:var_vv") == 1
    assert health["calibrator"]["releases_accepted"] == 0
    assert "refused by the filter" in health["calibrator"]["last_release"]["reason"]
    assert params["params"]["k_v"] == 1.0
    assert load_state(tmp_path / "state").params == MotionParams()


def test_a_persisted_state_beyond_bounds_is_not_restored(tmp_path):
    state = tmp_path / "state"
    save_state(state, 100.0, replace(MotionParams(), k_v=1e300),
               {"bias_acc_b_m_s2": [0.0] * 3, "var_bias_acc": [1e-4] * 3,
                "bias_gyro_b_rad_s": [0.0] * 3, "var_bias_gyro": [1e-8] * 3,
                "current_n_m_s": [1.68, 0.0], "var_current": [0.01, 0.01],   # spoofing's leftover
                "k_speed": 1.0, "var_k_speed": 0.01})
    port = free_port()
    daemon = Daemon(daemon_config(port, state, "calibrator.enabled=false",
                                  "calibrator.online.max_current_m_s=1.0"))
    daemon.start()
    try:
        rejected = daemon.health.rejected_by_reason()
        params, slow = daemon.params, daemon.estimator.slow_states()
    finally:
        daemon.stop()
    assert params == MotionParams()
    assert rejected.get("persisted_params_refused:k_v") == 1
    assert rejected.get("persisted_states_refused:current_n_m_s") == 1
    assert slow == {}  # nothing restored (not the spoofed 1.68 m/s): no slow states before alignment


def test_a_daemon_that_never_aligned_leaves_a_state_the_next_start_takes(tmp_path, caplog):
    """Started and stopped without a sample (on the bench, the autopilot not yet up), the daemon
    saved the filter's defaults with zero variances as its slow states, and the next start said
    "persisted slow states not usable". It keeps only what it has: its params."""
    state = tmp_path / "state"
    for _ in range(2):
        daemon = Daemon(daemon_config(free_port(), state, "calibrator.enabled=false"))
        daemon.start()
        daemon.stop()
    saved = load_state(state)
    assert saved is not None and saved.params == MotionParams() and saved.slow_states == {}
    assert not [r.getMessage() for r in caplog.records if "not usable" in r.getMessage()]
