"""The MAVLink side's settings (``[mavlink]``, ``[mavlink.convert]``, ``[mavlink.output]``): plain
dataclasses, no pymavlink — a process that only reads a :class:`adaptnav.service.config.ServiceConfig`
(the calibrator child unpickles one) need not load the MAVLink dialect (~13 MB).
:mod:`adaptnav.service.transport.mavlink_convert` and :mod:`.mavlink_bridge` use them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class PwmRpmCurve:
    """Piecewise-linear thruster curve PWM [µs] → propeller RPM (signed).

    Default: Blue Robotics T200 on a BlueROV2 — neutral 1500 µs, dead band ±25 µs,
    ±400 µs full scale, ~3500 rev/min at full throttle.
    """

    pwm_us: tuple[float, ...] = (1100.0, 1475.0, 1525.0, 1900.0)
    rpm: tuple[float, ...] = (-3500.0, 0.0, 0.0, 3500.0)
    neutral_us: float = 1500.0

    def validate(self) -> None:
        if len(self.pwm_us) != len(self.rpm) or len(self.pwm_us) < 2:
            raise ValueError("pwm_us and rpm need the same length (≥ 2)")
        if np.any(np.diff(self.pwm_us) <= 0):
            raise ValueError("pwm_us must increase strictly")
        if np.any(np.diff(self.rpm) < 0):
            raise ValueError("rpm must not decrease with pwm_us")
        if not (self.pwm_us[0] <= self.neutral_us <= self.pwm_us[-1]):
            raise ValueError("neutral_us outside the pwm_us table")

    def rpm_of_pwm(self, pwm_us: float) -> float:
        """RPM at a PWM width (clipped to the table ends)."""
        return float(np.interp(pwm_us, self.pwm_us, self.rpm))

    def pwm_of_rpm(self, rpm: float) -> int:
        """Inverse: the PWM width [µs, integer as on the wire] giving ``rpm``.

        Zero maps to ``neutral_us``; the dead band is skipped by inverting only the
        branch on the side of ``rpm``'s sign.
        """
        pwm = np.asarray(self.pwm_us, dtype=float)
        table = np.asarray(self.rpm, dtype=float)
        if rpm == 0.0 or not math.isfinite(rpm):
            return int(round(self.neutral_us))
        side = pwm >= self.neutral_us if rpm > 0 else pwm <= self.neutral_us
        p, r = pwm[side], table[side]
        # keep the strictly monotonic part that leaves the dead band (np.interp needs it)
        keep = np.r_[True, np.diff(r) != 0] if rpm > 0 else np.r_[np.diff(r) != 0, True]
        p, r = p[keep], r[keep]
        return int(round(float(np.interp(rpm, r, p))))


@dataclass(frozen=True)
class ThrusterConfig:
    """Which SERVO_OUTPUT_RAW channels drive the vehicle forward, and how."""

    channels: tuple[int, ...] = (1, 2, 3, 4)  # servoN_raw, 1-based as in ArduPilot
    forward_signs: tuple[float, ...] = (-1.0, -1.0, 1.0, 1.0)  # BlueROV2 vectored frame
    # lateral (strafe, starboard +) factors of the same channels (AP_Motors6DOF vectored:
    # +1, −1, +1, −1); empty: no lateral thrusters (RpmSample.sway_rpm = 0)
    lateral_signs: tuple[float, ...] = (1.0, -1.0, 1.0, -1.0)
    curve: PwmRpmCurve = field(default_factory=PwmRpmCurve)
    # ArduPilot's simulator (SITL, libraries/SITL/SIM_Submarine.cpp) has no ESC: its thrust is
    # linear in the PWM offset from 1500 µs, without the T200 Basic ESC's ±25 µs dead band. A
    # source that is that simulator (its truth, SIM_STATE / SIMSTATE / DataFlash SIM, or a SIM_*
    # parameter in the stream) is converted through this curve instead of ``curve`` (a profile that wants its
    # own curve there too sets both alike).
    simulator_curve: PwmRpmCurve = field(default_factory=lambda: PwmRpmCurve(
        pwm_us=(1100.0, 1500.0, 1900.0), rpm=(-3500.0, 0.0, 3500.0)))

    def validate(self) -> None:
        if len(self.channels) != len(self.forward_signs) or not self.channels:
            raise ValueError("channels and forward_signs need the same (non-zero) length")
        if self.lateral_signs and len(self.lateral_signs) != len(self.channels):
            raise ValueError("lateral_signs: one per channel (or empty)")
        if any(not 1 <= c <= 16 for c in self.channels):
            raise ValueError("channels are servo outputs 1..16")


@dataclass(frozen=True)
class ConvertConfig:
    """How ArduSub messages become samples (the ``[mavlink.convert]`` config section)."""

    # "auto": lock on the first IMU message type that carries a real (non-zero) sample
    imu_message: Literal["auto", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "HIGHRES_IMU"] = "auto"
    # the integrated IMU stream silent this long (mission time, s): another stream, of any rank,
    # takes over (an autopilot's IMU failover changes HIGHRES_IMU's id; a driver restarts)
    imu_stream_silent_s: float = 1.0
    # the external (water) pressure sensor's message. "auto": the one ArduSub made its primary
    # barometer (it picks the first water-type sensor and saves BARO_PRIMARY: 1 on a Pixhawk or
    # Navigator with a Bar30 — SCALED_PRESSURE2 — 2 on a board with two of its own), read from
    # PARAM_VALUE / PARM; SCALED_PRESSURE2 until it is known, or when it is 0 (no water sensor
    # found — or ArduSub's simulator, whose every baro reads the water)
    depth_message: Literal["auto", "SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3"] = "auto"
    thrusters: ThrusterConfig = field(default_factory=ThrusterConfig)
    gnss_min_fix_type: int = 3  # GPS_FIX_TYPE_3D_FIX
    gnss_sigma_per_hdop_m: float = 2.5  # σ_h = HDOP × this when h_acc is absent
    usbl_sigma_per_hdop_m: float = 1.0  # Water Linked UGPS reports HDOP only
    usbl_min_sigma_m: float = 0.3
    # GPS_RAW_INT that merely echoes GPS_INPUT (GPS1_TYPE=14) is dropped for this long
    # after the last GPS_INPUT, or the same acoustic fix would be fused twice
    gps_input_echo_window_s: float = 5.0
    # a pressure or position message equal to the previous one (REPEAT_CHECKED) within this
    # long (mission s) of when that reading came first is the same reading passed on again; a
    # steady reading still aids at least this often (a quantised barometer at rest repeats)
    repeat_window_s: float = 2.0
    altitude_orientation: int = 25  # MAV_SENSOR_ROTATION_PITCH_270 = looking down
    autopilot_component: int = 1  # MAV_COMP_ID_AUTOPILOT1
    reboot_backjump_s: float = 2.0  # a clock going back further than this is a reboot
    # companion-side drivers: BlueOS's DVL and UGPS extensions send as system 255, component 0
    aid_system_ids: tuple[int, ...] = (255,)
    aid_component_ids: tuple[int, ...] = ()  # empty: any component of those systems
    # "acoustic": GPS_RAW_INT (a DataFlash log's GPS) carries an underwater GPS's fixes (no
    # surface-only rule); "auto": acoustic when the autopilot says its GPS is a MAVLink one
    # (GPS_TYPE / GPS1_TYPE 14: GPS_INPUT from the companion — on an ROV, the underwater GPS),
    # read from its parameters (PARAM_VALUE, a DataFlash log's PARM)
    gps_raw_int_source: Literal["auto", "gnss", "acoustic"] = "auto"
    # DVL from VISION_POSITION_DELTA: BlueOS maps the DVL's figure of merit (its velocity
    # 1-σ, m/s) to confidence = 100·(1 − min(fom, 0.4)/0.4); inverted here
    dvl_confidence_fom_max_m_s: float = 0.4
    dvl_min_confidence: float = 1.0  # below: no bottom lock (valid = False)
    dvl_max_angle_delta_rad: float = 0.35  # rotation within one delta above which it is rejected
    # "ping": BlueOS's DVL driver (delta = the ping's velocity × dt, current frame, valid at the
    # message); "mean": displacement over the interval in the frame at its start (mid-interval)
    dvl_delta: Literal["ping", "mean"] = "ping"
    dvl_max_interval_s: float = 5.0
    # a delta without a time of its own (time_usec = 0, as BlueOS sends it) is placed at its
    # reception minus this (s): the DVL's and its driver's delivery latency, if known
    dvl_latency_s: float = 0.0
    vision_speed_frame: Literal["body", "ned"] = "body"  # BlueOS sends the DVL's body-frame velocity
    vision_position_sigma_m: float = 2.0  # GLOBAL_VISION_POSITION_ESTIMATE without a covariance
    # a sample without a placeable time is held at most this long (receive time) before the
    # source is taken to have no boot clock
    hold_max_s: float = 5.0
    hold_max_messages: int = 5000

    def validate(self) -> None:
        if self.gnss_sigma_per_hdop_m <= 0 or self.usbl_sigma_per_hdop_m <= 0:
            raise ValueError("sigma_per_hdop_m must be > 0")
        if self.reboot_backjump_s <= 0:
            raise ValueError("reboot_backjump_s must be > 0")
        if self.dvl_confidence_fom_max_m_s <= 0 or self.vision_position_sigma_m <= 0:
            raise ValueError("dvl_confidence_fom_max_m_s and vision_position_sigma_m must be > 0")
        if self.hold_max_s <= 0 or self.hold_max_messages <= 0:
            raise ValueError("hold_max_s and hold_max_messages must be > 0")
        if not 0.0 <= self.dvl_latency_s <= 1.0:
            raise ValueError("dvl_latency_s must be within [0, 1] s")
        if not self.imu_stream_silent_s > 0.0:
            raise ValueError("imu_stream_silent_s must be > 0")


@dataclass(frozen=True)
class OdometryConfig:
    """ODOMETRY output (the ``[mavlink.output]`` config section)."""

    sigma_best_m: float = 0.5  # horizontal 1-σ mapped to quality 100
    sigma_worst_m: float = 50.0  # ... and to quality 1
    invalid: Literal["silence", "failed"] = "silence"  # "failed": quality -1, NaN pose
    estimator_type: int = 3  # MAV_ESTIMATOR_TYPE_VIO
    vision_position_delta: bool = False  # also send VISION_POSITION_DELTA between outputs
    # below this quality nothing is sent (silence, not a down-rated solution); set ArduSub's
    # VISO_QUAL_MIN to the same number (docs/vehicle.md, ArduSub parameters) so both ends draw the line at one σ_h
    # (quality 10 ⇔ σ_h ≈ 33 m with the defaults)
    min_quality: int = 10
    # horizontal velocity 1-σ above which no aid has constrained the velocity for longer than
    # the covariance allows: the pose goes out alone (VISION_POSITION_ESTIMATE), no velocity
    max_velocity_sigma_m_s: float = 0.3

    def validate(self) -> None:
        if not 0 < self.sigma_best_m < self.sigma_worst_m:
            raise ValueError("need 0 < sigma_best_m < sigma_worst_m")
        if not 1 <= self.min_quality <= 100:
            raise ValueError("min_quality must be within [1, 100]")
        if not self.max_velocity_sigma_m_s > 0:
            raise ValueError("max_velocity_sigma_m_s must be > 0")


@dataclass(frozen=True)
class StreamRates:
    """Rates requested from the autopilot, Hz (0 = leave the autopilot's default)."""

    imu_hz: float = 50.0
    attitude_hz: float = 50.0
    pressure_hz: float = 10.0
    servo_hz: float = 10.0
    gps_raw_hz: float = 5.0
    distance_hz: float = 10.0


_NET_SCHEMES = ("udpin:", "udpout:", "udpbcast:", "udp:", "tcpin:", "tcp:")
_OTHER_SCHEMES = ("mcast:", "ws:", "wss:", "wsserver:")  # pymavlink's own, checked when opened


_DEFAULT_BAUD = 115200


def _check_port(port: str) -> None:
    if not (port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f"port {port!r} is not 1–65535")


def _baud(text: str) -> int:
    if not (text.isdigit() and int(text) > 0):
        raise ValueError(f"baud {text!r} is not a positive integer")
    return int(text)


def split_link_url(url: str) -> tuple[str, int]:
    """A bridge URL → (pymavlink device string, baud); ``ValueError`` (why, in a few words) for
    one that can never be opened. The forms: pymavlink's own (``udpin:H:P``, ``udpout:H:P``,
    ``tcp:H:P``, ``tcpin:H:P``, bare ``H:P`` for UDP, ``/dev/ttyACM0[,baud]``, ``COM3``,
    ``mcast:`` …) and ``serial:/dev/ttyACM0[:baud]``. A device that is missing or a host that
    does not answer is the link's business (retried), not this."""
    if not url:
        raise ValueError("empty")
    for scheme in _NET_SCHEMES:
        if url.startswith(scheme):
            host, sep, port = url[len(scheme):].rpartition(":")
            if not (sep and host):
                raise ValueError(f"{scheme[:-1]} needs HOST:PORT")
            _check_port(port)
            return url, _DEFAULT_BAUD
    if url.startswith(_OTHER_SCHEMES):
        return url, _DEFAULT_BAUD
    if url.startswith("serial:"):
        device, sep, baud = url[len("serial:"):].rpartition(":")
        if not sep:
            device, baud = baud, str(_DEFAULT_BAUD)
        if not device:
            raise ValueError("serial: needs a device (serial:/dev/ttyACM0[:BAUD])")
        return device, _baud(baud)
    if url.startswith("/"):
        device, sep, baud = url.rpartition(",")
        return (device, _baud(baud)) if sep else (url, _DEFAULT_BAUD)
    if ":" in url:  # pymavlink takes HOST:PORT without a scheme for UDP
        host, _, port = url.rpartition(":")
        try:
            _check_port(port)
            if not host:
                raise ValueError("no host")
        except ValueError as e:
            raise ValueError(f"{e} (no scheme: pymavlink reads HOST:PORT as UDP; udpin:, udpout:, tcp:, serial: …)") \
                from None
    return url, _DEFAULT_BAUD


@dataclass(frozen=True)
class BridgeConfig:
    """``[mavlink]`` section: link, identity, requested rates, conversion and output."""

    # loopback: only programs on this computer (the BlueOS MAVLink router) can feed the
    # filter; a LAN address or 0.0.0.0 is an explicit choice (deploy/adaptnav.toml)
    url: str = "udpin:127.0.0.1:14550"
    source_system: int = 1  # onboard components share the vehicle's system id
    source_component: int = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    heartbeat_period_s: float = 1.0
    link_timeout_s: float = 3.0
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 5.0
    # "auto": HIGHRES_IMU (float, ArduSub 4.5+), RAW_IMU (int16 mg, mrad/s) only as a fallback
    request_imu_message: str = "auto"
    imu_fallback_s: float = 3.0  # no HIGHRES_IMU this long after asking: fall back to RAW_IMU
    origin_retry_s: float = 5.0
    origin_retries: int = 5
    rates: StreamRates = field(default_factory=StreamRates)
    udp_rcvbuf_bytes: int = 4 * 1024 * 1024
    # MAVLink 2 signing, for an autopilot that requires it (ArduPilot drops unsigned messages
    # on a signed channel: our ODOMETRY would vanish): a file holding the passphrase the ground
    # station set the key from (the key is its SHA-256, as MAVProxy and QGroundControl derive
    # it) — a file, as zenoh.auth.password_file, so the secret is in neither the logged config
    # nor the query/config answer; "" off
    signing_passphrase_file: str = ""
    # ... and unsigned messages in are still taken (BlueOS's drivers — a DVL, a UGPS — send
    # through mavlink2rest, which does not sign); false: only correctly signed ones
    signing_accept_unsigned: bool = True
    convert: ConvertConfig = field(default_factory=ConvertConfig)
    output: OdometryConfig = field(default_factory=OdometryConfig)

    def validate(self) -> None:
        try:  # a form that can never be opened is said at start: it was retried forever with
            split_link_url(self.url)  # pymavlink's message ("invalid literal for int()")
        except ValueError as e:
            raise ValueError(f"url {self.url!r} cannot be opened: {e}") from None
        if self.heartbeat_period_s <= 0 or self.link_timeout_s <= 0:
            raise ValueError("heartbeat_period_s and link_timeout_s must be > 0")
        if not 0 < self.reconnect_min_s <= self.reconnect_max_s:
            raise ValueError("need 0 < reconnect_min_s ≤ reconnect_max_s")
        if self.request_imu_message not in ("auto", "RAW_IMU", "SCALED_IMU2", "HIGHRES_IMU"):
            raise ValueError("request_imu_message: auto, RAW_IMU, SCALED_IMU2 or HIGHRES_IMU")
        if self.imu_fallback_s <= 0 or self.origin_retry_s <= 0 or self.origin_retries < 0:
            raise ValueError("imu_fallback_s and origin_retry_s must be > 0, origin_retries ≥ 0")
