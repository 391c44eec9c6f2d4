"""The MAVLink time model and the message variants of real vehicles, on synthetic streams
encoded with pymavlink's own encoder and written as real ``.tlog`` files (8-byte receive
stamp + frame), read back through :class:`TlogSource` as a log would be.

Variants: UNIX ``time_usec`` at 100 Hz, a DVL driver as system 255 sending
VISION_POSITION_DELTA with ``time_usec = 0``, GPS_INPUT with ``time_usec = 0``, a fix that
arrives before any boot-clock message, a source with no boot clock at all, a reboot,
SYSTEM_TIME pairing, and message types nobody handles.
"""
import math
import struct

import numpy as np
import pytest

from adaptnav.service.transport.mavlink_convert import ConvertConfig, MavlinkConverter, mavlink2
from adaptnav.service.transport.tlog_source import TlogConfig, TlogSource

UNIX0 = 1_760_000_000.0  # the recording computer's wall clock at boot time 0 (s)


class Stream:
    """Frames with receive stamps; ``emit(t_recv_boot_s, msg, src)`` records one message
    as received ``t_recv_boot_s`` after the autopilot booted (plus a transport delay)."""

    def __init__(self, delay_s=0.004):
        self.records: list[tuple[float, bytes]] = []
        self.delay_s = delay_s
        self._mavs = {}

    def emit(self, t_boot_s, name, *args, src=(1, 1)):
        mav = self._mavs.get(src)
        if mav is None:
            mav = self._mavs[src] = mavlink2.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        frame = getattr(mav, name)(*args).pack(mav)
        self.records.append((UNIX0 + t_boot_s + self.delay_s, bytes(frame)))

    def heartbeat(self, t):
        self.emit(t, "heartbeat_encode", mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)

    def write(self, path):
        with open(path, "wb") as f:
            for t, frame in self.records:
                f.write(struct.pack(">Q", int(round(t * 1e6))) + frame)
        return path


def read(path, **convert):
    src = TlogSource(path, TlogConfig(convert=ConvertConfig(**convert)))
    samples = list(src)
    ts = [s.t_s for s in samples]
    assert ts == sorted(ts)
    return src, samples


def imu_highres(s, t_boot, t_usec, src=(1, 1)):
    s.emit(t_boot, "highres_imu_encode", t_usec, 0.0, 0.0, -9.80665, 0.0, 0.0, 0.001, 0, 0, 0, 0, 0, 0, 0, 0x3F,
           src=src)


def test_unix_time_usec_imu_at_100_hz_is_placed_on_the_boot_clock(tmp_path):
    s = Stream()
    s.heartbeat(0.0)
    for k in range(1000):  # 10 s of 100 Hz HIGHRES_IMU stamped in UNIX µs
        t = 20.0 + k * 0.01
        imu_highres(s, t, int(round((UNIX0 + t) * 1e6)))
        if k % 5 == 0:
            s.emit(t, "attitude_encode", int(round(t * 1000)), 0.0, 0.0, 0.5, 0, 0, 0)
    src, samples = read(s.write(tmp_path / "unix_imu.tlog"))
    imu = [x for x in samples if x.KIND == "imu"]
    att = [x for x in samples if x.KIND == "attitude"]
    # every sample but the first (no rate known yet) passes the strapdown rate check
    assert len(imu) == 999 and src.counters["rejected"].get("imu_too_slow", 0) == 1
    rate = src.counters["message_types"]["HIGHRES_IMU"]["rate_hz"]
    assert rate == pytest.approx(100.0, rel=1e-3)
    # one mission clock: the UNIX stamps land on the boot clock within the transport delay
    assert imu[0].t_s == pytest.approx(20.01, abs=0.005) and att[0].t_s == pytest.approx(20.0, abs=1e-9)
    assert np.allclose(np.diff([x.t_s for x in imu]), 0.01, atol=1e-6)
    assert src.counters["clock"]["unix_reference"] == "receive"


@pytest.mark.parametrize("clock_off_s", [2.0, -5.0])
def test_an_imu_keeping_its_own_unix_clock_is_placed_by_its_reception(tmp_path, clock_off_s):
    """A companion's INS whose UNIX clock is 2 s ahead of (or 5 s behind) the recording
    computer's: its stamps would put each sample 2 s early (or 5 s late, too late to fuse);
    placed by its lag, each lands at its reception less the transport delay, on the others'
    clock, and the clock report names the source."""
    s = Stream()
    s.heartbeat(0.0)
    for k in range(1000):
        t = 20.0 + k * 0.01
        imu_highres(s, t, int(round((UNIX0 + t + clock_off_s) * 1e6)), src=(1, 200))
        if k % 5 == 0:
            s.emit(t, "attitude_encode", int(round(t * 1000)), 0.0, 0.0, 0.5, 0, 0, 0)
    src, samples = read(s.write(tmp_path / "own_clock.tlog"))
    imu = [x for x in samples if x.KIND == "imu"]
    assert len(imu) == 999
    assert imu[0].t_s == pytest.approx(20.0, abs=0.01) and imu[-1].t_s == pytest.approx(29.99, abs=0.01)
    assert np.allclose(np.diff([x.t_s for x in imu]), 0.01, atol=1e-6)
    assert src.counters["clock"]["sources_off_the_clock"] == {"1/200": pytest.approx(-clock_off_s, abs=0.01)}


def test_dvl_from_a_companion_system_255_as_vision_position_delta(tmp_path):
    s = Stream()
    s.heartbeat(0.0)
    for k in range(50):
        t = 5.0 + 0.2 * k
        s.emit(t, "attitude_encode", int(t * 1000), 0.0, 0.0, 0.0, 0, 0, 0)
        if k % 2 == 0:  # 2.5 Hz DVL: 0.4 s deltas, time_usec = 0 (BlueOS sends none)
            conf = 100.0 if k < 40 else 0.0
            s.emit(t, "vision_position_delta_encode", 0, 400_000, [0.0, 0.0, 0.04], [0.4, -0.08, 0.0], conf,
                   src=(255, 0))
    s.emit(9.0, "vision_position_delta_encode", 0, 400_000, [0.0, 0.0, 0.5], [0.4, 0.0, 0.0], 100.0,
           src=(255, 0))  # spun 29° within one delta: rejected, not averaged
    s.emit(9.1, "vision_position_delta_encode", 0, 400_000, [0, 0, 0], [0.4, 0, 0], 100.0, src=(254, 1))
    log = s.write(tmp_path / "dvl.tlog")
    src, samples = read(log, dvl_delta="mean")
    dvl = [x for x in samples if x.KIND == "dvl"]
    assert len(dvl) == 25
    good = [d for d in dvl if d.valid]
    assert len(good) == 20 and not any(d.valid for d in dvl[20:])
    # 0.4 m over 0.4 s forward, −0.08 m sideways; the mean is rotated by half the 0.04 rad yaw
    v = np.array(good[0].vel_d_m_s)
    assert np.linalg.norm(v[:2]) == pytest.approx(math.hypot(1.0, 0.2), rel=1e-6)
    assert math.atan2(v[1], v[0]) == pytest.approx(math.atan2(-0.2, 1.0) - 0.02, abs=1e-6)
    assert math.isnan(good[0].sigma_m_s)  # confidence 100: the configured σ
    # time of validity: mid-interval, on the mission (boot) clock via the receive stamps
    assert good[0].t_s == pytest.approx(5.0 - 0.2, abs=0.01)
    assert src.counters["rejected"]["dvl_rotating"] == 1
    assert src.counters["rejected"]["other_system"] == 1  # system 254 is not configured
    assert src.counters["message_types"]["VISION_POSITION_DELTA"]["status"] == "used"
    # BlueOS's driver (the default): delta/dt is the ping's velocity in the current frame, at the message
    _, samples = read(log)
    ping = [x for x in samples if x.KIND == "dvl" and x.valid][0]
    assert ping.vel_d_m_s == pytest.approx((1.0, -0.2, 0.0)) and ping.t_s == pytest.approx(5.0, abs=0.01)


def test_dvl_confidence_maps_to_sigma_like_blueos():
    c = MavlinkConverter()
    c.convert(mavlink2.MAVLink(None, 1, 1).decode(bytearray(mavlink2.MAVLink(None, 1, 1).heartbeat_encode(
        mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(mavlink2.MAVLink(None, 1, 1)))))
    mav = mavlink2.MAVLink(None, 255, 0)
    c.convert(mav.decode(bytearray(mavlink2.MAVLink(None, 1, 1).attitude_encode(1000, 0, 0, 0, 0, 0, 0).pack(
        mavlink2.MAVLink(None, 1, 1)))))
    msg = mav.decode(bytearray(mav.vision_position_delta_encode(0, 200_000, [0, 0, 0], [0.2, 0, 0], 75.0).pack(mav)))
    (d,) = c.convert(msg)
    assert d.valid and d.sigma_m_s == pytest.approx(0.1)  # fom = 0.4·(1 − 0.75)


def test_gps_input_with_time_usec_zero_and_a_fix_before_any_boot_clock_is_held(tmp_path):
    s = Stream()
    # the underwater GPS's first fix arrives before the autopilot said anything
    s.emit(0.5, "gps_input_encode", 0, 0, 253, 0, 0, 3, 483861418, -1246305732, 0.0, 1.6, 65535,
           0, 0, 0, 0, 0, 0, 21, 0, src=(255, 0))
    s.heartbeat(0.9)
    for k in range(40):
        t = 1.0 + 0.1 * k
        s.emit(t, "attitude_encode", int(round(t * 1000)), 0.0, 0.0, 0.0, 0, 0, 0)
        if k % 10 == 5:
            s.emit(t, "gps_input_encode", 0, 0, 253, 0, 0, 3, 483861418 + k, -1246305732, 0.0, 1.6, 65535,
                   0, 0, 0, 0, 0, 0, 21, 0, src=(255, 0))
    src, samples = read(s.write(tmp_path / "fix_first.tlog"))
    usbl = [x for x in samples if x.KIND == "usbl"]
    assert len(usbl) == 5, "the early fix is held, not dropped"
    assert usbl[0].t_s == pytest.approx(0.5, abs=0.01)  # placed by its receive stamp
    assert [u.t_s for u in usbl[1:]] == pytest.approx([1.5, 2.5, 3.5, 4.5], abs=0.01)
    assert src.counters["clock"]["held_samples"] == 1
    assert "no_time_yet" not in src.counters["rejected"] and "no_time" not in src.counters["rejected"]


def test_a_source_without_a_boot_clock_runs_on_unix_time(tmp_path):
    s = Stream()
    for k in range(1000):  # a companion IMU in UNIX time, no autopilot at all
        t = 100.0 + 0.01 * k
        imu_highres(s, t, int(round((UNIX0 + t) * 1e6)), src=(2, 1))
    src, samples = read(s.write(tmp_path / "unix_only.tlog"))
    imu = [x for x in samples if x.KIND == "imu"]
    assert len(imu) == 999  # held until the hold expired, then all placed (the first: no rate yet)
    assert src.counters["clock"]["base"] == "unix"
    assert np.allclose(np.diff([x.t_s for x in imu]), 0.01, atol=1e-6)


def test_reboot_keeps_the_time_the_autopilot_was_down(tmp_path):
    s = Stream()
    s.heartbeat(0.0)
    for k in range(30):
        s.emit(100.0 + 0.1 * k, "attitude_encode", int(round((100.0 + 0.1 * k) * 1000)), 0.1, 0, 0, 0, 0, 0)
    # rebooted: 20 s later on the receive clock, boot clock at 2 s again
    for k in range(10):
        s.records.append((UNIX0 + 122.9 + 0.1 * k + 0.004, bytes(
            mavlink2.MAVLink(None, 1, 1).attitude_encode(int((2.0 + 0.1 * k) * 1000), 0.2, 0, 0, 0, 0, 0).pack(
                mavlink2.MAVLink(None, 1, 1)))))
    src, samples = read(s.write(tmp_path / "reboot.tlog"))
    after = [x for x in samples if x.roll_rad == pytest.approx(0.2)]
    assert src.counters["reboots"] == 1
    assert after[0].t_s == pytest.approx(122.9, abs=0.02)  # not 102.9: the down time is kept


def test_system_time_pairs_unix_and_boot_exactly(tmp_path):
    s = Stream(delay_s=0.3)  # a slow link: receive stamps would be 0.3 s late
    s.heartbeat(0.0)
    for k in range(20):
        t = 10.0 + 0.1 * k
        s.emit(t, "system_time_encode", int(round((UNIX0 + t) * 1e6)), int(round(t * 1000)))
        s.emit(t, "gps_input_encode", int(round((UNIX0 + t - 0.05) * 1e6)), 0, 253, 0, 0, 3, 483861418,
               -1246305732, 0.0, 1.6, 65535, 0, 0, 0, 0, 0, 0, 21, 0, src=(1, 220))
    src, samples = read(s.write(tmp_path / "system_time.tlog"))
    usbl = [x for x in samples if x.KIND == "usbl"]
    assert src.counters["clock"]["unix_reference"] == "SYSTEM_TIME"
    assert usbl[0].t_s == pytest.approx(9.95, abs=1e-3)  # its own UNIX stamp, not reception


def test_every_message_type_is_accounted_for(tmp_path):
    s = Stream()
    s.heartbeat(0.0)
    s.emit(1.0, "attitude_encode", 1000, 0, 0, 0, 0, 0, 0)
    s.emit(1.0, "vfr_hud_encode", 0, 0, 0, 0, 0, 0)
    s.emit(1.1, "wind_cov_encode", 1_100_000, 0, 0, 0, 0, 0, 0, 0, 0)  # nobody handles it
    src, _ = read(s.write(tmp_path / "types.tlog"))
    types = src.counters["message_types"]
    assert types["ATTITUDE"]["status"] == "used"
    assert types["VFR_HUD"]["status"] == "ignored" and "autopilot" in types["VFR_HUD"]["why"]
    assert types["WIND_COV"]["status"] == "unknown"
    assert types["HEARTBEAT"]["status"] == "ignored"
    assert sum(t["messages"] for t in types.values()) == src.counters["messages_read"]


def test_gps_raw_int_as_an_acoustic_source_becomes_a_position_fix(tmp_path):
    s = Stream()
    s.heartbeat(0.0)
    s.emit(1.0, "gps_raw_int_encode", 1_000_000, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 9)
    _, gnss = read(s.write(tmp_path / "g.tlog"))
    _, acoustic = read(tmp_path / "g.tlog", gps_raw_int_source="acoustic")
    assert [x.KIND for x in gnss] == ["gnss"] and [x.KIND for x in acoustic] == ["usbl"]


@pytest.mark.parametrize("name, gps_type, kind", [("GPS_TYPE", 14, "usbl"), ("GPS1_TYPE", 14, "usbl"),
                                                   ("GPS_TYPE", 1, "gnss"), ("GPS_TYPE2", 14, "gnss")])
def test_the_autopilot_s_gps_type_says_whether_its_fixes_are_an_underwater_gps_s(tmp_path, name, gps_type, kind):
    """By default (``gps_raw_int_source = "auto"``) a GPS_RAW_INT is an acoustic fix when the
    autopilot's first GPS is a MAVLink one (GPS_TYPE, from 4.6 GPS1_TYPE, = 14: GPS_INPUT from the
    companion — the real BlueROV2 UGPS log says 14), a surface fix otherwise."""
    s = Stream()
    s.heartbeat(0.0)
    s.emit(0.5, "param_value_encode", name.encode(), float(gps_type), 2, 900, 10)
    s.emit(1.0, "gps_raw_int_encode", 1_000_000, 3, 483861418, -1246305732, 0, 160, 65535, 0, 0, 9)
    src, samples = read(s.write(tmp_path / "g.tlog"))
    assert [x.KIND for x in samples] == [kind]
    assert src.counters["gps_fixes"]["taken_as"] == ("acoustic" if kind == "usbl" else "gnss")


def test_the_filter_takes_the_dvl_sigma_when_the_driver_says_it_is_worse():
    from adaptnav.fusion.aiding import dvl as aid_dvl
    from adaptnav.fusion.samples import DvlSample
    from adaptnav.fusion.state import initial_nominal

    x = initial_nominal(vel_n_m_s=(1.0, 0.0, 0.0))
    args = (x, np.zeros(3), np.zeros(3), np.eye(3), 0.02)
    r_cfg = aid_dvl.measure(DvlSample(1.0, (1.0, 0.0, 0.0)), *args).R
    r_low = aid_dvl.measure(DvlSample(1.0, (1.0, 0.0, 0.0), sigma_m_s=0.1), *args).R
    r_good = aid_dvl.measure(DvlSample(1.0, (1.0, 0.0, 0.0), sigma_m_s=0.001), *args).R
    assert np.allclose(np.diag(r_cfg), 0.02**2) and np.allclose(np.diag(r_low), 0.1**2)
    assert np.allclose(r_good, r_cfg)  # a driver never makes it more trusted than configured
