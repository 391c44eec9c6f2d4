"""A MAVLink log replays with the service's ``[mavlink.convert]`` (the section the live bridge
converts with), and a DataFlash log's thruster outputs (RCOU) become the same forward and
lateral RPM as the same outputs in SERVO_OUTPUT_RAW."""
import struct

import pytest

from adaptnav.service.runtime.replay import build_config, open_log, replay
from adaptnav.service.transport.mavlink_convert import ConvertConfig, MavlinkConverter, mavlink2
from adaptnav.service.transport.tlog_source import TlogSource

from .test_mavlink_time import Stream


def _pressure_log(path):
    """20 s of an autopilot: HIGHRES_IMU 50 Hz, ATTITUDE 10 Hz, the hull barometer
    (SCALED_PRESSURE, 1002 hPa) and the external depth sensor (SCALED_PRESSURE2, 1200 hPa)."""
    s = Stream()
    s.heartbeat(0.0)
    for k in range(1000):
        t = 1.0 + 0.02 * k
        s.emit(t, "highres_imu_encode", int(t * 1e6), 0.0, 0.0, -9.80665, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 20, 0x3F)
        if k % 5 == 0:
            s.emit(t, "attitude_encode", int(t * 1000), 0.0, 0.0, 0.3, 0, 0, 0)
        if k % 10 == 0:
            s.emit(t, "scaled_pressure_encode", int(t * 1000), 1002.0, 0.0, 3000)
            s.emit(t, "scaled_pressure2_encode", int(t * 1000), 1200.0, 0.0, 1500)
    return s.write(path)


def test_replay_converts_with_the_mavlink_convert_section(tmp_path):
    log = _pressure_log(tmp_path / "pressure.tlog")
    default = replay(open_log(log), build_config(), tmp_path / "default", plots=False, progress=False).summary
    assert default["message_types"]["SCALED_PRESSURE2"]["status"] == "used"
    assert default["message_types"]["SCALED_PRESSURE"]["status"] == "ignored"
    # WHEN the config says depth comes from SCALED_PRESSURE (a vehicle whose depth sensor is the first)
    cfg = build_config(overrides=['mavlink.convert.depth_message="SCALED_PRESSURE"'])
    other = replay(open_log(log), cfg, tmp_path / "configured", plots=False, progress=False).summary
    # THEN the replay converts as the live bridge would with that config
    assert other["message_types"]["SCALED_PRESSURE"]["status"] == "used"
    assert other["message_types"]["SCALED_PRESSURE2"]["status"] == "ignored"
    assert other["message_types"]["SCALED_PRESSURE"]["samples"] == default["message_types"]["SCALED_PRESSURE2"]["samples"]


def _dataflash_rcou(path, pwm_rows):
    """A DataFlash log (ArduPilot's binary format: FMT records, then records) with RCOU only."""
    size = {"B": 1, "H": 2, "Q": 8, "n": 4, "N": 16, "Z": 64}

    def fmt(type_id, name, form, labels):
        return struct.pack("<BBBBB4s16s64s", 0xA3, 0x95, 128, type_id, 3 + sum(size[c] for c in form),
                           name.encode(), form.encode(), labels.encode())

    with open(path, "wb") as f:
        f.write(fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
        f.write(fmt(65, "RCOU", "QHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6"))
        for k, pwm in enumerate(pwm_rows):
            f.write(struct.pack("<BBBQ6H", 0xA3, 0x95, 65, 1_000_000 + 100_000 * k, *pwm))
    return path


@pytest.mark.parametrize("pwm", [(1700, 1300, 1700, 1300, 1500, 1500),   # strafe to starboard
                                 (1300, 1300, 1700, 1700, 1500, 1500),   # forward
                                 (1620, 1500, 1580, 1450, 1500, 1500)])  # a mix
def test_dataflash_rcou_gives_the_forward_and_lateral_rpm_of_servo_output_raw(tmp_path, pwm):
    log = _dataflash_rcou(tmp_path / "rcou.BIN", [pwm] * 5)
    (df, *_) = [s for s in TlogSource(log) if s.KIND == "rpm"]
    c = MavlinkConverter(ConvertConfig())
    mav = mavlink2.MAVLink(None, 1, 1)
    msg = mav.decode(bytearray(mav.servo_output_raw_encode(1_000_000, 0, *pwm, 1500, 1500).pack(mav)))
    (tl,) = c.convert(msg)
    assert (df.rpm, df.sway_rpm) == pytest.approx((tl.rpm, tl.sway_rpm))
    assert df.sway_rpm != 0.0 or pwm[0] + pwm[2] == pwm[1] + pwm[3]  # lateral thrust is not lost
