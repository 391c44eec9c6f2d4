"""Drive a real ArduSub (SITL) through a dive, lanes and turns, and collect its DataFlash log.

This is the recording half of ``test_ardusub_bin.py``: no navigation daemon takes part (the
autopilot runs with its own defaults, as a user's vehicle), the ground station of
:mod:`tests.sitl.ardusub` arms, dives, drives and surfaces, then disarms — ArduSub writes
``logs/*.BIN`` in its working directory while armed (``LOG_DISARMED`` 0), with the simulator's
truth in its ``SIM``/``SIM2`` records.  ``log_bitmask`` None keeps the defaults of
``sub.parm`` (180222: IMU at 25 Hz, ATT at 10 Hz, RCOU at 10 Hz, GPS, BARO; no IMU_FAST, no
ATTITUDE_FAST) — what a real user's log carries.

Usage (writes OUT/ardusub.BIN and OUT/session.tlog)::

    python -m tests.sitl.bin_drive OUT [--log-bitmask N] [--leg-s 60] [--legs 4] [--pattern NAME]
    python -m tests.sitl.bin_drive --excerpt LOG.BIN EXCERPT.BIN   # the small copy for tests/data

:func:`excerpt` keeps, record for record (pymavlink's DFReader, ``get_msgbuf``: the bytes as
written), what the replay reads and the log's low-rate records, and drops the high-rate records
it ignores (EKF, controllers, magnetometer, housekeeping: 5 of the 15.7 MB of a 5.5 min log) and
all but 10 Hz of SIM2 (the simulator's 250 Hz physics step, 7.9 MB; the truth's velocity).
"""
from __future__ import annotations

import argparse
import math
import shutil
import time
from pathlib import Path

from .ardusub import MODE_ALT_HOLD, MODE_MANUAL, ArduSub, DvlDriver, Gcs, UgpsDriver, free_udp_port, mav

# what the ground station records alongside (a tlog is handy to compare the two paths)
RECORDED = ("RAW_IMU", "HIGHRES_IMU", "ATTITUDE", "SCALED_PRESSURE2", "SERVO_OUTPUT_RAW", "GPS_RAW_INT",
            "SYSTEM_TIME", "SIM_STATE", "LOCAL_POSITION_NED")
GCS_RATES = {"RAW_IMU": 50, "ATTITUDE": 50, "SCALED_PRESSURE2": 10, "SERVO_OUTPUT_RAW": 10,
             "GPS_RAW_INT": 5, "SYSTEM_TIME": 1, "SIM_STATE": 10}


def drive(gcs: Gcs, legs: int, leg_s: float) -> None:
    """Dive in MANUAL, lanes and turns under depth hold, a sideways leg, surface."""
    dive(gcs)
    for leg in range(legs):
        gcs.hold_sticks(leg_s, x=600 if leg % 2 == 0 else 450)
        if leg < legs - 1:
            gcs.hold_sticks(6, r=500 if leg % 2 == 0 else -500)
    gcs.hold_sticks(20, y=400)  # a sideways leg (lateral thrusters)
    _surface(gcs)


def _yaw(gcs: Gcs) -> float | None:
    att = gcs.messages["ATTITUDE"]
    return float(att[-1][1].yaw) if att else None


def turn_by(gcs: Gcs, deg: float, r: int = 500, x: int = 0, timeout_s: float = 30.0) -> None:
    """Yaw by ``deg`` (positive clockwise, seen from above) with the yaw stick at ``|r|``, closed
    on the autopilot's ATTITUDE yaw (the pilot watches the compass), then sticks neutral."""
    sign = 1 if deg > 0 else -1
    prev, turned = _yaw(gcs), 0.0
    gcs.stick = {"x": x, "y": 0, "z": 500, "r": sign * abs(r)}
    t_end = time.time() + timeout_s
    while time.time() < t_end and abs(turned) < abs(math.radians(deg)):
        time.sleep(0.02)
        now = _yaw(gcs)
        if prev is not None and now is not None:
            turned += (now - prev + math.pi) % (2 * math.pi) - math.pi
        prev = now
    gcs.stick = {"x": x, "y": 0, "z": 500, "r": 0}


def arm(gcs: Gcs) -> None:
    """Sticks neutral, MANUAL, armed, 5 s at rest (the log's first seconds)."""
    gcs.stick = {"x": 0, "y": 0, "z": 500, "r": 0}
    gcs.mode(MODE_MANUAL)
    gcs.arm()
    gcs.wait(lambda: any(m.base_mode & 128 for _, m in gcs.messages["HEARTBEAT"][-3:]), 30, "armed")
    gcs.hold_sticks(5)  # at rest, armed: the log's first seconds


def dive(gcs: Gcs) -> None:
    """Armed (:func:`arm`), 14 s down at z 200, then depth hold (ALT_HOLD)."""
    arm(gcs)
    gcs.hold_sticks(14, z=200)  # dive
    gcs.mode(MODE_ALT_HOLD)
    gcs.hold_sticks(3)


def _surface(gcs: Gcs) -> None:
    gcs.hold_sticks(5)
    gcs.mode(MODE_MANUAL)
    gcs.hold_sticks(20, z=800)  # surface
    gcs.hold_sticks(5)


def drive_survey(gcs: Gcs, legs: int = 5, leg_s: float = 80.0) -> None:
    """(a) A slow survey: a lawnmower of long lanes at low throttle (x 530/520), 90° turns and
    short cross legs (12 s), alternating right/left pairs; ~8.5 min submerged at 5 x 80 s."""
    dive(gcs)
    for leg in range(legs):
        gcs.hold_sticks(leg_s, x=530 if leg % 2 == 0 else 520)
        if leg < legs - 1:
            d = 90 if leg % 2 == 0 else -90
            turn_by(gcs, d, r=400)
            gcs.hold_sticks(12, x=530)
            turn_by(gcs, d, r=400)
    _surface(gcs)


def drive_brisk(gcs: Gcs, legs: int = 6, leg_s: float = 40.0) -> None:
    """(b) A brisk drive: x 750-800, turns both ways (90-180°, some while moving), and depth
    changes under ALT_HOLD with the z stick in the middle of lanes (down, then up as much)."""
    dive(gcs)
    turns = [120, -90, 180, -150, 90, -120]
    for leg in range(legs):
        x = 800 if leg % 2 == 0 else 750
        third = leg_s / 3
        gcs.hold_sticks(third, x=x)
        gcs.hold_sticks(third, x=x, z=300 if leg % 2 == 0 else 700)  # descend / climb while driving
        gcs.hold_sticks(third, x=x)
        if leg < legs - 1:
            turn_by(gcs, turns[leg], r=600, x=300 if leg % 3 == 2 else 0)  # every third turn on the move
    _surface(gcs)


def drive_arcs(gcs: Gcs, legs: int = 5, leg_s: float = 55.0) -> None:
    """(c) Continuous gentle yaw: lanes at x 600 with r ±150-250 held throughout (arcs,
    circles), the sign and rate changing each lane; no straight line."""
    dive(gcs)
    rates = [200, -150, 250, -200, 150]
    for leg in range(legs):
        gcs.hold_sticks(leg_s, x=600 if leg % 2 == 0 else 550, r=rates[leg % len(rates)])
    _surface(gcs)


def drive_stops(gcs: Gcs, legs: int = 4, leg_s: float = 50.0, hover_s: float = 30.0) -> None:
    """(d) Drive, hover, drive again: lanes at x 600/500 each followed by a 30 s hover with the
    sticks neutral (depth hold), a 90° turn from the hover, then the next lane."""
    dive(gcs)
    for leg in range(legs):
        gcs.hold_sticks(leg_s, x=600 if leg % 2 == 0 else 500)
        gcs.hold_sticks(hover_s)
        if leg < legs - 1:
            turn_by(gcs, 90 if leg % 2 == 0 else -90, r=500)
    _surface(gcs)


def drive_mixed(gcs: Gcs, legs: int = 6, leg_s: float | None = None) -> None:
    """(e) Mixed throttles in one drive: six lanes of 40-45 s at clearly different forward sticks
    (x 800, 530, 680, the fourth in reverse at -450, 750, 560) so one learned speed scale has to
    serve them all, turns of 90-150° both ways between lanes (the third on the move at x 300);
    ~6 min from arming to disarming. ``leg_s`` given: every lane that long."""
    dive(gcs)
    sticks = [800, 530, 680, -450, 750, 560]
    lane_s = [45.0, 40.0, 44.0, 45.0, 40.0, 45.0]
    turns = [120, -90, 150, -120, 100]
    for leg in range(legs):
        gcs.hold_sticks(lane_s[leg % len(lane_s)] if leg_s is None else leg_s, x=sticks[leg % len(sticks)])
        if leg < legs - 1:
            turn_by(gcs, turns[leg % len(turns)], r=500, x=300 if leg == 2 else 0)  # the third on the move
    _surface(gcs)


def drive_zigzag(gcs: Gcs, legs: int | None = None, leg_s: float | None = None) -> None:
    """(f) One of each manoeuvre, no turn between them: a long lane at low throttle (x 250,
    60 s), a zigzag while thrusting (x 650, yaw stick ±300 alternating every 8 s, 48 s), a
    sideways leg (y -400, 20 s), a lane astern (x -300, 30 s), a lane at x 700 (30 s) ending in
    a 180° pivot, a lane at x 400 with a descent in its middle (z 300 for 10 s); ~5 min from
    arming to disarming. ``legs`` and ``leg_s`` are ignored (the timings are the pattern's)."""
    dive(gcs)
    gcs.hold_sticks(60, x=250)  # a long lane at low throttle
    for k in range(6):  # a zigzag while thrusting
        gcs.hold_sticks(8, x=650, r=300 if k % 2 == 0 else -300)
    gcs.hold_sticks(20, y=-400)  # a sideways leg
    gcs.hold_sticks(30, x=-300)  # astern
    gcs.hold_sticks(30, x=700)
    turn_by(gcs, 180, r=500)  # a pivot right after the lane
    gcs.hold_sticks(15, x=400)
    gcs.hold_sticks(10, x=400, z=300)  # descend while driving
    gcs.hold_sticks(15, x=400)
    _surface(gcs)


def drive_manual(gcs: Gcs, legs: int | None = None, leg_s: float | None = None) -> None:
    """(g) The whole drive in MANUAL (no depth hold, no ALT_HOLD at all): dive on the z stick
    (z 200, 16 s), five lanes at x 500-700 (40-55 s) with the z stick trimmed a little off
    neutral so the depth wanders (the simulator's hull is buoyant: z 440-500 rises ~0.1 m/s,
    z 420 about holds on the vectored frame and sinks ~0.08 m/s on the Heavy, z 400-410
    sinks; the vectored frame wanders ~4.4-10 m, the Heavy ~7-18 m), 90° turns between the
    lanes (yaw stick 400, z stick neutral), surface on the z stick (z 900, 40 s); ~5.5 min from
    arming to disarming. ``legs`` and ``leg_s`` are ignored (the timings are the pattern's)."""
    arm(gcs)
    gcs.hold_sticks(16, z=200)  # dive
    gcs.hold_sticks(3, z=420)
    lanes = [(55, 600, 400), (40, 550, 440), (55, 700, 410), (40, 500, 440), (50, 650, 400)]  # (s, x, z trim)
    for k, (lane_s, x, z) in enumerate(lanes):
        gcs.hold_sticks(lane_s, x=x, z=z)
        if k < len(lanes) - 1:
            turn_by(gcs, 90 if k % 2 == 0 else -90, r=400)
    gcs.hold_sticks(3, z=420)
    gcs.hold_sticks(40, z=900)  # surface (the Heavy from ~18 m)
    gcs.hold_sticks(5)


def drive_box(gcs: Gcs, legs: int | None = None, leg_s: float | None = None) -> None:
    """(h) A box driven without stopping: a rectangle of four sides at x 550 (40, 35, 40, 35 s)
    under depth hold, each corner a 90° turn taken while thrusting (x 550, yaw stick 400 until
    the autopilot's yaw has turned 90°, ~6 s), then the same rectangle in the reverse direction
    (left turns); ~6.6 min from arming to disarming. ``legs`` and ``leg_s`` are ignored (the
    timings are the pattern's)."""
    dive(gcs)
    sides = [40.0, 35.0, 40.0, 35.0]
    for sign in (1, -1):  # clockwise, then anticlockwise
        for side_s in sides:
            gcs.hold_sticks(side_s, x=550)
            turn_by(gcs, sign * 90, r=400, x=550)  # the corner on the move
    gcs.hold_sticks(5, x=550)
    _surface(gcs)


def drive_creep(gcs: Gcs, legs: int | None = None, leg_s: float | None = None) -> None:
    """(i) An inspection at low throttle: lanes close to neutral (x 250, 150, 200, 250: ~0.15-
    0.26 m/s, 35-45 s), crab legs on the lateral thrusters (y +250 and -250, 25 s), long hovers
    with the sticks neutral (20-40 s) under depth hold, turns of 45°, -90° and 60° from the
    hover (yaw stick 300-400); ~6.7 min from arming to disarming. ``legs`` and ``leg_s`` are
    ignored (the timings are the pattern's)."""
    dive(gcs)
    gcs.hold_sticks(45, x=250)
    gcs.hold_sticks(30)  # hover
    turn_by(gcs, 45, r=300)
    gcs.hold_sticks(45, x=150)
    gcs.hold_sticks(25, y=250)  # crab
    gcs.hold_sticks(40)  # hover
    turn_by(gcs, -90, r=400)
    gcs.hold_sticks(45, x=200)
    gcs.hold_sticks(25, y=-250)  # crab back
    gcs.hold_sticks(25)  # hover
    turn_by(gcs, 60, r=300)
    gcs.hold_sticks(35, x=250)
    gcs.hold_sticks(20)  # hover
    _surface(gcs)


def drive_redive(gcs: Gcs, legs: int | None = None, leg_s: float | None = None) -> None:
    """(j) Two dives: dive, two lanes (x 600, 550, 45 s) with a 90° turn, surface and stay there
    40 s with the sticks neutral (the buoyant hull floats: a GNSS fix at the surface), dive
    again (z 200, 16 s, then depth hold), three lanes (x 650, 500, 600, 35-40 s) with a -120°
    turn and a 90° turn on the move (x 300), surface; ~6 min from arming to disarming.
    ``legs`` and ``leg_s`` are ignored (the timings are the pattern's)."""
    dive(gcs)
    gcs.hold_sticks(45, x=600)
    turn_by(gcs, 90, r=500)
    gcs.hold_sticks(45, x=550)
    gcs.hold_sticks(5)
    gcs.mode(MODE_MANUAL)
    gcs.hold_sticks(20, z=800)  # surface
    gcs.hold_sticks(40)  # at the surface
    gcs.hold_sticks(16, z=200)  # dive again
    gcs.mode(MODE_ALT_HOLD)
    gcs.hold_sticks(3)
    gcs.hold_sticks(40, x=650)
    turn_by(gcs, -120, r=500)
    gcs.hold_sticks(40, x=500)
    turn_by(gcs, 90, r=500, x=300)  # on the move
    gcs.hold_sticks(35, x=600)
    _surface(gcs)


PATTERNS = {"default": None, "survey": drive_survey, "brisk": drive_brisk, "arcs": drive_arcs,
            "stops": drive_stops, "mixed": drive_mixed, "zigzag": drive_zigzag, "manual": drive_manual,
            "box": drive_box, "creep": drive_creep, "redive": drive_redive}


def record(out: Path, log_bitmask: int | None = None, legs: int | None = 4, leg_s: float | None = 60.0,
           pattern: str = "default", dvl_hz: float | None = None, ugps_hz: float | None = None,
           heavy: bool = False) -> Path:
    """Run the autopilot, drive it, disarm; returns ``out/ardusub.BIN``. ``dvl_hz``: a DVL
    driver on the companion sends VISION_POSITION_DELTA at that rate (:class:`DvlDriver`;
    ArduSub logs it as VISO); ``ugps_hz``: an underwater GPS sends GPS_INPUT (:class:`UgpsDriver`,
    ``GPS1_TYPE`` 14: it replaces the simulated GPS; ArduSub logs it as GPS); ``heavy``: a
    BlueROV2 Heavy (SITL's ``vectored_6dof``, ``FRAME_CONFIG`` 2: the same four vectored
    horizontal thrusters, four vertical ones, eight outputs)."""
    out.mkdir(parents=True, exist_ok=True)
    work = out / "ardusub-work"
    work.mkdir(exist_ok=True)
    gcs_port, bridge_port = free_udp_port(), free_udp_port()
    sub = ArduSub(work, gcs_port, bridge_port, model="vectored_6dof" if heavy else "vectored").start()
    gcs = Gcs(gcs_port, keep=RECORDED, tlog=out / "session.tlog")
    dvl = ugps = None
    try:
        gcs.wait(lambda: gcs.count("HEARTBEAT") > 0, 120, "ArduSub's heartbeat")
        gcs.set_param("ARMING_CHECK", 0)
        if heavy:
            gcs.set_param("FRAME_CONFIG", 2)  # the motors are set up at boot
        if dvl_hz or ugps_hz or heavy:
            if dvl_hz:
                gcs.set_param("VISO_TYPE", 1)  # MAVLink visual odometry: takes effect after a reboot
            if ugps_hz:
                gcs.set_param("GPS1_TYPE", 14)  # a MAVLink GPS (GPS_INPUT)
                gcs.set_param("EK3_GPS_CHECK", 0)  # it reports no velocity or accuracies
            sub.restart()
            since = time.time()
            gcs.wait(lambda: any(w > since for w, _ in gcs.messages["HEARTBEAT"]), 120, "ArduSub back")
            gcs.interval("SIM_STATE", 50)  # the drivers' truth: keep it fresh
            if dvl_hz:
                dvl = DvlDriver(bridge_port, gcs, hz=dvl_hz)
            if ugps_hz:
                ugps = UgpsDriver(None if dvl else bridge_port, gcs, hz=ugps_hz, conn=dvl.conn if dvl else None)
        if log_bitmask is not None:
            gcs.set_param("LOG_BITMASK", log_bitmask)
        for mtype, hz in GCS_RATES.items():
            gcs.interval(mtype, hz)
        if dvl is not None or ugps is not None:  # the drivers' truth: keep it fresh
            gcs.interval("SIM_STATE", 50)
        # EKF3 aligned on its GPS before arming, as a pilot waits for it
        gcs.wait_text("EKF3 IMU0 is using GPS", 120)
        time.sleep(5.0)
        if pattern == "default":
            drive(gcs, 4 if legs is None else legs, 60.0 if leg_s is None else leg_s)
        else:  # the variants take their own lane counts and lengths unless given
            PATTERNS[pattern](gcs, **{k: v for k, v in (("legs", legs), ("leg_s", leg_s)) if v is not None})
        gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)  # disarm (forced): the log closes
        time.sleep(3.0)
    finally:
        if ugps is not None:
            ugps.close()
            print(f"UGPS: {ugps.sent} GPS_INPUT sent")
        if dvl is not None:
            dvl.close()
            print(f"DVL: {dvl.sent} VISION_POSITION_DELTA sent")
        gcs.close()
        sub.stop()
    bins = sorted((work / "logs").glob("*.BIN"), key=lambda p: p.stat().st_mtime)
    if not bins:
        raise RuntimeError(f"ArduSub wrote no DataFlash log in {work / 'logs'}")
    dest = out / "ardusub.BIN"
    shutil.copyfile(bins[-1], dest)
    return dest


# the excerpt: every record of these types (what the replay reads, and the log's low-rate
# records: format, parameters, text, modes, events, EKF origin and timing)
EXCERPT_TYPES = ("FMT", "FMTU", "UNIT", "MULT", "PARM", "MSG", "VER", "MODE", "EV", "ARM", "CMD", "ORGN", "MAVC",
                 "PM", "DSF", "DU32", "XKT", "XKV1", "XKV2", "IMU", "ATT", "BARO", "RCOU", "GPS", "GPA", "RFND", "SIM",
                 "VISO", "VISV", "VISP")
EXCERPT_SIM2_PERIOD_S = 0.1


def excerpt(src: Path, dst: Path) -> dict[str, int]:
    """Copy the records of :data:`EXCERPT_TYPES` and SIM2 at 10 Hz from ``src`` to ``dst``;
    returns the records written by type."""
    from collections import Counter

    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(src), zero_time_base=True)
    kept: Counter = Counter()
    last_sim2_us = -1e18
    with open(dst, "wb") as f:
        while (m := log.recv_msg()) is not None:
            mtype = m.get_type()
            if mtype == "SIM2":
                if m.TimeUS - last_sim2_us < EXCERPT_SIM2_PERIOD_S * 1e6:
                    continue
                last_sim2_us = m.TimeUS
            elif mtype not in EXCERPT_TYPES:
                continue
            f.write(m.get_msgbuf())
            kept[mtype] += 1
    return dict(kept)


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--excerpt"]:
        print(excerpt(Path(sys.argv[2]), Path(sys.argv[3])))
        sys.exit(0)
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--log-bitmask", type=int)
    ap.add_argument("--legs", type=int, help="lanes (default 4; a variant's own without it)")
    ap.add_argument("--leg-s", type=float, help="seconds per lane (default 60; a variant's own without it)")
    ap.add_argument("--pattern", choices=sorted(PATTERNS), default="default", help="drive shape")
    ap.add_argument("--dvl-hz", type=float, help="a DVL on the companion (VISION_POSITION_DELTA → VISO records)")
    ap.add_argument("--ugps-hz", type=float, help="an underwater GPS on the companion (GPS_INPUT → GPS records)")
    ap.add_argument("--heavy", action="store_true", help="a BlueROV2 Heavy (eight thrusters)")
    a = ap.parse_args()
    print(record(a.out, a.log_bitmask, a.legs, a.leg_s, a.pattern, a.dvl_hz, a.ugps_hz, a.heavy))
