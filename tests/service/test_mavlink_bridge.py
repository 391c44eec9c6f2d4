"""The bridge against real pymavlink peers on UDP loopback, both directions."""
import math
import queue
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest

from adaptnav.fusion.frames import GeoOrigin, euler_to_quat
from adaptnav.fusion.samples import AttitudeSample, DepthSample, ImuSample, RpmSample, UsblSample
from adaptnav.service.transport.mavlink_bridge import BridgeConfig, MavlinkBridge, StreamRates
from adaptnav.service.transport.mavlink_convert import mavlink2
from adaptnav.service.tools.sitl_vehicle import SitlVehicle, SitlVehicleConfig

from pymavlink import mavutil

from .test_daemon_support import wait_until

pytestmark = pytest.mark.timeout(60)


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Peer:
    """A pymavlink endpoint posing as ArduSub (system 1, component 1)."""

    def __init__(self, port):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                               source_component=1, dialect="ardupilotmega")
        self.got = []

    def heartbeat(self):
        self.conn.mav.heartbeat_send(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)

    def pump(self, seconds, until=None):
        if until is not None:
            seconds = max(seconds, 30.0)  # a condition wait: generous on a loaded machine
        end = time.monotonic() + seconds
        next_hb = 0.0
        while time.monotonic() < end:
            if time.monotonic() >= next_hb:
                self.heartbeat()
                next_hb = time.monotonic() + 0.2
            while (m := self.conn.recv_msg()) is not None:
                self.got.append(m)
            if until is not None and until():
                return True
            self.conn.select(0.02)
        return until is None

    def of_type(self, t):
        return [m for m in self.got if m.get_type() == t]

    def close(self):
        self.conn.close()


def drain(q, until, timeout=30.0):
    out = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            out.append(q.get(timeout=0.05))
        except queue.Empty:
            pass
        if until(out):
            break
    return out


@pytest.fixture
def link():
    port = free_udp_port()
    q = queue.Queue()
    cfg = BridgeConfig(link_timeout_s=0.6, reconnect_min_s=0.05)
    bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", q.put, GeoOrigin(math.radians(48.5), math.radians(-124.25), 0.0), cfg)
    peer = Peer(port)
    yield bridge, peer, q, port
    bridge.close()
    peer.close()


def nav(valid=True):
    cov = np.eye(18) * 0.01
    cov[0, 0] = cov[1, 1] = 4.0  # σ_h = 2 m
    return SimpleNamespace(t_s=30.0, pos_n_m=(5.0, 6.0, 7.0), vel_n_m_s=(1.0, 0.0, 0.0),
                           q_nb=tuple(euler_to_quat(0.0, 0.0, 0.0)), cov=cov, valid=valid, reset_counter=1)


def test_peer_messages_become_samples_in_si_units(link):
    bridge, peer, q, _ = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    mav = peer.conn.mav
    mav.attitude_send(10_000, 0.1, -0.2, 0.3, 0.0, 0.0, 0.0)
    # the bridge asked for HIGHRES_IMU (float SI); RAW_IMU's mg/mrad are the converter's tests
    mav.highres_imu_send(10_010_000, 0.0980665, -0.196133, -9.80665, 0.015, -0.017, 0.003, 0, 0, 0, 0, 0, 0, 0,
                         0x3F)
    mav.scaled_pressure2_send(10_020, 1513.25, 0.0, 1500)
    mav.servo_output_raw_send(10_030_000, 0, 1287, 1287, 1713, 1713, 1500, 1500, 1500, 1500)
    got = drain(q, lambda out: len(out) >= 4)
    by = {s.KIND: s for s in got}
    assert set(by) == {"attitude", "imu", "depth", "rpm"}
    assert by["attitude"].t_s == pytest.approx(10.0) and by["attitude"].pitch_rad == pytest.approx(-0.2)
    assert by["imu"].specific_force_b_m_s2 == pytest.approx((0.0980665, -0.196133, -9.80665))
    assert by["imu"].omega_b_rad_s == pytest.approx((0.015, -0.017, 0.003))
    assert by["depth"].pressure_pa == pytest.approx(151325.0, rel=1e-6)
    assert by["rpm"].rpm == pytest.approx(3500 * (1713 - 1525) / 375, rel=1e-3)


def test_bridge_speaks_as_onboard_component_and_requests_rates(link):
    bridge, peer, q, _ = link
    assert peer.pump(3.0, until=lambda: len(peer.of_type("COMMAND_LONG")) >= 6 and peer.of_type("SET_GPS_GLOBAL_ORIGIN"))
    peer.pump(1.2)  # at least one more 1 Hz heartbeat
    hbs = peer.of_type("HEARTBEAT")
    assert hbs and all(h.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER for h in hbs)
    assert hbs[0].get_srcComponent() == mavlink2.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    cmds = {int(c.param1): c.param2 for c in peer.of_type("COMMAND_LONG")
            if c.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL and c.target_system == 1}
    assert cmds[mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU] == pytest.approx(20_000)  # 50 Hz, float SI first
    assert mavlink2.MAVLINK_MSG_ID_RAW_IMU not in cmds  # only as a fallback
    assert cmds[mavlink2.MAVLINK_MSG_ID_ATTITUDE] == pytest.approx(20_000)
    assert mavlink2.MAVLINK_MSG_ID_SCALED_PRESSURE2 in cmds
    (origin,) = peer.of_type("SET_GPS_GLOBAL_ORIGIN")  # once
    assert (origin.latitude, origin.longitude) == (485_000_000, -1_242_500_000)


def test_odometry_goes_out_with_frd_frames_and_quality(link):
    bridge, peer, q, _ = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    assert bridge.send_nav(nav())
    assert peer.pump(2.0, until=lambda: peer.of_type("ODOMETRY"))
    (od,) = peer.of_type("ODOMETRY")
    assert od.frame_id == 20 and od.child_frame_id == 12  # LOCAL_FRD, BODY_FRD
    assert (od.x, od.y, od.z) == (5.0, 6.0, 7.0) and od.vx == pytest.approx(1.0)
    assert od.pose_covariance[0] == pytest.approx(4.0)
    # σ_h = 2 m between best 0.5 m and worst 50 m on the log scale: 100 − 99·log(4)/log(100)
    assert od.quality == round(100 - 99 * math.log(4) / math.log(100))
    assert od.reset_counter == 1


def test_invalid_solution_sends_nothing(link):
    bridge, peer, q, _ = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    assert not bridge.send_nav(nav(valid=False))
    bridge.send_nav(nav())  # a valid one after it, as a marker
    assert peer.pump(2.0, until=lambda: peer.of_type("ODOMETRY"))
    peer.pump(0.3)
    assert len(peer.of_type("ODOMETRY")) == 1 and peer.of_type("ODOMETRY")[0].quality > 0
    assert bridge.counters["nav_silenced"] == 1


def test_corrupt_frames_are_counted_and_the_bridge_keeps_working(link):
    bridge, peer, q, port = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    mav = peer.conn.mav
    good = mav.attitude_encode(20_000, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav)
    for i in range(5):
        bad = bytearray(good)
        bad[-1] ^= 0xFF  # CRC broken
        peer.conn.write(bytes(bad))
    peer.conn.write(b"\xfd\x09garbage that is no frame at all \x00\xff")
    mav.attitude_send(21_000, 0.4, 0.5, 0.6, 0, 0, 0)
    got = drain(q, lambda out: any(s.t_s == pytest.approx(21.0) for s in out))
    assert [s.roll_rad for s in got] == pytest.approx([0.4])  # the corrupt ones never became samples
    assert bridge.counters["corrupt_frames"] >= 6
    assert bridge._thread.is_alive()


def test_a_frame_relayed_with_trailing_zeros_cut_after_its_crc_is_restored(link):
    """A link through a ground station that re-serialises frames of a non-truncating sender (QGC
    with BlueOS's Ping driver): the frame fails the CRC as it arrives, and is restored."""
    from tests.service.mavlink_wire import qgc_logged

    bridge, peer, q, port = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    mav = peer.conn.mav
    echo = mav.distance_sensor_encode(30_000, 20, 5000, 3550, 2, 1, 25, 255)  # quality 0: a zero tail
    peer.conn.write(qgc_logged(echo, mav))
    garbled = bytearray(qgc_logged(mav.distance_sensor_encode(30_100, 20, 5000, 3560, 2, 1, 25, 255), mav))
    garbled[16] ^= 0x01  # and one garbled on top: stays corrupt
    peer.conn.write(bytes(garbled))
    mav.attitude_send(31_000, 0.4, 0.5, 0.6, 0, 0, 0)
    got = drain(q, lambda out: any(s.KIND == "attitude" for s in out))
    assert [(s.KIND, s.altitude_m) for s in got if s.KIND == "altitude"] == [("altitude", pytest.approx(35.5))]
    assert bridge.counters["corrupt_frames"] == 2 and bridge.counters["repaired_frames"] == 1
    assert bridge.health()["repaired_frames"] == 1


def test_the_bridge_asks_the_autopilot_s_gps_type_and_takes_a_mavlink_gps_as_an_underwater_one(link):
    """BlueROV2 with a Water Linked UGPS: GPS1_TYPE 14, its fixes reach us as GPS_RAW_INT only
    (no GPS_INPUT on this link): acoustic fixes, fused at any depth."""
    bridge, peer, q, _ = link
    asked = lambda: {m.param_id for m in peer.of_type("PARAM_REQUEST_READ")} >= {"GPS_TYPE", "GPS1_TYPE"}  # noqa: E731
    assert peer.pump(3.0, until=lambda: bridge.link_up.is_set() and asked())
    mav = peer.conn.mav
    mav.gps_raw_int_send(40_000_000, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 9)
    before = drain(q, lambda out: any(s.KIND in ("gnss", "usbl") for s in out))
    mav.param_value_send(b"GPS1_TYPE", 14.0, 2, 900, 10)  # the autopilot answers
    mav.gps_raw_int_send(41_000_000, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 9)
    after = drain(q, lambda out: any(s.KIND in ("gnss", "usbl") for s in out))
    assert [s.KIND for s in before if s.KIND in ("gnss", "usbl")] == ["gnss"]
    assert [s.KIND for s in after if s.KIND in ("gnss", "usbl")] == ["usbl"]


def test_the_water_sensor_follows_the_autopilot_s_baro_primary(link):
    """A board with two barometers of its own: ArduSub's Bar30 is its third and BARO_PRIMARY 2.
    The bridge asks for the parameter, then for SCALED_PRESSURE3's rate, and takes its depth."""
    bridge, peer, q, _ = link
    asked = lambda: "BARO_PRIMARY" in {m.param_id for m in peer.of_type("PARAM_REQUEST_READ")}  # noqa: E731
    assert peer.pump(3.0, until=lambda: bridge.link_up.is_set() and asked())
    mav = peer.conn.mav
    mav.param_value_send(b"BARO_PRIMARY", 2.0, 2, 900, 50)  # the autopilot answers

    def interval_asked(msg_id):
        return any(c.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL and int(c.param1) == msg_id
                   for c in peer.of_type("COMMAND_LONG"))

    assert peer.pump(3.0, until=lambda: interval_asked(mavlink2.MAVLINK_MSG_ID_SCALED_PRESSURE3))
    mav.scaled_pressure2_send(20_000, 1013.25, 0.0, 2500)  # the enclosure's air
    mav.scaled_pressure3_send(20_010, 1513.25, 0.0, 1500)  # the water at 5 m
    got = drain(q, lambda out: any(s.KIND == "depth" for s in out))
    assert [round(s.pressure_pa) for s in got if s.KIND == "depth"] == [151325]


def test_a_signing_autopilot_gets_signed_messages_and_unsigned_drivers_still_count(tmp_path):
    """An autopilot with MAVLink 2 signing drops unsigned messages: with the ground station's
    passphrase configured, everything the bridge sends is signed with its key (the peer checks
    every signature and keeps only good ones), and an unsigned message from a companion driver
    is still taken."""
    import hashlib

    port = free_udp_port()
    q = queue.Queue()
    passphrase = tmp_path / "signing"
    passphrase.write_text("reef 42\n")
    cfg = BridgeConfig(link_timeout_s=0.6, reconnect_min_s=0.05, signing_passphrase_file=str(passphrase))
    bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", q.put, GeoOrigin(math.radians(48.5), math.radians(-124.25), 0.0), cfg)
    peer = Peer(port)
    peer.conn.setup_signing(hashlib.sha256(b"reef 42").digest(), sign_outgoing=True)  # no unsigned accepted
    driver = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=0,
                                        dialect="ardupilotmega")  # mavlink2rest: unsigned
    try:
        assert peer.pump(3.0, until=lambda: bridge.link_up.is_set() and peer.of_type("HEARTBEAT"))
        bridge.send_nav(nav())
        assert peer.pump(3.0, until=lambda: peer.of_type("ODOMETRY"))
        assert all(m._signed for m in peer.got)
        assert peer.conn.mav.signing.goodsig_count >= len(peer.got) and peer.conn.mav.signing.reject_count == 0
        got = []

        def a_dvl_sample():  # the autopilot keeps beating meanwhile: the link stays up
            driver.mav.vision_speed_estimate_send(0, 0.5, 0.0, 0.0)
            got.extend(drain(q, lambda out: True, timeout=0.1))
            return any(s.KIND == "dvl" for s in got)

        assert peer.pump(3.0, until=a_dvl_sample)
        assert {s.vel_d_m_s for s in got if s.KIND == "dvl"} == {(0.5, 0.0, 0.0)}
        health = bridge.health()["signing"]
        assert health["signed_in"] > 0 and health["unsigned_accepted"] >= 1 and health["bad_signatures"] == 0
    finally:
        bridge.close()
        peer.close()
        driver.close()


def test_peer_restart_reconnects_and_re_requests_streams(link):
    bridge, peer, q, port = link
    assert peer.pump(3.0, until=bridge.link_up.is_set)
    n_req = bridge.counters["interval_requests"]
    peer.close()  # autopilot gone (reboot, cable, router restart)
    deadline = time.monotonic() + 30.0
    while bridge.link_up.is_set() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not bridge.link_up.is_set() and bridge.counters["link_losses"] >= 1
    peer2 = Peer(port)  # a new socket: new source port, as after a reboot
    try:
        assert peer2.pump(5.0, until=lambda: peer2.of_type("COMMAND_LONG") and bridge.link_up.is_set())
        assert bridge.counters["reconnects"] >= 1
        assert bridge.counters["interval_requests"] > n_req
        peer2.conn.mav.attitude_send(5_000, 0.7, 0.0, 0.0, 0, 0, 0)
        got = drain(q, lambda out: any(s.KIND == "attitude" for s in out))
        assert any(s.KIND == "attitude" and s.roll_rad == pytest.approx(0.7) for s in got)
    finally:
        peer2.close()


def test_sitl_vehicle_end_to_end_through_the_bridge():
    port = free_udp_port()
    q = queue.Queue()
    samples = []
    for i in range(300):  # 3 s at 100 Hz
        t = i / 100
        samples.append(ImuSample(t, (0.1, 0.2, -9.8), (0.01, -0.02, 0.03)))
        if i % 5 == 0:
            samples.append(AttitudeSample(t, 0.1, -0.05, 1.0))
        if i % 10 == 0:
            samples += [DepthSample(t, 150_000.0), RpmSample(t, 1200.0)]
        if i % 100 == 50:
            samples.append(UsblSample(t, 0.8, -2.1, 5.0, 1.5))
    bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", q.put, GeoOrigin(0.8, -2.1, 0.0),
                           BridgeConfig(request_imu_message="HIGHRES_IMU"))
    vehicle = SitlVehicle(samples, SitlVehicleConfig(url=f"udpout:127.0.0.1:{port}", speed=3.0)).start()
    try:
        assert bridge.wait_connected(30.0)
        for _ in range(5):
            bridge.send_nav(nav())
        assert vehicle.done.wait(60.0) and vehicle.error is None
        # the vehicle has stopped reading: what the bridge sent is read here, until it is all in
        rec = vehicle.received
        assert wait_until(lambda: vehicle.poll() >= 0 and rec["odometry"] == 5 and rec["origin"] is not None
                          and rec["onboard_heartbeats"] >= 1 and "HIGHRES_IMU" in rec["interval_requests"], 30)
    finally:
        bridge.close()
        vehicle.close()
    got = []
    while not q.empty():
        got.append(q.get())
    by = {}
    for s in got:
        by.setdefault(s.KIND, []).append(s)
    # after the 50 Hz request the 100 Hz IMU arrives as every second sample, floats intact
    # (when the request lands depends on the machine's load; the rate after it does not)
    t_imu = np.array([s.t_s for s in by["imu"]])
    assert len(t_imu) >= 10
    assert np.median(np.diff(t_imu)) == pytest.approx(0.02, abs=1e-3)
    assert len(t_imu) >= 0.9 * ((t_imu[-1] - t_imu[0]) / 0.02 + 1)
    assert by["imu"][-1].specific_force_b_m_s2 == pytest.approx((0.1, 0.2, -9.8), abs=1e-6)
    assert by["rpm"][-1].rpm == pytest.approx(1200.0, abs=3500 / 375)
    assert by["depth"][-1].pressure_pa == pytest.approx(150_000.0, rel=1e-6)
    assert by["usbl"][-1].lat_rad == pytest.approx(0.8, abs=1e-9) and by["usbl"][-1].depth_m == pytest.approx(5.0)
    assert vehicle.received["odometry"] == 5 and vehicle.received["origin"] is not None
    assert vehicle.received["interval_requests"]["HIGHRES_IMU"] == pytest.approx(20_000)
    assert vehicle.received["onboard_heartbeats"] >= 1


def free_tcp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TcpPeer(Peer):
    def __init__(self, port):
        self.conn = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1,
                                               source_component=1, dialect="ardupilotmega")
        self.got = []


def test_tcp_link_survives_the_autopilot_side_closing_and_coming_back():
    port = free_tcp_port()
    peer = TcpPeer(port)
    q = queue.Queue()
    bridge = MavlinkBridge(f"tcp:127.0.0.1:{port}", q.put, None,
                           BridgeConfig(link_timeout_s=5.0, reconnect_min_s=0.05, reconnect_max_s=0.2))
    try:
        assert peer.pump(5.0, until=lambda: peer.of_type("COMMAND_LONG") and bridge.link_up.is_set())
        peer.close()  # server gone: EOF on the bridge's socket, then refused connects
        deadline = time.monotonic() + 30.0
        while bridge.counters["link_losses"] == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert bridge.counters["link_losses"] >= 1
        time.sleep(0.5)  # a few refused re-connects with back-off
        peer = TcpPeer(port)
        assert peer.pump(5.0, until=lambda: peer.of_type("COMMAND_LONG") and bridge.link_up.is_set())
        peer.conn.mav.attitude_send(7_000, 0.25, 0.0, 0.0, 0, 0, 0)
        got = drain(q, lambda out: any(s.KIND == "attitude" for s in out))
        assert any(s.roll_rad == pytest.approx(0.25) for s in got)
        assert bridge.counters["reconnects"] >= 1 and bridge._thread.is_alive()
    finally:
        bridge.close()
        peer.close()


def test_simulated_mission_arrives_through_sitl_vehicle_and_bridge_intact():
    from adaptnav.fusion.frames import quat_to_euler
    from adaptnav.fusion.state import NavState
    from adaptnav.sim.scenario import load_scenario
    from adaptnav.sim.simulator import simulate

    result = simulate(load_scenario("short", ["duration_s=40.0"]))
    samples = list(result.iter_samples())
    imu_by_t = {round(s.t_s, 6): s for s in samples if s.KIND == "imu"}
    depth_by_t = {round(s.t_s, 3): s for s in samples if s.KIND == "depth"}
    rpm_by_t = {round(s.t_s, 6): s for s in samples if s.KIND == "rpm"}
    truth_by_t = {round(s.t_s, 3): s for s in samples if s.KIND == "truth"}
    imu_rate_hz = (len(imu_by_t) - 1) / (max(imu_by_t) - min(imu_by_t))

    port = free_udp_port()
    q = queue.Queue()
    bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", q.put, None,
                           BridgeConfig(request_imu_message="HIGHRES_IMU",
                                        rates=StreamRates(imu_hz=imu_rate_hz, pressure_hz=50.0, servo_hz=50.0)))
    vehicle = SitlVehicle(samples, SitlVehicleConfig(url=f"udpout:127.0.0.1:{port}", speed=20.0)).start()
    cov = np.eye(18) * 0.01
    state = NavState(t_s=1.0, pos_n_m=np.zeros(3), vel_n_m_s=np.zeros(3), q_nb=np.array([1.0, 0, 0, 0]),
                     bias_acc_b_m_s2=np.zeros(3), bias_gyro_b_rad_s=np.zeros(3), current_n_m_s=np.zeros(2),
                     k_speed=1.0, cov=cov, valid=True, reset_counter=0)
    try:
        assert bridge.wait_connected(5.0)
        assert bridge.send_nav(state)
        assert vehicle.done.wait(30.0) and vehicle.error is None
        vehicle.run(linger_s=0.3)  # serve the last ODOMETRY
    finally:
        bridge.close()
        vehicle.close()
    got = []
    while not q.empty():
        got.append(q.get())
    imu = [s for s in got if s.KIND == "imu"]
    # everything after the rate request arrives: at most the first second is at defaults
    assert len(imu) >= len(imu_by_t) - imu_rate_hz * 1.5
    for s in imu:
        ref = imu_by_t[round(s.t_s, 6)]  # µs timestamps: exact
        assert s.specific_force_b_m_s2 == pytest.approx(ref.specific_force_b_m_s2, rel=1e-6, abs=1e-6)
        assert s.omega_b_rad_s == pytest.approx(ref.omega_b_rad_s, rel=1e-6, abs=1e-7)
    depth = [s for s in got if s.KIND == "depth"]
    assert len(depth) >= len(depth_by_t) - 15
    for s in depth:
        assert s.pressure_pa == pytest.approx(depth_by_t[round(s.t_s, 3)].pressure_pa, rel=1e-6)
    rpm = [s for s in got if s.KIND == "rpm"]
    assert len(rpm) >= len(rpm_by_t) - 15
    for s in rpm:  # integer PWM µs on the wire: one step of the curve
        assert s.rpm == pytest.approx(rpm_by_t[round(s.t_s, 6)].rpm, abs=3500 / 375)
    att = [s for s in got if s.KIND == "attitude"]
    assert len(att) >= len(truth_by_t) - 15
    for s in att:
        roll, pitch, _ = quat_to_euler(np.asarray(truth_by_t[round(s.t_s, 3)].q_nb))
        assert (s.roll_rad, s.pitch_rad) == pytest.approx((roll, pitch), abs=1e-6)
    assert vehicle.received["odometry"] == 1 and vehicle.received["last_quality"] == 100


def test_serial_link_over_a_pseudo_terminal():
    import os

    master, slave = os.openpty()
    os.set_blocking(master, False)
    name = os.ttyname(slave)
    q = queue.Queue()
    bridge = MavlinkBridge(f"serial:{name}:57600", q.put, None, BridgeConfig())
    peer = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    received = []
    try:
        end = time.monotonic() + 30.0
        while time.monotonic() < end and not bridge.link_up.is_set():
            os.write(master, peer.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE,
                                                   mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(peer))
            time.sleep(0.1)
        assert bridge.link_up.is_set()
        os.write(master, peer.attitude_encode(3_000, 0.0, 0.3, 0.0, 0, 0, 0).pack(peer))
        got = drain(q, lambda out: any(s.KIND == "attitude" for s in out))
        assert [s.pitch_rad for s in got if s.KIND == "attitude"] == pytest.approx([0.3])
        end = time.monotonic() + 30.0
        while time.monotonic() < end and not any(m.get_type() == "HEARTBEAT" for m in received):
            try:
                received += parser.parse_buffer(os.read(master, 4096)) or []
            except BlockingIOError:
                time.sleep(0.05)
        assert any(m.get_type() == "COMMAND_LONG" for m in received)
        assert any(m.get_type() == "HEARTBEAT" and m.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER for m in received)
    finally:
        bridge.close()
        os.close(master)
        os.close(slave)


def test_a_log_file_is_not_a_live_link(tmp_path):
    from adaptnav.service.transport.mavlink_bridge import link_device

    f = tmp_path / "mission.tlog"
    f.write_bytes(b"")
    with pytest.raises(ValueError, match="replay"):
        link_device(str(f))
    assert link_device("serial:/dev/ttyACM0:921600") == ("/dev/ttyACM0", 921600)
    assert link_device("udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", 115200)
    # the same parser as the config's check (mavlink_config.split_link_url): a baud that is no
    # number was int()'s own "invalid literal" from the link's open, retried forever
    with pytest.raises(ValueError, match="baud 'fast' is not a positive integer"):
        link_device("serial:/dev/ttyACM0:fast")
