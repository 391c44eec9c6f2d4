"""The real ArduSub logs in ../shared/data/mavlink replay to the end, with counters."""
import math
from pathlib import Path

import numpy as np
import pytest

from adaptnav.service.transport.tlog_source import TlogConfig, TlogSource

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mavlink"
pytestmark = pytest.mark.realdata


def log_path(name):
    p = DATA / name
    if not p.is_file():
        pytest.skip(f"real data absent: {p}")
    return p


def replay(name, **cfg):
    src = TlogSource(log_path(name), TlogConfig(**cfg))
    samples = list(src)
    ts = [s.t_s for s in samples]
    assert ts == sorted(ts), "samples must come out in replay order"
    assert all(math.isfinite(t) for t in ts)
    return src, samples


def test_corrupt_frames_log_counts_all_1967_and_keeps_going():
    src, samples = replay("ardusub-4.1.0-corrupt-frames.tlog")
    assert src.counters["corrupt_frames"] == 1967  # the README's count of bad frames
    # all but 4 (camera-manager messages of another dialect) are frames QGC logged with their
    # trailing zeros cut after the CRC: the Ping driver's (component 194) own DISTANCE_SENSOR
    # and the ground station's commands, restored
    assert src.counters["repaired_frames"] == {"DISTANCE_SENSOR": 1949, "COMMAND_LONG": 4, "COMMAND_ACK": 4,
                                               "PARAM_REQUEST_LIST": 6}
    assert src.counters["messages_read"] > 40_000
    kinds = src.counters["samples_by_kind"]
    # 20 Hz ATTITUDE over the whole 316 s log, and the Ping echosounder's altitudes at ~9 Hz:
    # 28–41 m when it states a quality; the restored ones are those with quality 0 ("unknown",
    # the byte QGC cut), a few of them short false returns
    assert kinds["attitude"] > 6000
    alts = np.array([s.altitude_m for s in samples if s.KIND == "altitude"])
    assert len(alts) > 2850 and 27.0 < np.median(alts) < 42.0 and alts.min() > 15.0 and alts.max() < 42.0
    assert np.mean((alts > 27.0) & (alts < 42.0)) > 0.95
    assert samples[-1].t_s - samples[0].t_s > 300.0
    assert any("RAW_IMU at 2.0 Hz is too slow" in m for m in src.missing)
    assert "imu" not in kinds and src.counters["rejected"]["imu_too_slow"] > 600


def test_ugps_log_gives_underwater_gps_fixes_near_the_surface():
    src, samples = replay("ardusub-4.1.1-bluerov2-ugps.tlog")
    usbl = [s for s in samples if s.KIND == "usbl"]
    # the UGPS extension sends each acoustic fix ~4× (1011 GPS_INPUT at 3.8 Hz, 106 positions):
    # each is one sample (a position it keeps sending longer: one every repeat_window_s), the
    # repeats are accounted as such (fused again they counted as several fixes)
    assert 140 < len(usbl) < 200
    # (the same position within 2 s only where the message says something new: 3 of 1011 change
    # satellites_visible or fix_type)
    assert sum(b.t_s - a.t_s < 2.0 for a, b in zip(usbl, usbl[1:])
               if (a.lat_rad, a.lon_rad, a.sigma_h_m) == (b.lat_rad, b.lon_rad, b.sigma_h_m)) <= 3
    gps_input = src.counters["message_types"]["GPS_INPUT"]
    assert gps_input["messages"] == 1011 and sum(gps_input["ignored"].values()) > 800
    lat = [math.degrees(s.lat_rad) for s in usbl]
    assert 48.38 < min(lat) and max(lat) < 48.39  # the README's site
    depths = [s.pressure_pa for s in samples if s.KIND == "depth"]
    assert len(depths) > 450 and all(99_000 < p < 115_000 for p in depths)  # near the surface
    # ArduSub echoes GPS_INPUT as GPS_RAW_INT (GPS1_TYPE=14): not fused a second time
    assert src.counters["rejected"]["gnss_echo_of_gps_input"] > 500


def test_bench_log_has_no_depth_and_says_so():
    src, samples = replay("ardusub-4.1.2-bench.tlog")
    rolls = [s.roll_rad for s in samples if s.KIND == "attitude"]
    assert len(rolls) > 2000
    assert abs(math.degrees(sorted(rolls)[len(rolls) // 2]) + 92.0) < 3.0  # on its side
    assert any("no depth" in m for m in src.missing)
    assert src.counters["corrupt_frames"] == 0


def test_dataflash_bin_gives_a_usable_imu_stream():
    src, samples = replay("ardusub-4.1.0-small.BIN")
    imu = [s for s in samples if s.KIND == "imu"]
    assert len(imu) > 500
    # stationary: |specific force| ≈ g
    g = sorted(math.dist((0, 0, 0), s.specific_force_b_m_s2) for s in imu)[len(imu) // 2]
    assert abs(g - 9.81) < 0.2
    assert not any("IMU" in m for m in src.missing)


def test_slow_imu_can_be_kept_on_request():
    src, samples = replay("ardusub-4.1.2-bench.tlog", drop_slow_imu=False)
    assert src.counters["samples_by_kind"]["imu"] > 400


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        TlogSource(tmp_path / "nope.tlog")


def test_truncated_log_reads_what_is_there(tmp_path):
    data = log_path("ardusub-4.1.2-bench.tlog").read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 3 + 7])  # mid-frame
    src, samples = replay_path(cut)
    assert src.counters["messages_read"] > 5000 and samples


def replay_path(p):
    src = TlogSource(p)
    return src, list(src)


def write_tlog(path, frames):
    """A .tlog is (8-byte big-endian µs wall time + one MAVLink frame) records."""
    import struct

    with open(path, "wb") as f:
        for i, frame in enumerate(frames):
            f.write(struct.pack(">Q", 1_700_000_000_000_000 + i * 1000) + bytes(frame))


def test_synthetic_log_duplicates_nan_reboot_and_a_fast_imu(tmp_path):
    from adaptnav.service.transport.mavlink_convert import mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
    frames = [hb.pack(mav)]
    for i in range(100):  # 2 s of 50 Hz HIGHRES_IMU from boot time 100 s
        t_us = 100_000_000 + i * 20_000
        frames.append(mav.highres_imu_encode(t_us, 0, 0, -9.8, 0, 0, 0.01, 0, 0, 0, 0, 0, 0, 20, 0x3F).pack(mav))
        if i % 10 == 0:
            att = mav.attitude_encode(t_us // 1000, 0.1, 0.0, 0.0, 0, 0, 0).pack(mav)
            frames += [att, att]  # logged twice
    frames.append(mav.attitude_encode(102_000, math.nan, 0.0, 0.0, 0, 0, 0).pack(mav))
    frames.append(mav.attitude_encode(5_000, 0.2, 0.0, 0.0, 0, 0, 0).pack(mav))  # rebooted: boot time 5 s
    p = tmp_path / "synthetic.tlog"
    write_tlog(p, frames)
    src, samples = replay_path(p)
    kinds = src.counters["samples_by_kind"]
    assert kinds["imu"] >= 98  # 50 Hz ≥ 20 Hz: usable (first sample has no rate yet)
    assert kinds["attitude"] == 11  # 10 unique + the one after the reboot
    assert src.counters["rejected"]["duplicate_time"] == 10
    assert src.counters["rejected"]["non_finite"] == 1
    assert src.counters["reboots"] == 1
    assert samples[-1].KIND == "attitude" and samples[-1].roll_rad == pytest.approx(0.2) and samples[-1].t_s >= 101.98
    ts = [s.t_s for s in samples]
    assert ts == sorted(ts)
    assert not any("IMU" in m for m in src.missing)


def test_frames_logged_with_trailing_zeros_cut_after_the_crc_are_restored_and_used(tmp_path):
    """A QGC tlog of a BlueOS vehicle with Water Linked's underwater GPS: every GPS_INPUT (its
    ``yaw`` extension is 0) fails pymavlink's CRC as stored; restored, each is a fix. A frame
    garbled on top of that stays corrupt and is not used."""
    from adaptnav.service.transport.mavlink_convert import mavlink2
    from tests.service.mavlink_wire import qgc_logged

    autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    ugps = mavlink2.MAVLink(None, srcSystem=1, srcComponent=220)
    frames = [autopilot.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                         0, 0, 4).pack(autopilot)]
    lat0_e7, lon0_e7 = 473_977_420, 85_455_940
    for i in range(40):  # 4 s of 10 Hz ATTITUDE (the boot clock), a fix every 0.5 s
        frames.append(autopilot.attitude_encode(100_000 + 100 * i, 0.0, 0.0, 0.3, 0, 0, 0).pack(autopilot))
        if i % 5 == 2:
            fix = ugps.gps_input_encode(0, 0, 253, 0, 0, 3, lat0_e7 + 10 * i, lon0_e7, 0.0, 1.6, 65535,
                                        0, 0, 0, 0, 0, 0, 12, 0)
            frames.append(qgc_logged(fix, ugps))
    garbled = bytearray(frames[-1] if frames[-1][7] == 232 else frames[-2])
    garbled[14] ^= 0x40  # one bit of the latitude
    frames.append(bytes(garbled))
    p = tmp_path / "qgc-bluos-ugps.tlog"
    write_tlog(p, frames)
    src, samples = replay_path(p)
    fixes = [s for s in samples if s.KIND == "usbl"]
    assert src.counters["corrupt_frames"] == 9  # as stored: 8 fixes + the garbled one
    assert src.counters["repaired_frames"] == {"GPS_INPUT": 8}
    assert len(fixes) == 8
    assert [round(math.degrees(f.lat_rad) * 1e7) for f in fixes] == [lat0_e7 + 10 * i for i in range(2, 40, 5)]


def _pymavlink_reads(path) -> tuple[list, int]:
    """pymavlink's own log reader on ``path``: (type, record stamp, frame bytes, a damaged
    frame's reason) of each message, and the bytes its parser holds at the end."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    theirs = []
    while (m := conn.recv_match()) is not None:
        theirs.append((m.get_type(), m._timestamp, bytes(m.get_msgbuf()), getattr(m, "reason", None)))
    left = conn.mav.buf_len()
    conn.close()
    return theirs, left


def _tlog_reader_reads(path) -> tuple[list, int]:
    from adaptnav.service.transport.mavlink_frames import TlogReader

    reader = TlogReader(path)
    ours = [(m.get_type(), m._timestamp, bytes(m.get_msgbuf()), getattr(m, "reason", None)) for m in reader]
    left = reader.mav.buf_len()
    reader.close()
    return ours, left


def _parse_char_reads(path) -> tuple[list, int]:
    """pymavlink's parser fed a tlog as its log reader feeds it (a record's stamp, then
    ``bytes_needed()`` at a time until a message comes; robust parsing), without its
    reader's start-of-file index: the reference for every frame, whole or damaged."""
    import struct

    from pymavlink.dialects.v20 import ardupilotmega

    mav = ardupilotmega.MAVLink(None)
    mav.robust_parsing = True
    data, pos, t_s, out = Path(path).read_bytes(), 0, None, []
    while True:
        if pos + 8 <= len(data):
            t_s = struct.unpack_from(">Q", data, pos)[0] * 1e-6
        pos = min(pos + 8, len(data))
        while True:
            chunk = data[pos:pos + mav.bytes_needed()]
            pos += len(chunk)
            msg = mav.parse_char(chunk)
            if msg is not None:
                out.append((msg.get_type(), t_s, bytes(msg.get_msgbuf()), getattr(msg, "reason", None)))
                break
            if not chunk:
                return out, mav.buf_len()


def test_the_tlog_reader_reads_frames_of_every_kind_as_pymavlinks_parser_does(tmp_path):
    """Frames of every kind a recorder may hold, read as pymavlink's parser reads them: v2,
    v1 (one of 2 bytes of payload after a v2 frame: the parser's first read of 12 bytes then
    takes 2 bytes of the next record's stamp, and the frame after it is lost), signed, a
    payload cut of its trailing zeros, a flipped bit (CRC), an unknown message id, incompat
    flags it does not know, garbage between records, and a last frame cut by the file's end."""
    from adaptnav.service.transport.mavlink_convert import mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    signer = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    signer.signing.secret_key, signer.signing.sign_outgoing = bytes(range(32)), True
    signer.signing.link_id, signer.signing.timestamp = 1, 1_000
    v2 = [mav.attitude_encode(1000 * i, 0.1, -0.2, 0.3, 0.0, 0.0, 0.01).pack(mav) for i in range(6)]
    v1_short = mav.param_request_list_encode(1, 1).pack(mav, force_mavlink1=True)
    v1 = mav.heartbeat_encode(12, 3, 0, 0, 4).pack(mav, force_mavlink1=True)
    signed = signer.attitude_encode(5000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(signer)
    zeros = mav.scaled_pressure2_encode(7000, 0.0, 0.0, 0).pack(mav)  # payload truncated to 4 bytes
    flipped = bytearray(v2[2])
    flipped[14] ^= 0x08
    unknown = bytearray(v2[3])
    unknown[7:10] = (0xEE, 0xEE, 0x0E)  # msgid 0x0EEEEE
    incompat = bytearray(v2[4])
    incompat[2] = 0x02
    frames = [v2[0], v1, signed, zeros, bytes(flipped), v2[5], bytes(unknown), bytes(incompat), v2[1],
              v1_short, v2[2], b"\x00\x17garbage", v1_short, v1_short, v2[0], v2[1][:9]]
    path = tmp_path / "kinds.tlog"
    write_tlog(path, frames)
    theirs, left = _parse_char_reads(path)
    kinds = [m[0] for m in theirs]
    assert {"ATTITUDE", "HEARTBEAT", "SCALED_PRESSURE2", "UNKNOWN_978670", "PARAM_REQUEST_LIST"} <= set(kinds)
    assert kinds.count("BAD_DATA") >= 4
    assert _tlog_reader_reads(path) == (theirs, left)


@pytest.mark.parametrize("name", ["ardusub-4.1.0-corrupt-frames.tlog", "ardusub-4.1.2-bench.tlog"])
def test_the_tlog_reader_reads_what_pymavlink_reads(name, tmp_path):
    """The replay's own tlog loop gives pymavlink's log reader's messages (damaged frames
    included, each with its record's stamp), also on a file cut inside a frame."""
    data = log_path(name).read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 11])
    for path in (log_path(name), cut):
        theirs, left = _pymavlink_reads(path)
        assert len(theirs) > 10_000 and _tlog_reader_reads(path) == (theirs, left)
