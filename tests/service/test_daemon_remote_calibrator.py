"""The calibrator as its own bus node (`adaptnav run --calibrator-only`): it learns from
the sensor topics and the daemon (calibrator.location = "remote") applies its releases."""
from __future__ import annotations

import threading

import pytest

from adaptnav.service.calibrator.node import run_node
from adaptnav.service.daemon import Daemon
from adaptnav.service.runtime.replay import build_config
from adaptnav.service.runtime.sources import simulate

from .test_daemon_support import Collector, connected, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(170)


def test_remote_calibrator_node_release_reaches_daemon(tmp_path):
    from adaptnav.fusion.samples import ImuBatch
    from adaptnav.sim.scenario import load_scenario

    scenario = load_scenario("short", ["duration_s=200"])
    port = free_port()
    common = [f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "zenoh.scouting=false", "vehicle.name=testauv",
              "calibrator.online.step_s=2.0", "calibrator.online.min_window_steps=20",
              "calibrator.online.period_steps=10", "calibrator.online.n_particles=200",
              "calibrator.online.em_iterations=2"]
    cfg = build_config(scenario, None, common + [f'state_dir="{tmp_path}/d"', 'calibrator.location="remote"'])
    node_cfg = build_config(scenario, None, common + [f'state_dir="{tmp_path}/n"'])
    daemon = Daemon(cfg)
    daemon.start()
    stop = threading.Event()
    node = threading.Thread(target=run_node, args=(node_cfg, stop), daemon=True)
    node.start()
    bus = peer(port)
    col = Collector(bus)
    try:
        assert connected(bus)  # the daemon's subscriptions
        assert wait_until(lambda: bus.get("calibrator", 0.5))  # the node is up (subscribed before it answers)
        n = 0
        for item in simulate(scenario).iter_blocks():
            samples = item.samples() if isinstance(item, ImuBatch) else [item]
            for s in samples:
                if s.KIND != "truth":
                    bus.publish_sample(s)
                    n += 1
                    if n % 1000 == 0:  # flow control on the daemon's queue
                        wait_until(lambda: (h := bus.get("health", 1.0)) and h["queue_depth"] < 3000, 60)
        assert col.wait_for(bus.keys.params, timeout_s=120), "the calibrator node published no release"
        # the first release may come while the daemon is still behind the published samples
        # (it runs the filter, the node only queues them): wait on what the two report -- the
        # node having taken over 100 of the daemon's free-inertial velocities -- not on how
        # fast either ran; the deadline only bounds a failure
        node_status = wait_until(lambda: (s := bus.get("calibrator", 1.0))
                                 and s["received"].get("inertial_velocity", 0) > 100 and s, 120) \
            or bus.get("calibrator", 2.0)
        # stop the node and let the daemon drain its queue: no release is then in flight and
        # none is applied after the comparison (a release held for its data time may never be)
        stop.set()
        node.join(10)
        health = wait_until(lambda: (h := bus.get("health", 1.0)) and h["queue_depth"] == 0
                            and h["calibrator"]["releases"] >= 1 and h, 60)
        releases = col.get(bus.keys.params)
        inertial = col.wait_for(bus.keys.nav_inertial, lambda docs: len(docs) > 100, timeout_s=60)
    finally:
        stop.set()
        node.join(10)
        bus.close()
        daemon.stop()
    assert health, "the daemon did not count the node's releases"
    assert releases[0]["type"] == "calibration_release"
    assert health["calibrator"]["state"] == "remote"
    published = {r["t_s"]: r for r in releases}
    last = published.get(health["calibrator"]["last_release"]["t_s"])
    assert last is not None, "the daemon's last release is not one the node published"
    if last["accepted"]:  # the daemon now uses what the node learned
        assert daemon.params.to_dict() == pytest.approx(last["params"])
    # the daemon hands the node its free-inertial velocity (the surge-noise evidence) over the bus
    assert len(inertial) > 100 and inertial[0]["type"] == "inertial_velocity"
    times = [d["t_s"] for d in inertial]
    assert all(b > a for a, b in zip(times, times[1:]))
    assert node_status and node_status["received"].get("inertial_velocity", 0) > 100, node_status


def _side_scan_node(tmp_path, duration_s: float):
    """A survey with side-scan (no DVL), a calibrator node for it started in a thread, and the
    vehicle's side of the bus (a peer listening where the node connects): (scenario, vehicle,
    stop, node)."""
    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.transport.bus import Bus
    from adaptnav.sim.scenario import load_scenario

    scenario = load_scenario("survey", ["seed=2", f"duration_s={duration_s}", "dvl.enabled=false",
                                        "sonar.enabled=true"])
    port = free_port()
    node_cfg = build_config(scenario, None, [f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "zenoh.scouting=false",
                                             "vehicle.name=testauv", f'state_dir="{tmp_path}/n"'])
    vehicle = Bus(ZenohConfig(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), scouting=False), "testauv")
    stop = threading.Event()
    node = threading.Thread(target=run_node, args=(node_cfg, stop), daemon=True)
    node.start()
    return scenario, vehicle, stop, node


class _Intercepted:
    """The node's real calibrator with ``before(sample)`` run ahead of each ``observe`` (to hold
    one sample there, or fail on it)."""

    def __init__(self, calibrator, before) -> None:
        self._calibrator, self._before = calibrator, before

    def observe(self, sample) -> None:
        self._before(sample)
        self._calibrator.observe(sample)

    def __getattr__(self, name):
        return getattr(self._calibrator, name)


def _intercept(monkeypatch, before) -> None:
    """The calibrator node makes an :class:`_Intercepted` calibrator."""
    import adaptnav.service.calibrator.node as node_module

    real_make = node_module.make_calibrator
    monkeypatch.setattr(node_module, "make_calibrator", lambda *a: _Intercepted(real_make(*a), before))


def test_remote_calibrator_node_says_what_its_side_scan_front_end_made_of_the_pings(tmp_path):
    """The node's status (query ``calibrator``) carries its object front end's counts, as the
    daemon's health does for a calibrator child: every side-scan ping published is counted."""
    scenario, vehicle, stop, node = _side_scan_node(tmp_path, 60.0)
    try:
        first = wait_until(lambda: vehicle.get("calibrator", 0.5), 60)
        assert first, "the calibrator node did not answer"
        assert "side_scan" in first and first["side_scan"] is None  # null before the first ping
        pings = 0
        for s in simulate(scenario).iter_samples():
            if s.KIND in ("sonar", "rpm", "depth", "heading"):
                vehicle.publish_sample(s)
                pings += s.KIND == "sonar"
                if pings and pings % 100 == 0 and s.KIND == "sonar":  # the node's pace: none dropped
                    wait_until(lambda: vehicle.get("calibrator", 1.0)["received"].get("sonar", 0) >= pings - 50, 60)
        status = wait_until(lambda: (st := vehicle.get("calibrator", 1.0)) and st["received"].get("sonar") == pings
                            and st, 60)
    finally:
        stop.set()
        node.join(10)
        vehicle.close()
    assert pings > 300
    assert status, "the node did not take every ping"
    assert status["overflow"] == {}
    report = status["side_scan"]
    assert report["pings"] == pings and report["resampled"] == 0 and "bad geometry" not in report["rejected"]
    assert report["blocks"] >= pings // 160 - 1


def test_remote_calibrator_node_counts_a_ping_only_once_its_front_end_took_it(tmp_path, monkeypatch):
    """A status asked while a ping is still in the front end (a block of pings being searched
    for objects takes a while) must not count it as received before the front end's report does:
    the two always agree. The node's real calibrator, held inside its first ping's ``observe``."""
    inside, go_on = threading.Event(), threading.Event()

    def held_at_first_ping(sample) -> None:
        if sample.KIND == "sonar" and not inside.is_set():
            inside.set()
            assert go_on.wait(60)

    _intercept(monkeypatch, held_at_first_ping)
    scenario, vehicle, stop, node = _side_scan_node(tmp_path, 20.0)
    try:
        assert wait_until(lambda: vehicle.get("calibrator", 0.5), 60), "the calibrator node did not answer"
        ping = next(s for s in simulate(scenario).iter_samples() if s.KIND == "sonar")
        vehicle.publish_sample(ping)
        assert inside.wait(60), "the node did not take the ping"
        during = vehicle.get("calibrator", 5.0)
        go_on.set()
        after = wait_until(lambda: (st := vehicle.get("calibrator", 1.0)) and st["received"].get("sonar") == 1
                           and st, 60)
    finally:
        go_on.set()
        stop.set()
        node.join(10)
        vehicle.close()
    assert during is not None
    assert during["received"].get("sonar", 0) == 0 and during["side_scan"] is None, during
    assert after, "the ping was never counted"
    assert after["side_scan"]["pings"] == 1


def test_remote_calibrator_node_counts_a_sample_its_calibrator_failed_on_and_goes_on(tmp_path, monkeypatch):
    """An exception out of the calibrator for one sample is logged and counted in the status
    (``errors``), the sample is not counted as taken, and the node takes the next ones."""
    failed = []

    def fails_on_first_depth(sample) -> None:
        if sample.KIND == "depth" and not failed:
            failed.append(sample)
            raise ValueError("a sample the calibrator cannot take")

    _intercept(monkeypatch, fails_on_first_depth)
    scenario, vehicle, stop, node = _side_scan_node(tmp_path, 20.0)
    try:
        assert wait_until(lambda: vehicle.get("calibrator", 0.5), 60), "the calibrator node did not answer"
        depths = [s for s in simulate(scenario).iter_samples() if s.KIND == "depth"][:5]
        for s in depths:
            vehicle.publish_sample(s)
        status = wait_until(lambda: (st := vehicle.get("calibrator", 1.0))
                            and st["received"].get("depth", 0) + st["errors"].get("depth", 0) == len(depths) and st, 60)
        alive = node.is_alive()
    finally:
        stop.set()
        node.join(10)
        vehicle.close()
    assert status, "the node did not answer for every depth sample"
    assert alive
    assert status["errors"] == {"depth": 1} and status["received"]["depth"] == len(depths) - 1
