"""Live MAVLink bridge to ArduSub (pymavlink): samples in, ODOMETRY out.

One thread owns the link.  It

- opens the URL with ``mavutil.mavlink_connection`` (``udpin:``, ``udpout:``, ``tcp:``,
  ``tcpin:``, serial ``/dev/...[,baud]``) as an onboard component (HEARTBEAT at 1 Hz,
  ``MAV_TYPE_ONBOARD_CONTROLLER``, component ``MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY``);
- on every (re)appearance of the autopilot's HEARTBEAT, asks for the streams it needs
  with ``MAV_CMD_SET_MESSAGE_INTERVAL`` (ArduSub streams RAW_IMU at 2 Hz unless asked)
  and sends ``SET_GPS_GLOBAL_ORIGIN`` once per link;
- converts what arrives with :class:`adaptnav.service.transport.mavlink_convert.MavlinkConverter` and
  hands each sample to ``on_sample`` (which should only enqueue);
- survives corrupt frames (pymavlink's robust parser yields ``BAD_DATA``; counted),
  link loss (no autopilot traffic for ``link_timeout_s``) and socket errors (re-open
  with exponential back-off; counted).

:meth:`MavlinkBridge.send_nav` is called by the daemon's output at its own rate
(≥ 4 Hz for ArduSub, which drops external navigation ~15 s after the last message); an
invalid solution is never sent as plausible zeros (see
:func:`adaptnav.service.transport.mavlink_convert.odometry_fields`).
"""
from __future__ import annotations

import dataclasses
import logging
import os
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from adaptnav.service.transport.mavlink_convert import (  # sets MAVLINK20 before pymavlink loads
    ConvertConfig,
    MavlinkConverter,
    OdometryConfig,
    gps_global_origin_fields,
    mavlink2,
    odometry_fields,
    vision_position_delta_fields,
)
from adaptnav.fusion.frames import GeoOrigin

from pymavlink import mavutil  # noqa: E402

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StreamRates:
    """Rates requested from the autopilot, Hz (0 = leave the autopilot's default)."""

    imu_hz: float = 50.0
    attitude_hz: float = 50.0
    pressure_hz: float = 10.0
    servo_hz: float = 10.0
    gps_raw_hz: float = 5.0
    distance_hz: float = 10.0


@dataclass(frozen=True)
class BridgeConfig:
    """``[mavlink]`` section: link, identity, requested rates, conversion and output."""

    url: str = "udpin:0.0.0.0:14550"
    source_system: int = 1  # onboard components share the vehicle's system id
    source_component: int = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    heartbeat_period_s: float = 1.0
    link_timeout_s: float = 3.0
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 5.0
    request_imu_message: str = "RAW_IMU"  # ArduSub 4.x streams RAW_IMU; HIGHRES_IMU on newer builds
    rates: StreamRates = field(default_factory=StreamRates)
    udp_rcvbuf_bytes: int = 4 * 1024 * 1024
    convert: ConvertConfig = field(default_factory=ConvertConfig)
    output: OdometryConfig = field(default_factory=OdometryConfig)

    def validate(self) -> None:
        if self.heartbeat_period_s <= 0 or self.link_timeout_s <= 0:
            raise ValueError("heartbeat_period_s and link_timeout_s must be > 0")
        if not 0 < self.reconnect_min_s <= self.reconnect_max_s:
            raise ValueError("need 0 < reconnect_min_s ≤ reconnect_max_s")
        if self.request_imu_message not in ("RAW_IMU", "SCALED_IMU2", "HIGHRES_IMU"):
            raise ValueError("request_imu_message: RAW_IMU, SCALED_IMU2 or HIGHRES_IMU")


def link_device(url: str) -> tuple[str, int]:
    """A bridge URL → (pymavlink device string, baud).

    Accepts pymavlink's own forms (``udpin:H:P``, ``udpout:H:P``, ``tcp:H:P``,
    ``tcpin:H:P``, ``/dev/ttyACM0`` or ``/dev/ttyACM0,115200``) and
    ``serial:/dev/ttyACM0[:baud]``.  A path to a regular file is refused: pymavlink
    would open it as a *log*, which is the replay's job, not the live bridge's.
    """
    baud = 115200
    device = url
    if url.startswith("serial:"):
        device = url[len("serial:"):]
        if ":" in device:
            device, _, b = device.rpartition(":")
            baud = int(b)
    elif url.startswith("/") and "," in url:
        device, _, b = url.rpartition(",")
        baud = int(b)
    if not device:
        raise ValueError(f"MAVLink URL {url!r}: no device")
    if os.path.isfile(device):
        raise ValueError(f"MAVLink URL {url!r} is a file: replay logs with `adaptnav replay`, not the bridge")
    return device, baud


def _raise_link_closed() -> None:
    raise ConnectionError("link closed by peer")


def message_intervals(config: BridgeConfig) -> dict[int, float]:
    """MAVLink message id → requested interval (µs) for SET_MESSAGE_INTERVAL."""
    r = config.rates
    wanted = {
        config.request_imu_message: r.imu_hz,
        "ATTITUDE": r.attitude_hz,
        config.convert.depth_message: r.pressure_hz,
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
        ``messages_by_type``, ``corrupt_frames``, ``samples``, ``rejected`` (by reason),
        ``send_errors``, ``reconnects``, ``link_losses``, ``odometry_sent``,
        ``nav_silenced`` (invalid solutions not sent), ``callback_errors``,
        ``interval_requests``, ``origin_sent``, ``packets_lost`` (gaps in the MAVLink
        sequence numbers per sender, pymavlink's ``mav_loss``: frames lost on the link,
        e.g. a full UDP receive buffer, are counted, never silent).
    """

    def __init__(self, url: str | None, on_sample: Callable[[Any], None],
                 origin: GeoOrigin | None = None, config: BridgeConfig | None = None):
        self.config = config or BridgeConfig()
        self.url = url or self.config.url
        self.on_sample = on_sample
        self.origin = origin
        convert = self.config.convert
        if convert.imu_message == "auto":  # lock on the IMU stream we ask for
            convert = dataclasses.replace(convert, imu_message=self.config.request_imu_message)
        self.converter = MavlinkConverter(convert)
        self.counters: dict[str, Any] = {
            "messages_by_type": {}, "corrupt_frames": 0, "samples": 0, "rejected": self.converter.rejected,
            "send_errors": 0, "reconnects": 0, "link_losses": 0, "odometry_sent": 0, "nav_silenced": 0, "nav_no_link": 0,
            "callback_errors": 0, "interval_requests": 0, "origin_sent": 0, "command_acks": 0,
            "packets_lost": 0,
        }
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
    def send_nav(self, nav_state: Any, omega_b_rad_s: Any = None) -> bool:
        """Send ODOMETRY for ``nav_state``; False when silenced, no link or a send error."""
        fields = odometry_fields(nav_state, self.config.output, omega_b_rad_s)
        if fields is None:
            self.counters["nav_silenced"] += 1
            return False
        if not self.link_up.is_set():
            self.counters["nav_no_link"] += 1
            return False
        ok = self._send("odometry_send", **fields) and self._count("odometry_sent")
        if self.config.output.vision_position_delta:
            delta = None if self._prev_nav is None else vision_position_delta_fields(self._prev_nav, nav_state)
            if delta is not None and self._send("vision_position_delta_send", **delta):
                self._count("vision_delta_sent")
            self._prev_nav = nav_state
        return ok

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

    def _on_autopilot_up(self, sysid: int, compid: int) -> None:
        self.autopilot = (sysid, compid)
        r = self.config.rates
        log.info("MAVLink link up: autopilot system %d component %d on %s; requesting %s at %g Hz",
                 sysid, compid, self.url, self.config.request_imu_message, r.imu_hz,
                 extra={"event": {"event": "link_up", "peer": f"{sysid}/{compid}", "url": self.url}})
        for msg_id, interval_us in message_intervals(self.config).items():
            if self._send("command_long_send", target_system=sysid, target_component=compid,
                          command=mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, confirmation=0,
                          param1=float(msg_id), param2=float(interval_us), param3=0.0, param4=0.0,
                          param5=0.0, param6=0.0, param7=0.0):
                self.counters["interval_requests"] += 1
        if self.origin is not None and self._send(
                "set_gps_global_origin_send", **gps_global_origin_fields(self.origin, sysid)):
            self.counters["origin_sent"] += 1
        self.link_up.set()

    def _handle(self, msg: Any) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.counters["corrupt_frames"] += 1
            return
        by_type = self.counters["messages_by_type"]
        by_type[mtype] = by_type.get(mtype, 0) + 1
        if mtype == "HEARTBEAT" and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
            self._last_rx = time.monotonic()
            if self.autopilot is None:
                self._on_autopilot_up(msg.get_srcSystem(), msg.get_srcComponent())
        elif mtype == "COMMAND_ACK":
            self.counters["command_acks"] += 1
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
