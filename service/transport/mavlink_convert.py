"""MAVLink ↔ adaptnav samples: every unit conversion at the MAVLink edge lives here.

In (from ArduSub), one pure function per message, time already mapped to mission
seconds ``t_s``:

====================  ===============================================  =================
message               fields → sample                                  conversion
====================  ===============================================  =================
RAW_IMU, SCALED_IMU*  x/y/z acc [mg], x/y/z gyro [mrad/s] → ImuSample  ×g/1000, ×1e-3
HIGHRES_IMU           acc [m/s²], gyro [rad/s] → ImuSample             none
ATTITUDE              roll, pitch, yaw [rad] → AttitudeSample          yaw wrapped
SCALED_PRESSURE2      press_abs [hPa] → DepthSample.pressure_pa        ×100
SERVO_OUTPUT_RAW      thruster PWM [µs] → RpmSample                    :class:`PwmRpmCurve`
GPS_RAW_INT           lat/lon [degE7], h_acc [mm] / eph [HDOP×100]     → rad, m
GPS_INPUT             lat/lon [degE7], alt [m up], accuracies [m]      → UsblSample
DISTANCE_SENSOR       current_distance [cm], downward only             ×0.01
VISION_POSITION_DELTA position_delta [m] / time_delta_usec → DvlSample  ÷ Δt (body frame)
VISION_SPEED_ESTIMATE x, y, z [m/s] → DvlSample                        body (or NED)
ODOMETRY              vx, vy, vz [m/s] with no pose, BODY_FRD → DvlSample  none (a DVL's)
====================  ===============================================  =================

ArduSub scales RAW_IMU like SCALED_IMU (mg, mrad/s): the real logs in
``../shared/data/mavlink`` read ``zacc ≈ -1000`` at rest — i.e. the body-FRD specific
force ``f_b = R_bn (a_n - g_n) = (0, 0, -g)``, our convention.  An all-zero SCALED_IMU2
means "no second IMU" (ArduSub still streams it) and is rejected, never fused.

Thrusters: ``rpm = mean_i s_i · curve(pwm_i)`` over the forward thrusters ``i`` with
their forward-thrust signs ``s_i`` (BlueROV2 vectored frame: motors 1–4 with forward
factors −1, −1, +1, +1 in ArduSub's AP_Motors6DOF); ``curve`` is a piecewise-linear
table with a dead band around the 1500 µs neutral (a T200 on its ESC) — or, once the source
shows it is ArduPilot's simulator, ``simulator_curve`` without one
(:meth:`MavlinkConverter.take_simulator`).  The simulated vehicle uses the inverse
(:meth:`PwmRpmCurve.pwm_of_rpm`).

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
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from adaptnav.service.transport.mavlink_config import (  # noqa: F401 (re-exported)
    ConvertConfig,
    OdometryConfig,
    PwmRpmCurve,
    ThrusterConfig,
)

# ODOMETRY, GPS_INPUT and HIGHRES_IMU's extensions need MAVLink 2; pymavlink chooses the
# wire protocol from this variable when a dialect is loaded, so set it before import.
os.environ.setdefault("MAVLINK20", "1")
# mavutil loads its global dialect at import: "all" (every dialect merged, ~5 MB) unless told;
# everything here speaks ardupilotmega
os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin, dcm_to_euler, quat_to_dcm, wrap_angle  # noqa: E402
from adaptnav.fusion.samples import (  # noqa: E402
    AltitudeSample,
    AttitudeSample,
    DepthSample,
    DvlSample,
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
GPS_TYPE_MAV = 14  # ArduPilot's GPS_TYPE for a MAVLink GPS (GPS_INPUT)

# best first: float SI, then the int16 mg / mrad/s messages (SCALED_IMU: PX4's and other
# autopilots' first IMU, scaled by definition; RAW_IMU is ArduPilot's, scaled like it)
IMU_MESSAGES = ("HIGHRES_IMU", "SCALED_IMU2", "SCALED_IMU", "RAW_IMU")
PRESSURE_MESSAGES = ("SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3")


class ConversionError(ValueError):
    """A MAVLink message that cannot become a sample; ``reason`` is the counter key."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# --------------------------------------------------------------------------- time
class _WindowMin:
    """Minimum of ``value`` over the last ``window_s`` of ``key`` (monotonic deque, O(1))."""

    def __init__(self, window_s: float):
        self.window_s = window_s
        self._q: deque[tuple[float, float]] = deque()

    def push(self, key: float, value: float) -> float:
        q = self._q
        while q and q[-1][1] >= value:
            q.pop()
        q.append((key, value))
        while q[0][0] < key - self.window_s:
            q.popleft()
        return q[0][1]


class MissionClock:
    """One time model for a MAVLink source: every stamp → mission time ``t_s``.

    Three clocks meet here:

    - the autopilot's **boot clock** (``time_boot_ms``, and ``time_usec`` below
      :data:`UNIX_EPOCH_MIN_US` from the autopilot's component);
    - **UNIX time** (``time_usec`` ≥ :data:`UNIX_EPOCH_MIN_US` from any component,
      ``SYSTEM_TIME.time_unix_usec``);
    - the **receive stamp** (UNIX seconds): the tlog's own 8-byte stamp per message, or the
      wall clock at reception on a live link (pymavlink's ``msg._timestamp`` in both cases).

    ``t_s`` is the boot clock plus ``boot_offset_s`` (0 until a reboot or a 32-bit wrap)
    whenever the source has a boot clock; a source without one (only UNIX stamps or receive
    stamps) gets ``t_s = unix − epoch`` with the epoch the first such stamp, once the hold
    has expired (:meth:`start_without_boot_clock`).

    Two offsets link them.  ``recv_offset_s`` (``recv = t_s + recv_offset_s``) from the
    receive stamps of boot-stamped messages, as the minimum of ``recv − t_s`` over the last
    ``window_s`` (the transport delay is ≥ 0, so the smallest difference is the least
    delayed message; a sliding window follows a receive clock that drifts or is stepped):
    a sample without a usable stamp of its own (``time_usec = 0``, another component's boot
    clock) maps to ``t_s = recv − recv_offset_s``.  ``unix_offset_s`` (``t_unix = t_s +
    unix_offset_s``): exactly from a ``SYSTEM_TIME`` pair of the autopilot
    (``unix_reference = "SYSTEM_TIME"``), else the receive relation (``"receive"``); a
    UNIX-stamped sample maps to ``t_s = t_unix − unix_offset_s``.  The two differ when the
    autopilot's clock and the recording computer's drift apart (a SITL falling behind the
    wall clock on a loaded machine: 2.3 s in 150 s), which is why each stamp uses its own.
    Until they are known such samples cannot be placed: the converter *holds* them
    (:class:`MavlinkConverter`).

    Jumps: the boot clock going back by more than ``reboot_backjump_s`` is a reboot (or,
    near 2³² ms, a wrap); after a reboot the receive stamps place the new boot clock on the
    mission clock (the time the autopilot was down is kept), without them the mission clock
    continues from the last time seen.  A change of ``unix_offset_s`` by more than
    ``jump_s`` is counted in ``unix_jumps`` (a receive clock stepped by NTP, a GPS time
    arriving).

    A UNIX-stamped source whose clock is not the reference's (a companion or INS keeping its
    own time, seconds off the recorder's or the autopilot's GPS time) is seen in its *lag*,
    the time from its stamp to its reception (both on the mission clock), minimum over
    ``window_s``: a few milliseconds of transport for a clock that agrees. Below
    ``-skew_future_s`` (stamped in the future of its own reception) or above ``skew_late_s``
    its samples are placed by that lag — its least-delayed one at its reception — instead of
    by its stamp (``skewed`` says which sources and by how much): an IMU clock 2 s ahead
    made every sample 2 s early (valid 8 % of the log), 5 s behind made 95 % of them too late
    to fuse.
    """

    def __init__(self, reboot_backjump_s: float = 2.0, window_s: float = 10.0, jump_s: float = 1.0,
                 skew_future_s: float = 0.1, skew_late_s: float = 1.0):
        self.reboot_backjump_s = reboot_backjump_s
        self.jump_s = jump_s
        self.window_s = window_s
        self.skew_future_s = skew_future_s
        self.skew_late_s = skew_late_s
        self._source_lag: dict[Any, _WindowMin] = {}
        self.skewed: dict[Any, float] = {}  # source → the lag its samples are placed by (s)
        self.boot_offset_s = 0.0
        self.last_boot_s: float | None = None
        self.now_s: float | None = None  # latest mission time mapped
        self.unix_offset_s: float | None = None
        self.unix_reference: str | None = None  # "SYSTEM_TIME" | "GPS" (a DataFlash log) | "receive" | "epoch"
        self.recv_offset_s: float | None = None
        self.base: str | None = None  # "boot" | "unix"
        self.reboots = 0
        self.wraps = 0
        self.unix_jumps = 0
        self._recv_min = _WindowMin(window_s)

    # -- what is known
    @property
    def offset_s(self) -> float:
        """Boot clock → mission clock offset (kept for the DataFlash reader)."""
        return self.boot_offset_s

    def unix_of(self, t_s: float) -> float | None:
        """UNIX time of mission time ``t_s``, None without a wall-clock reference."""
        return None if self.unix_offset_s is None else t_s + self.unix_offset_s

    def _advance(self, t: float) -> float:
        if self.now_s is None or t > self.now_s:
            self.now_s = t
        return t

    def _set_unix_offset(self, offset: float, reference: str) -> None:
        if self.unix_offset_s is not None and abs(offset - self.unix_offset_s) > self.jump_s:
            self.unix_jumps += 1
        self.unix_offset_s = offset
        self.unix_reference = reference

    # -- the boot clock
    def map_boot_s(self, boot_s: float, recv_s: float | None = None) -> float:
        """Autopilot boot time (s) → ``t_s``; learns ``unix_offset_s`` from ``recv_s``."""
        if self.base is None:
            self.base = "boot"
        elif self.last_boot_s is None and self.recv_offset_s is not None and recv_s is not None:
            # the first boot stamp of a source that started on UNIX time: place it by reception
            self.boot_offset_s = (recv_s - self.recv_offset_s) - boot_s
        if self.last_boot_s is not None and boot_s < self.last_boot_s - self.reboot_backjump_s:
            last_t = self.last_boot_s + self.boot_offset_s
            if self.last_boot_s > U32_WRAP_S_MS - 3600.0 and boot_s < 3600.0:
                self.boot_offset_s += U32_WRAP_S_MS
                self.wraps += 1
            else:
                self.reboots += 1
                if recv_s is not None and self.recv_offset_s is not None:
                    # the receive clock kept running while the autopilot rebooted
                    self.boot_offset_s = max(recv_s - self.recv_offset_s, last_t) - boot_s
                else:
                    self.boot_offset_s = last_t - boot_s  # continue the mission clock
                if self.unix_reference in ("SYSTEM_TIME", "GPS"):
                    self.unix_reference = "receive"  # the old pair is void until the next one
                    self.unix_offset_s = self.recv_offset_s
        if self.last_boot_s is None or boot_s > self.last_boot_s or boot_s < self.last_boot_s - self.reboot_backjump_s:
            self.last_boot_s = boot_s
        t = boot_s + self.boot_offset_s
        if recv_s is not None:
            self.recv_offset_s = self._recv_min.push(recv_s, recv_s - t)
            if self.unix_reference in (None, "receive"):
                self._set_unix_offset(self.recv_offset_s, "receive")
        return self._advance(t)

    def from_boot_ms(self, time_boot_ms: int, recv_s: float | None = None) -> float:
        return self.map_boot_s(time_boot_ms / 1000.0, recv_s)

    def from_u32_usec(self, time_usec: int, recv_s: float | None = None) -> float:
        """32-bit µs (SERVO_OUTPUT_RAW): unwrapped to the candidate nearest the latest boot time."""
        base = time_usec / 1e6
        if self.last_boot_s is not None:
            base += round((self.last_boot_s - base) / U32_WRAP_S_US) * U32_WRAP_S_US
        return self.map_boot_s(base, recv_s)

    def stale_boot_s(self, boot_s: float) -> float | None:
        """A boot-clock sensor time that may be old (GPS_RAW_INT repeats its last fix's
        time): mapped with the current offset, without moving the clock."""
        if self.last_boot_s is None:
            return None
        return boot_s + self.boot_offset_s

    # -- UNIX time and reception
    def pair_system_time(self, unix_s: float, boot_s: float, recv_s: float | None = None) -> None:
        """The autopilot's SYSTEM_TIME: an exact (UNIX, boot) pair."""
        t = self.map_boot_s(boot_s, recv_s)
        self.pair_unix(unix_s, t, "SYSTEM_TIME")

    def pair_unix(self, unix_s: float, t_s: float, reference: str) -> None:
        """A (UNIX, mission time) pair from the source's own clocks (``reference``: SYSTEM_TIME,
        or a DataFlash log's GPS time): it outranks the receive relation until a reboot."""
        self._set_unix_offset(unix_s - t_s, reference)

    def from_unix_s(self, unix_s: float, recv_s: float | None = None, source: Any = None) -> float | None:
        """UNIX time → ``t_s`` (None while no reference links UNIX to the mission clock); with
        the ``source`` that stamped it and its reception ``recv_s``, a source whose clock is
        not the reference's is placed by its lag (class docstring)."""
        if self.unix_offset_s is None:
            return None
        t = unix_s - self.unix_offset_s
        if source is not None and recv_s is not None and self.recv_offset_s is not None:
            window = self._source_lag.get(source)
            if window is None:
                window = self._source_lag[source] = _WindowMin(self.window_s)
            lag = window.push(recv_s, recv_s - self.recv_offset_s - t)
            if lag < -self.skew_future_s or lag > self.skew_late_s:
                t += lag
                self.skewed[source] = lag
        return self._advance(t)

    def from_receive(self, recv_s: float | None) -> float | None:
        """Reception time → ``t_s``; without a receive stamp the latest mission time."""
        if recv_s is None:
            return self.now_s
        if self.recv_offset_s is None:
            return None
        return self._advance(recv_s - self.recv_offset_s)

    def start_without_boot_clock(self, epoch_unix_s: float) -> None:
        """No boot clock came in time: the mission clock is UNIX time − ``epoch_unix_s``."""
        if self.unix_offset_s is None:
            self.base = self.base or "unix"
            self._set_unix_offset(epoch_unix_s, "epoch")
        if self.recv_offset_s is None:
            self.recv_offset_s = epoch_unix_s



# --------------------------------------------------------------------------- in: pure
def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def imu_from_scaled(msg: Any, t_s: float, source: str = "autopilot") -> ImuSample:
    """RAW_IMU / SCALED_IMU(2,3): acc [mg], gyro [mrad/s] → SI, body FRD (``source``:
    :attr:`ImuSample.source`; these are a flight controller's own IMU messages)."""
    acc = (msg.xacc, msg.yacc, msg.zacc)
    gyro = (msg.xgyro, msg.ygyro, msg.zgyro)
    if not any(acc) and not any(gyro):
        raise ConversionError("imu_absent", f"{msg.get_type()} all zeros (no such IMU)")
    return ImuSample(t_s, tuple(a * MG_TO_M_S2 for a in acc), tuple(g * MRAD_TO_RAD for g in gyro), source)


def imu_from_highres(msg: Any, t_s: float, source: str = "") -> ImuSample:
    """HIGHRES_IMU: already m/s² and rad/s; needs the acc and gyro bits of fields_updated
    (``source``: :attr:`ImuSample.source`, who sent it)."""
    if msg.fields_updated and (msg.fields_updated & 0x3F) != 0x3F:
        raise ConversionError("imu_partial", "HIGHRES_IMU without all acc/gyro fields updated")
    acc = (float(msg.xacc), float(msg.yacc), float(msg.zacc))
    gyro = (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro))
    if not _finite(*acc, *gyro):
        raise ConversionError("non_finite", "HIGHRES_IMU")
    return ImuSample(t_s, acc, gyro, source)


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


def rpm_from_pwm(pwm_us_of: Any, t_s: float, thrusters: ThrusterConfig) -> RpmSample:
    """Mean signed forward (and lateral) RPM of the configured thrusters; ``pwm_us_of(channel)``
    is a channel's output (µs, 1-based channel; ≤ 0: not output).  One rule for every reader
    (SERVO_OUTPUT_RAW, DataFlash RCOU)."""
    rpms = []
    for ch in thrusters.channels:
        pwm = pwm_us_of(ch)
        if pwm <= 0:
            raise ConversionError("thruster_not_output", f"channel {ch} = 0")
        rpms.append(thrusters.curve.rpm_of_pwm(pwm))
    sway = float(np.mean(np.multiply(thrusters.lateral_signs, rpms))) if thrusters.lateral_signs else 0.0
    return RpmSample(t_s, float(np.mean(np.multiply(thrusters.forward_signs, rpms))), sway)


def rpm_from_servo(msg: Any, t_s: float, thrusters: ThrusterConfig) -> RpmSample:
    """SERVO_OUTPUT_RAW → :func:`rpm_from_pwm`."""
    return rpm_from_pwm(lambda ch: servo_pwm(msg, ch), t_s, thrusters)


def gnss_from_gps_raw_int(msg: Any, t_s: float, cfg: ConvertConfig, acoustic: bool = False) -> GnssSample:
    """GPS_RAW_INT → GnssSample; σ from ``h_acc``, else HDOP × ``gnss_sigma_per_hdop_m`` —
    ``usbl_sigma_per_hdop_m`` for an underwater GPS's fix (``acoustic``: its HDOP means that,
    as in its GPS_INPUT)."""
    if msg.fix_type < cfg.gnss_min_fix_type:
        raise ConversionError("gnss_no_fix", f"fix_type={msg.fix_type}")
    h_acc_mm = getattr(msg, "h_acc", 0) or 0
    if h_acc_mm > 0:
        sigma = h_acc_mm / 1000.0
    elif msg.eph not in (0, 65535):
        sigma = msg.eph / 100.0 * (cfg.usbl_sigma_per_hdop_m if acoustic else cfg.gnss_sigma_per_hdop_m)
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


def dvl_from_vision_position_delta(msg: Any, t_end_s: float, cfg: ConvertConfig, timed: bool = True) -> DvlSample:
    """VISION_POSITION_DELTA (a DVL driver's displacement over ``time_delta_usec``) → DvlSample.

    ``dvl_delta = "ping"`` (default): the Water Linked DVL driver of BlueOS sends
    ``position_delta = v·dt`` with ``v`` the DVL's velocity at its latest ping, in the current
    body frame, and ``dt`` the time since the DVL's previous report — so ``delta/dt`` is that
    velocity, valid when the message was stamped (or received), not rotated.  ``"mean"``: a
    driver that integrates over the interval in the body frame at its *start*: the mean
    velocity is rotated by half the interval's rotation ``angle_delta`` into the body frame at
    mid-interval, the time of validity of a mean.  Taking a BlueOS delta for a mean puts a
    1 Hz DVL 0.5 s early and half a turn's angle off: on the navigation-grade AUV class
    (tests/service/test_auv_navgrade.py, pings off the motion steps) end errors 10.0/5.3/9.5 m
    instead of 2.2/1.0/2.8 m, heading up to 0.84° off.
    ``confidence`` (0–100 %) → ``valid`` (≥ ``dvl_min_confidence``) and the velocity 1-σ
    ``fom = fom_max·(1 − confidence/100)`` (the BlueOS DVL extension's mapping, inverted).
    A rotation above ``dvl_max_angle_delta_rad`` within one delta is rejected: a mean over
    it is not one body-frame velocity.  The body frame is the DVL's frame for the filter
    (``filter.dvl.rotation_bd_rpy_rad`` = 0: the driver has already rotated its head).

    Time: ``t_end_s`` is the end of the interval — the message's own ``time_usec`` when it
    has one (``timed``), else its reception, which comes ``dvl_latency_s`` after the DVL's
    measurement (subtracted). A ping is valid at the end, a mean at mid-interval
    ``t_end − Δt/2``; the estimator fuses either at its own time, against the state then
    (:mod:`adaptnav.fusion.eskf`, late measurements up to ``filter.max_delay_s``).
    """
    dt = msg.time_delta_usec / 1e6
    if not 0.0 < dt <= cfg.dvl_max_interval_s:
        raise ConversionError("dvl_bad_interval", f"time_delta_usec={msg.time_delta_usec}")
    dpos = np.asarray(msg.position_delta, dtype=float)
    conf = float(msg.confidence)
    if not (np.all(np.isfinite(dpos)) and math.isfinite(conf)):
        raise ConversionError("non_finite", "VISION_POSITION_DELTA")
    ang = np.asarray(msg.angle_delta, dtype=float)
    if not np.all(np.isfinite(ang)):
        ang = np.zeros(3)  # not reported: no rotation correction
    # the BlueOS driver sends differences of Euler angles unwrapped: a heading through ±180°
    # reads as a turn of ~2π within one delta
    ang = (ang + math.pi) % (2.0 * math.pi) - math.pi
    if float(np.linalg.norm(ang)) > cfg.dvl_max_angle_delta_rad:
        raise ConversionError("dvl_rotating", f"|angle_delta| = {np.linalg.norm(ang):.3f} rad")
    sigma = cfg.dvl_confidence_fom_max_m_s * (1.0 - min(max(conf, 0.0), 100.0) / 100.0)
    sigma = sigma if sigma > 0.0 else math.nan
    valid = conf >= cfg.dvl_min_confidence
    if not timed:
        t_end_s -= cfg.dvl_latency_s
    if cfg.dvl_delta == "ping":
        return DvlSample(t_end_s, tuple(float(v) for v in dpos / dt), valid, sigma_m_s=sigma)
    from scipy.spatial.transform import Rotation

    vel_mid = Rotation.from_rotvec(0.5 * ang).inv().apply(dpos / dt)
    return DvlSample(t_end_s - 0.5 * dt, tuple(float(v) for v in vel_mid), valid, sigma_m_s=sigma)


def dvl_from_vision_speed(msg: Any, t_s: float, cfg: ConvertConfig, R_nb: np.ndarray | None = None) -> DvlSample:
    """VISION_SPEED_ESTIMATE → DvlSample.  The BlueOS DVL extension sends the DVL's body
    velocity (``vision_speed_frame = "body"``, the default); ``"ned"`` (the MAVLink
    definition) needs ``R_nb`` at ``t_s``.  1-σ from the covariance diagonal when given."""
    vel = np.array([msg.x, msg.y, msg.z], dtype=float)
    if not np.all(np.isfinite(vel)):
        raise ConversionError("non_finite", "VISION_SPEED_ESTIMATE")
    if cfg.vision_speed_frame == "ned":
        if R_nb is None:
            raise ConversionError("no_attitude", "VISION_SPEED_ESTIMATE in NED needs the attitude")
        vel = R_nb.T @ vel
    sigma = _sigma_of_diagonal(getattr(msg, "covariance", None), [0, 4, 8])  # row-major 3×3
    return DvlSample(t_s, tuple(float(v) for v in vel), True, sigma_m_s=sigma)


def _sigma_of_diagonal(covariance: Any, diagonal: list[int]) -> float:
    """1-σ from a MAVLink covariance field: the square root of the largest of its ``diagonal``
    entries; NaN (unknown) when one is missing or not finite, or none is positive."""
    cov = np.asarray(covariance or [math.nan], dtype=float)
    if cov.size <= max(diagonal):
        return math.nan
    diag = cov[diagonal]
    return float(math.sqrt(diag.max())) if np.all(np.isfinite(diag)) and diag.max() > 0 else math.nan


def dvl_from_odometry(msg: Any, t_s: float) -> DvlSample:
    """ODOMETRY with a body-frame velocity and no pose → DvlSample: a DVL driver's (the Water
    Linked DVL extension's ODOMETRY mode: x, y, z and q NaN, ``child_frame_id`` BODY_FRD, the
    velocity's variance on the covariance diagonal, quality 1–100). An ODOMETRY with a pose is
    a navigator's output — the autopilot's, ours — and is ignored; quality −1 is a failure."""
    pose = np.array([msg.x, msg.y, msg.z], dtype=float)
    if np.isfinite(pose).any() or msg.child_frame_id != mavlink2.MAV_FRAME_BODY_FRD:
        raise IgnoredMessage("a navigator's output (a pose: the autopilot's, ours), not a sensor")
    if getattr(msg, "quality", 0) == -1:
        raise ConversionError("odometry_failed", "quality -1")
    vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
    if not np.all(np.isfinite(vel)):
        raise ConversionError("non_finite", "ODOMETRY velocity")
    sigma = _sigma_of_diagonal(getattr(msg, "velocity_covariance", None), [0, 6, 11])  # upper triangle, 6×6
    return DvlSample(t_s, tuple(float(v) for v in vel), True, sigma_m_s=sigma)


def usbl_from_global_vision(msg: Any, t_s: float, origin: GeoOrigin, cfg: ConvertConfig) -> UsblSample:
    """GLOBAL_VISION_POSITION_ESTIMATE (local NED position from the EKF origin, m) → UsblSample.
    σ_h from the covariance (upper triangle: x at 0, y at 6) or ``vision_position_sigma_m``."""
    pos = np.array([msg.x, msg.y, msg.z], dtype=float)
    if not np.all(np.isfinite(pos)):
        raise ConversionError("non_finite", "GLOBAL_VISION_POSITION_ESTIMATE")
    cov = np.asarray(getattr(msg, "covariance", [math.nan]) or [math.nan], dtype=float)
    sigma = cfg.vision_position_sigma_m
    if cov.size >= 7 and math.isfinite(cov[0]) and math.isfinite(cov[6]) and max(cov[0], cov[6]) > 0:
        sigma = math.sqrt(max(cov[0], cov[6]))
    lat, lon, _ = origin.to_geodetic(pos)
    return UsblSample(t_s, float(lat), float(lon), float(pos[2]), max(sigma, cfg.usbl_min_sigma_m))


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
# Message types deliberately not turned into samples, and why (summary.json says so; a type
# neither handled nor listed here is reported as unknown).
# Readings a sender may pass on again unchanged when its stream runs faster than its sensor:
# ArduSub's simulator streams SCALED_PRESSURE* at 20 Hz from a 10 Hz barometer (every value
# twice in the free-drive tlog), the Water Linked UGPS extension sends each acoustic fix ~4×
# (GPS_INPUT, the real BlueROV2 log). Fused again, one reading counts as several (σ/√n): the
# free-drive's depth failed its innovation test half the time. A message of these types whose
# fields but the send-time stamp (and a yaw beside a position: the UGPS extension passes the
# vehicle's on) equal the previous one's from the same sender, within
# ``repeat_window_s`` of that reading's first arrival, is that repeat (GPS_RAW_INT keeps its fix
# time in the comparison: a new fix at rest differs in it).
REPEAT_CHECKED = frozenset({"SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3", "GPS_RAW_INT", "GPS_INPUT",
                            "GLOBAL_VISION_POSITION_ESTIMATE"})
_NOT_THE_READING = frozenset({"time_boot_ms", "yaw"})
WHY_REPEAT = "the previous reading again (a stream faster than its sensor), not a new one"
# ArduPilot's simulator's own messages: the source is SITL (MavlinkConverter.take_simulator)
SIMULATOR_MESSAGES = frozenset(("SIM_STATE", "SIMSTATE"))
_WHY_AUTOPILOT_SOLUTION = "the autopilot's own estimate (an output of its EKF, not a sensor)"
_WHY_HOUSEKEEPING = "status / housekeeping (no navigation content)"
_WHY_GCS = "ground-station traffic (commands, parameters, missions, pilot input)"
IGNORED_WHY: dict[str, str] = {
    **{m: _WHY_AUTOPILOT_SOLUTION for m in (
        "AHRS", "AHRS2", "AHRS3", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED",
        "VFR_HUD", "NAV_CONTROLLER_OUTPUT", "HOME_POSITION", "POSITION_TARGET_GLOBAL_INT",
        "POSITION_TARGET_LOCAL_NED", "ESTIMATOR_STATUS")},
    **{m: _WHY_HOUSEKEEPING for m in (
        "SYS_STATUS", "BATTERY_STATUS", "POWER_STATUS", "HWSTATUS", "MEMINFO", "VIBRATION", "SENSOR_OFFSETS",
        "MOUNT_STATUS", "GIMBAL_DEVICE_ATTITUDE_STATUS", "AUTOPILOT_VERSION", "STORAGE_INFORMATION",
        "VIDEO_STREAM_STATUS", "NAMED_VALUE_FLOAT", "NAMED_VALUE_INT", "TIMESYNC",
        "MISSION_CURRENT", "RC_CHANNELS", "RC_CHANNELS_RAW", "TERRAIN_REPORT", "TERRAIN_REQUEST",
        "ESC_TELEMETRY_1_TO_4", "ESC_TELEMETRY_5_TO_8", "CAMERA_INFORMATION", "CAMERA_SETTINGS",
        "EXTENDED_SYS_STATE", "PING", "RADIO_STATUS", "FENCE_STATUS")},
    **{m: _WHY_GCS for m in (
        "MANUAL_CONTROL", "COMMAND_LONG", "COMMAND_INT", "COMMAND_ACK", "REQUEST_DATA_STREAM",
        "PARAM_SET", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_EXT_VALUE", "PARAM_EXT_REQUEST_LIST",
        "MISSION_ACK", "MISSION_COUNT", "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_ITEM_INT",
        "SET_MODE", "SET_MESSAGE_INTERVAL", "SET_GPS_GLOBAL_ORIGIN", "RC_CHANNELS_OVERRIDE", "GPS_RTCM_DATA")},
    "HEARTBEAT": "link liveness; gives the autopilot's system id",
    "PARAM_VALUE": "the autopilot's parameters: BARO_PRIMARY names its water pressure sensor, "
                   "GPS_TYPE/GPS1_TYPE says whether its GPS fixes are an underwater GPS's, no sample",
    "EKF_STATUS_REPORT": "the autopilot's EKF health: its attitude flag gates ATTITUDE, no sample",
    "STATUSTEXT": "text; the autopilot's EKF (re)start and yaw alignment gate ATTITUDE, no sample",
    "SYSTEM_TIME": "clock reference (UNIX ↔ boot pairing), no sample",
    "GPS_GLOBAL_ORIGIN": "the autopilot's EKF origin (places GLOBAL_VISION_POSITION_ESTIMATE), no sample",
    "SIM_STATE": "simulator ground truth (never fused; the log replay makes it the truth of its metrics; "
                 "says the thrusters are the simulator's, mavlink.convert.thrusters.simulator_curve)",
    "SIMSTATE": "simulator ground truth (never fused; says the thrusters are the simulator's)",
    "RANGEFINDER": "ArduPilot's copy of DISTANCE_SENSOR (that one is used)",
    "SCALED_IMU3": "a third IMU: one IMU stream is integrated",
    # BlueOS's DVL extension in its "position estimate" mode, visual odometry, or a navigator's
    # pose to the autopilot (the bridge's own without velocity): a track drifting in its own frame
    "VISION_POSITION_ESTIMATE": "a pose in the sender's own frame (a DVL's or camera's odometry, or a navigator's "
                                "output to the autopilot), not an absolute fix; a DVL's velocity comes as "
                                "VISION_POSITION_DELTA or VISION_SPEED_ESTIMATE",
}


def attitude_word_from_text(text: str) -> bool | None:
    """What an autopilot's text (STATUSTEXT, DataFlash MSG) says of its attitude: False on an
    EKF (re)start ("EKF3 IMU0 initialised": yaw 0 until aligned), True on its yaw alignment,
    None when it says nothing about it."""
    text = text.lower()
    if "ekf" in text and "initialised" in text:
        return False
    if "yaw alignment complete" in text:
        return True
    return None


class IgnoredMessage(Exception):
    """A handled message type that is not for us in this instance (``why`` says why)."""

    def __init__(self, why: str):
        super().__init__(why)
        self.why = why


@dataclass
class TypeAccount:
    """What became of one message type: messages read, samples made, rejected/ignored by why."""

    messages: int = 0
    samples: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    ignored: dict[str, int] = field(default_factory=dict)
    t_first_s: float = math.nan
    t_last_s: float = math.nan
    stamped: int = 0

    def stamp(self, t_s: float) -> None:
        if self.stamped == 0:
            self.t_first_s = t_s
        self.t_last_s = t_s
        self.stamped += 1

    def rate_hz(self) -> float | None:
        """Rate on the mission clock (messages that received a time)."""
        span = self.t_last_s - self.t_first_s
        return (self.stamped - 1) / span if self.stamped > 1 and span > 0 else None


class MavlinkConverter:
    """Turns a stream of MAVLink messages into samples (one instance per link or log).

    Holds the little state conversion needs: the :class:`MissionClock`, the autopilot's
    system id (learned from its HEARTBEAT), the IMU message type locked on, the EKF origin
    (from config or ``GPS_GLOBAL_ORIGIN``), and when GPS_INPUT was last seen.

    Who is listened to: every handled type from the autopilot's system (any component: the
    UGPS extension sends GPS_INPUT as component 220, a Ping driver DISTANCE_SENSOR as 194);
    the aiding types (:data:`AID_MESSAGES`) also from ``aid_system_ids`` (BlueOS's DVL and
    UGPS extensions send as system 255, component 0), restricted to ``aid_component_ids``
    when that is not empty.  Anything else is ``other_system``.

    Samples whose time cannot be placed yet (a UNIX ``time_usec`` or a receive stamp before
    any clock reference) are **held**, not dropped, and come out of a later :meth:`convert`
    (or :meth:`flush`) once the clock is known; after ``hold_max_s`` of receive time
    without a boot clock the source is taken to have none (:meth:`MissionClock.start_without_boot_clock`).

    ``rejected`` counts messages that were not turned into samples, by reason;
    :meth:`accounting` says, for every message type seen, what became of it.
    """

    def __init__(self, config: ConvertConfig | None = None, origin: GeoOrigin | None = None):
        self.config = config or ConvertConfig()
        self.time = MissionClock(self.config.reboot_backjump_s)
        self.autopilot_sysid: int | None = None
        self.autopilot_firmware: int | None = None  # MAV_AUTOPILOT_* of its heartbeat
        self.autopilot_gps_type: int | None = None  # its GPS_TYPE / GPS1_TYPE parameter
        self.autopilot_baro_primary: int | None = None  # its BARO_PRIMARY parameter
        # the thrusters in effect: the vehicle's curve, or the simulator's once the source is
        # known to be ArduPilot's simulator (``simulator``: what said so; :meth:`take_simulator`)
        self.thrusters = self.config.thrusters
        self.simulator: str | None = None
        self.imu_message: str | None = None if self.config.imu_message == "auto" else self.config.imu_message
        self._imu_lock: tuple[str, tuple[int, int, int], tuple[int, bool]] | None = None  # (type, source, rank)
        self.imu_switches = 0  # moves to a better IMU stream, or off a silent one (auto)
        self._imu_lock_t = -math.inf  # mission time of the integrated stream's latest sample
        self.last_gps_input_t: float | None = None
        self.origin = origin
        self.origin_from: str | None = "config" if origin is not None else None
        # where the EKF origin may be found when a local fix needs one before it came (a log's
        # reader: its GPS_GLOBAL_ORIGIN further on); None: nowhere (live, the bridge asks for it)
        self.origin_lookup: Callable[[], GeoOrigin | None] | None = None
        self.rejected: dict[str, int] = {}
        self.types: dict[str, TypeAccount] = {}
        self.held = 0  # samples held until the clock was known (released later)
        # the latest reading of each (REPEAT_CHECKED type, system, component), and when it came first
        self._last_reading: dict[tuple[str, int, int], tuple[tuple, float]] = {}
        self._held: list[tuple[Any, str, float | None]] = []
        self._first_unix_s: float | None = None
        self._first_hold_recv_s: float | None = None
        # the autopilot's own word on its attitude (None: it said nothing): ATTITUDE is not
        # passed on while its EKF says its attitude is not aligned — ArduSub sends yaw 0 then
        # (the filter seeds its heading from the first settled yaw)
        self.autopilot_attitude_ok: bool | None = None

    # ------------------------------------------------------------------ public
    def convert(self, msg: Any) -> list:
        """Samples carried by one message (usually 0 or 1), plus held ones now placeable."""
        mtype = msg.get_type()
        acc = self.types.get(mtype)
        if acc is None:
            acc = self.types[mtype] = TypeAccount()
        acc.messages += 1
        recv_s = getattr(msg, "_timestamp", None)
        recv_s = float(recv_s) if isinstance(recv_s, (int, float)) and recv_s > 0 else None
        out = self._convert_one(msg, mtype, recv_s, acc)
        if self._held:
            if self.time.unix_offset_s is None and self._hold_expired(recv_s):
                self._start_without_boot_clock()
            if self.time.unix_offset_s is not None:
                out += self._release_held()
        return out

    def flush(self) -> list:
        """End of the stream: place what is still held (or count it ``no_time``)."""
        if self._held and self.time.unix_offset_s is None:
            self._start_without_boot_clock()
        out = self._release_held()
        for _, mtype, _ in self._held:
            self._count_reject(self.types[mtype], "no_time")
        self._held = []
        return out

    def accounting(self, handlers: Any = None, ignored_why: dict[str, str] | None = None) -> dict[str, dict]:
        """Per message type: ``status`` (used | rejected | ignored | unknown), ``why``,
        ``messages``, ``samples``, ``rejected``/``ignored`` by reason, ``rate_hz`` (mission clock).
        ``handlers`` / ``ignored_why``: the types converted and the types ignored on purpose
        (default: this converter's MAVLink tables; a DataFlash log passes its records')."""
        handlers = _HANDLERS if handlers is None else handlers
        ignored_why = IGNORED_WHY if ignored_why is None else ignored_why
        out = {}
        for mtype, a in sorted(self.types.items()):
            handled = mtype in handlers
            if a.samples:
                status, why = "used", None
            elif handled and a.rejected:
                status, why = "rejected", "every message rejected (see rejected)"
            elif a.ignored:
                status, why = "ignored", "; ".join(sorted(a.ignored))
            elif mtype in ignored_why:
                status, why = "ignored", ignored_why[mtype]
            elif handled:
                status, why = "held", "no time reference yet"
            else:
                status, why = "unknown", "no converter for this message type"
            d: dict[str, Any] = {"status": status, "messages": a.messages, "samples": a.samples}
            if why:
                d["why"] = why
            if a.rejected:
                d["rejected"] = dict(a.rejected)
            if a.ignored:
                d["ignored"] = dict(a.ignored)
            rate = a.rate_hz()
            if rate is not None:
                d["rate_hz"] = round(rate, 3)
            out[mtype] = d
        return out

    def clock_report(self) -> dict[str, Any]:
        """The time model's state, for summaries and health."""
        c = self.time
        return {"base": c.base, "unix_reference": c.unix_reference, "unix_offset_s": c.unix_offset_s,
                "receive_offset_s": c.recv_offset_s,
                "reboots": c.reboots, "wraps": c.wraps, "unix_jumps": c.unix_jumps, "held_samples": self.held,
                # UNIX-stamped sources whose clock is off the reference's, placed by their lag (s)
                "sources_off_the_clock": {f"{s[0]}/{s[1]}": round(lag, 3) for s, lag in c.skewed.items()}}

    # ------------------------------------------------------------------ internals
    def _count_reject(self, acc: TypeAccount, reason: str) -> list:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        acc.rejected[reason] = acc.rejected.get(reason, 0) + 1
        return []

    def _reject(self, reason: str) -> list:  # kept for handlers' callers outside this class
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return []

    def _hold_expired(self, recv_s: float | None) -> bool:
        if recv_s is None or self._first_hold_recv_s is None:
            return len(self._held) >= self.config.hold_max_messages
        return recv_s - self._first_hold_recv_s > self.config.hold_max_s

    def _start_without_boot_clock(self) -> None:
        epoch = self._first_unix_s if self._first_unix_s is not None else self._first_hold_recv_s
        if epoch is not None:
            self.time.start_without_boot_clock(math.floor(epoch))

    def _release_held(self) -> list:
        held, self._held = self._held, []
        out = []
        for msg, mtype, recv_s in held:
            out += self._convert_one(msg, mtype, recv_s, self.types[mtype], releasing=True)
        return out

    def _autopilot_attitude_word(self, msg: Any, mtype: str) -> None:
        """EKF_STATUS_REPORT's attitude flag (set once tilt and yaw are aligned, ArduPilot
        EKF3: flags 0 → 167 right after "initial yaw alignment complete"); STATUSTEXT of an
        EKF (re)start ("initialised": yaw 0 until aligned) and of its yaw alignment."""
        if not self._is_autopilot(msg):
            return
        if mtype == "EKF_STATUS_REPORT":
            self.autopilot_attitude_ok = bool(msg.flags & mavlink2.EKF_ATTITUDE) \
                and not msg.flags & mavlink2.EKF_UNINITIALIZED
            return
        word = attitude_word_from_text(str(getattr(msg, "text", "")))
        if word is not None:
            self.autopilot_attitude_ok = word

    def _attitude(self, msg, mtype, t_s):
        if self.autopilot_attitude_ok is False and self._is_autopilot(msg):
            raise ConversionError("attitude_not_aligned", "the autopilot's EKF says its attitude is not aligned")
        return attitude_from_attitude(msg, t_s)

    def _is_autopilot(self, msg: Any) -> bool:
        return (msg.get_srcComponent() == self.config.autopilot_component
                and (self.autopilot_sysid is None or msg.get_srcSystem() == self.autopilot_sysid))

    def _accepted_source(self, msg: Any, mtype: str) -> bool:
        sysid = msg.get_srcSystem()
        if self.autopilot_sysid is None or sysid == self.autopilot_sysid:
            return True
        if mtype not in AID_MESSAGES or sysid not in self.config.aid_system_ids:
            return False
        comps = self.config.aid_component_ids
        return not comps or msg.get_srcComponent() in comps

    def _timed(self, msg: Any) -> bool:
        """``msg`` carries a time of its own that :meth:`_stamp` uses (UNIX ``time_usec``, or
        the autopilot's boot clock), not its reception."""
        usec = getattr(msg, "time_usec", 0)
        return usec >= UNIX_EPOCH_MIN_US or (usec > 0 and self._is_autopilot(msg))

    def _stamp(self, msg: Any, mtype: str, recv_s: float | None) -> float | None:
        """Mission time of ``msg`` (None: not placeable yet, hold it)."""
        own_clock = self._is_autopilot(msg)
        boot_ms = getattr(msg, "time_boot_ms", None)
        # a 0 stamp while the boot clock has not gone further than a reboot's back-jump is the
        # start of the boot clock (a simulator's first samples); later 0 means "no time"
        last_boot = self.time.last_boot_s
        first_boot_stamp = last_boot is None or last_boot < self.config.reboot_backjump_s
        if boot_ms is not None and own_clock and (boot_ms > 0 or first_boot_stamp):
            return self.time.from_boot_ms(boot_ms, recv_s)
        usec = getattr(msg, "time_usec", getattr(msg, "usec", None))
        if usec is not None and usec >= UNIX_EPOCH_MIN_US:
            if self._first_unix_s is None:
                self._first_unix_s = usec / 1e6
            return self.time.from_unix_s(usec / 1e6, recv_s, (msg.get_srcSystem(), msg.get_srcComponent()))
        if usec is not None and own_clock and (usec > 0 or first_boot_stamp):  # later 0: "no time"
            if mtype == "SERVO_OUTPUT_RAW":
                return self.time.from_u32_usec(usec, recv_s)
            if mtype == "GPS_RAW_INT":  # repeats the time of its last fix: do not move the clock
                t = self.time.stale_boot_s(usec / 1e6)
                return t if t is not None else self.time.map_boot_s(usec / 1e6, recv_s)
            return self.time.map_boot_s(usec / 1e6, recv_s)
        # no usable stamp of its own (0, or another component's clock): the reception time
        return self.time.from_receive(recv_s)

    def _convert_one(self, msg: Any, mtype: str, recv_s: float | None, acc: TypeAccount,
                     releasing: bool = False) -> list:
        if mtype == "HEARTBEAT":
            if self.autopilot_sysid is None and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
                self.autopilot_sysid = msg.get_srcSystem()
            if self._is_autopilot(msg):
                self.autopilot_firmware = msg.autopilot
            return []
        if mtype == "SYSTEM_TIME":
            if self._is_autopilot(msg) and msg.time_unix_usec >= UNIX_EPOCH_MIN_US and msg.time_boot_ms > 0:
                self.time.pair_system_time(msg.time_unix_usec / 1e6, msg.time_boot_ms / 1000.0, recv_s)
            elif self._is_autopilot(msg) and msg.time_boot_ms > 0:
                self.time.from_boot_ms(msg.time_boot_ms, recv_s)
            return []
        handler = _HANDLERS.get(mtype)
        if handler is None:
            if mtype in SIMULATOR_MESSAGES and self.simulator is None and self._is_autopilot(msg):
                self.take_simulator(mtype)
            if mtype == "PARAM_VALUE" and self._is_autopilot(msg):
                self.note_parameter(str(msg.param_id), float(msg.param_value))
            if mtype in ("EKF_STATUS_REPORT", "STATUSTEXT"):
                self._autopilot_attitude_word(msg, mtype)
            if mtype == "GPS_GLOBAL_ORIGIN" and self.origin_from != "config" and self._is_autopilot(msg):
                self.origin = GeoOrigin(msg.latitude * DEG_E7_TO_RAD, msg.longitude * DEG_E7_TO_RAD,
                                        msg.altitude / 1000.0)
                self.origin_from = "GPS_GLOBAL_ORIGIN"
            elif self._is_autopilot(msg) and getattr(msg, "time_boot_ms", 0):
                self.time.from_boot_ms(msg.time_boot_ms, recv_s)  # every boot stamp teaches the clock
            return []
        if not self._accepted_source(msg, mtype):
            return self._count_reject(acc, "other_system")
        t_s = self._stamp(msg, mtype, recv_s)
        if t_s is None:
            if not releasing:
                if self._first_hold_recv_s is None:
                    self._first_hold_recv_s = recv_s
                self._held.append((msg, mtype, recv_s))
                self.held += 1
            else:
                self._held.append((msg, mtype, recv_s))
            return []
        acc.stamp(t_s)
        if mtype in REPEAT_CHECKED:
            key = (mtype, msg.get_srcSystem(), msg.get_srcComponent())
            reading = tuple(getattr(msg, f) for f in msg.fieldnames if f not in _NOT_THE_READING)
            last = self._last_reading.get(key)
            if last is not None and last[0] == reading and 0.0 <= t_s - last[1] < self.config.repeat_window_s:
                acc.ignored[WHY_REPEAT] = acc.ignored.get(WHY_REPEAT, 0) + 1
                return []
            self._last_reading[key] = (reading, t_s)
        try:
            sample = handler(self, msg, mtype, t_s)
        except IgnoredMessage as e:
            acc.ignored[e.why] = acc.ignored.get(e.why, 0) + 1
            return []
        except ConversionError as e:
            return self._count_reject(acc, e.reason)
        except (AttributeError, TypeError, ValueError, OverflowError):
            return self._count_reject(acc, "malformed")
        acc.samples += 1
        return [sample]

    # handlers -------------------------------------------------------------------
    def _imu(self, msg, mtype, t_s):
        """One IMU stream is integrated (two interleaved would corrupt strapdown): a stream is
        a message type from one (system, component).  ``imu_message = "auto"`` locks on the
        first with a real sample and moves up to a better one when it appears — float
        ``HIGHRES_IMU`` over ``SCALED_IMU2`` over int16 ``RAW_IMU``, then a dedicated IMU
        (a companion's driver) over the autopilot's own — since a real autopilot streams its
        RAW_IMU at a few Hz whether or not a better IMU is on board."""
        # a stream is also one IMU: the id field of HIGHRES_IMU and RAW_IMU (MAVLink 2 extension)
        # tells a component's IMUs apart, and two interleaved in one strapdown would corrupt it
        # (pymavlink's message classes also carry ``id``, the message id: only the field counts)
        imu_id = int(msg.id or 0) if "id" in getattr(msg, "fieldnames", ()) else 0
        src = (msg.get_srcSystem(), msg.get_srcComponent(), imu_id)
        if self.config.imu_message != "auto" and mtype != self.imu_message:
            raise IgnoredMessage(f"another IMU stream ({self.imu_message}) is integrated")
        rank = (IMU_MESSAGES[::-1].index(mtype), src[1] != self.config.autopilot_component)
        lock = self._imu_lock if self._imu_lock is not None and self._imu_lock[0] == self.imu_message else None
        silent = lock is not None and t_s - self._imu_lock_t > self.config.imu_stream_silent_s
        if lock is not None and (mtype, src) != lock[:2] and rank <= lock[2] and not silent:
            raise IgnoredMessage(f"another IMU stream ({lock[0]} from {_stream_name(lock[1])}) is integrated")
        # who measured it (filter.imu.grade = auto): RAW_IMU / SCALED_IMU* are a flight
        # controller's MEMS (int16 mg, mrad/s); so is HIGHRES_IMU from the autopilot's component
        # when that is a flight-controller firmware — ArduPilot and PX4 stamp it on their boot
        # clock. A HIGHRES_IMU in UNIX time, from another component, or from a vehicle computer
        # whose heartbeat says "generic autopilot" is an IMU of its own (the noise decides its class)
        own = mtype != "HIGHRES_IMU" or (
            self._is_autopilot(msg) and msg.time_usec < UNIX_EPOCH_MIN_US
            and self.autopilot_firmware != mavlink2.MAV_AUTOPILOT_GENERIC)
        source = "autopilot" if own else "dedicated"
        sample = imu_from_highres(msg, t_s, source) if mtype == "HIGHRES_IMU" else imu_from_scaled(msg, t_s, source)
        if lock is None or (mtype, src) != lock[:2]:
            self.imu_switches += lock is not None
            self._imu_lock = (mtype, src, rank)
            self.imu_message = mtype
            why = ("the first with a real sample" if lock is None else
                   f"{lock[0]} from {_stream_name(lock[1])} silent" if rank <= lock[2] else
                   f"better than {lock[0]} from {_stream_name(lock[1])}")
            logging.getLogger(__name__).info(
                "IMU stream: %s from %s (%s)", mtype, _stream_name(src), why,
                extra={"event": {"event": "imu_stream", "message": mtype, "system": src[0], "component": src[1],
                                 "imu_id": src[2]}})
        self._imu_lock_t = t_s
        return sample

    def integrated_imu_stream(self) -> str | None:
        """The IMU stream integrated now, e.g. ``"HIGHRES_IMU from 1/1"`` (None: none yet)."""
        lock = self._imu_lock
        return None if lock is None else f"{lock[0]} from {_stream_name(lock[1])}"

    def _pressure(self, msg, mtype, t_s):
        if mtype != self.depth_message:
            raise IgnoredMessage(f"depth comes from {self.depth_message} (the external sensor)")
        return depth_from_pressure(msg, t_s)

    def _gps_raw(self, msg, mtype, t_s):
        if self.last_gps_input_t is not None and t_s - self.last_gps_input_t < self.config.gps_input_echo_window_s:
            raise ConversionError("gnss_echo_of_gps_input")
        return self.gps_fix(gnss_from_gps_raw_int(msg, t_s, self.config, self.gps_fixes_acoustic()))

    def count_unknown(self, mtype: str) -> None:
        """A message of a type the dialect does not know (BlueOS's recordings name it):
        accounted as unknown."""
        self.types.setdefault(mtype, TypeAccount()).messages += 1

    def gps_fix(self, g: GnssSample) -> GnssSample | UsblSample:
        """The autopilot's GPS fix ``g`` as what it is: a surface GNSS fix, or an underwater
        GPS's acoustic one (:meth:`gps_fixes_acoustic`: no surface-only rule)."""
        if self.gps_fixes_acoustic():
            return UsblSample(g.t_s, g.lat_rad, g.lon_rad, math.nan, max(g.sigma_h_m, self.config.usbl_min_sigma_m))
        return g

    def gps_fixes_acoustic(self) -> bool:
        """Are the autopilot's GPS fixes an underwater GPS's (``gps_raw_int_source``)?"""
        source = self.config.gps_raw_int_source
        return source == "acoustic" or (source == "auto" and self.autopilot_gps_type == GPS_TYPE_MAV)

    @property
    def depth_message(self) -> str:
        """The external pressure sensor's message (``convert.depth_message``; "auto": the
        autopilot's BARO_PRIMARY when it names a sensor beyond its first, else SCALED_PRESSURE2)."""
        if self.config.depth_message != "auto":
            return self.config.depth_message
        return PRESSURE_MESSAGES[self.water_baro_instance]

    @property
    def water_baro_instance(self) -> int:
        """The autopilot's water pressure sensor (0-based barometer instance): BARO_PRIMARY when
        it is 1 or 2, else 1 (a BlueROV2's Bar30 beside the board's own barometer)."""
        primary = self.autopilot_baro_primary
        return primary if primary in (1, 2) else 1

    def take_simulator(self, why: str) -> None:
        """The source is ArduPilot's simulator (``why``: the message, record or parameter that
        said so): its thrusters go through ``thrusters.simulator_curve`` from now on (SITL has
        no ESC dead band). Said once."""
        if self.simulator is not None:
            return
        self.simulator = why
        self.thrusters = replace(self.config.thrusters, curve=self.config.thrusters.simulator_curve)
        logging.getLogger(__name__).info(
            "the source is ArduPilot's simulator (%s): thrusters through mavlink.convert.thrusters."
            "simulator_curve (no ESC dead band)", why)

    def thruster_report(self) -> dict[str, Any]:
        """Which PWM → RPM curve the thrusters went through, and why, for summaries."""
        if self.simulator is None:
            return {"curve": "vehicle", "why": "mavlink.convert.thrusters.curve (no simulator seen)"}
        return {"curve": "simulator", "why": f"ArduPilot's simulator ({self.simulator}): "
                "mavlink.convert.thrusters.simulator_curve"}

    def note_parameter(self, name: str, value: float) -> None:
        """One of the autopilot's parameters (PARAM_VALUE, a DataFlash log's PARM)."""
        if name.startswith("SIM_"):  # only a simulator build has the SIM_ group
            self.take_simulator(f"its parameter {name}")
        if name == "BARO_PRIMARY" and math.isfinite(value):
            self.autopilot_baro_primary = int(value)
        if name in ("GPS_TYPE", "GPS1_TYPE") and math.isfinite(value):
            if self.autopilot_gps_type != int(value):
                logging.getLogger(__name__).info("the autopilot's first GPS is type %d%s", int(value),
                         " (MAVLink: GPS_INPUT from the companion, taken as an underwater GPS's fixes)"
                         if int(value) == GPS_TYPE_MAV else "")
            self.autopilot_gps_type = int(value)

    def gps_report(self) -> dict[str, Any]:
        """What the autopilot's GPS fixes were taken as, and why, for summaries and health."""
        acoustic = self.gps_fixes_acoustic()
        if self.config.gps_raw_int_source != "auto":
            why = f"configured (mavlink.convert.gps_raw_int_source = {self.config.gps_raw_int_source!r})"
        elif self.autopilot_gps_type is None:
            why = "the autopilot's GPS type is unknown (no GPS_TYPE/GPS1_TYPE parameter seen): a surface GNSS"
        else:
            why = f"the autopilot's GPS_TYPE/GPS1_TYPE is {self.autopilot_gps_type}" + (
                " (MAVLink: an underwater GPS's GPS_INPUT)" if acoustic else "")
        return {"taken_as": "acoustic" if acoustic else "gnss", "why": why}

    def _gps_input(self, msg, mtype, t_s):
        self.last_gps_input_t = t_s
        return usbl_from_gps_input(msg, t_s, self.config)

    def _vision_position(self, msg, mtype, t_s):
        if self.origin is None and self.origin_lookup is not None:
            # a log may carry the autopilot's GPS_GLOBAL_ORIGIN after the first such fixes: asked
            # once, at the first fix that needs it (a walk over the file, none for other logs)
            lookup, self.origin_lookup = self.origin_lookup, None
            self.origin = lookup()
            if self.origin is not None:
                self.origin_from = "GPS_GLOBAL_ORIGIN"
        if self.origin is None:
            raise ConversionError("no_origin", "GLOBAL_VISION_POSITION_ESTIMATE before any origin")
        return usbl_from_global_vision(msg, t_s, self.origin, self.config)


def _stream_name(src: tuple[int, int, int]) -> str:
    """``system/component`` of an IMU stream, ``#id`` added for a component's further IMUs."""
    return f"{src[0]}/{src[1]}" + (f" #{src[2]}" if src[2] else "")


_HANDLERS = {
    "RAW_IMU": MavlinkConverter._imu,
    "SCALED_IMU": MavlinkConverter._imu,
    "SCALED_IMU2": MavlinkConverter._imu,
    "HIGHRES_IMU": MavlinkConverter._imu,
    "ATTITUDE": MavlinkConverter._attitude,
    "SCALED_PRESSURE": MavlinkConverter._pressure,
    "SCALED_PRESSURE2": MavlinkConverter._pressure,
    "SCALED_PRESSURE3": MavlinkConverter._pressure,
    "SERVO_OUTPUT_RAW": lambda self, m, k, t: rpm_from_servo(m, t, self.thrusters),
    "GPS_RAW_INT": MavlinkConverter._gps_raw,
    "GPS_INPUT": MavlinkConverter._gps_input,
    "DISTANCE_SENSOR": lambda self, m, k, t: altitude_from_distance_sensor(m, t, self.config),
    "VISION_POSITION_DELTA": lambda self, m, k, t: dvl_from_vision_position_delta(m, t, self.config, self._timed(m)),
    "VISION_SPEED_ESTIMATE": lambda self, m, k, t: dvl_from_vision_speed(m, t, self.config),
    "GLOBAL_VISION_POSITION_ESTIMATE": MavlinkConverter._vision_position,
    "ODOMETRY": lambda self, m, k, t: dvl_from_odometry(m, t),
}
# types accepted from the aiding systems (companion drivers) as well as from the autopilot
AID_MESSAGES = frozenset({"VISION_POSITION_DELTA", "VISION_SPEED_ESTIMATE", "GLOBAL_VISION_POSITION_ESTIMATE",
                          "GPS_INPUT", "DISTANCE_SENSOR", "HIGHRES_IMU", "ODOMETRY"})

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


def horizontal_velocity_sigma_m_s(cov: np.ndarray) -> float:
    """sqrt of the largest eigenvalue of the north/east velocity covariance."""
    _, vel, _ = _cov_slices()
    p = np.asarray(cov)[vel, vel][:2, :2]
    if not np.all(np.isfinite(p)):
        return math.nan
    return float(math.sqrt(max(np.linalg.eigvalsh(0.5 * (p + p.T))[-1], 0.0)))


def vision_position_estimate_fields(odometry: dict[str, Any]) -> dict[str, Any]:
    """The pose of ODOMETRY fields as VISION_POSITION_ESTIMATE (no velocity): what goes out
    when the velocity is not constrained. Same frame (ArduSub reads it as local FRD)."""
    q = np.asarray(odometry["q"], dtype=float)
    roll, pitch, yaw = dcm_to_euler(quat_to_dcm(q))
    return dict(usec=odometry["time_usec"], x=odometry["x"], y=odometry["y"], z=odometry["z"],
                roll=float(roll), pitch=float(pitch), yaw=float(yaw), covariance=odometry["pose_covariance"],
                reset_counter=odometry["reset_counter"])


def nav_is_valid(nav: Any) -> bool:
    """The solution may be sent: flagged valid and every sent number finite."""
    if not getattr(nav, "valid", False):
        return False
    parts = [np.asarray(nav.pos_n_m, float), np.asarray(nav.vel_n_m_s, float), np.asarray(nav.q_nb, float)]
    return all(np.all(np.isfinite(p)) for p in parts) and abs(np.linalg.norm(parts[2]) - 1.0) < 1e-3


def odometry_fields(nav: Any, cfg: OdometryConfig | None = None,
                    omega_b_rad_s: Any = None) -> dict[str, Any] | None:
    """``NavState`` → keyword arguments of ``MAVLink.odometry_send``.

    Returns ``None`` for an invalid solution (or one below ``cfg.min_quality``) when
    ``cfg.invalid == "silence"``;
    with ``"failed"`` the message has quality −1 and NaN pose and velocity.
    ``omega_b_rad_s`` (3,) rad/s is sent as the angular rates when given (NaN otherwise).
    """
    cfg = cfg or OdometryConfig()
    time_usec = int(round(max(float(nav.t_s), 0.0) * 1e6))
    reset_counter = int(getattr(nav, "reset_counter", 0)) % 256
    nan3 = [math.nan] * 3
    rates = nan3 if omega_b_rad_s is None else [float(w) for w in omega_b_rad_s]
    valid = nav_is_valid(nav) and quality_from_sigma(horizontal_sigma_m(nav.cov), cfg) >= cfg.min_quality
    if not valid:
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
