"""Live MAVLink bridge to ArduSub (pymavlink): samples in, ODOMETRY out.

One thread owns the link.  It

- opens the URL with ``mavutil.mavlink_connection`` (``udpin:``, ``udpout:``, ``tcp:``,
  ``tcpin:``, serial ``/dev/...[,baud]``) as an onboard component (HEARTBEAT at 1 Hz,
  ``MAV_TYPE_ONBOARD_CONTROLLER``, component ``MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY``);
- on every (re)appearance of the autopilot's HEARTBEAT, and after it rebooted (its boot
  clock went back), asks for the streams it needs with ``MAV_CMD_SET_MESSAGE_INTERVAL``
  (ArduSub streams RAW_IMU at 2 Hz unless asked): ``HIGHRES_IMU`` (float SI) first, and
  ``RAW_IMU`` only when no HIGHRES_IMU came within ``imu_fallback_s`` (``request_imu_message
  = "auto"``);
- sends ``SET_GPS_GLOBAL_ORIGIN`` and asks for the autopilot's ``GPS_GLOBAL_ORIGIN`` back;
  until the answer matches, re-sends every ``origin_retry_s`` (at most ``origin_retries``
  times; a mismatch is reported in health), and again after the autopilot rebooted;
- converts what arrives with :class:`adaptnav.service.transport.mavlink_convert.MavlinkConverter` and
  hands each sample to ``on_sample`` (which should only enqueue);
- survives corrupt frames (pymavlink's robust parser yields ``BAD_DATA``; counted),
  link loss (no autopilot traffic for ``link_timeout_s``) and socket errors (re-open
  with exponential back-off; counted).

:meth:`MavlinkBridge.offer_nav` takes every nav state and sends ODOMETRY on a fixed
schedule of ``output_rate_hz`` on the data clock (:class:`OutputSchedule`: a state a hair
early for its slot is still sent, so 10 Hz states give 10 Hz ODOMETRY, within ArduSub's
300 ms window); ArduSub drops external navigation ~15 s after the last message.  What is
sent is honest: nothing below ``output.min_quality`` or for an invalid solution (never
plausible zeros, see :func:`adaptnav.service.transport.mavlink_convert.odometry_fields`);
the pose alone (VISION_POSITION_ESTIMATE) when the velocity σ says no aid has constrained
it; ``reset_counter`` continues across daemon restarts (persisted in ``state_path``: a
restart is a reset for the autopilot).  :meth:`MavlinkBridge.health` exports the counters,
the converter's rejections and per-type accounting, the origin's state and command acks.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

from adaptnav.service.transport.mavlink_convert import (  # sets MAVLINK20 before pymavlink loads
    ConvertConfig,
    MavlinkConverter,
    OdometryConfig,
    gps_global_origin_fields,
    horizontal_velocity_sigma_m_s,
    mavlink2,
    odometry_fields,
    vision_position_delta_fields,
    vision_position_estimate_fields,
)
from adaptnav.fusion.frames import GeoOrigin

from adaptnav.service.transport.mavlink_config import BridgeConfig, StreamRates  # noqa: F401 (re-exported)
from adaptnav.service.transport.mavlink_config import split_link_url
from adaptnav.service.transport.mavlink_frames import untruncated

from pymavlink import mavutil  # noqa: E402

log = logging.getLogger(__name__)


def link_device(url: str) -> tuple[str, int]:
    """A bridge URL → (pymavlink device string, baud) (:func:`split_link_url`'s forms). A path
    to a regular file is refused: pymavlink would open it as a *log*, which is the replay's
    job, not the live bridge's."""
    try:
        device, baud = split_link_url(url)
    except ValueError as e:
        raise ValueError(f"MAVLink URL {url!r}: {e}") from None
    if os.path.isfile(device):
        raise ValueError(f"MAVLink URL {url!r} is a file: replay logs with `adaptnav replay`, not the bridge")
    return device, baud


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink2.enums.get(enum, {}).get(int(value))
    return entry.name if entry is not None else str(value)


def _raise_link_closed() -> None:
    raise ConnectionError("link closed by peer")


class OutputSchedule:
    """Fixed-rate output slots on the data clock.

    ``due(t_s)`` is True for the state nearest each slot ``k / rate_hz`` from its side: a
    state stamped a hair before its slot (floating-point sums of IMU intervals) takes that
    slot instead of waiting for the next one — the old rule (next = state time + period)
    skipped every second state and halved a 10 Hz output to 5 Hz.  The slack is just under
    half the interval between offered states (at most a quarter period), so faster states
    are never taken early.  A gap or a clock that went back re-anchors the slots.
    """

    def __init__(self, rate_hz: float):
        self.period_s = 1.0 / rate_hz
        self.next_s: float | None = None
        self._last_t: float | None = None

    def due(self, t_s: float) -> bool:
        dt_in = t_s - self._last_t if self._last_t is not None and t_s > self._last_t else self.period_s
        self._last_t = t_s
        slack = min(0.49 * dt_in, 0.25 * self.period_s)
        if self.next_s is None or t_s < self.next_s - 2.0 * self.period_s or t_s > self.next_s + self.period_s:
            self.next_s = t_s  # first state, clock went back, or a gap: re-anchor
        if t_s < self.next_s - slack:
            return False
        self.next_s += self.period_s
        return True


def _signing_key(passphrase_file: str) -> bytes | None:
    """The MAVLink 2 signing key from the passphrase in ``passphrase_file`` (its SHA-256, as
    MAVProxy and QGroundControl derive it; line end stripped); None when signing is off.

    Raises
    ------
    OSError
        The file cannot be read (said at start, not on the first send).
    """
    if not passphrase_file:
        return None
    return hashlib.sha256(Path(passphrase_file).read_text().rstrip("\r\n").encode()).digest()


def message_intervals(config: BridgeConfig, imu_message: str | None = None,
                      depth_message: str | None = None) -> dict[int, float]:
    """MAVLink message id → requested interval (µs) for SET_MESSAGE_INTERVAL (``depth_message``:
    the converter's, as the autopilot's BARO_PRIMARY decided an "auto" one)."""
    r = config.rates
    imu = imu_message or config.request_imu_message
    if imu == "auto":
        imu = "HIGHRES_IMU"
    depth = depth_message or config.convert.depth_message
    wanted = {
        imu: r.imu_hz,
        "ATTITUDE": r.attitude_hz,
        "SCALED_PRESSURE2" if depth == "auto" else depth: r.pressure_hz,
        "SERVO_OUTPUT_RAW": r.servo_hz,
        "GPS_RAW_INT": r.gps_raw_hz,
        "DISTANCE_SENSOR": r.distance_hz,
    }
    return {getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"): 1e6 / hz for name, hz in wanted.items() if hz > 0}


class MavlinkBridge:
    """The MAVLink link to the autopilot, in its own thread.

    Parameters
    ----------
    url : str
        pymavlink connection string (overrides ``config.url`` when given).
    on_sample : callable
        Called from the bridge thread with every converted sample; must not block.
    origin : GeoOrigin or None
        Mission origin sent once per link as SET_GPS_GLOBAL_ORIGIN.
    config : BridgeConfig, optional

    Attributes
    ----------
    counters : dict
        ``messages_by_type``, ``corrupt_frames``, ``repaired_frames`` (of those, the frames that
        failed the CRC only because trailing zeros were cut after it: restored and used,
        :mod:`.mavlink_frames`),
        ``samples``, ``rejected`` (by reason),
        ``send_errors``, ``reconnects``, ``link_losses``, ``odometry_sent``,
        ``nav_silenced`` (invalid solutions not sent), ``callback_errors``,
        ``interval_requests``, ``origin_sent``, ``packets_lost`` (gaps in the MAVLink
        sequence numbers per sender, pymavlink's ``mav_loss``: frames lost on the link,
        e.g. a full UDP receive buffer, are counted, never silent).
    """

    def __init__(self, url: str | None, on_sample: Callable[[Any], None],
                 origin: GeoOrigin | None = None, config: BridgeConfig | None = None,
                 state_path: str | os.PathLike | None = None, output_rate_hz: float | None = None):
        self.config = config or BridgeConfig()
        self.url = url or self.config.url
        self.on_sample = on_sample
        self.origin = origin
        convert = self.config.convert
        self.imu_stream = self.config.request_imu_message
        if self.imu_stream == "auto":
            self.imu_stream = "HIGHRES_IMU"  # RAW_IMU only if the autopilot has no HIGHRES_IMU
        if convert.imu_message == "auto":  # lock on the IMU stream we ask for
            convert = dataclasses.replace(convert, imu_message=self.imu_stream)
        self.converter = MavlinkConverter(convert, origin)
        self._depth_requested = self.converter.depth_message  # the pressure stream asked for
        self._signing_key = _signing_key(self.config.signing_passphrase_file)
        self.counters: dict[str, Any] = {
            "messages_by_type": {}, "corrupt_frames": 0, "repaired_frames": 0, "samples": 0, "rejected": self.converter.rejected,
            "send_errors": 0, "reconnects": 0, "link_losses": 0, "odometry_sent": 0, "nav_silenced": 0, "nav_no_link": 0,
            "callback_errors": 0, "interval_requests": 0, "origin_sent": 0, "command_acks": 0,
            "packets_lost": 0, "pose_only_sent": 0, "autopilot_reboots": 0,
        }
        self.command_acks: dict[str, int] = {}  # "COMMAND:RESULT" → count
        self.origin_confirmed = False
        self.autopilot_origin: tuple[float, float] | None = None  # degrees, as the autopilot reports it
        self._origin_attempts = 0
        self._next_origin_s = math.inf
        self._imu_requested_s: float | None = None
        self._reboots_seen = 0
        rate = output_rate_hz or getattr(self.config, "output_rate_hz", 10.0)
        self.schedule = OutputSchedule(rate)
        self._sent_wall: deque[float] = deque(maxlen=200)  # wall times of the last sends (rate)
        self.first_sent: dict[str, Any] | None = None  # fields of the first pose sent (tests, health)
        self.last_sent: dict[str, Any] | None = None
        self.state_path = None if state_path is None else Path(state_path)
        self.reset_base = self._load_reset_base()
        self._persisted_reset: int | None = None
        self._lost_closed = 0  # packets lost on links closed since
        self._conn: Any = None
        self._prev_nav: Any = None
        self._lock = threading.Lock()  # pymavlink's sequence counter and socket are not thread-safe
        self._stop = threading.Event()
        self.autopilot: tuple[int, int] | None = None  # (system, component) once seen
        self.link_up = threading.Event()
        self._last_rx = 0.0
        self._opened_once = False
        self._thread = threading.Thread(target=self._run, name="mavlink-bridge", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public
    def offer_nav(self, nav_state: Any, omega_b_rad_s: Any = None) -> bool:
        """Every nav state comes here; ODOMETRY goes out on the fixed output schedule."""
        if not self.schedule.due(float(nav_state.t_s)):
            return False
        return self.send_nav(nav_state, omega_b_rad_s)

    def send_nav(self, nav_state: Any, omega_b_rad_s: Any = None) -> bool:
        """Send ODOMETRY for ``nav_state`` now (the pose alone when its velocity is not
        constrained); False when silenced, no link or a send error."""
        fields = odometry_fields(nav_state, self.config.output, omega_b_rad_s)
        if fields is None:
            self.counters["nav_silenced"] += 1
            return False
        if not self.link_up.is_set():
            self.counters["nav_no_link"] += 1
            return False
        fields["reset_counter"] = (int(fields["reset_counter"]) + self.reset_base) % 256
        self._persist_reset(fields["reset_counter"])
        if horizontal_velocity_sigma_m_s(nav_state.cov) > self.config.output.max_velocity_sigma_m_s:
            ok = self._send("vision_position_estimate_send", **vision_position_estimate_fields(fields)) \
                and self._count("pose_only_sent")
        else:
            ok = self._send("odometry_send", **fields) and self._count("odometry_sent")
        if ok:
            self._sent_wall.append(time.monotonic())
            self.last_sent = fields
            if self.first_sent is None:
                self.first_sent = fields
        if self.config.output.vision_position_delta:
            delta = None if self._prev_nav is None else vision_position_delta_fields(self._prev_nav, nav_state)
            if delta is not None and self._send("vision_position_delta_send", **delta):
                self._count("vision_delta_sent")
            self._prev_nav = nav_state
        return ok

    def output_rate_hz(self) -> float | None:
        """Measured rate of what was sent over the last sends (wall clock)."""
        w = list(self._sent_wall)
        return (len(w) - 1) / (w[-1] - w[0]) if len(w) > 2 and w[-1] > w[0] else None

    def health(self) -> dict[str, Any]:
        """What the link did, for the daemon's health topic."""
        c = self.counters
        types = self.converter.accounting()
        return {
            **{k: c.get(k, 0) for k in ("packets_lost", "corrupt_frames", "repaired_frames", "link_losses", "reconnects",
                                        "callback_errors", "odometry_sent", "pose_only_sent", "nav_silenced",
                                        "nav_no_link", "send_errors", "interval_requests", "origin_sent",
                                        "samples", "autopilot_reboots")},
            "link_up": self.link_up.is_set(),
            "autopilot": list(self.autopilot) if self.autopilot else None,
            "imu_stream": self.imu_stream,
            # the stream integrated now ("HIGHRES_IMU from 1/1"), and how often it changed (a
            # better one appeared, or the integrated one fell silent)
            "imu_integrated": self.converter.integrated_imu_stream(),
            "imu_switches": self.converter.imu_switches,
            "output_rate_hz": self.output_rate_hz(),
            "reset_counter_base": self.reset_base,
            "origin_confirmed": self.origin_confirmed,
            "autopilot_origin_deg": list(self.autopilot_origin) if self.autopilot_origin else None,
            "command_acks": dict(self.command_acks),
            "messages_by_type": dict(c["messages_by_type"]),
            "rejected": dict(self.converter.rejected),
            # per type: used / rejected (with reasons) / ignored (why) / unknown; e.g. why a
            # DISTANCE_SENSOR never became an altitude sample
            "message_types": {k: {kk: v[kk] for kk in ("status", "why", "rejected", "rate_hz") if kk in v}
                              for k, v in types.items()},
            "clock": self.converter.clock_report(),
            # which PWM → RPM curve the thrusters go through (the simulator's once SIM_STATE or a
            # SIM_* parameter said the autopilot is ArduPilot's SITL), as replay's summary.json
            "thrusters": self.converter.thruster_report(),
            "signing": self._signing_report(),
        }

    def _signing_report(self) -> dict[str, Any] | None:
        """MAVLink 2 signing's counts (None: off): signed messages in, bad signatures and the
        messages refused for them, unsigned ones taken."""
        signing = getattr(getattr(self._conn, "mav", None), "signing", None)
        if self._signing_key is None or signing is None:
            return None
        return {"signed_in": signing.goodsig_count, "bad_signatures": signing.badsig_count,
                "refused": signing.reject_count, "unsigned_accepted": signing.unsigned_count}

    def wait_connected(self, timeout_s: float) -> bool:
        """Block until the autopilot's heartbeat has been seen (or timeout)."""
        return self.link_up.wait(timeout_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        with self._lock:
            self._close_conn()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ internals
    def _load_reset_base(self) -> int:
        """The reset_counter sent last by an earlier run + 1 (a restart is a reset), or 0."""
        if self.state_path is None:
            return 0
        try:
            return (int(json.loads(self.state_path.read_text())["reset_counter"]) + 1) % 256
        except FileNotFoundError:
            return 0
        except (ValueError, KeyError, TypeError, OSError) as e:
            log.warning("%s unusable (%s): reset_counter starts at 1", self.state_path, e)
            return 1

    def _persist_reset(self, value: int) -> None:
        if self.state_path is None or value == self._persisted_reset:
            return
        try:
            self.state_path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.state_path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"reset_counter": int(value)}))
            os.replace(tmp, self.state_path)
            self._persisted_reset = value
        except OSError as e:
            self.counters["persist_errors"] = self.counters.get("persist_errors", 0) + 1
            log.warning("could not persist reset_counter to %s: %s", self.state_path, e)

    def _count(self, key: str, n: int = 1) -> bool:
        self.counters[key] = self.counters.get(key, 0) + n
        return True

    def _send(self, method: str, **kwargs) -> bool:
        with self._lock:
            if self._conn is None:
                return False
            try:
                getattr(self._conn.mav, method)(**kwargs)
                return True
            except Exception as e:  # socket errors, serial unplugged, struct range
                self.counters["send_errors"] += 1
                log.debug("MAVLink send %s failed: %s", method, e)
                return False

    def _open(self) -> None:
        device, baud = link_device(self.url)
        conn = mavutil.mavlink_connection(
            device, baud=baud, source_system=self.config.source_system,
            source_component=self.config.source_component, dialect="ardupilotmega", autoreconnect=False,
            retries=0)  # one TCP connect attempt: our loop owns the back-off
        if self._signing_key is not None:
            accept = (lambda _mav, _msg_id: True) if self.config.signing_accept_unsigned else None
            conn.setup_signing(self._signing_key, sign_outgoing=True, allow_unsigned_callback=accept)
        if isinstance(conn, mavutil.mavtcp):
            # pymavlink prints and carries on at a TCP EOF/reset unless autoreconnect, which
            # would block this thread in its own retry loop: raise instead, so the loop
            # below counts the loss and re-opens with back-off
            conn.handle_eof = conn.handle_disconnect = _raise_link_closed
        port = getattr(conn, "port", None)
        if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
            try:  # room for bursts (accelerated simulation, log playback into the link)
                port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.config.udp_rcvbuf_bytes)
            except OSError:
                pass
        with self._lock:
            self._conn = conn
        if self._opened_once:
            self.counters["reconnects"] += 1
        self._opened_once = True
        self._last_rx = time.monotonic()
        self.autopilot = None
        self.link_up.clear()

    def _close_conn(self) -> None:
        if self._conn is not None:
            self._lost_closed += int(getattr(self._conn, "mav_loss", 0))
            try:
                self._conn.close()
            except Exception:
                pass
            self._conn = None

    def _heartbeat(self) -> None:
        self._send("heartbeat_send", type=mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                   autopilot=mavlink2.MAV_AUTOPILOT_INVALID, base_mode=0, custom_mode=0,
                   system_status=mavlink2.MAV_STATE_ACTIVE)

    def _command(self, command: int, *params: float) -> bool:
        sysid, compid = self.autopilot
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        return self._send("command_long_send", target_system=sysid, target_component=compid,
                          command=command, confirmation=0, param1=p[0], param2=p[1], param3=p[2],
                          param4=p[3], param5=p[4], param6=p[5], param7=p[6])

    def _request_streams(self) -> None:
        self._depth_requested = self.converter.depth_message
        for msg_id, interval_us in message_intervals(self.config, self.imu_stream, self._depth_requested).items():
            if self._command(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us):
                self.counters["interval_requests"] += 1
        self._imu_requested_s = time.monotonic()

    def _send_origin(self) -> None:
        if self.origin is None:
            return
        if self._send("set_gps_global_origin_send", **gps_global_origin_fields(self.origin, self.autopilot[0])):
            self.counters["origin_sent"] += 1
        # ArduSub answers GPS_GLOBAL_ORIGIN on the setter's channel; ask for it explicitly too
        self._command(mavlink2.MAV_CMD_REQUEST_MESSAGE, mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
        self._origin_attempts += 1
        self._next_origin_s = time.monotonic() + self.config.origin_retry_s

    def _on_autopilot_up(self, sysid: int, compid: int) -> None:
        self.autopilot = (sysid, compid)
        r = self.config.rates
        log.info("MAVLink link up: autopilot system %d component %d on %s; requesting %s at %g Hz",
                 sysid, compid, self.url, self.imu_stream, r.imu_hz,
                 extra={"event": {"event": "link_up", "peer": f"{sysid}/{compid}", "url": self.url}})
        self._request_streams()
        # is its GPS an underwater one (MAVLink)? (ArduPilot < / ≥ 4.6) Which baro is the water sensor?
        for name in (b"GPS_TYPE", b"GPS1_TYPE", b"BARO_PRIMARY"):
            self._send("param_request_read_send", target_system=sysid, target_component=compid, param_id=name,
                       param_index=-1)
        self.origin_confirmed = False
        self._origin_attempts = 0
        self._send_origin()
        self.link_up.set()

    def _supervise(self) -> None:
        """Periodic duties: IMU fallback, origin confirmation, autopilot reboots."""
        if self.autopilot is None:
            return
        if self.converter.depth_message != self._depth_requested:  # its BARO_PRIMARY named another sensor
            self._request_streams()
        now = time.monotonic()
        reboots = self.converter.time.reboots
        if reboots != self._reboots_seen:  # its boot clock went back: streams and origin are lost
            self._reboots_seen = reboots
            self.counters["autopilot_reboots"] = reboots
            self._on_autopilot_up(*self.autopilot)
            return
        if (self.config.request_imu_message == "auto" and self.imu_stream == "HIGHRES_IMU"
                and self._imu_requested_s is not None and now - self._imu_requested_s > self.config.imu_fallback_s
                and not self.counters["messages_by_type"].get("HIGHRES_IMU")):
            log.warning("MAVLink: no HIGHRES_IMU %.0f s after asking; falling back to RAW_IMU", self.config.imu_fallback_s)
            self.imu_stream = "RAW_IMU"
            self.converter.imu_message = "RAW_IMU"
            self._request_streams()
        if (self.origin is not None and not self.origin_confirmed and now >= self._next_origin_s
                and self._origin_attempts <= self.config.origin_retries):
            self._send_origin()

    def _on_origin(self, msg: Any) -> None:
        lat, lon = msg.latitude / 1e7, msg.longitude / 1e7
        self.autopilot_origin = (lat, lon)
        if self.origin is not None:
            want = gps_global_origin_fields(self.origin, 0)
            self.origin_confirmed = abs(msg.latitude - want["latitude"]) <= 1 and abs(msg.longitude - want["longitude"]) <= 1

    def _handle(self, msg: Any) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.counters["corrupt_frames"] += 1
            restored = untruncated(msg, self._conn.mav) if self._conn is not None else None
            if restored is None:
                return
            # a link relayed by a ground station that cut trailing zeros after the CRC
            self.counters["repaired_frames"] += 1
            msg, mtype = restored, restored.get_type()
        by_type = self.counters["messages_by_type"]
        by_type[mtype] = by_type.get(mtype, 0) + 1
        if mtype == "HEARTBEAT" and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
            self._last_rx = time.monotonic()
            if self.autopilot is None:
                self._on_autopilot_up(msg.get_srcSystem(), msg.get_srcComponent())
        elif mtype == "COMMAND_ACK":
            self.counters["command_acks"] += 1
            key = f"{_enum_name('MAV_CMD', msg.command)}:{_enum_name('MAV_RESULT', msg.result)}"
            self.command_acks[key] = self.command_acks.get(key, 0) + 1
        elif mtype == "GPS_GLOBAL_ORIGIN" and self.autopilot is not None and msg.get_srcSystem() == self.autopilot[0]:
            self._on_origin(msg)
        elif self.autopilot is not None and msg.get_srcSystem() == self.autopilot[0]:
            self._last_rx = time.monotonic()
        for sample in self.converter.convert(msg):
            self.counters["samples"] += 1
            try:
                self.on_sample(sample)
            except Exception:
                self.counters["callback_errors"] += 1
                log.exception("on_sample raised; sample dropped")

    def _run(self) -> None:
        backoff = self.config.reconnect_min_s
        next_hb = 0.0
        while not self._stop.is_set():
            if self._conn is None:
                try:
                    self._open()
                    backoff = self.config.reconnect_min_s
                except Exception as e:  # port busy, host down, serial absent
                    log.warning("MAVLink open %s failed (%s); retry in %.1f s", self.url, e, backoff)
                    if self._stop.wait(backoff):
                        break
                    backoff = min(2.0 * backoff, self.config.reconnect_max_s)
                    continue
            now = time.monotonic()
            if now >= next_hb:
                self._heartbeat()
                next_hb = now + self.config.heartbeat_period_s
                self._supervise()
            try:
                got = 0
                while got < 1000:  # drain what is there, but keep heartbeats going
                    msg = self._conn.recv_msg()
                    if msg is None:
                        break
                    got += 1
                    self._handle(msg)
                if got:
                    self.counters["packets_lost"] = self._lost_closed + int(getattr(self._conn, "mav_loss", 0))
                if got == 0:
                    self._conn.select(0.02)
            except Exception as e:  # socket closed by peer, serial gone, parser blew up
                log.warning("MAVLink link %s error: %s; reconnecting", self.url, e)
                self.counters["link_losses"] += 1
                with self._lock:
                    self._close_conn()
                self._stop.wait(backoff)
                backoff = min(2.0 * backoff, self.config.reconnect_max_s)
                continue
            if self.autopilot is not None and time.monotonic() - self._last_rx > self.config.link_timeout_s:
                # silent autopilot: re-open (a fresh socket drops stale peers and
                # re-runs the stream requests when it comes back, possibly rebooted)
                log.warning("MAVLink link down: no traffic from autopilot %d/%d for %.1f s; re-opening %s",
                            *self.autopilot, self.config.link_timeout_s, self.url,
                            extra={"event": {"event": "link_down", "peer": "%d/%d" % self.autopilot}})
                self.counters["link_losses"] += 1
                with self._lock:
                    self._close_conn()
