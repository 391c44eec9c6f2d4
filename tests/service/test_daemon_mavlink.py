"""Daemon with the MAVLink bridge on: a simulated ArduSub on UDP loopback feeds it,
nav states go out on Zenoh and ODOMETRY (LOCAL_FRD / BODY_FRD) goes back to the vehicle."""
from __future__ import annotations

import time

import pytest

from adaptnav.service.daemon import Daemon
from adaptnav.service.runtime.replay import build_config

from .test_daemon_support import Collector, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(120)


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_sitl_vehicle_through_daemon_and_back(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mav
    from adaptnav.sim.scenario import load_scenario

    from adaptnav.service.tools.sitl_vehicle import SitlVehicle, SitlVehicleConfig
    from adaptnav.service.runtime.sources import simulate

    scenario = load_scenario("short", ["duration_s=40"])
    zport, uport = free_port(), _free_udp_port()
    cfg = build_config(scenario, None, [
        f'zenoh.listen=["tcp/127.0.0.1:{zport}"]', "zenoh.scouting=false", "vehicle.name=testauv",
        f'state_dir="{tmp_path}"', "calibrator.enabled=false", "mavlink.enabled=true",
        f'mavlink.url="udpin:127.0.0.1:{uport}"', "mavlink.output_rate_hz=5"])
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(zport)
    col = Collector(bus)
    vehicle = SitlVehicle(simulate(scenario).iter_samples(),
                          SitlVehicleConfig(url=f"udpout:127.0.0.1:{uport}", speed=4.0))
    try:
        vehicle.start()
        odo = wait_until(lambda: vehicle.received["odometry"] >= 5, timeout_s=60)
        navs = col.get(bus.keys.nav_state)
        # the daemon's counters, once they report both kinds (the first ODOMETRY may come
        # before the daemon has counted the first depth sample; no pace assumed between them)
        health = wait_until(lambda: (h := bus.get("health", 0.5)) and {"imu", "depth"} <= set(h["sensors"]) and h,
                            60) or bus.get("health")
    finally:
        vehicle.stop()
        vehicle.close()
        bus.close()
        daemon.stop()
    assert navs, "no nav state on Zenoh from MAVLink input"
    assert {"imu", "depth"} <= set(health["sensors"]), health["sensors"].keys()
    assert odo, f"no ODOMETRY back to the vehicle: {vehicle.received}"
    last = vehicle.received["last_odometry"]
    assert last.frame_id == mav.MAV_FRAME_LOCAL_FRD and last.child_frame_id == mav.MAV_FRAME_BODY_FRD
    assert vehicle.received["origin"] is not None
    assert abs(vehicle.received["origin"].latitude / 1e7 - cfg.origin.lat_deg) < 1e-6
    # the autopilot's samples run in the bridge's thread, not handed one by one to the runner
    # thread (queued only when they find it busy), many held for the bursts before the epochs
    # (IMU 3 of every 5 at 50 Hz and 10 Hz output, and the aids among them)
    path, n = health["live_path"], health["mavlink"]["samples"]
    assert sum(path.values()) >= n > 0
    assert path.get("queued", 0) < 0.1 * n, path
    assert path.get("held_for_burst", 0) > 0.25 * n, path
