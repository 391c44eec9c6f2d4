"""MAVLink ↔ adaptnav samples: every unit conversion at the MAVLink edge lives here.

In (from ArduSub), one pure function per message, time already mapped to mission
seconds ``t_s``:

====================  ===============================================  =================
message               fields → sample                                  conversion
====================  ===============================================  =================
RAW_IMU, SCALED_IMU2  x/y/z acc [mg], x/y/z gyro [mrad/s] → ImuSample  ×g/1000, ×1e-3
HIGHRES_IMU           acc [m/s²], gyro [rad/s] → ImuSample             none
ATTITUDE              roll, pitch, yaw [rad] → AttitudeSample          yaw wrapped
SCALED_PRESSURE2      press_abs [hPa] → DepthSample.pressure_pa        ×100
SERVO_OUTPUT_RAW      thruster PWM [µs] → RpmSample                    :class:`PwmRpmCurve`
GPS_RAW_INT           lat/lon [degE7], h_acc [mm] / eph [HDOP×100]     → rad, m
GPS_INPUT             lat/lon [degE7], alt [m up], accuracies [m]      → UsblSample
DISTANCE_SENSOR       current_distance [cm], downward only             ×0.01
====================  ===============================================  =================

ArduSub scales RAW_IMU like SCALED_IMU (mg, mrad/s): the real logs in
``../shared/data/mavlink`` read ``zacc ≈ -1000`` at rest — i.e. the body-FRD specific
force ``f_b = R_bn (a_n - g_n) = (0, 0, -g)``, our convention.  An all-zero SCALED_IMU2
means "no second IMU" (ArduSub still streams it) and is rejected, never fused.

Thrusters: ``rpm = mean_i s_i · curve(pwm_i)`` over the forward thrusters ``i`` with
their forward-thrust signs ``s_i`` (BlueROV2 vectored frame: motors 1–4 with forward
factors −1, −1, +1, +1 in ArduSub's AP_Motors6DOF); ``curve`` is a piecewise-linear
table with a dead band around the 1500 µs neutral.  The simulated vehicle uses the
inverse (:meth:`PwmRpmCurve.pwm_of_rpm`).

Time: ``time_boot_ms`` / ``time_usec`` of the autopilot map to mission seconds through
:class:`TimeMapper` (32-bit millisecond wrap after 49.7 days and reboots keep the
mission clock monotonic).  Messages from other components (a Ping echosounder driver,
the Water Linked UGPS extension) carry their own clocks; they are stamped with the
autopilot time at reception (error ≤ one autopilot message interval).

Out (to ArduSub): :func:`odometry_fields` turns a ``NavState`` into ODOMETRY with
``frame_id = MAV_FRAME_LOCAL_FRD``, ``child_frame_id = MAV_FRAME_BODY_FRD`` (the only
combination ArduSub's EKF3 follows, see DESIGN.md "MAVLink"): position ``pos_n``,
attitude ``q_nb`` (w, x, y, z as MAVLink), velocity in body ``vel_b = R_nbᵀ vel_n``,
covariances as the 21-element row-major upper triangles, and
``quality = 100 − 99·clip(log(σ_h/σ_best) / log(σ_worst/σ_best), 0, 1)`` from the
horizontal 1-σ ``σ_h = sqrt(λ_max(P_NE))``.  An invalid or non-finite solution gives
``None`` (silence) or, on request, quality −1 ("failed" in the MAVLink spec) with NaN
pose — never zeros that look valid.
"""
from __future__ import annotations

import logging

import math
import os
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

# ODOMETRY, GPS_INPUT and HIGHRES_IMU's extensions need MAVLink 2; pymavlink chooses the
# wire protocol from this variable when a dialect is loaded, so set it before import.
os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, dcm_to_euler, quat_to_dcm, wrap_angle  # noqa: E402
from adaptnav.fusion.samples import (  # noqa: E402
    AltitudeSample,
    AttitudeSample,
    DepthSample,
    GnssSample,
    ImuSample,
    RpmSample,
    UsblSample,
)

DEG_E7_TO_RAD = math.pi / 180.0 * 1e-7
MG_TO_M_S2 = GRAVITY_M_S2 / 1000.0
MRAD_TO_RAD = 1e-3
HPA_TO_PA = 100.0
U32_WRAP_S_MS = 2**32 / 1000.0  # time_boot_ms (uint32 ms) wraps after 49.7 days
U32_WRAP_S_US = 2**32 / 1e6  # SERVO_OUTPUT_RAW.time_usec is uint32 µs: wraps every 71.6 min
UNIX_EPOCH_MIN_US = 1e15  # time_usec above this is UNIX time (2001+), not time since boot

IMU_MESSAGES = ("HIGHRES_IMU", "SCALED_IMU2", "RAW_IMU")
PRESSURE_MESSAGES = ("SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3")


class ConversionError(ValueError):
    """A MAVLink message that cannot become a sample; ``reason`` is the counter key."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# --------------------------------------------------------------------------- config
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
    imu_message: Literal["auto", "RAW_IMU", "SCALED_IMU2", "HIGHRES_IMU"] = "auto"
    depth_message: Literal["SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3"] = "SCALED_PRESSURE2"
    thrusters: ThrusterConfig = field(default_factory=ThrusterConfig)
    gnss_min_fix_type: int = 3  # GPS_FIX_TYPE_3D_FIX
    gnss_sigma_per_hdop_m: float = 2.5  # σ_h = HDOP × this when h_acc is absent
    usbl_sigma_per_hdop_m: float = 1.0  # Water Linked UGPS reports HDOP only
    usbl_min_sigma_m: float = 0.3
    # GPS_RAW_INT that merely echoes GPS_INPUT (GPS1_TYPE=14) is dropped for this long
    # after the last GPS_INPUT, or the same acoustic fix would be fused twice
    gps_input_echo_window_s: float = 5.0
    altitude_orientation: int = 25  # MAV_SENSOR_ROTATION_PITCH_270 = looking down
    autopilot_component: int = 1  # MAV_COMP_ID_AUTOPILOT1
    reboot_backjump_s: float = 2.0  # a clock going back further than this is a reboot

    def validate(self) -> None:
        if self.gnss_sigma_per_hdop_m <= 0 or self.usbl_sigma_per_hdop_m <= 0:
            raise ValueError("sigma_per_hdop_m must be > 0")
        if self.reboot_backjump_s <= 0:
            raise ValueError("reboot_backjump_s must be > 0")


@dataclass(frozen=True)
class OdometryConfig:
    """ODOMETRY output (the ``[mavlink.output]`` config section)."""

    sigma_best_m: float = 0.5  # horizontal 1-σ mapped to quality 100
    sigma_worst_m: float = 50.0  # ... and to quality 1
    invalid: Literal["silence", "failed"] = "silence"  # "failed": quality -1, NaN pose
    estimator_type: int = 3  # MAV_ESTIMATOR_TYPE_VIO
    vision_position_delta: bool = False  # also send VISION_POSITION_DELTA between outputs

    def validate(self) -> None:
        if not 0 < self.sigma_best_m < self.sigma_worst_m:
            raise ValueError("need 0 < sigma_best_m < sigma_worst_m")


# --------------------------------------------------------------------------- time
class TimeMapper:
    """Autopilot boot time (s) → monotonic mission time ``t_s``.

    ``t_s = boot_s + offset``.  A 32-bit ``time_boot_ms`` wrap adds 2³²/1000 s to the
    offset; any other backward jump larger than ``reboot_backjump_s`` is a reboot and
    the offset continues the mission clock from the last time seen (``reboots`` counts
    them).  Small backward steps (messages sent slightly out of order) pass through
    unchanged — ordering is the replay's job.
    """

    def __init__(self, reboot_backjump_s: float = 2.0):
        self.reboot_backjump_s = reboot_backjump_s
        self.offset_s = 0.0
        self.last_boot_s: float | None = None
        self.now_s: float | None = None  # latest mission time mapped (reception clock)
        self.reboots = 0
        self.wraps = 0

    def map_boot_s(self, boot_s: float) -> float:
        if self.last_boot_s is not None and boot_s < self.last_boot_s - self.reboot_backjump_s:
            last_t = self.last_boot_s + self.offset_s
            if self.last_boot_s > U32_WRAP_S_MS - 3600.0 and boot_s < 3600.0:
                self.offset_s += U32_WRAP_S_MS
                self.wraps += 1
            else:
                self.offset_s = last_t - boot_s  # continue the mission clock after a reboot
                self.reboots += 1
        if self.last_boot_s is None or boot_s > self.last_boot_s or boot_s < self.last_boot_s - self.reboot_backjump_s:
            self.last_boot_s = boot_s
        t = boot_s + self.offset_s
        if self.now_s is None or t > self.now_s:
            self.now_s = t
        return t

    def from_boot_ms(self, time_boot_ms: int) -> float:
        return self.map_boot_s(time_boot_ms / 1000.0)

    def from_usec(self, time_usec: int, clock: bool = True) -> float | None:
        """64-bit ``time_usec`` since boot (0 or UNIX time: the latest time instead).

        ``clock=False`` for sensor times that may be stale (GPS_RAW_INT repeats the time
        of its last fix): mapped with the current offset without moving the clock.
        """
        if time_usec <= 0 or time_usec >= UNIX_EPOCH_MIN_US:
            return self.now_s
        if not clock and self.now_s is not None:
            return time_usec / 1e6 + self.offset_s
        return self.map_boot_s(time_usec / 1e6)

    def from_u32_usec(self, time_usec: int) -> float | None:
        """32-bit µs (SERVO_OUTPUT_RAW): unwrapped to the candidate nearest the latest boot time."""
        if self.last_boot_s is None:
            return self.map_boot_s(time_usec / 1e6)
        base = time_usec / 1e6
        k = round((self.last_boot_s - base) / U32_WRAP_S_US)
        return self.map_boot_s(base + k * U32_WRAP_S_US)


# --------------------------------------------------------------------------- in: pure
def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def imu_from_scaled(msg: Any, t_s: float) -> ImuSample:
    """RAW_IMU / SCALED_IMU(2,3): acc [mg], gyro [mrad/s] → SI, body FRD."""
    acc = (msg.xacc, msg.yacc, msg.zacc)
    gyro = (msg.xgyro, msg.ygyro, msg.zgyro)
    if not any(acc) and not any(gyro):
        raise ConversionError("imu_absent", f"{msg.get_type()} all zeros (no such IMU)")
    return ImuSample(t_s, tuple(a * MG_TO_M_S2 for a in acc), tuple(g * MRAD_TO_RAD for g in gyro))


def imu_from_highres(msg: Any, t_s: float) -> ImuSample:
    """HIGHRES_IMU: already m/s² and rad/s; needs the acc and gyro bits of fields_updated."""
    if msg.fields_updated and (msg.fields_updated & 0x3F) != 0x3F:
        raise ConversionError("imu_partial", "HIGHRES_IMU without all acc/gyro fields updated")
    acc = (float(msg.xacc), float(msg.yacc), float(msg.zacc))
    gyro = (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro))
    if not _finite(*acc, *gyro):
        raise ConversionError("non_finite", "HIGHRES_IMU")
    return ImuSample(t_s, acc, gyro)


def attitude_from_attitude(msg: Any, t_s: float) -> AttitudeSample:
    if not _finite(msg.roll, msg.pitch, msg.yaw):
        raise ConversionError("non_finite", "ATTITUDE")
    return AttitudeSample(t_s, float(msg.roll), float(msg.pitch), float(wrap_angle(msg.yaw)))


def depth_from_pressure(msg: Any, t_s: float) -> DepthSample:
    """SCALED_PRESSURE*: ``press_abs`` hPa → Pa."""
    p = float(msg.press_abs)
    if not math.isfinite(p) or p <= 0.0:
        raise ConversionError("bad_pressure", f"press_abs={p}")
    return DepthSample(t_s, p * HPA_TO_PA)


def servo_pwm(msg: Any, channel: int) -> int:
    """``servoN_raw`` of SERVO_OUTPUT_RAW (1-based channel), µs; 0 = not output."""
    return int(getattr(msg, f"servo{channel}_raw", 0) or 0)


def rpm_from_servo(msg: Any, t_s: float, thrusters: ThrusterConfig) -> RpmSample:
    """Mean signed forward (and lateral) RPM of the configured thrusters."""
    rpms = []
    for ch in thrusters.channels:
        pwm = servo_pwm(msg, ch)
        if pwm <= 0:
            raise ConversionError("thruster_not_output", f"servo{ch}_raw = 0")
        rpms.append(thrusters.curve.rpm_of_pwm(pwm))
    sway = float(np.mean(np.multiply(thrusters.lateral_signs, rpms))) if thrusters.lateral_signs else 0.0
    return RpmSample(t_s, float(np.mean(np.multiply(thrusters.forward_signs, rpms))), sway)


def gnss_from_gps_raw_int(msg: Any, t_s: float, cfg: ConvertConfig) -> GnssSample:
    if msg.fix_type < cfg.gnss_min_fix_type:
        raise ConversionError("gnss_no_fix", f"fix_type={msg.fix_type}")
    h_acc_mm = getattr(msg, "h_acc", 0) or 0
    if h_acc_mm > 0:
        sigma = h_acc_mm / 1000.0
    elif msg.eph not in (0, 65535):
        sigma = msg.eph / 100.0 * cfg.gnss_sigma_per_hdop_m
    else:
        raise ConversionError("gnss_no_accuracy", "neither h_acc nor eph")
    return GnssSample(t_s, msg.lat * DEG_E7_TO_RAD, msg.lon * DEG_E7_TO_RAD, sigma)


_GPS_IGNORE_ALT = 1
_GPS_IGNORE_HDOP = 2
_GPS_IGNORE_VDOP = 4
_GPS_IGNORE_H_ACC = 64
_GPS_IGNORE_V_ACC = 128


def usbl_from_gps_input(msg: Any, t_s: float, cfg: ConvertConfig) -> UsblSample:
    """GPS_INPUT (Water Linked UGPS and similar acoustic positioning) → UsblSample.

    ``depth_m`` is NaN when the altitude is flagged as ignored (UGPS sends none: the
    vehicle's own depth sensor measures depth); ``sigma_h_m`` from ``horiz_accuracy``
    or HDOP × ``usbl_sigma_per_hdop_m``.
    """
    if msg.fix_type < 2:
        raise ConversionError("usbl_no_fix", f"fix_type={msg.fix_type}")
    flags = msg.ignore_flags
    if not flags & _GPS_IGNORE_H_ACC and msg.horiz_accuracy > 0:
        sigma_h = float(msg.horiz_accuracy)
    elif not flags & _GPS_IGNORE_HDOP and 0 < msg.hdop < 100:
        sigma_h = float(msg.hdop) * cfg.usbl_sigma_per_hdop_m
    else:
        raise ConversionError("usbl_no_accuracy", "neither horiz_accuracy nor hdop")
    sigma_h = max(sigma_h, cfg.usbl_min_sigma_m)
    depth = math.nan if flags & _GPS_IGNORE_ALT else -float(msg.alt)
    sigma_v = float(msg.vert_accuracy) if not flags & _GPS_IGNORE_V_ACC and msg.vert_accuracy > 0 else math.nan
    return UsblSample(t_s, msg.lat * DEG_E7_TO_RAD, msg.lon * DEG_E7_TO_RAD, depth, sigma_h, sigma_v)


def altitude_from_distance_sensor(msg: Any, t_s: float, cfg: ConvertConfig) -> AltitudeSample:
    if msg.orientation != cfg.altitude_orientation:
        raise ConversionError("distance_not_down", f"orientation={msg.orientation}")
    if getattr(msg, "signal_quality", 0) == 1:  # 1 = invalid signal (0 = unknown)
        raise ConversionError("distance_invalid", "signal_quality=1")
    d_cm = msg.current_distance
    if not msg.min_distance <= d_cm <= msg.max_distance:
        raise ConversionError("distance_out_of_range", f"{d_cm} cm not in [{msg.min_distance}, {msg.max_distance}]")
    return AltitudeSample(t_s, d_cm / 100.0)


# --------------------------------------------------------------------------- in: stateful
class MavlinkConverter:
    """Turns a stream of ArduSub messages into samples (one instance per link or log).

    Holds the little state conversion needs: the :class:`TimeMapper`, the autopilot's
    system id (learned from its HEARTBEAT; messages of other systems — ground stations —
    are ignored), the IMU message type locked on, and when GPS_INPUT was last seen.
    ``rejected`` counts messages that were not turned into samples, by reason.
    """

    def __init__(self, config: ConvertConfig | None = None):
        self.config = config or ConvertConfig()
        self.time = TimeMapper(self.config.reboot_backjump_s)
        self.autopilot_sysid: int | None = None
        self.imu_message: str | None = None if self.config.imu_message == "auto" else self.config.imu_message
        self.last_gps_input_t: float | None = None
        self.rejected: dict[str, int] = {}

    def _reject(self, reason: str) -> list:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return []

    def _stamp(self, msg: Any, mtype: str) -> float | None:
        """Mission time of ``msg``; the autopilot's own clock, else reception time."""
        if msg.get_srcComponent() != self.config.autopilot_component:
            return self.time.now_s
        if hasattr(msg, "time_boot_ms"):
            return self.time.from_boot_ms(msg.time_boot_ms)
        if mtype == "SERVO_OUTPUT_RAW":
            return self.time.from_u32_usec(msg.time_usec)
        if hasattr(msg, "time_usec"):
            return self.time.from_usec(msg.time_usec, clock=mtype != "GPS_RAW_INT")
        return self.time.now_s

    def convert(self, msg: Any) -> list:
        """Samples carried by one message (usually 0 or 1)."""
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if self.autopilot_sysid is None and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
                self.autopilot_sysid = msg.get_srcSystem()
            return []
        handler = _HANDLERS.get(mtype)
        if handler is None:
            return []
        if self.autopilot_sysid is not None and msg.get_srcSystem() != self.autopilot_sysid:
            return self._reject("other_system")
        t_s = self._stamp(msg, mtype)
        if t_s is None:
            return self._reject("no_time_yet")
        try:
            sample = handler(self, msg, mtype, t_s)
        except ConversionError as e:
            return self._reject(e.reason)
        except (AttributeError, TypeError, ValueError, OverflowError):
            return self._reject("malformed")
        return [] if sample is None else [sample]

    # handlers -------------------------------------------------------------------
    def _imu(self, msg, mtype, t_s):
        if self.imu_message is not None and mtype != self.imu_message:
            self.rejected["imu_other_stream"] = self.rejected.get("imu_other_stream", 0) + 1
            return None
        sample = imu_from_highres(msg, t_s) if mtype == "HIGHRES_IMU" else imu_from_scaled(msg, t_s)
        if self.imu_message is None:
            self.imu_message = mtype  # lock: two IMUs interleaved would corrupt strapdown
            logging.getLogger(__name__).info("IMU stream: %s (the first with a real sample; others ignored)",
                                             mtype, extra={"event": {"event": "imu_stream", "message": mtype}})
        return sample

    def _pressure(self, msg, mtype, t_s):
        if mtype != self.config.depth_message:
            return None  # the internal barometer measures hull air, not water
        return depth_from_pressure(msg, t_s)

    def _gps_raw(self, msg, mtype, t_s):
        if self.last_gps_input_t is not None and t_s - self.last_gps_input_t < self.config.gps_input_echo_window_s:
            raise ConversionError("gnss_echo_of_gps_input")
        return gnss_from_gps_raw_int(msg, t_s, self.config)

    def _gps_input(self, msg, mtype, t_s):
        self.last_gps_input_t = t_s
        return usbl_from_gps_input(msg, t_s, self.config)


_HANDLERS = {
    "RAW_IMU": MavlinkConverter._imu,
    "SCALED_IMU2": MavlinkConverter._imu,
    "HIGHRES_IMU": MavlinkConverter._imu,
    "ATTITUDE": lambda self, m, k, t: attitude_from_attitude(m, t),
    "SCALED_PRESSURE": MavlinkConverter._pressure,
    "SCALED_PRESSURE2": MavlinkConverter._pressure,
    "SCALED_PRESSURE3": MavlinkConverter._pressure,
    "SERVO_OUTPUT_RAW": lambda self, m, k, t: rpm_from_servo(m, t, self.config.thrusters),
    "GPS_RAW_INT": MavlinkConverter._gps_raw,
    "GPS_INPUT": MavlinkConverter._gps_input,
    "DISTANCE_SENSOR": lambda self, m, k, t: altitude_from_distance_sensor(m, t, self.config),
}


# --------------------------------------------------------------------------- out
def _cov_slices():
    """Error-state slices (position, velocity, attitude) of ``NavState.cov``."""
    try:
        from adaptnav.fusion.state import ATT, POS, VEL  # the filter's named slices
    except ImportError:  # fusion/state.py not landed yet: its documented layout
        POS, VEL, ATT = slice(0, 3), slice(3, 6), slice(6, 9)
    return POS, VEL, ATT


def upper_triangle(m: np.ndarray) -> list[float]:
    """Row-major upper triangle of a square matrix (MAVLink covariance layout)."""
    iu = np.triu_indices(m.shape[0])
    return [float(v) for v in m[iu]]


def quality_from_sigma(sigma_h_m: float, cfg: OdometryConfig) -> int:
    """Horizontal 1-σ → MAVLink quality 1…100 (log scale between best and worst)."""
    if not math.isfinite(sigma_h_m):
        return -1
    frac = math.log(max(sigma_h_m, 1e-9) / cfg.sigma_best_m) / math.log(cfg.sigma_worst_m / cfg.sigma_best_m)
    return int(round(100.0 - 99.0 * min(max(frac, 0.0), 1.0)))


def horizontal_sigma_m(cov: np.ndarray) -> float:
    """sqrt of the largest eigenvalue of the north/east position covariance."""
    pos, _, _ = _cov_slices()
    p_ne = np.asarray(cov)[pos, pos][:2, :2]
    if not np.all(np.isfinite(p_ne)):
        return math.nan
    return float(math.sqrt(max(np.linalg.eigvalsh(0.5 * (p_ne + p_ne.T))[-1], 0.0)))


def nav_is_valid(nav: Any) -> bool:
    """The solution may be sent: flagged valid and every sent number finite."""
    if not getattr(nav, "valid", False):
        return False
    parts = [np.asarray(nav.pos_n_m, float), np.asarray(nav.vel_n_m_s, float), np.asarray(nav.q_nb, float)]
    return all(np.all(np.isfinite(p)) for p in parts) and abs(np.linalg.norm(parts[2]) - 1.0) < 1e-3


def odometry_fields(nav: Any, cfg: OdometryConfig | None = None,
                    omega_b_rad_s: Any = None) -> dict[str, Any] | None:
    """``NavState`` → keyword arguments of ``MAVLink.odometry_send``.

    Returns ``None`` for an invalid solution when ``cfg.invalid == "silence"``;
    with ``"failed"`` the message has quality −1 and NaN pose and velocity.
    ``omega_b_rad_s`` (3,) rad/s is sent as the angular rates when given (NaN otherwise).
    """
    cfg = cfg or OdometryConfig()
    time_usec = int(round(max(float(nav.t_s), 0.0) * 1e6))
    reset_counter = int(getattr(nav, "reset_counter", 0)) % 256
    nan3 = [math.nan] * 3
    rates = nan3 if omega_b_rad_s is None else [float(w) for w in omega_b_rad_s]
    if not nav_is_valid(nav):
        if cfg.invalid == "silence":
            return None
        return dict(time_usec=time_usec, frame_id=mavlink2.MAV_FRAME_LOCAL_FRD,
                    child_frame_id=mavlink2.MAV_FRAME_BODY_FRD, x=math.nan, y=math.nan, z=math.nan,
                    q=[math.nan] * 4, vx=math.nan, vy=math.nan, vz=math.nan, rollspeed=math.nan,
                    pitchspeed=math.nan, yawspeed=math.nan, pose_covariance=[math.nan] * 21,
                    velocity_covariance=[math.nan] * 21, reset_counter=reset_counter,
                    estimator_type=cfg.estimator_type, quality=-1)
    q = np.asarray(nav.q_nb, dtype=float)
    R_nb = quat_to_dcm(q)
    vel_b = R_nb.T @ np.asarray(nav.vel_n_m_s, dtype=float)
    cov = np.asarray(nav.cov, dtype=float)
    POS, VEL, ATT = _cov_slices()
    # pose (x, y, z, roll, pitch, yaw): small attitude errors ≈ roll/pitch/yaw errors
    idx = np.r_[np.arange(cov.shape[0])[POS], np.arange(cov.shape[0])[ATT]]
    pose_cov = cov[np.ix_(idx, idx)]
    twist_cov = np.full((6, 6), 0.0)
    twist_cov[:3, :3] = R_nb.T @ cov[VEL, VEL] @ R_nb  # velocity is sent in body FRD
    twist_cov[3:, 3:] = np.diag([math.nan] * 3)  # angular-rate variance not estimated
    sigma_h = horizontal_sigma_m(cov)
    return dict(time_usec=time_usec, frame_id=mavlink2.MAV_FRAME_LOCAL_FRD,
                child_frame_id=mavlink2.MAV_FRAME_BODY_FRD,
                x=float(nav.pos_n_m[0]), y=float(nav.pos_n_m[1]), z=float(nav.pos_n_m[2]),
                q=[float(v) for v in q], vx=float(vel_b[0]), vy=float(vel_b[1]), vz=float(vel_b[2]),
                rollspeed=rates[0], pitchspeed=rates[1], yawspeed=rates[2],
                pose_covariance=upper_triangle(pose_cov), velocity_covariance=upper_triangle(twist_cov),
                reset_counter=reset_counter, estimator_type=cfg.estimator_type,
                quality=quality_from_sigma(sigma_h, cfg))


def gps_global_origin_fields(origin: GeoOrigin, target_system: int) -> dict[str, Any]:
    """Keyword arguments of ``set_gps_global_origin_send`` (degE7, mm)."""
    return dict(target_system=int(target_system),
                latitude=int(round(math.degrees(origin.lat_rad) * 1e7)),
                longitude=int(round(math.degrees(origin.lon_rad) * 1e7)),
                altitude=int(round(origin.alt_m * 1000.0)))


def vision_position_delta_fields(prev: Any, cur: Any) -> dict[str, Any] | None:
    """Two consecutive valid ``NavState`` → VISION_POSITION_DELTA (body frame of ``prev``)."""
    if not (nav_is_valid(prev) and nav_is_valid(cur)) or cur.t_s <= prev.t_s:
        return None
    R0 = quat_to_dcm(np.asarray(prev.q_nb, float))
    R1 = quat_to_dcm(np.asarray(cur.q_nb, float))
    dpos_b = R0.T @ (np.asarray(cur.pos_n_m, float) - np.asarray(prev.pos_n_m, float))
    droll, dpitch, dyaw = dcm_to_euler(R0.T @ R1)
    sigma = horizontal_sigma_m(np.asarray(cur.cov, float))
    confidence = float(np.clip(quality_from_sigma(sigma, OdometryConfig()), 0, 100))
    return dict(time_usec=int(round(cur.t_s * 1e6)), time_delta_usec=int(round((cur.t_s - prev.t_s) * 1e6)),
                angle_delta=[droll, dpitch, dyaw], position_delta=[float(v) for v in dpos_b],
                confidence=confidence)
