"""The autopilot link done right: ODOMETRY on a fixed schedule, HIGHRES_IMU with a RAW_IMU
fallback, reset_counter across restarts, the pose alone when the velocity is not
constrained, silence below the quality ArduSub is told to accept, the origin confirmed
(re-sent until it is), and health that says what the link did — against a pymavlink peer
on UDP loopback."""
import math
import queue
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
import pytest

from adaptnav.fusion.frames import GeoOrigin, euler_to_quat
from adaptnav.service.transport.mavlink_bridge import BridgeConfig, MavlinkBridge, OutputSchedule
from adaptnav.service.transport.mavlink_convert import OdometryConfig, mavlink2, quality_from_sigma

from .test_mavlink_bridge import Peer, free_udp_port

pytestmark = pytest.mark.timeout(90)
ORIGIN = GeoOrigin(math.radians(48.5), math.radians(-124.25), 0.0)


def nav(t_s=30.0, sigma_h=2.0, sigma_v=0.1, reset_counter=1, valid=True):
    cov = np.eye(18) * 0.01
    cov[0, 0] = cov[1, 1] = sigma_h**2
    cov[3, 3] = cov[4, 4] = sigma_v**2
    return SimpleNamespace(t_s=t_s, pos_n_m=(5.0, 6.0, 7.0), vel_n_m_s=(1.0, 0.0, 0.0),
                           q_nb=tuple(euler_to_quat(0.0, 0.0, 0.3)), cov=cov, valid=valid,
                           reset_counter=reset_counter)


@contextmanager
def linked(tmp_path=None, **cfg):
    """A bridge on UDP loopback and a pymavlink peer (the autopilot), closed on exit;
    yields (bridge, peer, queue of converted samples)."""
    port = free_udp_port()
    q = queue.Queue()
    config = BridgeConfig(**{"link_timeout_s": 5.0, "heartbeat_period_s": 0.1, **cfg})
    bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", q.put, ORIGIN, config,
                           state_path=None if tmp_path is None else tmp_path / "bridge.json")
    peer = Peer(port)
    try:
        yield bridge, peer, q
    finally:
        bridge.close()
        peer.close()


def test_output_schedule_sends_every_slot_even_when_states_come_a_hair_early():
    sched = OutputSchedule(10.0)
    # 10 Hz states whose stamps are sums of IMU intervals: a hair before each slot
    t = [k * 0.1 - (1e-9 if k % 2 else 0.0) for k in range(100)]
    assert sum(sched.due(x) for x in t) == 100  # the old rule sent 50 (every second one)
    sched = OutputSchedule(10.0)
    t50 = [k * 0.02 for k in range(500)]  # 50 Hz states → 10 Hz output, evenly spaced
    sent = [x for x in t50 if sched.due(x)]
    assert len(sent) == 100 and np.allclose(np.diff(sent), 0.1, atol=1e-9)
    # a gap and a clock that went back re-anchor the slots instead of bursting or stalling
    assert sched.due(100.0) and not sched.due(100.05) and sched.due(100.1)
    assert sched.due(3.0) and sched.due(3.1)


def test_raw_imu_only_when_the_autopilot_has_no_highres_imu():
    with linked(imu_fallback_s=0.5) as (bridge, peer, q):
        def requested(msg_id):
            return [c for c in peer.of_type("COMMAND_LONG")
                    if c.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL and int(c.param1) == msg_id]

        assert peer.pump(5.0, until=lambda: requested(mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU))
        assert not requested(mavlink2.MAVLINK_MSG_ID_RAW_IMU)
        # this autopilot never sends HIGHRES_IMU: the bridge asks for RAW_IMU instead
        assert peer.pump(5.0, until=lambda: requested(mavlink2.MAVLINK_MSG_ID_RAW_IMU))
        assert bridge.imu_stream == "RAW_IMU" and bridge.health()["imu_stream"] == "RAW_IMU"
        peer.conn.mav.raw_imu_send(1_000_000, 0, 0, -1000, 1, 2, 3, 0, 0, 0)
        got = []
        assert peer.pump(5.0, until=lambda: got.extend(_drain(q)) or any(s.KIND == "imu" for s in got))
        health = bridge.health()
        assert health["imu_integrated"].startswith("RAW_IMU from ") and health["imu_switches"] == 0


def test_highres_imu_keeps_its_stream():
    with linked(imu_fallback_s=0.5) as (bridge, peer, q):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        peer.conn.mav.highres_imu_send(2_000_000, 0, 0, -9.8, 0, 0, 0.01, 0, 0, 0, 0, 0, 0, 0, 0x3F)
        peer.pump(1.5)
        assert bridge.imu_stream == "HIGHRES_IMU"
        assert any(s.KIND == "imu" for s in _drain(q))


def _drain(q):
    out = []
    while not q.empty():
        out.append(q.get())
    return out


def test_reset_counter_continues_across_a_restart(tmp_path):
    with linked(tmp_path) as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        assert bridge.send_nav(nav(reset_counter=4))
        assert peer.pump(5.0, until=lambda: peer.of_type("ODOMETRY"))
        first = peer.of_type("ODOMETRY")[-1].reset_counter
    # the daemon restarts: its filter counts from 0 again, the autopilot must see a reset
    with linked(tmp_path) as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        assert bridge.send_nav(nav(reset_counter=0))
        assert peer.pump(5.0, until=lambda: peer.of_type("ODOMETRY"))
        second = peer.of_type("ODOMETRY")[-1].reset_counter
    assert first == 4 and second == 5


def test_an_unconstrained_velocity_is_not_sent_as_valid():
    with linked() as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        assert bridge.send_nav(nav(sigma_v=1.5))  # no velocity aid for minutes: σ_v 1.5 m/s
        assert peer.pump(5.0, until=lambda: peer.of_type("VISION_POSITION_ESTIMATE"))
        (pose,) = peer.of_type("VISION_POSITION_ESTIMATE")
        assert (pose.x, pose.y, pose.z) == (5.0, 6.0, 7.0) and pose.yaw == pytest.approx(0.3, abs=1e-6)
        assert not peer.of_type("ODOMETRY")
        assert bridge.counters["pose_only_sent"] == 1 and bridge.counters["odometry_sent"] == 0


def test_below_the_quality_arduSub_is_told_to_accept_nothing_is_sent():
    cfg = OdometryConfig()
    assert quality_from_sigma(40.0, cfg) < cfg.min_quality <= quality_from_sigma(30.0, cfg)
    with linked() as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        assert not bridge.send_nav(nav(sigma_h=40.0))
        assert bridge.send_nav(nav(sigma_h=30.0, t_s=31.0))
        assert peer.pump(5.0, until=lambda: peer.of_type("ODOMETRY"))
        peer.pump(0.3)
        (od,) = peer.of_type("ODOMETRY")
        assert od.time_usec == 31_000_000 and od.quality >= cfg.min_quality


def test_origin_is_resent_until_the_autopilot_confirms_it():
    with linked(origin_retry_s=0.3) as (bridge, peer, _):
        assert peer.pump(10.0, until=lambda: len(peer.of_type("SET_GPS_GLOBAL_ORIGIN")) >= 3)
        assert not bridge.origin_confirmed
        o = peer.of_type("SET_GPS_GLOBAL_ORIGIN")[-1]
        peer.conn.mav.gps_global_origin_send(o.latitude, o.longitude, o.altitude, 0)  # as ArduSub answers
        assert peer.pump(5.0, until=lambda: bridge.origin_confirmed)
        n = len(peer.of_type("SET_GPS_GLOBAL_ORIGIN"))
        peer.pump(1.0)
        assert len(peer.of_type("SET_GPS_GLOBAL_ORIGIN")) == n  # confirmed: no more re-sends
        h = bridge.health()
        assert h["origin_confirmed"] and h["origin_sent"] == n
        assert h["autopilot_origin_deg"] == pytest.approx([48.5, -124.25])


def test_autopilot_reboot_re_requests_streams_and_the_origin():
    with linked(origin_retry_s=30.0) as (bridge, peer, _):
        assert peer.pump(5.0, until=lambda: peer.of_type("SET_GPS_GLOBAL_ORIGIN"))
        peer.conn.mav.attitude_send(600_000, 0, 0, 0, 0, 0, 0)
        peer.pump(0.3)
        n_cmd = len(peer.of_type("COMMAND_LONG"))
        peer.conn.mav.attitude_send(3_000, 0, 0, 0, 0, 0, 0)  # boot clock back to 3 s: rebooted
        assert peer.pump(5.0, until=lambda: len(peer.of_type("SET_GPS_GLOBAL_ORIGIN")) >= 2)
        assert len(peer.of_type("COMMAND_LONG")) > n_cmd + 5
        assert bridge.health()["autopilot_reboots"] == 1


def test_health_says_what_the_link_did_and_why_a_rangefinder_gives_no_altitude():
    with linked() as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        peer.conn.mav.command_ack_send(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink2.MAV_RESULT_ACCEPTED)
        peer.conn.mav.command_ack_send(mavlink2.MAV_CMD_REQUEST_MESSAGE, mavlink2.MAV_RESULT_UNSUPPORTED)
        # the simulator's echosounder: 49.49 m with max_distance 30 m (no seabed in range)
        for k in range(3):
            peer.conn.mav.distance_sensor_send(1000 + k, 20, 3000, 4949, 4, 0, 25, 0)
        assert peer.pump(5.0, until=lambda: bridge.counters["command_acks"] >= 2
                         and bridge.counters["messages_by_type"].get("DISTANCE_SENSOR", 0) >= 3)
        h = bridge.health()
        assert h["command_acks"] == {"MAV_CMD_SET_MESSAGE_INTERVAL:MAV_RESULT_ACCEPTED": 1,
                                     "MAV_CMD_REQUEST_MESSAGE:MAV_RESULT_UNSUPPORTED": 1}
        ds = h["message_types"]["DISTANCE_SENSOR"]
        assert ds["status"] == "rejected" and ds["rejected"] == {"distance_out_of_range": 3}
        assert h["rejected"]["distance_out_of_range"] == 3 and h["link_up"]
        assert h["messages_by_type"]["DISTANCE_SENSOR"] == 3


def test_health_says_which_thruster_curve_and_turns_to_the_simulators_on_its_sim_state():
    """A live daemon against ArduPilot's SITL converts thrust through the simulator's curve once
    the autopilot's SIM_STATE arrives; health says so (as a replay's summary.json does)."""
    with linked() as (bridge, peer, _):
        assert peer.pump(5.0, until=bridge.link_up.is_set)
        assert bridge.health()["thrusters"]["curve"] == "vehicle"
        peer.conn.mav.sim_state_send(1, 0, 0, 0, *[0.0] * 17)
        assert peer.pump(5.0, until=lambda: bridge.counters["messages_by_type"].get("SIM_STATE", 0) >= 1)
        thrusters = bridge.health()["thrusters"]
        assert thrusters["curve"] == "simulator" and "SIM_STATE" in thrusters["why"]
