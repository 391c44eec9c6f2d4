"""MAVLink ↔ sample conversions: units, time mapping, thruster curve, ODOMETRY out."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from adaptnav.service.transport.mavlink_convert import (
    ConvertConfig,
    MavlinkConverter,
    OdometryConfig,
    PwmRpmCurve,
    MissionClock,
    gps_global_origin_fields,
    mavlink2,
    odometry_fields,
    quality_from_sigma,
)
from adaptnav.fusion.frames import GeoOrigin, euler_to_quat


def wire(encode_name, *args, src=(1, 1)):
    """Encode → bytes → decode, so the message has a real header like one off the wire."""
    mav = mavlink2.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    buf = getattr(mav, encode_name)(*args).pack(mav)
    return mavlink2.MAVLink(None).decode(bytearray(buf))


def heartbeat():
    return wire("heartbeat_encode", mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)


def converter(**kw):
    c = MavlinkConverter(ConvertConfig(**kw))
    c.convert(heartbeat())
    return c


def test_raw_imu_is_mg_and_mrad_per_s():
    c = converter()
    (s,) = c.convert(wire("raw_imu_encode", 5_000_000, 10, -20, -1000, 15, -17, 3, 0, 0, 0))
    assert s.t_s == pytest.approx(5.0)
    assert s.specific_force_b_m_s2 == pytest.approx((0.0980665, -0.196133, -9.80665))
    assert s.omega_b_rad_s == pytest.approx((0.015, -0.017, 0.003))



def test_highres_imu_from_the_autopilot_component_is_a_flight_controllers_only_on_its_boot_clock():
    """ArduPilot and PX4 stamp HIGHRES_IMU on their boot clock; an AUV's vehicle computer that
    streams its FOG from component 1 in UNIX time, or says it is a generic autopilot, is not a
    flight controller's MEMS (filter.imu.grade = auto would otherwise call a FOG consumer)."""
    def highres(usec, src=(1, 1)):
        return wire("highres_imu_encode", usec, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F, src=src)

    (boot,) = converter().convert(highres(2_000_000))
    c = converter()
    # held until the UNIX clock can be placed on the boot clock, then released at the end
    (unix,) = c.convert(highres(1_767_000_000_000_000)) + c.flush()
    generic = MavlinkConverter(ConvertConfig())
    generic.convert(wire("heartbeat_encode", mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_GENERIC, 0, 0, 4))
    (gen,) = generic.convert(highres(2_000_000))
    assert (boot.source, unix.source, gen.source) == ("autopilot", "dedicated", "dedicated")

def test_all_zero_scaled_imu2_is_an_absent_sensor_not_a_sample():
    c = converter(imu_message="auto")
    assert c.convert(wire("scaled_imu2_encode", 1000, 0, 0, 0, 0, 0, 0, 5, 6, 7)) == []
    assert c.rejected["imu_absent"] == 1
    # auto mode locks on the first real IMU stream, then ignores the others
    assert len(c.convert(wire("raw_imu_encode", 1_100_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0))) == 1
    assert c.convert(wire("scaled_imu3_encode", 1150, 1, 2, -1000, 0, 0, 0, 0, 0, 0)) == []
    assert c.accounting()["SCALED_IMU3"]["status"] == "ignored"


def test_scaled_imu_is_an_imu_stream_ranked_above_raw_imu():
    """SCALED_IMU (PX4's and other autopilots' first IMU: mg, mrad/s by definition) is integrated,
    a flight controller's MEMS; over RAW_IMU (whose scaling is only ArduPilot's convention)."""
    c = converter(imu_message="auto")
    (raw,) = c.convert(wire("raw_imu_encode", 1_000_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0))
    (scaled,) = c.convert(wire("scaled_imu_encode", 1010, 10, -20, -990, 1, 2, 3, 0, 0, 0))
    assert c.integrated_imu_stream() == "SCALED_IMU from 1/1" and c.imu_switches == 1
    assert scaled.specific_force_b_m_s2 == pytest.approx((0.0980665, -0.196133, -9.7085835))
    assert scaled.omega_b_rad_s == pytest.approx((1e-3, 2e-3, 3e-3))
    assert scaled.source == "autopilot"
    assert c.convert(wire("raw_imu_encode", 1_020_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)) == []  # the worse one
    assert c.accounting()["SCALED_IMU"]["status"] == "used"


def test_auto_imu_moves_up_to_a_better_stream_and_then_ignores_the_worse():
    c = converter(imu_message="auto")
    # the autopilot's int16 RAW_IMU comes first (ArduSub streams it at a few Hz)
    (raw,) = c.convert(wire("raw_imu_encode", 1_100_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0))
    # a float HIGHRES_IMU from the autopilot is better: switched to
    (own,) = c.convert(wire("highres_imu_encode", 1_150_000, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F))
    # a companion's dedicated IMU (component 200) sending HIGHRES_IMU is better still
    dedicated = wire("highres_imu_encode", 1_160_000, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F,
                     src=(1, 200))
    (ded,) = c.convert(dedicated)
    assert c.imu_switches == 2
    # each sample says who measured it (the auto IMU grade's prior): both of the autopilot's
    # streams are its flight controller's MEMS, the other component's is an IMU of its own
    assert (raw.source, own.source, ded.source) == ("autopilot", "autopilot", "dedicated")
    # from then on the autopilot's streams are ignored on purpose, and say why
    assert c.convert(wire("raw_imu_encode", 1_200_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)) == []
    assert c.convert(wire("highres_imu_encode", 1_210_000, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F)) == []
    acct = c.accounting()["RAW_IMU"]
    assert acct["ignored"] == {"another IMU stream (HIGHRES_IMU from 1/200) is integrated": 1}
    (s,) = c.convert(wire("highres_imu_encode", 1_170_000, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F,
                          src=(1, 200)))
    assert s.specific_force_b_m_s2[2] == pytest.approx(-9.81)


def test_highres_imu_attitude_pressure_distance():
    c = converter(imu_message="HIGHRES_IMU")
    (imu,) = c.convert(wire("highres_imu_encode", 2_500_000, 0.5, -0.25, -9.5, 0.01, 0.02, -0.03,
                            0, 0, 0, 0, 0, 0, 20, 0x3F))
    assert imu.t_s == pytest.approx(2.5)
    assert imu.specific_force_b_m_s2 == pytest.approx((0.5, -0.25, -9.5))
    (att,) = c.convert(wire("attitude_encode", 2600, 0.1, -0.2, 3.5, 0, 0, 0))
    assert att.t_s == pytest.approx(2.6)
    assert att.yaw_rad == pytest.approx(3.5 - 2 * math.pi, abs=1e-6)
    (dep,) = c.convert(wire("scaled_pressure2_encode", 2700, 1513.25, 0.0, 1500))
    assert dep.pressure_pa == pytest.approx(151325.0, rel=1e-6)
    assert c.convert(wire("scaled_pressure_encode", 2700, 1013.0, 0.0, 3000)) == []  # hull barometer
    (alt,) = c.convert(wire("distance_sensor_encode", 2800, 20, 5000, 3948, 1, 1, 25, 255))
    assert alt.altitude_m == pytest.approx(39.48)
    assert c.convert(wire("distance_sensor_encode", 2800, 20, 5000, 3948, 1, 1, 0, 255)) == []  # forward
    assert c.convert(wire("distance_sensor_encode", 2800, 20, 5000, 9000, 1, 1, 25, 255)) == []  # out of range


def test_gps_input_is_usbl_and_its_gps_raw_int_echo_is_dropped():
    c = converter()
    c.convert(wire("attitude_encode", 10_000, 0, 0, 0, 0, 0, 0))
    (u,) = c.convert(wire("gps_input_encode", 0, 0, 253, 0, 0, 3, 483861418, -1246305732, 0.0, 1.6, 65535,
                          0, 0, 0, 0, 0, 0, 21, 0, src=(1, 220)))
    assert u.t_s == pytest.approx(10.0)  # UGPS component: stamped with the autopilot clock
    assert u.lat_rad == pytest.approx(math.radians(48.3861418), abs=1e-12)
    assert u.lon_rad == pytest.approx(math.radians(-124.6305732), abs=1e-12)
    assert u.sigma_h_m == pytest.approx(1.6)  # HDOP × 1 m
    assert math.isnan(u.depth_m)  # altitude flagged ignored: depth comes from the depth sensor
    echo = wire("gps_raw_int_encode", 10_100_000, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 21)
    assert c.convert(echo) == []
    assert c.rejected["gnss_echo_of_gps_input"] == 1


def test_gps_raw_int_needs_a_fix_and_uses_h_acc():
    c = converter()
    assert c.convert(wire("gps_raw_int_encode", 1_000_000, 1, 1, 1, 0, 160, 65535, 0, 0, 0)) == []
    (g,) = c.convert(wire("gps_raw_int_encode", 1_000_000, 3, 100_000_000, 200_000_000, 0, 160, 65535, 0, 0, 9,
                          0, 1500, 0, 0, 0))
    assert g.lat_rad == pytest.approx(math.radians(10.0))
    assert g.sigma_h_m == pytest.approx(1.5)


def test_messages_from_a_ground_station_are_ignored():
    c = converter()
    assert c.convert(wire("attitude_encode", 1000, 0.1, 0, 0, 0, 0, 0, src=(255, 190))) == []
    assert c.rejected["other_system"] == 1


def test_pwm_rpm_curve_dead_band_and_inverse():
    curve = PwmRpmCurve()
    assert curve.rpm_of_pwm(1500) == 0.0
    assert curve.rpm_of_pwm(1520) == 0.0  # inside the ±25 µs dead band
    assert curve.rpm_of_pwm(1900) == pytest.approx(3500.0)
    assert curve.rpm_of_pwm(1100) == pytest.approx(-3500.0)
    assert curve.rpm_of_pwm(1712.5) == pytest.approx(1750.0)
    for rpm in (-3000.0, -10.0, 0.0, 12.0, 1750.0, 3400.0):
        assert curve.rpm_of_pwm(curve.pwm_of_rpm(rpm)) == pytest.approx(rpm, abs=3500 / 375)


def test_servo_output_to_rpm_uses_forward_signs():
    c = converter()
    # BlueROV2 vectored: motors 1, 2 push forward with PWM < 1500, motors 3, 4 with > 1500
    (r,) = c.convert(wire("servo_output_raw_encode", 3_000_000, 0, 1287, 1287, 1713, 1713, 1500, 1500, 1500, 1500))
    expected = 3500 * (1713 - 1525) / 375
    assert r.rpm == pytest.approx(expected, rel=1e-3)


def _forward_rpm(c, offset_us):
    """The converter's forward RPM for all four thrusters ``offset_us`` forward of neutral."""
    (r,) = c.convert(wire("servo_output_raw_encode", 3_000_000, 0, 1500 - offset_us, 1500 - offset_us,
                          1500 + offset_us, 1500 + offset_us, 1500, 1500, 1500, 1500))
    return r.rpm


def test_the_simulators_own_messages_switch_the_thrusters_to_its_curve_without_dead_band():
    c = converter()
    assert _forward_rpm(c, 20) == 0.0 and c.thruster_report()["curve"] == "vehicle"
    # a ground station's SIM_STATE (another system) says nothing of the autopilot
    c.convert(wire("simstate_encode", 0, 0, 0, 0, 0, -9.8, 0, 0, 0, 0, 0, src=(255, 190)))
    assert _forward_rpm(c, 20) == 0.0
    c.convert(wire("sim_state_encode", 1, 0, 0, 0, *[0.0] * 17))
    assert _forward_rpm(c, 20) == pytest.approx(3500 * 20 / 400)
    assert _forward_rpm(c, -100) == pytest.approx(-3500 * 100 / 400)
    report = c.thruster_report()
    assert report["curve"] == "simulator" and "SIM_STATE" in report["why"]


def test_a_simulators_parameter_says_the_same():
    c = converter()
    c.convert(wire("param_value_encode", b"SIM_SPEEDUP", 1.0, 9, 900, 1))
    assert _forward_rpm(c, 20) == pytest.approx(3500 * 20 / 400)
    d = converter()
    d.convert(wire("param_value_encode", b"SERVO1_MIN", 1100.0, 9, 900, 1))
    assert _forward_rpm(d, 20) == 0.0


def test_mission_clock_wrap_and_reboot_keep_mission_time_monotonic():
    tm = MissionClock(reboot_backjump_s=2.0)
    assert tm.from_boot_ms(1000) == pytest.approx(1.0)
    assert tm.from_boot_ms(990) == pytest.approx(0.99)  # small out-of-order: not a reboot
    t_before = tm.from_boot_ms(500_000)
    t_after = tm.from_boot_ms(3_000)  # autopilot rebooted
    assert tm.reboots == 1 and t_after >= t_before
    assert tm.from_boot_ms(4_000) == pytest.approx(t_after + 1.0)
    tm2 = MissionClock()
    near_wrap = 2**32 - 500
    t1 = tm2.from_boot_ms(near_wrap)
    t2 = tm2.from_boot_ms(500)  # uint32 wrapped after 49.7 days
    assert tm2.wraps == 1 and t2 - t1 == pytest.approx(1.0, abs=1e-6)


def nav(valid=True, sigma=0.5, yaw=math.pi / 2, **kw):
    cov = np.eye(18) * 1e-4
    cov[0, 0] = cov[1, 1] = sigma**2
    base = dict(t_s=12.5, pos_n_m=(10.0, -4.0, 3.0), vel_n_m_s=(0.0, 1.5, 0.1),
                q_nb=tuple(euler_to_quat(0.0, 0.0, yaw)), cov=cov, valid=valid, reset_counter=3)
    base.update(kw)
    return SimpleNamespace(**base)


def test_odometry_frames_body_velocity_and_covariance():
    f = odometry_fields(nav())
    assert f["frame_id"] == mavlink2.MAV_FRAME_LOCAL_FRD == 20
    assert f["child_frame_id"] == mavlink2.MAV_FRAME_BODY_FRD == 12
    assert (f["x"], f["y"], f["z"]) == (10.0, -4.0, 3.0)
    # heading east (yaw 90°) moving east at 1.5 m/s = forward 1.5 m/s in body FRD
    assert (f["vx"], f["vy"], f["vz"]) == pytest.approx((1.5, 0.0, 0.1), abs=1e-9)
    assert f["pose_covariance"][0] == pytest.approx(0.25) and f["pose_covariance"][6] == pytest.approx(0.25)
    assert len(f["pose_covariance"]) == 21 and len(f["velocity_covariance"]) == 21
    assert f["reset_counter"] == 3 and f["time_usec"] == 12_500_000
    assert f["quality"] == 100


def test_quality_falls_with_sigma():
    cfg = OdometryConfig(sigma_best_m=0.5, sigma_worst_m=50.0)
    q = [quality_from_sigma(s, cfg) for s in (0.1, 0.5, 5.0, 50.0, 500.0)]
    # log scale: σ = 5 m is half-way (in log) between 0.5 m and 50 m
    assert q[0] == q[1] == 100 and q[2] in (50, 51) and q[3] == q[4] == 1


@pytest.mark.parametrize("bad", [dict(valid=False), dict(pos_n_m=(math.nan, 0.0, 0.0)), dict(q_nb=(0.0, 0.0, 0.0, 0.0))])
def test_invalid_solution_is_never_sent_as_plausible_numbers(bad):
    assert odometry_fields(nav(**bad)) is None
    f = odometry_fields(nav(**bad), OdometryConfig(invalid="failed"))
    assert f["quality"] == -1 and math.isnan(f["x"]) and math.isnan(f["vx"])


def test_origin_in_deg_e7_and_mm():
    o = GeoOrigin(math.radians(48.5), math.radians(-124.25), 12.5)
    f = gps_global_origin_fields(o, 1)
    assert (f["latitude"], f["longitude"], f["altitude"]) == (485_000_000, -1_242_500_000, 12_500)


def test_vision_position_delta_is_in_the_previous_body_frame():
    from adaptnav.service.transport.mavlink_convert import vision_position_delta_fields

    a = nav(t_s=10.0, pos_n_m=(0.0, 0.0, 0.0), yaw=math.pi / 2)
    b = nav(t_s=10.5, pos_n_m=(0.0, 2.0, 0.0), yaw=math.pi / 2 + 0.1)  # 2 m east while facing east
    f = vision_position_delta_fields(a, b)
    assert f["position_delta"] == pytest.approx([2.0, 0.0, 0.0], abs=1e-9)
    assert f["angle_delta"] == pytest.approx([0.0, 0.0, 0.1], abs=1e-9)
    assert f["time_delta_usec"] == 500_000
    assert vision_position_delta_fields(a, nav(valid=False)) is None


def test_odometry_from_the_filter_nav_state():
    from adaptnav.fusion.state import NavState

    cov = np.eye(18) * 0.04
    s = NavState(t_s=2.0, pos_n_m=np.array([1.0, 2.0, 3.0]), vel_n_m_s=np.array([0.5, 0.0, 0.0]),
                 q_nb=np.array([1.0, 0.0, 0.0, 0.0]), bias_acc_b_m_s2=np.zeros(3), bias_gyro_b_rad_s=np.zeros(3),
                 current_n_m_s=np.zeros(2), k_speed=1.0, cov=cov, valid=True, reset_counter=7)
    f = odometry_fields(s)
    assert (f["x"], f["vx"], f["reset_counter"], f["quality"]) == (1.0, 0.5, 7, 100)
    assert f["pose_covariance"][15] == pytest.approx(0.04)  # roll variance from the ATT block


def test_attitude_waits_for_the_autopilots_word_that_its_yaw_is_aligned():
    """ArduSub sends ATTITUDE with yaw 0 while its EKF3 starts (EKF_STATUS_REPORT flags 1024,
    then 0) and the aligned yaw once "initial yaw alignment complete" (flags 167): ATTITUDE is
    passed on only while the autopilot does not say its attitude is unaligned."""
    c = converter()

    def att(ms, yaw):
        return c.convert(wire("attitude_encode", ms, 0.0, 0.0, yaw, 0.0, 0.0, 0.0))

    def ekf(flags):
        c.convert(wire("ekf_status_report_encode", flags, 0.0, 0.0, 0.0, 0.0, 0.0))

    def text(t):
        c.convert(wire("statustext_encode", 6, t.encode()))

    assert len(att(1000, 3.0)) == 1  # nothing said yet: the settle test in the filter decides
    ekf(mavlink2.EKF_UNINITIALIZED)
    assert att(1100, 0.0) == []
    ekf(0)
    assert att(1200, 0.0) == []
    text("EKF3 IMU0 MAG0 initial yaw alignment complete")
    assert len(att(1300, 1.2)) == 1
    ekf(167)
    assert len(att(1400, 1.2)) == 1
    text("EKF3 IMU0 initialised")  # an EKF restart (forced reset): yaw 0 again until aligned
    assert att(1500, 0.0) == []
    assert c.rejected["attitude_not_aligned"] == 3
    acct = c.accounting()
    assert acct["EKF_STATUS_REPORT"]["status"] == "ignored" and "ATTITUDE" in acct["EKF_STATUS_REPORT"]["why"]
    # a ground station's texts are not the autopilot's word
    text_gcs = wire("statustext_encode", 6, b"EKF3 IMU0 MAG0 initial yaw alignment complete", src=(255, 190))
    c.convert(text_gcs)
    assert att(1600, 0.0) == []


def test_a_components_second_imu_is_another_stream_and_a_silent_stream_is_replaced():
    """HIGHRES_IMU's id tells a component's IMUs apart: two interleaved in one strapdown would
    corrupt it, so the second is ignored while the first streams; when the integrated stream
    goes silent (an autopilot's IMU failover, a driver restart) another takes over."""
    def highres(usec, imu_id, az=-9.81):
        return wire("highres_imu_encode", usec, 0, 0, az, 0, 0, 0, 0, 0, 0, 0, 0, 0, 20, 0x3F, imu_id)

    c = converter()
    (first,) = c.convert(highres(1_000_000, 0))
    assert c.convert(highres(1_005_000, 1, az=-9.7)) == []
    assert c.accounting()["HIGHRES_IMU"]["ignored"] == {"another IMU stream (HIGHRES_IMU from 1/1) is integrated": 1}
    (again,) = c.convert(highres(1_010_000, 0))
    assert c.imu_switches == 0
    # IMU 0 stops; IMU 1 goes on: ignored until the first has been silent for imu_stream_silent_s
    assert c.convert(highres(1_900_000, 1, az=-9.7)) == []
    (taken,) = c.convert(highres(2_100_000, 1, az=-9.7))
    assert c.imu_switches == 1 and taken.specific_force_b_m_s2[2] == pytest.approx(-9.7)
    assert c.integrated_imu_stream() == "HIGHRES_IMU from 1/1 #1"
    # and now IMU 0 is the other stream
    assert c.convert(highres(2_105_000, 0)) == []


def test_an_imu_message_without_an_id_field_is_one_stream_named_without_one():
    """pymavlink's message classes carry ``id`` (the message id, 116 for SCALED_IMU2): only a
    declared id field (HIGHRES_IMU's, RAW_IMU's) tells IMUs apart."""
    c = converter(imu_message="auto")
    (s,) = c.convert(wire("scaled_imu2_encode", 1000, 1, 2, -1000, 0, 0, 0, 5, 6, 7))
    assert c.integrated_imu_stream() == "SCALED_IMU2 from 1/1"


def test_a_reading_passed_on_again_is_one_sample_not_two():
    """A stream faster than its sensor repeats the reading (ArduSub SITL's barometer: 10 Hz
    streamed at 20 Hz; the UGPS extension's GPS_INPUT: each acoustic fix ~4×)."""
    from adaptnav.service.transport.mavlink_convert import WHY_REPEAT

    c = converter()
    assert len(c.convert(wire("scaled_pressure2_encode", 1000, 1500.25, 0.0, 1500))) == 1
    assert c.convert(wire("scaled_pressure2_encode", 1050, 1500.25, 0.0, 1500)) == []  # the same reading
    assert len(c.convert(wire("scaled_pressure2_encode", 1100, 1500.75, 0.0, 1500))) == 1
    # a steady reading is still a reading every repeat_window_s (a quantised sensor at rest)
    assert len(c.convert(wire("scaled_pressure2_encode", 3200, 1500.75, 0.0, 1500))) == 1
    assert c.accounting()["SCALED_PRESSURE2"]["ignored"] == {WHY_REPEAT: 1}

    def fix(yaw_cdeg, lat=483861418):
        return wire("gps_input_encode", 0, 0, 253, 0, 0, 3, lat, -1246305732, 0.0, 1.6, 65535,
                    0, 0, 0, 0, 0, 0, 21, yaw_cdeg, src=(255, 0))
    c = converter()
    c.convert(wire("attitude_encode", 5000, 0.0, 0.0, 0.0, 0, 0, 0))  # the boot clock
    assert len(c.convert(fix(100))) == 1
    assert c.convert(fix(250)) == []  # the vehicle's yaw beside the same fix
    assert len(c.convert(fix(250, lat=483861419))) == 1  # a new fix (1 cm north)
    # GPS_RAW_INT: the same position at a new fix time is a new fix
    c = converter()
    for fix_time_us in (1_000_000, 1_000_000, 1_200_000):
        c.convert(wire("gps_raw_int_encode", fix_time_us, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 9))
    account = c.accounting()["GPS_RAW_INT"]
    assert account["samples"] + sum(account.get("rejected", {}).values()) == 2 and account["ignored"] == {WHY_REPEAT: 1}
