"""A real ``.tlog`` of the class "AUV with a navigation-grade IMU and a DVL", built from the
simulator, with its post-processed truth kept beside it; and the DVL dead reckoning a user
would compute from the same log (the reference our replay must beat).

What the log holds, as a BlueOS/ArduSub vehicle with a fibre-optic INS on the companion writes it
(message layout measured on ``../shared/data/mavlink/ardusub-4.1.1-bluerov2-ugps.tlog``):

- ``HIGHRES_IMU`` at 100 Hz from the companion's IMU driver (system 1, component 200
  ``MAV_COMP_ID_IMU``), ``time_usec`` in UNIX µs of the companion's clock; the navigation grade
  of :mod:`adaptnav.sim.imu` on the rotating earth (:mod:`adaptnav.sim.navgrade`);
- ``ATTITUDE`` at 10 Hz and ``SCALED_PRESSURE``/``SCALED_PRESSURE2`` (internal barometer /
  external depth sensor) at 5 Hz from the autopilot (1, 1) on its boot clock (which runs
  20 ppm fast against UNIX time); its attitude has a consumer AHRS's errors
  (:data:`adaptnav.sim.navgrade.COMPASS_AHRS`: magnetic heading off by a few degrees) or, with
  ``ahrs = ins_ahrs_errors(lat)``, the vehicle's own navigation-grade INS's (0.05° sec L);
- ``SYSTEM_TIME`` at 1 Hz from the autopilot with ``time_unix_usec = 0`` (an ArduSub without
  GPS time, as in the real log), optionally with its UNIX time;
- optionally the autopilot's own ``RAW_IMU`` at 4 Hz (consumer MEMS, int16 mg / mrad/s) — a
  real ArduSub streams it whether or not anybody uses it;
- ``VISION_POSITION_DELTA`` at 1 Hz from the BlueOS DVL driver (system 255, component 0):
  as the Water Linked driver computes it, ``position_delta = v·dt`` with ``v`` the DVL's
  velocity at the ping (the simulator's 4-beam Janus DVL: scale factor, misalignment, beam
  biases, outliers, drop-outs) and ``dt`` the time since its previous ping,
  ``angle_delta`` the difference of the autopilot's Euler angles, ``confidence`` from the
  figure of merit (4 mm/s, more by the ping's error beyond 5 cm/s: a bad beam, which the
  instrument sees in its beams' disagreement), ``time_usec = 0`` (or, ``dvl_time_usec``, the ping's UNIX time, as a
  driver that forwards the DVL's time of validity would), sent ``dvl_latency_s`` after the
  ping; invalid pings are not sent;
- one ``GPS_INPUT`` from the underwater GPS extension (1, 220) at the start, the vehicle
  already under water: ``time_usec = 0``, HDOP only (``ignore_flags = 253``), as in the real log;
- ``HEARTBEAT`` at 1 Hz from the autopilot, the GCS (255, 190) and the IMU driver.

Each message gets the receive stamp of the companion that records the log (its UNIX clock at
reception: transport delay 2 ms + exponential 3 ms), in receive order.  No thruster outputs.
The simulation starts ``lead_in_s`` before the log so the vehicle is already cruising.

Truth (``<name>.truth.csv``): ``t_unix_s, t_boot_s, lat_deg, lon_deg, depth_m, yaw_deg`` at 10 Hz;
the DVL's drawn errors (``<name>.dvl_errors.json``: scale factor, misalignment, the velocity
bias its beam biases leave) for :func:`shared_errors_m`.
"""
from __future__ import annotations

import csv
import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin  # noqa: E402
from adaptnav.sim.imu import IMU_GRADES, triad_errors  # noqa: E402
from adaptnav.sim.navgrade import AhrsErrors, ahrs_attitude, rotating_earth_imu  # noqa: E402

UNIX0_S = 1_767_000_000.0      # the companion's UNIX time at simulation time 0
BOOT0_S = 1800.0               # the autopilot booted this long before simulation time 0
BOOT_DRIFT = 20e-6             # its crystal runs this much fast
IMU_SRC, AP_SRC, DVL_SRC, UGPS_SRC, GCS_SRC = (1, 200), (1, 1), (255, 0), (1, 220), (255, 190)


@dataclass(frozen=True)
class AuvLog:
    """One mission of the class (a few variants differ in these)."""

    name: str
    seed: int
    pattern: str = "straight"            # sim trajectory.pattern
    heading_deg: float = 30.0
    duration_s: float = 900.0            # of the log (the simulation adds lead_in_s)
    lead_in_s: float = 20.0
    leg_length_m: float = 300.0
    leg_spacing_m: float = 40.0
    speed_m_s: float = 1.5
    lat_deg: float = 59.4
    lon_deg: float = 10.5
    autopilot_raw_imu: bool = True       # the autopilot's own RAW_IMU at 4 Hz in the log too
    system_time_unix: bool = False       # the autopilot's SYSTEM_TIME carries UNIX time
    ahrs: AhrsErrors = AhrsErrors()      # the autopilot's attitude errors
    sim_overrides: tuple[str, ...] = ()  # scenario overrides after the class's (error bisection)
    dvl_latency_s: float = 0.05          # the DVL driver sends this long after the ping
    dvl_time_usec: bool = False          # ... stamping it with the ping's UNIX time (BlueOS: 0)
    # the IMU's sender: "companion" (its driver, component 200) or "vehicle_computer" (the
    # vehicle's own computer, component 1, whose heartbeat says generic autopilot, not ArduPilot)
    imu_sender: str = "companion"
    # other members of the class (defaults: the layout above)
    imu_rate_hz: float = 100.0           # the FOG's HIGHRES_IMU rate (100–200 Hz; 50 Hz)
    imu_clock_offset_s: float = 0.0      # the IMU's UNIX time_usec minus the recorder's UNIX clock
    stop_s: tuple[float, float] | None = None  # (from, to) s of the log: the vehicle stops (10 s ramps)
    fix_at_s: float = 5.0                # the single fix, this long into the log
    fix_time_usec: bool = False          # GPS_INPUT.time_usec the fix's UNIX time (BlueOS UGPS: 0)
    # the fix as "GPS_INPUT" (1, 220) or "GLOBAL_VISION_POSITION_ESTIMATE" (255, 0: local NED
    # from the autopilot's EKF origin, which its GPS_GLOBAL_ORIGIN gives once at the start)
    fix_message: str = "GPS_INPUT"
    ekf_origin_at_s: float | None = 0.2  # GLOBAL_VISION_POSITION_ESTIMATE: GPS_GLOBAL_ORIGIN this long into the log (None: never)
    dvl_message: str = "VISION_POSITION_DELTA"  # or "VISION_SPEED_ESTIMATE" (body velocity at the ping)
    depth_in_scaled_pressure2: bool = True  # False: the depth sensor in SCALED_PRESSURE, no internal barometer
    system_time: bool = True             # the autopilot's SYSTEM_TIME in the log at all
    imu_drop_prob: float = 0.0           # HIGHRES_IMU messages lost on the link (each independently)


def _boot_s(t_sim: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(t_sim) + BOOT0_S) * (1.0 + BOOT_DRIFT)


def _scenario(v: AuvLog, rng: np.random.Generator):
    from adaptnav.sim.scenario import load_scenario

    scale = float(np.clip(0.003 * rng.standard_normal(), -0.008, 0.008))
    mis = 0.3 * rng.standard_normal(3)
    return load_scenario("survey", [
        f"seed={v.seed}", f"duration_s={v.duration_s + v.lead_in_s}", f"trajectory.pattern=\"{v.pattern}\"",
        f"trajectory.heading_deg={v.heading_deg}", f"trajectory.leg_length_m={v.leg_length_m}",
        f"trajectory.leg_spacing_m={v.leg_spacing_m}", f"trajectory.speed_m_s={v.speed_m_s}",
        "trajectory.depth_m=25.0", "trajectory.start_depth_m=25.0", "environment.bottom_depth_m=45.0",
        f"origin.lat_deg={v.lat_deg}", f"origin.lon_deg={v.lon_deg}",
        "imu.grade=\"navigation\"", f"imu.rate_hz={v.imu_rate_hz}", "heading.enabled=false", "usbl.enabled=false",
        "gnss.fix_times_s=[]", "depth.rate_hz=5.0", "truth.rate_hz=10.0",
        "dvl.enabled=true", "dvl.rate_hz=1.0", "dvl.start_s=0.37", f"dvl.scale_factor_error={scale}",
        f"dvl.misalignment_rpy_deg=[{mis[0]}, {mis[1]}, {mis[2]}]", "dvl.outlier_prob=0.005",
        "dvl.dropout_prob=0.02", *v.sim_overrides,
    ])


class _Writer:
    """Frames with receive stamps, sorted on write."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.records: list[tuple[int, int, bytes]] = []
        self._mavs: dict = {}

    def emit(self, t_sim: float, src: tuple[int, int], name: str, *args) -> None:
        mav = self._mavs.get(src)
        if mav is None:
            mav = self._mavs[src] = mavlink2.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        frame = bytes(getattr(mav, name)(*args).pack(mav))
        delay = 0.002 + self.rng.exponential(0.003)
        self.records.append((int(round((UNIX0_S + t_sim + delay) * 1e6)), len(self.records), frame))

    def write(self, path: Path) -> None:
        self.records.sort()
        with open(path, "wb") as f:
            for stamp, _, frame in self.records:
                f.write(struct.pack(">Q", stamp) + frame)


def _true_head_velocity(sc, d, t_s) -> np.ndarray:
    """(K, 3) m/s: the DVL head's true velocity at ``t_s`` (the dense truth's nearest
    instant; the head's true orientation, mount and misalignment, and its lever arm)."""
    from scipy.spatial.transform import Rotation

    i = np.minimum(np.round(np.asarray(t_s) * sc.imu.rate_hz).astype(int), len(d.t_s) - 1)
    rot_nb = Rotation.from_quat(np.asarray(d.q_nb)[i][:, [1, 2, 3, 0]])
    # body rate from consecutive attitudes (the truth keeps no rates): R_nb(t)ᵀ R_nb(t + dt)
    j = np.minimum(i + 1, len(d.t_s) - 1)
    dt = float(d.t_s[1] - d.t_s[0])
    omega_b = (rot_nb.inv() * Rotation.from_quat(np.asarray(d.q_nb)[j][:, [1, 2, 3, 0]])).as_rotvec() / dt
    vel_b = rot_nb.inv().apply(np.asarray(d.vel_n_m_s)[i]) + np.cross(omega_b, np.asarray(sc.dvl.lever_arm_b_m))
    r, p, y = np.radians(sc.dvl.mount_rpy_deg)
    mr, mp, my = np.radians(sc.dvl.misalignment_rpy_deg)
    rot_bd = Rotation.from_euler("ZYX", [y, p, r]) * Rotation.from_euler("ZYX", [my, mp, mr])
    return rot_bd.inv().apply(vel_b)


def _simulate_with_stop(sc, v: AuvLog):
    """:func:`adaptnav.sim.simulator.simulate` with the vehicle stopping over ``v.stop_s`` (log
    seconds): the motion model's reported surge and turn rate scaled down to 0 and back up over
    10 s ramps (heading held while stopped; the model's noise stays)."""
    from unittest import mock

    import adaptnav.sim.vehicle as vehicle
    from adaptnav.sim.simulator import simulate

    a, b = (v.lead_in_s + s for s in v.stop_s)
    real = vehicle.sample_velocities
    k = [0]

    def stopping(params, v_rep, w_rep, rng, size=None):
        t = k[0] * sc.motion.step_s
        k[0] += 1
        f = float(np.clip(max((a - t) / 10.0, (t - b) / 10.0), 0.0, 1.0))
        return real(params, v_rep * f, w_rep * f, rng, size)

    with mock.patch.object(vehicle, "sample_velocities", stopping):
        return simulate(sc)


def write_auv_tlog(v: AuvLog, out_dir: str | Path) -> tuple[Path, Path]:
    """Simulate ``v`` and write ``<name>.tlog`` and ``<name>.truth.csv`` into ``out_dir``."""
    from adaptnav.sim.simulator import simulate

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([v.seed, 11])
    rng_scn, rng_att, rng_ap_imu, rng_fix, rng_link = rng.spawn(5)
    sc = _scenario(v, rng_scn)
    if v.stop_s is None:
        res = simulate(sc)
    else:
        res = _simulate_with_stop(sc, v)
    origin = sc.origin.geo()
    d = res.dense
    f_b, w_b = rotating_earth_imu(d.pos_n_m, d.vel_n_m_s, d.q_nb, origin,
                                  res.imu.specific_force_b_m_s2, res.imu.omega_b_rad_s)
    t_imu = res.imu.t_s
    t0, t1 = v.lead_in_s, v.lead_in_s + v.duration_s
    w = _Writer(rng_link)

    # heartbeats, system time
    own_computer = v.imu_sender == "vehicle_computer"
    imu_src = AP_SRC if own_computer else IMU_SRC
    firmware = mavlink2.MAV_AUTOPILOT_GENERIC if own_computer else mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
    for t in np.arange(t0, t1, 1.0):
        w.emit(t, AP_SRC, "heartbeat_encode", mavlink2.MAV_TYPE_SUBMARINE, firmware, 81, 19, mavlink2.MAV_STATE_ACTIVE)
        w.emit(t + 0.3, GCS_SRC, "heartbeat_encode", mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 192, 0, 4)
        w.emit(t + 0.5, IMU_SRC, "heartbeat_encode", mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
               mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4)
        unix_us = int(round((UNIX0_S + t + 0.1) * 1e6)) if v.system_time_unix else 0  # at its boot stamp
        if v.system_time:
            w.emit(t + 0.1, AP_SRC, "system_time_encode", unix_us, int(_boot_s(t + 0.1) * 1000))

    # the companion's navigation-grade IMU, UNIX time
    keep = (t_imu >= t0) & (t_imu < t1)
    sent = keep.copy()
    if v.imu_drop_prob > 0.0:
        sent &= np.random.default_rng([v.seed, 12]).random(len(keep)) >= v.imu_drop_prob
    for t, f, g in zip(t_imu[sent], f_b[sent], w_b[sent]):
        w.emit(float(t), imu_src, "highres_imu_encode", int(round((UNIX0_S + t + v.imu_clock_offset_s) * 1e6)),
               *map(float, f), *map(float, g), 0.0, 0.0, 0.0, 1013.25, 0.0, 0.0, 22.0, 0x1FFF, 0)

    # the autopilot's own consumer IMU (RAW_IMU, int16 mg / mrad/s) at 4 Hz
    if v.autopilot_raw_imu:
        idx = np.nonzero(keep)[0][::max(1, int(round(sc.imu.rate_hz / 4.0)))]
        g = IMU_GRADES["consumer"]
        ba, wa = triad_errors(g.accel, len(idx), 0.25, rng_ap_imu)
        bg, wg = triad_errors(g.gyro, len(idx), 0.25, rng_ap_imu)
        acc = np.round((f_b[idx] + ba + wa) / (GRAVITY_M_S2 / 1000.0)).astype(int)
        gyr = np.round((w_b[idx] + bg + wg) / 1e-3).astype(int)
        for i, a, r in zip(idx, acc, gyr):
            t = float(t_imu[i])
            w.emit(t, AP_SRC, "raw_imu_encode", int(_boot_s(t) * 1e6), *map(int, a), *map(int, r), 0, 0, 0, 0, 35)

    # the autopilot's attitude (consumer AHRS) at 10 Hz; the DVL driver differences it too
    t_att = np.arange(t0, t1, 0.1)
    i_att = np.minimum(np.round(t_att * sc.imu.rate_hz).astype(int), len(d.t_s) - 1)
    att = ahrs_attitude(t_att, d.euler_rad[i_att], v.ahrs, rng_att)
    rates = w_b[np.maximum(i_att - 1, 0)]
    for t, e, r in zip(t_att, att, rates):
        w.emit(float(t), AP_SRC, "attitude_encode", int(_boot_s(t) * 1000), *map(float, e), *map(float, r))

    # depth sensor (SCALED_PRESSURE2, hPa) and the internal barometer
    for s in res.samples["depth"]:
        if t0 <= s.t_s < t1:
            boot_ms = int(_boot_s(s.t_s) * 1000)
            if v.depth_in_scaled_pressure2:
                w.emit(s.t_s, AP_SRC, "scaled_pressure2_encode", boot_ms, s.pressure_pa / 100.0, 0.0, 1200, 0)
                w.emit(s.t_s, AP_SRC, "scaled_pressure_encode", boot_ms, 1002.5, 0.0, 3100, 0)
            else:
                w.emit(s.t_s, AP_SRC, "scaled_pressure_encode", boot_ms, s.pressure_pa / 100.0, 0.0, 1200, 0)

    # the BlueOS DVL driver: v·dt at each valid ping, Euler-angle differences, confidence
    last_ping_t = None
    last_att = None
    v_true_d = _true_head_velocity(sc, d, [s.t_s for s in res.samples["dvl"]])
    for k_dvl, s in enumerate(res.samples["dvl"]):
        t = s.t_s
        j = min(int(np.searchsorted(t_att, t, side="right")) - 1, len(t_att) - 1)
        cur_att = att[j] if j >= 0 else None
        dt = None if last_ping_t is None else t - last_ping_t
        last_ping_t = t
        if t < t0 or t >= t1 or dt is None or not s.valid or cur_att is None:
            last_att = cur_att
            continue
        v_d = np.asarray(s.vel_d_m_s)
        # the DVL's figure of merit (its velocity 1-σ): a few mm/s, more with a bad beam —
        # which the instrument sees in its beams' disagreement: the error of this ping's
        # velocity, not the vehicle's speed. (A FOM from |v| − the nominal speed gave half
        # the pings of the simulator's surging vehicle σ 3–13 cm/s, the accelerating ones —
        # a DVL placed 55 ms late reads low there —, and the filter, trusting the rest,
        # ran 2–4 mm/s fast along track: +1–1.5 m over a 6-min leg.)
        fom = 0.004 + 0.5 * max(0.0, float(np.linalg.norm(v_d - v_true_d[k_dvl])) - 0.05)
        conf = 100.0 * (1.0 - min(0.4, fom) / 0.4)
        dang = [0.0, 0.0, 0.0] if last_att is None else list(map(float, cur_att - last_att))
        stamp_us = int(round((UNIX0_S + t) * 1e6)) if v.dvl_time_usec else 0
        if v.dvl_message == "VISION_SPEED_ESTIMATE":
            cov = [fom**2, 0.0, 0.0, 0.0, fom**2, 0.0, 0.0, 0.0, fom**2]
            w.emit(t + v.dvl_latency_s, DVL_SRC, "vision_speed_estimate_encode", stamp_us, *map(float, v_d), cov, 0)
        else:
            w.emit(t + v.dvl_latency_s, DVL_SRC, "vision_position_delta_encode", stamp_us, int(round(dt * 1e6)), dang,
                   list(map(float, v_d * dt)), conf)
        last_att = cur_att

    # one underwater-GPS fix, already under water, 5 s into the log
    t_fix = t0 + v.fix_at_s
    i_fix = int(round(t_fix * sc.imu.rate_hz))
    hdop = 1.6
    ne = d.pos_n_m[i_fix, :2] + hdop * rng_fix.standard_normal(2)
    lat, lon, _ = origin.to_geodetic(np.array([ne[0], ne[1], 0.0]))
    if v.fix_message == "GLOBAL_VISION_POSITION_ESTIMATE":
        # the autopilot's EKF origin: where the vehicle was launched, 80 m north, 30 m west of here
        ekf_origin = GeoOrigin(*origin.to_geodetic(np.array([80.0, -30.0, 0.0]))[:2], 0.0)
        if v.ekf_origin_at_s is not None:
            w.emit(t0 + v.ekf_origin_at_s, AP_SRC, "gps_global_origin_encode", int(round(math.degrees(ekf_origin.lat_rad) * 1e7)),
                   int(round(math.degrees(ekf_origin.lon_rad) * 1e7)), 0, int(round((UNIX0_S + t0) * 1e6)))
        x, y, _ = ekf_origin.to_ned(np.array([lat]), np.array([lon]))[0]
        cov = [float("nan")] * 21
        cov[0] = cov[6] = hdop**2
        usec = int(round((UNIX0_S + t_fix) * 1e6)) if v.fix_time_usec else 0
        w.emit(t_fix + 0.3, DVL_SRC, "global_vision_position_estimate_encode", usec, float(x), float(y),
               float(d.pos_n_m[i_fix, 2]), 0.0, 0.0, 0.0, cov, 0)
    else:
        usec = int(round((UNIX0_S + t_fix) * 1e6)) if v.fix_time_usec else 0
        w.emit(t_fix + 0.3, UGPS_SRC, "gps_input_encode", usec, 0, 253, 0, 0, 3, int(round(math.degrees(lat) * 1e7)),
               int(round(math.degrees(lon) * 1e7)), 0.0, hdop, 65535, 0, 0, 0, 0, 0, 0, 12, 0)

    tlog = out / f"{v.name}.tlog"
    w.write(tlog)
    from adaptnav.sim.sensors import janus_beams

    bias_d = np.linalg.pinv(janus_beams(math.radians(sc.dvl.beam_angle_deg))) @ np.asarray(sc.dvl.beam_bias_m_s)
    (out / f"{v.name}.dvl_errors.json").write_text(json.dumps({
        "scale_factor_error": sc.dvl.scale_factor_error, "misalignment_rpy_deg": list(sc.dvl.misalignment_rpy_deg),
        "bias_d_m_s": bias_d.tolist()}))
    truth_path = out / f"{v.name}.truth.csv"
    t_truth = np.arange(t0, t1, 0.1)
    i_truth = np.minimum(np.round(t_truth * sc.imu.rate_hz).astype(int), len(d.t_s) - 1)
    lat, lon, _ = origin.to_geodetic(d.pos_n_m[i_truth])
    with open(truth_path, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["t_unix_s", "t_boot_s", "lat_deg", "lon_deg", "depth_m", "yaw_deg"])
        for k, t in enumerate(t_truth):
            wr.writerow([f"{UNIX0_S + t:.6f}", f"{_boot_s(t):.6f}", f"{math.degrees(lat[k]):.10f}",
                         f"{math.degrees(lon[k]):.10f}", f"{d.pos_n_m[i_truth[k], 2]:.4f}",
                         f"{math.degrees(d.euler_rad[i_truth[k], 2]):.5f}"])
    return tlog, truth_path


# ------------------------------------------------------------------------------ scoring
def read_truth(path: Path) -> dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def dvl_dead_reckoning(tlog: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a user computes from the log without a filter: start at the acoustic fix, then
    integrate the DVL's velocity — each VISION_POSITION_DELTA's ``position_delta / dt``, rotated
    to north/east with the autopilot's latest ATTITUDE (roll, pitch, yaw) — over the time since
    the previous delta (receive stamps: a ping the driver did not send is bridged, not lost).
    Returns (t_unix_s (K,), lat_rad (K,), lon_rad (K,)) at the receive stamps, from the fix on."""
    from pymavlink import mavutil
    from scipy.spatial.transform import Rotation

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    att = None
    origin = None
    ekf_origin = _ekf_origin(tlog)  # a user reads it wherever it is in the log
    ne = np.zeros(2)
    rows = []
    try:
        while (m := conn.recv_match()) is not None:
            kind = m.get_type()
            if kind == "ATTITUDE":
                att = (m.roll, m.pitch, m.yaw)
            elif _is_fix(m) and origin is None:
                origin = GeoOrigin(*_fix_lat_lon_rad(m, ekf_origin), 0.0)
                rows.append((m._timestamp, 0.0, 0.0))
            elif kind in ("VISION_POSITION_DELTA", "VISION_SPEED_ESTIMATE") and origin is not None and att is not None \
                    and getattr(m, "confidence", 100.0) > 0:
                R_nb = Rotation.from_euler("ZYX", [att[2], att[1], att[0]])
                vel_b = (np.asarray(m.position_delta, dtype=float) / (m.time_delta_usec * 1e-6)
                         if kind == "VISION_POSITION_DELTA" else np.array([m.x, m.y, m.z]))
                vel_ne = R_nb.apply(vel_b)[:2]
                ne = ne + vel_ne * (m._timestamp - rows[-1][0])
                rows.append((m._timestamp, ne[0], ne[1]))
    finally:
        conn.close()
    a = np.array(rows)
    lat, lon, _ = origin.to_geodetic(np.column_stack([a[:, 1], a[:, 2], np.zeros(len(a))]))
    return a[:, 0], lat, lon


def _is_fix(m) -> bool:
    return m.get_type() == "GPS_INPUT" or m.get_type() == "GLOBAL_VISION_POSITION_ESTIMATE"


def _fix_lat_lon_rad(m, ekf_origin: GeoOrigin | None) -> tuple[float, float]:
    """The single fix's latitude and longitude (rad): GPS_INPUT's, or a GLOBAL_VISION_POSITION_ESTIMATE's
    local NED position placed from the autopilot's EKF origin (its GPS_GLOBAL_ORIGIN)."""
    if m.get_type() == "GPS_INPUT":
        return math.radians(m.lat * 1e-7), math.radians(m.lon * 1e-7)
    lat, lon, _ = ekf_origin.to_geodetic(np.array([m.x, m.y, 0.0]))
    return float(lat), float(lon)


def _ekf_origin(tlog: Path) -> GeoOrigin | None:
    """The autopilot's GPS_GLOBAL_ORIGIN, wherever it is in the log (None: none)."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    try:
        m = conn.recv_match(type="GPS_GLOBAL_ORIGIN")
    finally:
        conn.close()
    return None if m is None else GeoOrigin(math.radians(m.latitude * 1e-7), math.radians(m.longitude * 1e-7), 0.0)


def _read_fix(tlog: Path):
    """(the fix message, its latitude and longitude rad) of the log's single fix."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    ekf_origin = _ekf_origin(tlog)
    try:
        while (m := conn.recv_match(type=["GPS_INPUT", "GLOBAL_VISION_POSITION_ESTIMATE"])) is not None:
            return (m, *_fix_lat_lon_rad(m, ekf_origin))
    finally:
        conn.close()
    raise ValueError(f"{tlog}: no fix")


def shared_errors_m(tlog: Path, truth: dict[str, np.ndarray], dvl_errors: dict) -> np.ndarray:
    """Horizontal error (m) at the truth's epochs from the fix on, (K,): :func:`shared_error_ne_m`."""
    _, e = shared_error_ne_m(tlog, truth, dvl_errors)
    return np.hypot(e[:, 0], e[:, 1])


def shared_error_ne_m(tlog: Path, truth: dict[str, np.ndarray], dvl_errors: dict) -> tuple[np.ndarray, np.ndarray]:
    """(t_unix_s (K,), error north/east (K, 2) m) at the truth's epochs from the fix on, of a navigator that knew
    the heading exactly and integrated the DVL without noise from the log's single fix — what
    the errors no aid in the log observes leave: the fix's own error (against the truth where
    the log places it), the DVL's scale factor ``s``, yaw misalignment ``ψ`` and the bias of its
    beams ``b``: ``e(t) = e_fix + s D − ψ e_z × D + Σ R_z(yaw) b Δt`` with ``D`` the displacement
    since the fix (first order; Kinsey & Whitcomb, IEEE JOE 2006). Neither the replay nor the
    dead reckoning removes these; a result better than this is luck (its own errors — for the
    dead reckoning its compass's — cancelling part of them)."""
    fix, fix_lat, fix_lon = _read_fix(tlog)
    o = GeoOrigin(math.radians(truth["lat_deg"][0]), math.radians(truth["lon_deg"][0]), 0.0)
    tn = o.to_ned(np.radians(truth["lat_deg"]), np.radians(truth["lon_deg"]))[:, :2]
    fix_ne = o.to_ned(np.array([fix_lat]), np.array([fix_lon]))[0, :2]
    t = truth["t_unix_s"]
    k = t >= fix._timestamp
    at_fix = np.array([np.interp(fix._timestamp, t, tn[:, j]) for j in range(2)])
    D = tn[k] - at_fix
    psi = math.radians(dvl_errors["misalignment_rpy_deg"][2])
    yaw = np.radians(truth["yaw_deg"][k])
    b = np.asarray(dvl_errors["bias_d_m_s"], dtype=float)
    dt = np.diff(np.concatenate([[fix._timestamp], t[k]]))
    bias_ne = np.cumsum(np.stack([np.cos(yaw) * b[0] - np.sin(yaw) * b[1],
                                  np.sin(yaw) * b[0] + np.cos(yaw) * b[1]], axis=1) * dt[:, None], axis=0)
    e = (fix_ne - at_fix) + dvl_errors["scale_factor_error"] * D - psi * np.stack([-D[:, 1], D[:, 0]], axis=1) + bias_ne
    return t[k], e


def horizontal_errors_m(t_s: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray,
                        truth_t_s: np.ndarray, truth: dict[str, np.ndarray]) -> np.ndarray:
    """Horizontal distance (m) of positions at ``t_s`` to the truth interpolated there (both
    clocks the same: ``truth_t_s`` is the truth's column on the positions' clock)."""
    e = horizontal_error_ne_m(t_s, lat_rad, lon_rad, truth_t_s, truth)[1]
    return np.hypot(e[:, 0], e[:, 1])


def horizontal_error_ne_m(t_s: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray,
                          truth_t_s: np.ndarray, truth: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(the epochs of ``t_s`` inside the truth (K,), position − truth north/east (K, 2) m)."""
    o = GeoOrigin(math.radians(truth["lat_deg"][0]), math.radians(truth["lon_deg"][0]), 0.0)
    tn = o.to_ned(np.radians(truth["lat_deg"]), np.radians(truth["lon_deg"]))
    p = o.to_ned(lat_rad, lon_rad)
    inside = (t_s >= truth_t_s[0]) & (t_s <= truth_t_s[-1])
    n = np.interp(t_s[inside], truth_t_s, tn[:, 0])
    e = np.interp(t_s[inside], truth_t_s, tn[:, 1])
    return t_s[inside], np.column_stack([p[inside, 0] - n, p[inside, 1] - e])


def error_budget(tlog: Path, truth: dict[str, np.ndarray], dvl_errors: dict, ours: tuple, dr: tuple) -> dict:
    """Each navigator's error split into what it shares with the other and what is its own:
    ``e(t) = e_shared(t) + ∫ δψ(τ) e_z × v(τ) dτ + rest`` — the errors no aid observes
    (:func:`shared_error_ne_m`), its heading error δψ acting on the true velocity ``v``, and
    the rest (its integration of the DVL: timing, noise, outliers, turns, its start). For a
    filter whose heading converges (a gyrocompass after a compass seed) the rest also holds
    the correction its position gets through its correlation with the heading — the two parts
    then largely cancel, and only their sum means anything.

    Parameters
    ----------
    ours : (t_boot_s (K,), error north/east (K, 2) m, heading error (K,) rad) of the replay
    dr : (t_unix_s (J,), error north/east (J, 2) m) of the dead reckoning; its heading error
        is the log's ATTITUDE's (read from ``tlog``)

    Returns
    -------
    dict : per navigator (``"ours"``, ``"dr"``) the norms (m) at the end of ``shared``,
        ``heading`` and ``rest`` and the RMS of ``rest``
    """
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    att = []
    try:
        while (m := conn.recv_match(type="ATTITUDE")) is not None:
            att.append((m.time_boot_ms * 1e-3, m.yaw))
    finally:
        conn.close()
    att = np.array(att)
    tb, tu = truth["t_boot_s"], truth["t_unix_s"]
    yaw_t = np.unwrap(np.radians(truth["yaw_deg"]))
    o = GeoOrigin(math.radians(truth["lat_deg"][0]), math.radians(truth["lon_deg"][0]), 0.0)
    tn = o.to_ned(np.radians(truth["lat_deg"]), np.radians(truth["lon_deg"]))[:, :2]
    vel = np.column_stack([np.gradient(tn[:, 0], tb), np.gradient(tn[:, 1], tb)])
    t_sh, e_sh = shared_error_ne_m(tlog, truth, dvl_errors)
    t_sh = np.interp(t_sh, tu, tb)
    out = {}
    for name, t, e, dpsi in (
            ("ours", *ours),
            ("dr", np.interp(dr[0], tu, tb), dr[1], None)):
        k = t >= t_sh[0]
        t, e = t[k], e[k]
        if dpsi is None:  # the ATTITUDE's yaw error, held between samples as the dead reckoning does
            j = np.clip(np.searchsorted(att[:, 0], t, side="right") - 1, 0, len(att) - 1)
            dpsi = np.angle(np.exp(1j * (att[j, 1] - np.interp(att[j, 0], tb, yaw_t))))
        else:
            dpsi = np.asarray(dpsi)[k]
        v = np.column_stack([np.interp(t, tb, vel[:, 0]), np.interp(t, tb, vel[:, 1])])
        dt = np.diff(np.concatenate([[t[0]], t]))
        heading = np.cumsum(dpsi[:, None] * np.column_stack([-v[:, 1], v[:, 0]]) * dt[:, None], axis=0)
        shared = np.column_stack([np.interp(t, t_sh, e_sh[:, j]) for j in range(2)])
        rest = e - shared - heading
        out[name] = {"shared_end_m": float(np.hypot(*shared[-1])), "heading_end_m": float(np.hypot(*heading[-1])),
                     "rest_end_m": float(np.hypot(*rest[-1])),
                     "rest_rms_m": float(np.sqrt(np.mean(np.sum(rest**2, axis=1))))}
    return out
