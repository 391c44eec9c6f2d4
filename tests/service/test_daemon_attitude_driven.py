"""The daemon on an autopilot that streams at ArduSub's default rates (RAW_IMU at 2 Hz, ATTITUDE
at 10 Hz) with an underwater GPS on the companion (BlueOS's UGPS extension: GPS_INPUT from
system 255): a pymavlink peer on UDP loopback plays the vehicle, the daemon's MAVLink bridge
reads it, the attitude drives the strapdown, nav states go out on Zenoh and ODOMETRY back.

No wall-clock pacing: the peer sends a second of data at a time and waits until the daemon's
health has counted it (data time is the messages' own boot clock)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import Collector, daemon_config, free_port, peer, wait_until

pytestmark = pytest.mark.timeout(180)

DEPTH_M = 5.0
PRESS_HPA = (101325.0 + 1025.0 * 9.80665 * DEPTH_M) / 100.0


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_default_rate_autopilot_with_an_underwater_gps_navigates_on_its_attitude(tmp_path):
    from pymavlink import mavutil
    from pymavlink.dialects.v20 import ardupilotmega as mav

    zport, uport = free_port(), _free_udp_port()
    cfg = daemon_config(zport, tmp_path, "calibrator.enabled=false", "mavlink.enabled=true",
                        f'mavlink.url="udpin:127.0.0.1:{uport}"', "mavlink.output_rate_hz=5")
    lat0, lon0 = cfg.origin.lat_deg, cfg.origin.lon_deg
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(zport)
    col = Collector(bus)
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{uport}", source_system=1, source_component=1,
                                           dialect="ardupilotmega")
    ugps = mavutil.mavlink_connection(f"udpout:127.0.0.1:{uport}", source_system=255, source_component=0,
                                      dialect="ardupilotmega")
    rng = np.random.default_rng(5)
    sent = 0
    health = None
    try:
        for second in range(60):  # a vehicle holding station at 5 m, heading 40°
            t0 = 10.0 + second
            autopilot.mav.heartbeat_send(mav.MAV_TYPE_SUBMARINE, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
            for k in range(10):
                t = t0 + 0.1 * k
                ms = int(round(t * 1000))
                autopilot.mav.attitude_send(ms, 0.01, -0.02, math.radians(40.0), 0.0, 0.0, 0.0)
                sent += 1
                if k % 5 == 0:
                    autopilot.mav.raw_imu_send(ms * 1000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
                    autopilot.mav.scaled_pressure2_send(ms, PRESS_HPA, 0.0, 1500)
                    autopilot.mav.servo_output_raw_send(ms * 1000, 0, *([1500] * 8))
            dn, de = rng.normal(0.0, 1.0, 2)
            ugps.mav.gps_input_send(0, 0, 253, 0, 0, 3, int(round((lat0 + dn / 111_200.0) * 1e7)),
                                    int(round((lon0 + de / (111_200.0 * math.cos(math.radians(lat0)))) * 1e7)),
                                    0.0, 1.0, 65535, 0, 0, 0, 0, 0, 0, 12, 0)
            # flow control: the next second once the daemon has counted this one's attitudes
            health = wait_until(lambda: (h := bus.get("health", 0.5)) and
                                h["sensors"].get("attitude", {}).get("count", 0) >= sent and h, 30)
            assert health, f"the daemon did not take second {second}'s attitude samples"
        navs = wait_until(lambda: [n for n in col.get(bus.keys.nav_state) if n["t_s"] >= 69.0], 30)
        odometry = wait_until(lambda: autopilot.recv_match(type="ODOMETRY", blocking=False), 30)
        health = bus.get("health", 2.0)
    finally:
        autopilot.close()
        ugps.close()
        bus.close()
        daemon.stop()
    # THEN the filter runs on the attitude's increments and says so
    assert health["imu_grade"] == "attitude", health["imu_grade"]
    assert health["status"].startswith("navigating on the attitude"), health["status"]
    assert health["sensors"]["usbl"]["count"] >= 50
    # AND the nav state is valid at the end, where the fixes are (within its 3σ), at the depth
    last = navs[-1]
    assert last["valid"], last.get("invalid_reasons")
    cov = np.asarray(last["cov"], dtype=float)
    n = int(round(math.sqrt(cov.size)))
    cov = cov.reshape(n, n)
    sigma_h = math.sqrt(max(cov[0, 0], cov[1, 1]))
    assert sigma_h < 2.0 and math.hypot(*last["pos_n_m"][:2]) <= 3.0 * sigma_h + 0.5
    assert last["pos_n_m"][2] == pytest.approx(DEPTH_M, abs=0.3)
    assert math.degrees(last["euler_rad"][2]) == pytest.approx(40.0, abs=1.0)
    # AND the autopilot gets it back as ODOMETRY
    assert odometry is not None
