"""A DataFlash log (``.BIN``) of a newer ArduSub, record by record: GPS fixes, GPS time, the
simulator's truth, the EKF's word on its attitude, and every record type accounted for.

The logs are written here (:mod:`tests.service.dataflash_log`) with ArduSub 4.7's record
layouts; the expected values are the ones written, not recomputed by the code under test.
"""
import math

import pytest

from adaptnav.service.transport.tlog_source import TlogSource

from .dataflash_log import DataflashWriter, ardusub_formats

LAT0, LON0 = -35.363262, 149.165237
GPS_WEEK, GPS_MS0 = 2446, 545_352_800  # 2026-11-28 07:29 UTC in GPS time (the SITL run's)
UNIX_OF_GPS_MS0 = 1_795_850_934.8  # 315964800 + 2446·604800 + 545352.8 − 18 (GPS − UTC)
M_PER_DEG_LAT = 110_948.0  # a degree of latitude at 35.36° (WGS-84 meridian arc)


def _log(path, seconds=20.0, t0_s=50.0, dive_at_s=None, msgs=(), extra=None, formats=None, records=()):
    """An armed ArduSub at rest at the surface (then, from ``dive_at_s``, 3 m deep and moving
    north at 0.5 m/s): IMU 0 and 1 at 25 Hz, ATT/BARO 0 and 1/RCOU/SIM at 10 Hz, SIM2 at
    50 Hz, GPS and GPA at 5 Hz (the GPA after its GPS, as ArduPilot writes them). ``formats``
    declares more record types, ``records`` (``(name, TimeUS, *fields)``) are written in time
    order among the others, ``extra`` writes at the end."""
    w = ardusub_formats(DataflashWriter(path))
    if formats:
        formats(w)
    w.write("PARM", int(t0_s * 1e6) - 1000, "LOG_BITMASK", 180222.0)
    pending = list(msgs)
    more = sorted(records, key=lambda r: r[1])
    for k in range(int(seconds * 50)):
        t = t0_s + k * 0.02
        us = round(t * 1e6)
        while pending and pending[0][0] <= us:  # in time order, as the autopilot writes them
            w.write("MSG", *pending.pop(0))
        while more and more[0][1] <= us:
            w.write(*more.pop(0))
        moving = dive_at_s is not None and t >= dive_at_s
        north = 0.5 * (t - dive_at_s) if moving else 0.0
        lat = LAT0 + north / M_PER_DEG_LAT
        w.write("SIM2", us, north, 0.0, 3.0 if moving else 0.0, 0.5 if moving else 0.0, 0.0, 0.0)
        if k % 2 == 0:
            for i in (0, 1):
                w.write("IMU", us, i, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
        if k % 5 == 0:
            w.write("ATT", us, 0.0, 0.0, 0.0, 0.0, 10.0, 10.0)
            for i in (0, 1):
                w.write("BARO", us, i, 0.0, 101325.0 + (3.0 * 1025 * 9.80665 if moving else 0.0), 20.0)
            w.write("RCOU", us, 1500, 1500, 1500, 1500, 1500, 1500)
            w.write("SIM", us, 0.0, 0.0, 10.0, lat, LON0, -3.0 if moving else 0.0, 1.0, 0.0, 0.0, 0.0)
            w.write("XKF1", us, 0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0)
        if k % 10 == 0:
            ms = GPS_MS0 + round((t - t0_s) * 1000)
            w.write("GPS", us, 0, 6, ms, GPS_WEEK, 10, 0.8, lat, LON0, 0.0, 0.0)
            w.write("GPA", us, 0, 1.2, 0.4, 0.9, 0.2, 0.0)
    if extra:
        extra(w)
    return w.close()


def _read(path):
    src = TlogSource(path)
    return src, list(src)


def test_gps_fixes_become_gnss_samples_and_their_time_the_log_s_unix_time(tmp_path):
    src, samples = _read(_log(tmp_path / "gps.BIN"))
    fixes = [s for s in samples if s.KIND == "gnss"]
    # GIVEN 5 Hz GPS over 20 s: every fix is a sample, at the home position
    assert len(fixes) == 100
    assert math.degrees(fixes[0].lat_rad) == pytest.approx(LAT0, abs=1e-7)
    assert math.degrees(fixes[0].lon_rad) == pytest.approx(LON0, abs=1e-7)
    # the first fix has no GPA yet: HDop 0.8 × 2.5 m; the others the GPA's HAcc 0.4 m
    assert fixes[0].sigma_h_m == pytest.approx(2.0) and [f.sigma_h_m for f in fixes[1:]] == pytest.approx([0.4] * 99)
    # THEN the GPS time (week, ms of week, less the 18 leap seconds) is the log's UNIX time
    clock = src.counters["clock"]
    assert clock["unix_reference"] == "GPS"
    assert fixes[0].t_s + clock["unix_offset_s"] == pytest.approx(UNIX_OF_GPS_MS0, abs=1e-3)
    assert not any("position fixes" in m for m in src.missing)


def test_a_gps_without_a_3d_fix_is_rejected_and_counted(tmp_path):
    def no_fix(w):
        w.write("GPS", 71_000_000, 0, 1, GPS_MS0 + 21_000, GPS_WEEK, 3, 9.0, 0.0, 0.0, 0.0, 0.0)

    src, samples = _read(_log(tmp_path / "nofix.BIN", extra=no_fix))
    assert sum(s.KIND == "gnss" for s in samples) == 100
    assert src.counters["rejected"]["gnss_no_fix"] == 1
    assert src.counters["message_types"]["GPS"]["rejected"] == {"gnss_no_fix": 1}


def test_sim_records_are_the_truth_around_the_first_fix(tmp_path):
    src, samples = _read(_log(tmp_path / "sim.BIN", seconds=30.0, dive_at_s=60.0))
    assert src.has_truth
    truth = [s for s in samples if s.KIND == "truth"]
    assert len(truth) == 300  # every SIM record (10 Hz), none fused: truth is its own kind
    last = truth[-1]
    # 19.9 s north at 0.5 m/s from the first fix (the origin), 3 m deep; SIM2's velocity
    assert last.pos_n_m[0] == pytest.approx(0.5 * 19.9, abs=0.02) and abs(last.pos_n_m[1]) < 0.01
    assert last.pos_n_m[2] == pytest.approx(3.0, abs=0.01)
    assert last.vel_n_m_s == pytest.approx((0.5, 0.0, 0.0))
    assert last.q_nb == (1.0, 0.0, 0.0, 0.0)
    types = src.counters["message_types"]
    assert types["SIM"]["status"] == "ignored" and "truth" in types["SIM"]["why"]


def test_att_is_withheld_while_the_autopilot_s_ekf_says_its_attitude_is_not_aligned(tmp_path):
    # GIVEN the EKF restarting at 55 s ("initialised": yaw 0 until aligned) and aligned at 60 s
    msgs = [(55_000_000, "EKF3 IMU0 initialised"), (60_000_000, "EKF3 IMU0 MAG0 initial yaw alignment complete")]
    src, samples = _read(_log(tmp_path / "ekf.BIN", msgs=msgs))
    att = [s.t_s for s in samples if s.KIND == "attitude"]
    # THEN no ATT between the two (10 Hz: 50 withheld), every other ATT passed on
    assert not any(55.0 <= t < 60.0 for t in att)
    assert len(att) == 150
    assert src.counters["rejected"]["attitude_not_aligned"] == 50


def test_every_record_type_is_used_ignored_with_why_or_unknown(tmp_path):
    def foreign(w):
        w.fmt("ZZZZ", "Qf", "TimeUS,Value")
        w.write("ZZZZ", 70_000_000, 1.0)

    src, samples = _read(_log(tmp_path / "types.BIN", extra=foreign))
    types = src.counters["message_types"]
    for used in ("IMU", "ATT", "BARO", "RCOU", "GPS"):
        assert types[used]["status"] == "used", (used, types[used])
    # the second IMU and the hull barometer: ignored, saying which instance is used
    assert types["IMU"]["ignored"] == {"other instance (IMU 0 is integrated)": 500}
    assert types["BARO"]["ignored"] == {"other instance (BARO 1 is the water sensor)": 200}
    assert types["IMU"]["rate_hz"] == pytest.approx(25.0)
    for ignored, word in (("XKF1", "estimate"), ("PARM", "housekeeping"), ("GPA", "accuracy"), ("FMT", "format"),
                          ("SIM2", "truth")):
        assert types[ignored]["status"] == "ignored" and word in types[ignored]["why"], (ignored, types[ignored])
    assert types["ZZZZ"]["status"] == "unknown"
    assert [k for k, v in types.items() if v["status"] == "unknown"] == ["ZZZZ"]


def test_unix_time_comes_from_the_least_delayed_gps_fix(tmp_path):
    """A fix is logged when it arrives, after its time of validity by the receiver's latency
    (tens of ms, jittering): the pairing takes the least delayed fix of the recent ones, not the
    last one."""
    w = ardusub_formats(DataflashWriter(tmp_path / "latency.BIN"))
    delays_s = (0.12, 0.05, 0.09, 0.15, 0.07)
    for k in range(50):  # fix k valid at mission time 50 + 0.2 k, i.e. GPS time GPS_MS0 + 200 k ms
        t_fix = 50.0 + 0.2 * k
        w.write("IMU", round(t_fix * 1e6), 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
        w.write("GPS", round((t_fix + delays_s[k % 5]) * 1e6), 0, 6, GPS_MS0 + 200 * k, GPS_WEEK, 10, 0.8,
                LAT0, LON0, 0.0, 0.0)
    src, _ = _read(w.close())
    clock = src.counters["clock"]
    # THEN UNIX = mission time + (UNIX of GPS_MS0 − 50 s − the least delay, 0.05 s)
    assert clock["unix_reference"] == "GPS"
    assert clock["unix_offset_s"] == pytest.approx(UNIX_OF_GPS_MS0 - 50.0 - 0.05, abs=1e-4)


def test_a_dvl_s_deltas_as_the_autopilot_logged_them_become_dvl_samples(tmp_path):
    """VISO: a DVL driver's VISION_POSITION_DELTA as ArduSub received and logged it (rotated
    into the body frame, stamped on arrival, dt in s): its velocity, validity from the
    confidence, the latency configured for an unstamped delta; VISV at its corrected time."""
    def formats(w):
        w.fmt("VISO", "Qffffffff", "TimeUS,dt,AngDX,AngDY,AngDZ,PosDX,PosDY,PosDZ,conf")
        w.fmt("VISV", "QQIffffBB", "TimeUS,RTimeUS,CTimeMS,VX,VY,VZ,VErr,Rst,Ign")
        w.fmt("VISP", "QQIffffffffBB", "TimeUS,RTimeUS,CTimeMS,PX,PY,PZ,Roll,Pitch,Yaw,PErr,AErr,Rst,Ign")

    # 5 Hz, 0.5 m/s forward, 0.02 m/s to starboard, the lock lost at the 10th
    records = [("VISO", 56_000_000 + k * 200_000, 0.2, 0.0, 0.0, 0.001, 0.1, 0.004, 0.0, 0.0 if k == 10 else 90.0)
               for k in range(20)]
    records += [("VISV", 60_010_000, 123, 59_950, 0.5, 0.02, 0.0, 0.1, 0, 0),
                ("VISP", 60_010_000, 123, 59_950, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0, 0)]
    src, samples = _read(_log(tmp_path / "dvl.BIN", seconds=30.0, dive_at_s=55.0, formats=formats, records=records))
    dvls = [s for s in samples if s.KIND == "dvl"]
    viso, visv = dvls[:20], dvls[20:]
    assert [s.t_s for s in viso] == pytest.approx([56.0 + 0.2 * k for k in range(20)])
    assert all(s.vel_d_m_s == pytest.approx((0.5, 0.02, 0.0), abs=1e-6) for s in viso)
    assert [s.valid for s in viso] == [k != 10 for k in range(20)]
    assert viso[0].sigma_m_s == pytest.approx(0.4 * (1 - 0.9))  # BlueOS's FOM ↔ confidence mapping
    assert len(visv) == 1 and visv[0].t_s == pytest.approx(59.95) and visv[0].vel_d_m_s == pytest.approx((0.5, 0.02, 0.0))
    types = src.counters["message_types"]
    assert types["VISO"]["status"] == "used" and types["VISO"]["samples"] == 20
    assert types["VISP"]["status"] == "ignored" and "own frame" in types["VISP"]["why"]


@pytest.mark.parametrize("gps_type, kind", [(14, "usbl"), (1, "gnss")])
def test_a_mavlink_gps_s_fixes_are_an_underwater_gps_s_at_any_depth(tmp_path, gps_type, kind):
    """GPS1_TYPE 14 (a BlueROV2 with a Water Linked UGPS: GPS_INPUT from the companion, logged as
    GPS): the fixes under water are acoustic fixes, not a radio GPS that must be refused there."""
    path = _log(tmp_path / "ugps.BIN", seconds=20.0, dive_at_s=55.0,
                records=[("PARM", 49_999_000, "GPS1_TYPE", float(gps_type))])
    src, samples = _read(path)
    fixes = [s for s in samples if s.KIND in ("gnss", "usbl")]
    assert len(fixes) > 90 and {s.KIND for s in fixes} == {kind}
    assert src.counters["gps_fixes"]["taken_as"] == ("acoustic" if kind == "usbl" else "gnss")


def test_the_log_time_guard_holds_a_jump_until_the_next_record_says_which():
    """:class:`LogTimeGuard` on times (s) as a log gives them: a logging pause (both records
    after it taken, the first once the second agrees), a lone damaged time ahead or behind
    (refused, the next record taken), a damaged first time (refused when the next disagrees)."""
    from adaptnav.service.transport.dataflash import LogTimeGuard

    def verdicts(times):
        guard, out = LogTimeGuard(back_s=1.0, jump_s=5.0), []
        for t in times:
            verdict, held_taken = guard.judge(t)
            if out and out[-1] == "hold":
                out[-1] = "take" if held_taken else "refuse"
            out.append(verdict)
        return out

    # the first record is held until the second agrees
    assert verdicts([10.0, 10.1, 10.2]) == ["take"] * 3
    # a pause of 36 s (the public log's last messages): nothing lost
    assert verdicts([10.0, 10.1, 46.0, 46.1, 46.2]) == ["take"] * 5
    # a time damaged ahead (a flipped high bit) or behind (zeroed): that record only
    assert verdicts([10.0, 10.1, 1e7, 10.2, 10.3]) == ["take", "take", "refuse", "take", "take"]
    assert verdicts([10.0, 10.1, 0.0, 10.2, 10.3]) == ["take", "take", "refuse", "take", "take"]
    # records a little out of order (within back_s) are taken
    assert verdicts([10.0, 10.5, 9.8, 10.6]) == ["take"] * 4
    # a damaged first time: refused when the next disagrees, and the next starts the log
    assert verdicts([1e7, 10.0, 10.1, 10.2]) == ["refuse", "take", "take", "take"]
