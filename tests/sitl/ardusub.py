"""A real ArduSub (software in the loop, ``../shared/sitl/ardusub``) on loopback, and a
ground station that drives it.

:class:`ArduSub` starts the autopilot in its own working directory (it keeps its
parameters in ``eeprom.bin`` there), SERIAL0 sending to the ground station's UDP port and
SERIAL1 to the bridge's; ``restart()`` is the reboot some parameters need.  :class:`Gcs` is
a ground station (system 255, component 190, the id ArduSub takes MANUAL_CONTROL from): it
sets and reads back parameters, requests streams, arms, changes mode, sends the pilot's
sticks, and records what it receives (every message of the types asked for, with the
reception wall time) — optionally into a ``.tlog`` file.
"""
from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
SITL_DIR = REPO.parent / "shared" / "sitl"
BINARY = SITL_DIR / "ardusub"
DEFAULTS = SITL_DIR / "sub.parm"
HOME = (-35.363262, 149.165237)  # the README's home (lat, lon in degrees)

MODE_STABILIZE, MODE_ALT_HOLD, MODE_MANUAL = 0, 2, 19


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_instance() -> tuple[int, Any]:
    """An instance number whose RC-input port (UDP 5501 + 10·N) and serial ports (TCP 5760 +
    10·N, bound on all interfaces) are free, and the lock that reserves it: two harnesses
    started in the same second probed the same free ports and started the same instance (the
    second autopilot could not bind them). The lock (``flock`` on a file per instance in the
    temporary directory) is held until the caller closes it."""
    import fcntl
    import tempfile

    for n in range(1, 60):
        lock = open(Path(tempfile.gettempdir()) / f"adaptnav-sitl-instance-{n}.lock", "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.bind(("0.0.0.0", 5501 + 10 * n))
            with socket.socket() as s:
                s.bind(("0.0.0.0", 5760 + 10 * n))
            return n, lock
        except OSError:
            lock.close()
            continue
    raise RuntimeError("no free SITL instance")


class ArduSub:
    """The autopilot process (stopped by its PID)."""

    def __init__(self, workdir: Path, gcs_port: int, bridge_port: int, home=HOME, model: str = "vectored"):
        self.workdir = Path(workdir)
        self.model = model  # SITL's vehicle: "vectored" (BlueROV2), "vectored_6dof" (BlueROV2 Heavy)
        self.gcs_port, self.bridge_port, self.home = gcs_port, bridge_port, home
        self.instance, self._instance_lock = free_instance()  # held while this object lives
        self.proc: subprocess.Popen | None = None

    def start(self) -> "ArduSub":
        lat, lon = self.home
        cmd = [str(BINARY), "--model", self.model, "--speedup", "1", "--defaults", str(DEFAULTS),
               f"-I{self.instance}", "--home", f"{lat},{lon},0,0",
               "--serial0", f"udpclient:127.0.0.1:{self.gcs_port}",
               "--serial1", f"udpclient:127.0.0.1:{self.bridge_port}"]
        self.log = open(self.workdir / "ardusub.out", "ab")
        self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdout=self.log, stderr=subprocess.STDOUT)
        return self

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self.proc = None
        if getattr(self, "log", None):
            self.log.close()

    def restart(self) -> None:
        self.stop()
        self.start()


class Gcs:
    """A ground station on ``udpin:127.0.0.1:port`` with a receiving thread.

    ``messages[type]`` holds ``(wall_s, msg)`` for every type in ``keep``; ``tlog`` (a path)
    records those types as a telemetry log (8-byte big-endian µs + frame).
    """

    def __init__(self, port: int, keep: tuple[str, ...], tlog: Path | None = None):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="ardupilotmega")
        self.keep = set(keep) | {"HEARTBEAT", "STATUSTEXT", "PARAM_VALUE", "COMMAND_ACK"}
        self.messages: dict[str, list[tuple[float, Any]]] = defaultdict(list)
        self.statustext: list[tuple[float, str]] = []
        self._tlog = open(tlog, "wb") if tlog else None
        self.target = (1, 1)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.stick: dict | None = None  # sticks the pilot holds, sent at 10 Hz by the thread
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_hb = next_stick = 0.0
        while not self._stop.is_set():
            now = time.time()
            if now >= next_hb:
                with self._lock:
                    self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                next_hb = now + 1.0
            if self.stick is not None and now >= next_stick:
                self.sticks(**self.stick)
                next_stick = now + 0.1
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is None:
                continue
            mtype = msg.get_type()
            if mtype not in self.keep or msg.get_srcSystem() != 1:
                continue
            wall = time.time()
            self.messages[mtype].append((wall, msg))
            if mtype == "STATUSTEXT":
                self.statustext.append((wall, msg.text))
            if self._tlog is not None and mtype not in ("PARAM_VALUE", "COMMAND_ACK"):
                self._tlog.write(struct.pack(">Q", int(wall * 1e6)) + bytes(msg.get_msgbuf()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if self._tlog is not None:
            self._tlog.close()
        self.conn.close()

    # -- waiting
    def wait(self, pred: Callable[[], bool], timeout_s: float, what: str) -> None:
        t_end = time.time() + timeout_s
        while time.time() < t_end:
            if pred():
                return
            time.sleep(0.05)
        raise TimeoutError(f"waited {timeout_s:.0f} s for {what}; STATUSTEXT: {self.statustext[-8:]}")

    def wait_text(self, needle: str, timeout_s: float, since_wall: float = 0.0) -> float:
        """Wall time of the first STATUSTEXT containing ``needle`` after ``since_wall``."""
        found: list[float] = []

        def pred():
            found[:] = [w for w, t in list(self.statustext) if w >= since_wall and needle in t]
            return bool(found)

        self.wait(pred, timeout_s, f"STATUSTEXT '{needle}'")
        return found[0]

    def ext_nav_in_use(self, at_wall: float) -> bool:
        """Whether ArduSub was using external navigation at ``at_wall``: its last STATUSTEXT
        on the matter before then ("is using external nav data" / "stopped aiding")."""
        state = False
        for w, text in list(self.statustext):
            if w > at_wall:
                break
            if "using external nav" in text:
                state = True
            elif "stopped aiding" in text:
                state = False
        return state

    def count(self, mtype: str) -> int:
        return len(self.messages[mtype])

    # -- commands
    def command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        with self._lock:
            self.conn.mav.command_long_send(*self.target, command, 0, *p)

    def set_param(self, name: str, value: float, timeout_s: float = 10.0) -> None:
        """PARAM_SET, confirmed by the PARAM_VALUE it answers with."""
        t0 = time.time()
        with self._lock:
            self.conn.mav.param_set_send(*self.target, name.encode(), float(value), mav.MAV_PARAM_TYPE_REAL32)

        def confirmed():
            return any(w >= t0 and m.param_id == name and abs(m.param_value - value) < 1e-4
                       for w, m in list(self.messages["PARAM_VALUE"]))

        self.wait(confirmed, timeout_s, f"PARAM_VALUE {name}={value}")

    def interval(self, mtype: str, hz: float) -> None:
        self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, getattr(mav, f"MAVLINK_MSG_ID_{mtype}"), 1e6 / hz)

    def arm(self) -> None:
        self.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196)  # 21196: force (SITL, no checks)

    def mode(self, custom_mode: int) -> None:
        with self._lock:
            self.conn.mav.set_mode_send(self.target[0], mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode)

    def sticks(self, x: int = 0, y: int = 0, z: int = 500, r: int = 0) -> None:
        with self._lock:
            self.conn.mav.manual_control_send(self.target[0], x, y, z, r, 0)

    def hold_sticks(self, seconds: float, **sticks) -> None:
        """The pilot holds the sticks for ``seconds`` (then they stay there)."""
        self.stick = {"x": 0, "y": 0, "z": 500, "r": 0, **sticks}
        time.sleep(seconds)


class DvlDriver:
    """A DVL driver on the companion, as BlueOS's Water Linked extension: VISION_POSITION_DELTA
    at ``hz`` to the autopilot's second serial port (``udpin:127.0.0.1:port``), system 1,
    component 197, ``time_usec`` 0, ``position_delta`` = the body-frame velocity × the time
    since the previous report, ``confidence`` 100 %.

    The velocity is the simulator's truth (SIM_STATE, as the ground station ``gcs`` receives
    it: ``vn, ve, vd`` rotated into the body frame by ``q1..q4``) with white noise of
    ``noise_m_s`` per axis (``seed``) and a scale factor error ``scale_error`` (the datasheet's
    ±0.2–0.5 %): what a bottom-locked DVL reports. ArduSub needs ``VISO_TYPE`` 1 (MAVLink) to
    take it, and then logs every delta as a VISO record.
    """

    def __init__(self, port: int, gcs: Gcs, hz: float = 5.0, noise_m_s: float = 0.01, scale_error: float = 0.003,
                 seed: int = 0):
        import numpy as np

        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=197,
                                               dialect="ardupilotmega")
        self.gcs, self.period_s = gcs, 1.0 / hz
        self.noise_m_s, self.scale = noise_m_s, 1.0 + scale_error
        self.rng = np.random.default_rng(seed)
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _velocity_b(self) -> Any:
        import numpy as np

        states = self.gcs.messages["SIM_STATE"]
        if not states:
            return None
        m = states[-1][1]
        w, x, y, z = m.q1, m.q2, m.q3, m.q4
        r_nb = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return self.scale * (r_nb.T @ np.array([m.vn, m.ve, m.vd])) + self.noise_m_s * self.rng.standard_normal(3)

    def _run(self) -> None:
        last = None
        while not self._stop.is_set():
            self.conn.recv_match(blocking=True, timeout=self.period_s)  # the autopilot's heartbeats: its address
            now = time.monotonic()
            if last is not None and now - last < self.period_s:
                continue
            vel = self._velocity_b()
            if vel is None or not getattr(self.conn, "clients", None):  # nothing to send, or no autopilot yet
                last = now
                continue
            dt = self.period_s if last is None else now - last
            last = now
            try:
                self.conn.mav.vision_position_delta_send(0, int(dt * 1e6), [0.0, 0.0, 0.0],
                                                         [float(v) * dt for v in vel], 100.0)
                self.sent += 1
            except OSError:  # the autopilot is restarting: its port is gone for a moment
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


class UgpsDriver:
    """An underwater GPS on the companion, as BlueOS's Water Linked UGPS extension: GPS_INPUT at
    ``hz`` to the autopilot's second serial port, system 1, component 220, ``time_usec`` 0 and
    no GPS time, 3D fix, HDOP ``hdop``, velocities and accuracies flagged as absent (ArduSub
    needs ``GPS1_TYPE`` 14 — ``GPS_TYPE`` before 4.6 — to take it, and logs each as a GPS record).

    The position is the simulator's truth (SIM_STATE as the ground station ``gcs`` receives it)
    with white noise of ``sigma_m`` per horizontal axis (``seed``): an acoustic fix, at any
    depth. Shares :class:`DvlDriver`'s port when both run (``conn``)."""

    IGNORE = 4 | 8 | 16 | 32 | 64 | 128  # vel horiz/vert, speed, horizontal and vertical accuracy

    def __init__(self, port: int | None, gcs: Gcs, hz: float = 2.0, sigma_m: float = 1.0, hdop: float = 1.0,
                 seed: int = 1, conn: Any = None):
        import numpy as np

        self.conn = conn or mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1,
                                                       source_component=220, dialect="ardupilotmega")
        self.mav = mav.MAVLink(self.conn, srcSystem=1, srcComponent=220)
        self.gcs, self.period_s, self.sigma_m, self.hdop = gcs, 1.0 / hz, sigma_m, hdop
        self.rng = np.random.default_rng(seed)
        self.sent = 0
        self._own_conn = conn is None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import math

        while not self._stop.wait(self.period_s):
            if self._own_conn:
                while self.conn.recv_match(blocking=False) is not None:  # the autopilot's address
                    pass
            states = self.gcs.messages["SIM_STATE"]
            if not states or not getattr(self.conn, "clients", None):
                continue
            m = states[-1][1]
            d_n, d_e = self.sigma_m * self.rng.standard_normal(2)
            lat = m.lat_int * 1e-7 + math.degrees(d_n / 6_378_137.0)
            lon = m.lon_int * 1e-7 + math.degrees(d_e / (6_378_137.0 * math.cos(math.radians(m.lat_int * 1e-7))))
            try:
                self.mav.gps_input_send(0, 0, self.IGNORE, 0, 0, 3, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                        0.0, self.hdop, 1.0, 0, 0, 0, 0, 0, 0, 10, 0)
                self.sent += 1
            except OSError:
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if self._own_conn:
            self.conn.close()
