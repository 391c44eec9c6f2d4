"""The real ArduSub logs in ../shared/data/mavlink replay to the end, with counters."""
import math
from pathlib import Path

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
    assert src.counters["messages_read"] > 40_000
    kinds = src.counters["samples_by_kind"]
    # 20 Hz ATTITUDE over the whole 316 s log, and the Ping echosounder's 28–41 m altitudes
    assert kinds["attitude"] > 6000
    alts = [s.altitude_m for s in samples if s.KIND == "altitude"]
    assert len(alts) > 800 and 27.0 < min(alts) and max(alts) < 42.0
    assert samples[-1].t_s - samples[0].t_s > 300.0
    assert any("RAW_IMU at 2.0 Hz is too slow" in m for m in src.missing)
    assert "imu" not in kinds and src.counters["rejected"]["imu_too_slow"] > 600


def test_ugps_log_gives_underwater_gps_fixes_near_the_surface():
    src, samples = replay("ardusub-4.1.1-bluerov2-ugps.tlog")
    usbl = [s for s in samples if s.KIND == "usbl"]
    assert len(usbl) > 900
    lat = [math.degrees(s.lat_rad) for s in usbl]
    assert 48.38 < min(lat) and max(lat) < 48.39  # the README's site
    depths = [s.pressure_pa for s in samples if s.KIND == "depth"]
    assert len(depths) > 600 and all(99_000 < p < 115_000 for p in depths)  # near the surface
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
