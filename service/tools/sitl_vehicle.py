"""A simulated vehicle behind an ArduSub-like MAVLink endpoint (demo and tests).

It takes timestamped samples (``adaptnav.sim.simulate(...).iter_samples()`` or any iterable of
samples in time order) and speaks to the link as ArduSub would:

- HEARTBEAT at 1 Hz as ``MAV_TYPE_SUBMARINE`` / ``MAV_AUTOPILOT_ARDUPILOTMEGA``
  (system 1, component 1);
- the sensor streams at ArduSub's default rates (IMU 2 Hz, ATTITUDE 10 Hz, ...) until
  a ``MAV_CMD_SET_MESSAGE_INTERVAL`` changes them (answered with COMMAND_ACK) —
  HIGHRES_IMU, RAW_IMU or SCALED_IMU2 from :class:`ImuSample`, ATTITUDE from
  :class:`AttitudeSample` (or, for a simulator that has none, truth roll/pitch with the
  latest :class:`HeadingSample` as yaw — an AHRS's output), SCALED_PRESSURE2 from :class:`DepthSample`,
  SERVO_OUTPUT_RAW from :class:`RpmSample` through the inverse thruster curve,
  GPS_RAW_INT from :class:`GnssSample` (surface fixes), GPS_INPUT from
  :class:`UsblSample` (as the Water Linked UGPS component 220 does), DISTANCE_SENSOR
  from :class:`AltitudeSample`;
- ``time_boot_ms`` follows the data time: ``time_boot_ms = round(1000 (t_s + boot_offset_s))``;
  ``speed`` sets the pace (data seconds per wall second; 0 = as fast as possible);
- it records what comes back: ODOMETRY count and last message/quality,
  SET_GPS_GLOBAL_ORIGIN, the onboard component's heartbeats and the interval requests.

Unit conversions go through :mod:`adaptnav.service.transport.mavlink_convert` constants, the inverse of
what the bridge applies.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from adaptnav.service.transport.mavlink_convert import (  # sets MAVLINK20 before pymavlink loads
    DEG_E7_TO_RAD,
    HPA_TO_PA,
    MG_TO_M_S2,
    MRAD_TO_RAD,
    ThrusterConfig,
    mavlink2,
)
from adaptnav.fusion.frames import quat_to_euler

from pymavlink import mavutil  # noqa: E402

# ArduSub's stream defaults (SRn_* parameters as shipped): what a bridge sees before asking
ARDUSUB_DEFAULT_RATES_HZ = {
    "RAW_IMU": 2.0, "SCALED_IMU2": 2.0, "HIGHRES_IMU": 0.0, "ATTITUDE": 10.0,
    "SCALED_PRESSURE2": 2.0, "SERVO_OUTPUT_RAW": 2.0, "GPS_RAW_INT": 2.0, "DISTANCE_SENSOR": 2.0,
}
_IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2")


@dataclass(frozen=True)
class SitlVehicleConfig:
    """The simulated vehicle's endpoint."""

    url: str = "udpout:127.0.0.1:14550"
    system_id: int = 1
    component_id: int = 1
    ugps_component_id: int = 220  # Water Linked UGPS extension on BlueOS
    speed: float = 10.0  # data seconds per wall second; 0 = as fast as possible
    boot_offset_s: float = 0.0
    heartbeat_period_s: float = 1.0
    second_imu: bool = False  # a BlueROV2 Navigator/Pixhawk streams zeros for an absent IMU2
    thrusters: ThrusterConfig = field(default_factory=ThrusterConfig)
    pwm_channels: int = 8
    distance_min_cm: int = 20
    distance_max_cm: int = 5000


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))


class SitlVehicle:
    """Stream samples as an ArduSub vehicle and record what the other side sends.

    Parameters
    ----------
    samples : iterable
        Samples in non-decreasing ``t_s`` order.
    config : SitlVehicleConfig, optional
    on_other_sample : callable, optional
        Called (in the vehicle thread, at the data pace) with every sample that has no
        ArduSub MAVLink message, e.g. side-scan pings that a sonar driver on the
        companion computer publishes itself; such samples are still counted in
        ``sent["not_sent_by_kind"]``.

    Attributes
    ----------
    received : dict
        ``odometry`` (count), ``last_odometry`` (the message), ``last_quality``,
        ``origin`` (SET_GPS_GLOBAL_ORIGIN message or None), ``onboard_heartbeats``,
        ``interval_requests`` ({message name: interval µs}).
    sent : dict
        Messages sent by type; ``not_sent_by_kind`` for samples with no ArduSub message.
    """

    def __init__(self, samples: Iterable[Any], config: SitlVehicleConfig | None = None,
                 on_other_sample: Callable[[Any], None] | None = None):
        self.config = config or SitlVehicleConfig()
        self.on_other_sample = on_other_sample
        self.samples = samples
        self.interval_s = {k: (1.0 / v if v > 0 else math.inf) for k, v in ARDUSUB_DEFAULT_RATES_HZ.items()}
        self._last_sent_t: dict[str, float] = {}
        self.received: dict[str, Any] = {"odometry": 0, "pose_only": 0, "last_odometry": None, "last_quality": None,
                                         "origin": None, "onboard_heartbeats": 0, "interval_requests": {},
                                         "odometry_log": []}
        self.sent: dict[str, Any] = {"not_sent_by_kind": {}}
        self.t_data_s: float | None = None
        self._omega_b = (0.0, 0.0, 0.0)
        self._heading_rad: float | None = None
        self._have_attitude_samples = False
        self._ugps_seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.conn = mavutil.mavlink_connection(self.config.url, source_system=self.config.system_id,
                                               source_component=self.config.component_id,
                                               dialect="ardupilotmega")
        self.done = threading.Event()
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ running
    def start(self) -> "SitlVehicle":
        self._thread = threading.Thread(target=self._run_guarded, name="sitl-vehicle", daemon=True)
        self._thread.start()
        return self

    def _run_guarded(self) -> None:
        try:
            self.run()
        except BaseException as e:  # reported to the caller through .error
            self.error = e
        finally:
            self.done.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def close(self) -> None:
        self.stop()
        self.conn.close()

    def run(self, linger_s: float = 0.0) -> None:
        """Send every sample (paced by ``speed``), then keep serving for ``linger_s``."""
        wall0 = time.monotonic()
        t0: float | None = None
        next_hb_wall = 0.0
        last_hb_data = -math.inf
        next_poll_wall = 0.0
        for sample in self.samples:
            if self._stop.is_set():
                return
            t = float(sample.t_s)
            t0 = t if t0 is None else t0
            if self.config.speed > 0:
                target = wall0 + (t - t0) / self.config.speed
                while not self._stop.is_set():
                    self.poll()
                    dt = target - time.monotonic()
                    if dt <= 0:
                        break
                    self.conn.select(min(dt, 0.02))
            elif time.monotonic() >= next_poll_wall:  # unpaced: poll every few ms, not per sample
                self.poll()
                next_poll_wall = time.monotonic() + 0.005
            self.t_data_s = t
            now = time.monotonic()
            if now >= next_hb_wall or t - last_hb_data >= self.config.heartbeat_period_s:
                self.heartbeat()
                next_hb_wall = now + self.config.heartbeat_period_s
                last_hb_data = t
            self.send_sample(sample)
        end = time.monotonic() + linger_s
        while not self._stop.is_set() and time.monotonic() < end:
            if time.monotonic() >= next_hb_wall:
                self.heartbeat()
                next_hb_wall = time.monotonic() + self.config.heartbeat_period_s
            self.poll()
            self.conn.select(0.02)

    # ------------------------------------------------------------------ receiving
    def poll(self) -> int:
        """Handle everything that has arrived; returns the number of messages."""
        n = 0
        while True:
            msg = self.conn.recv_msg()
            if msg is None:
                return n
            n += 1
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        mtype = msg.get_type()
        rec = self.received
        if mtype == "ODOMETRY":
            rec["odometry"] += 1
            rec["last_odometry"] = msg
            rec["last_quality"] = msg.quality
            rec["odometry_log"].append((self.t_data_s, msg))
        elif mtype == "VISION_POSITION_ESTIMATE":  # the bridge's pose without velocity
            rec["pose_only"] += 1
        elif mtype == "SET_GPS_GLOBAL_ORIGIN":
            rec["origin"] = msg
        elif mtype == "HEARTBEAT" and msg.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER:
            rec["onboard_heartbeats"] += 1
        elif mtype == "COMMAND_LONG" and msg.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL \
                and msg.target_system in (0, self.config.system_id):
            name = mavlink2.mavlink_map[int(msg.param1)].msgname if int(msg.param1) in mavlink2.mavlink_map else None
            result = mavlink2.MAV_RESULT_UNSUPPORTED
            if name is not None:
                us = msg.param2
                rec["interval_requests"][name] = us
                if us < 0:
                    self.interval_s[name] = math.inf
                elif us == 0:
                    hz = ARDUSUB_DEFAULT_RATES_HZ.get(name, 0.0)
                    self.interval_s[name] = 1.0 / hz if hz > 0 else math.inf
                else:
                    self.interval_s[name] = us / 1e6
                result = mavlink2.MAV_RESULT_ACCEPTED
            self.conn.mav.command_ack_send(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, result)

    # ------------------------------------------------------------------ sending
    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 19,  # ArduSub MANUAL
                                     mavlink2.MAV_STATE_ACTIVE)
        self._count("HEARTBEAT")

    def _count(self, name: str) -> None:
        self.sent[name] = self.sent.get(name, 0) + 1

    def _due(self, name: str, t: float) -> bool:
        """Rate limiter in data time (5 % slack so 200 Hz → 50 Hz keeps every 4th)."""
        interval = self.interval_s.get(name, math.inf)
        if not math.isfinite(interval):
            return False
        last = self._last_sent_t.get(name)
        if last is not None and t - last < 0.95 * interval:
            return False
        self._last_sent_t[name] = t
        return True

    def _send_attitude(self, t: float, roll: float, pitch: float, yaw: float) -> None:
        if self._due("ATTITUDE", t):
            self.conn.mav.attitude_send(self._boot_ms(t), float(roll), float(pitch), float(yaw),
                                        *map(float, self._omega_b))
            self._count("ATTITUDE")

    def _boot_ms(self, t: float) -> int:
        return int(round((t + self.config.boot_offset_s) * 1000.0))

    def _boot_us(self, t: float) -> int:
        return int(round((t + self.config.boot_offset_s) * 1e6))

    def send_sample(self, s: Any) -> None:
        kind = s.KIND
        mav = self.conn.mav
        t = float(s.t_s)
        if kind == "imu":
            self._omega_b = s.omega_b_rad_s
            f, w = s.specific_force_b_m_s2, s.omega_b_rad_s
            for name in _IMU_MESSAGES:
                if not self._due(name, t):
                    continue
                if name == "HIGHRES_IMU":
                    mav.highres_imu_send(self._boot_us(t), *map(float, f), *map(float, w), 0.0, 0.0, 0.0,
                                         math.nan, 0.0, math.nan, 15.0, 0x3F)
                elif name == "RAW_IMU":
                    mav.raw_imu_send(self._boot_us(t), *(_i16(a / MG_TO_M_S2) for a in f),
                                     *(_i16(g / MRAD_TO_RAD) for g in w), 0, 0, 0)
                else:
                    acc = [_i16(a / MG_TO_M_S2) for a in f] if self.config.second_imu else [0, 0, 0]
                    gyr = [_i16(g / MRAD_TO_RAD) for g in w] if self.config.second_imu else [0, 0, 0]
                    mav.scaled_imu2_send(self._boot_ms(t), *acc, *gyr, 0, 0, 0)
                self._count(name)
        elif kind == "attitude":
            self._have_attitude_samples = True
            self._send_attitude(t, s.roll_rad, s.pitch_rad, s.yaw_rad)
        elif kind == "heading":
            self._heading_rad = s.yaw_rad
        elif kind == "truth" and not self._have_attitude_samples:
            # ArduSub's ATTITUDE is its AHRS output: roll/pitch are good to a fraction of
            # a degree, heading is the compass's — so truth roll/pitch, measured heading
            roll, pitch, yaw = quat_to_euler(np.asarray(s.q_nb, dtype=float))
            yaw = self._heading_rad if self._heading_rad is not None else yaw
            self._send_attitude(t, roll, pitch, yaw)
        elif kind == "depth":
            if self._due("SCALED_PRESSURE2", t):
                mav.scaled_pressure2_send(self._boot_ms(t), s.pressure_pa / HPA_TO_PA, 0.0, 1500)
                self._count("SCALED_PRESSURE2")
        elif kind == "rpm":
            if self._due("SERVO_OUTPUT_RAW", t):
                pwm = [1500] * max(self.config.pwm_channels, 8)
                th = self.config.thrusters
                for ch, sign in zip(th.channels, th.forward_signs):
                    # rpm = mean_i sign_i·curve(pwm_i): give every thruster sign_i·rpm
                    pwm[ch - 1] = th.curve.pwm_of_rpm(sign * s.rpm)
                mav.servo_output_raw_send(self._boot_us(t) % 2**32, 0, *pwm[:16])
                self._count("SERVO_OUTPUT_RAW")
        elif kind == "gnss":
            mav.gps_raw_int_send(self._boot_us(t), 3, int(round(s.lat_rad / DEG_E7_TO_RAD)),
                                 int(round(s.lon_rad / DEG_E7_TO_RAD)), 0, 100, 65535, 0, 65535, 12,
                                 0, int(round(s.sigma_h_m * 1000)), 0, 0, 0, 0)
            self._count("GPS_RAW_INT")
        elif kind == "usbl":
            flags = 4 | 8 | 16 | 32  # VDOP, horizontal/vertical velocity, speed accuracy ignored
            if not math.isfinite(s.depth_m):
                flags |= 1
            if not math.isfinite(s.sigma_v_m):
                flags |= 128
            alt = -s.depth_m if math.isfinite(s.depth_m) else 0.0
            sv = s.sigma_v_m if math.isfinite(s.sigma_v_m) else 0.0
            # the UGPS is its own component with its own sequence numbers (the receiver
            # counts gaps per sender as lost packets)
            vehicle_seq, mav.seq = mav.seq, self._ugps_seq
            self.conn.mav.srcComponent = self.config.ugps_component_id
            try:
                mav.gps_input_send(0, 0, flags, 0, 0, 3, int(round(s.lat_rad / DEG_E7_TO_RAD)),
                                   int(round(s.lon_rad / DEG_E7_TO_RAD)), alt, 1.0, 65535.0, 0.0, 0.0, 0.0,
                                   0.0, float(s.sigma_h_m), sv, 0)
            finally:
                self.conn.mav.srcComponent = self.config.component_id
                self._ugps_seq, mav.seq = mav.seq, vehicle_seq
            self._count("GPS_INPUT")
        elif kind in ("altitude", "dvl"):
            alt_m = s.altitude_m
            if not np.isfinite(alt_m):
                return
            if self._due("DISTANCE_SENSOR", t):
                cm = int(round(alt_m * 100.0))
                mav.distance_sensor_send(self._boot_ms(t), self.config.distance_min_cm, self.config.distance_max_cm,
                                         max(0, min(cm, 65535)), mavlink2.MAV_DISTANCE_SENSOR_ULTRASOUND, 1,
                                         mavlink2.MAV_SENSOR_ROTATION_PITCH_270, 255)
                self._count("DISTANCE_SENSOR")
        else:
            nk = self.sent["not_sent_by_kind"]
            nk[kind] = nk.get(kind, 0) + 1
            if self.on_other_sample is not None:
                self.on_other_sample(s)
