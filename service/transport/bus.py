"""Zenoh bus of the live service (zenoh-python 1.x).

Key expressions (``<v>`` = vehicle name, DESIGN.md "Service")::

    adaptnav/<v>/sensor/<kind>         samples (imu, dvl, depth, heading, gnss, usbl, rpm, ...)
    adaptnav/<v>/nav/state             NavState with covariance (10 Hz)
    adaptnav/<v>/nav/inertial          free-inertial velocity (10 Hz; for a remote calibrator)
    adaptnav/<v>/nav/aid/<source>      AidStatus per aiding source (1 Hz, latest)
    adaptnav/<v>/calibration/params    calibrator releases
    adaptnav/<v>/health                health report (1 Hz)
    adaptnav/<v>/query/{state,params,config,health}   queryables

Payloads are JSON objects carrying ``type`` and ``schema_version`` (samples through
:mod:`adaptnav.service.transport.codec`; the service's own messages likewise, registered there), so a
third-party subscriber (``zenoh-cli``, a Python one-liner) can read them.

Zenoh runs subscriber callbacks on its own threads and forbids blocking there: the
callbacks here only decode and enqueue; a malformed payload is counted, never raised.
"""
from __future__ import annotations

import json
import logging
import math
import os
import queue
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

import orjson
import zenoh

from adaptnav.fusion.samples import SampleError

from adaptnav.service.config import ZenohConfig
from adaptnav.service.transport import codec

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1

# Zenoh's thread pools (its ``ZENOH_RUNTIME`` environment variable, RON; read once, when the
# process opens its first session): one worker receiving on the links and one for all the
# rest (transmission, accepting, the network's upkeep, the application's tasks) instead of
# Zenoh's six (two receiving, one each for the others). Live at 200 Hz both receiving
# workers woke for the samples (~1.2 % of a core each, as long again waiting in the run
# queue: /proc/<tid>/schedstat), and each thread that wakes is a core a sample waits for on
# a small computer. The live daemon at 200 Hz with its calibrator,
# alternated four times in 60 s windows against Zenoh's default: 7.06 % of a core against
# 7.92 % (median; lower in all four pairs), the outside client's p50 0.85 ms against 0.97.
# A ZENOH_RUNTIME already in the environment wins.
ZENOH_RUNTIME = "(rx: (worker_threads: 1), acc: (handover: app), tx: (handover: app), net: (handover: app))"


class Keys:
    """Key expressions for one vehicle."""

    def __init__(self, vehicle: str) -> None:
        self.vehicle = vehicle
        self.root = f"adaptnav/{vehicle}"
        self.all = f"{self.root}/**"
        self.sensors = f"{self.root}/sensor/*"
        self.nav_state = f"{self.root}/nav/state"
        self.imu = self.sensor("imu")
        self.nav_inertial = f"{self.root}/nav/inertial"
        self.params = f"{self.root}/calibration/params"
        self.health = f"{self.root}/health"

    def sensor(self, kind: str) -> str:
        return f"{self.root}/sensor/{kind}"

    def aid(self, source: str) -> str:
        return f"{self.root}/nav/aid/{source}"

    def lossless(self, key: str) -> bool:
        """Whether a publisher on ``key`` waits when the link is congested rather than drop:
        a driver's sensor sample (a side-scan ping, a USBL fix is not sent twice) and a
        calibration release. Zenoh's default drops a publication whose queue is full, without a
        word to either side — on a loaded computer the demo's sonar driver lost 2 of 721 pings
        so. Nav states, aid status and health stay droppable: the next one replaces them, and
        the daemon publishing them must not wait for a slow subscriber."""
        return key.startswith(f"{self.root}/sensor/") or key == self.params

    def express(self, key: str) -> bool:
        """Whether a publisher on ``key`` sends each message at once, never held for a batch:
        the IMU samples, where the navigation's latency starts. Zenoh batches otherwise
        while the writer keeps writing, holding a message up to
        ``transport.link.tx.queue.batching.time_limit`` (1 ms): a driver that publishes a
        side-scan ping right after an IMU sample held the sample while it encoded the ping
        (the IMU's hop 1.3 → 1.0 ms at p50). Not the nav states: each express message takes
        a transmission-queue slot of its own, and a droppable one is then dropped when the
        link's thread is starved — the daemon of `tests/service/test_demo.py` lost up to 18
        of ~1780 states with two busy processes beside it, none batched."""
        return key == self.imu

    def query(self, name: str) -> str:
        return f"{self.root}/query/{name}"

    def schema_of(self, key: str) -> str:
        """The schema name of what is published on ``key`` (``adaptnav.<kind>``): the
        payload encoding says it, so generic tools know the JSON without being told."""
        rel = key[len(self.root) + 1:] if key.startswith(self.root + "/") else key
        parts = rel.split("/")
        if parts[0] == "sensor" and len(parts) == 2:
            return f"adaptnav.{parts[1]}"
        return "adaptnav." + {"nav/state": "nav_state", "nav/inertial": "inertial_velocity",
                              "calibration/params": "calibration_release", "health": "health"}.get(
            rel, "aid_status" if rel.startswith("nav/aid/") else
            (parts[1] if parts[0] == "query" and len(parts) == 2 else "message"))


def json_encoding(schema: str) -> zenoh.Encoding:
    """``application/json`` with the schema name (e.g. ``adaptnav.nav_state``)."""
    return zenoh.Encoding.APPLICATION_JSON.with_schema(schema)


def zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """Our :class:`ZenohConfig` → a ``zenoh.Config`` (JSON5 of the zenoh 1.x config schema:
    ``transport.link.tls``, ``transport.auth.usrpwd``, ``access_control``).

    Raises
    ------
    OSError
        ``zenoh.auth.password_file`` cannot be read.
    """
    doc: dict[str, Any] = {
        "mode": cfg.mode,
        "connect": {"endpoints": list(cfg.connect),
                    # a client waits (retrying) for its router/daemon instead of failing at once
                    "timeout_ms": {"client": -1 if cfg.connect_timeout_s < 0 else int(cfg.connect_timeout_s * 1000)},
                    "retry": {"period_init_ms": 200, "period_max_ms": 2000, "period_increase_factor": 2}},
        "listen": {"endpoints": list(cfg.listen)},
        # gossip too: with scouting off, peers must only talk to the endpoints given
        "scouting": {"multicast": {"enabled": bool(cfg.scouting)},
                     "gossip": {"enabled": bool(cfg.scouting)}},
    }
    # Zenoh's shared memory only where asked for (ZenohConfig.shared_memory: its pool costs the
    # vehicle computer tens of MB for messages that are small anyway)
    transport = {**(_security_transport(cfg) or {}), "shared_memory": {"enabled": bool(cfg.shared_memory)}}
    doc["transport"] = transport
    acl = cfg.access_control
    if acl.enabled:
        doc["access_control"] = {
            "enabled": True, "default_permission": acl.default_permission,
            "rules": [{"id": r.id, "messages": list(r.messages), "flows": list(r.flows),
                       "permission": r.permission, "key_exprs": list(r.key_exprs)} for r in acl.rules],
            # an empty property is "anyone" for us; Zenoh refuses an empty list: left out
            "subjects": [{"id": s.id, **{k: list(getattr(s, k)) for k in
                                         ("cert_common_names", "usernames", "interfaces", "link_protocols")
                                         if getattr(s, k)}} for s in acl.subjects],
            "policies": [{**({"id": p.id} if p.id else {}), "rules": list(p.rules), "subjects": list(p.subjects)}
                         for p in acl.policies],
        }
    return zenoh.Config.from_json5(json.dumps(doc))


def _security_transport(cfg: ZenohConfig) -> dict[str, Any]:
    """The ``transport`` part of the Zenoh config: TLS files and user/password (only what is set)."""
    from pathlib import Path

    tls = cfg.tls
    link = {k: getattr(tls, k) for k in ("root_ca_certificate", "listen_certificate", "listen_private_key",
                                         "connect_certificate", "connect_private_key") if getattr(tls, k)}
    if link or tls.enable_mtls or not tls.verify_name_on_connect or tls.close_link_on_expiration:
        link.update(enable_mtls=tls.enable_mtls, verify_name_on_connect=tls.verify_name_on_connect,
                    close_link_on_expiration=tls.close_link_on_expiration)
    out: dict[str, Any] = {"link": {"tls": link}} if link else {}
    auth = cfg.auth
    usrpwd: dict[str, Any] = {}
    if auth.user:  # the password is read here, never kept in the (logged, queryable) config
        usrpwd.update(user=auth.user, password=Path(auth.password_file).read_text().rstrip("\r\n"))
    if auth.dictionary_file:
        usrpwd["dictionary_file"] = auth.dictionary_file
    if usrpwd:
        out["auth"] = {"usrpwd": usrpwd}
    return out


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "to_dict"):
        return obj.to_dict()
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def _strict(obj: Any) -> Any:
    """Non-finite floats → None so the payload is strict JSON."""
    if isinstance(obj, dict):
        return {k: _strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):
        return _strict(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _fast_json(doc: dict[str, Any]) -> bytes:
    """Compact strict JSON: numpy arrays and scalars as numbers, non-finite floats as
    ``null`` (as :func:`_strict`), float text round-trips (shortest repr)."""
    return orjson.dumps(doc, default=_json_default, option=orjson.OPT_SERIALIZE_NUMPY)


def message(kind: str, body: dict[str, Any]) -> bytes:
    """A service message (nav_state, aid_status, motion_params, health, config) as JSON."""
    doc = {"type": kind, "schema_version": SCHEMA_VERSION, **body}
    try:  # fast path: a nav state (324 covariance floats) takes ~20 µs, json.dumps ~220 µs
        return _fast_json(doc)
    except (orjson.JSONEncodeError, TypeError):  # odd keys or values: the general way
        doc = {"type": kind, "schema_version": SCHEMA_VERSION, **_strict(body)}
        return json.dumps(doc, separators=(",", ":"), default=_json_default, allow_nan=False).encode()


# The service's own message kinds, registered with the codec (schemas for MCAP channels
# and third-party readers). Decoding gives the JSON dict back: these are read by tools,
# not turned into objects by the service. (A calibrator release has its own type and
# codec: adaptnav.service.transport.release.)
SERVICE_KINDS: dict[str, tuple[str, str]] = {
    # kind: (MCAP topic, description)
    "nav_state": ("/adaptnav/nav/state", "navigation state with 18x18 error covariance"),
    "aid_status": ("/adaptnav/nav/aid", "one fusion attempt of an aiding source"),
    "motion_params": ("/adaptnav/motion_params", "motion parameters in use"),
    "health": ("/adaptnav/health", "health report"),
    "service_config": ("/adaptnav/config", "effective service configuration"),
}


def _num(description: str) -> dict:
    return {"type": ["number", "null"], "description": description}


def _vec(n: int | None, description: str) -> dict:
    out: dict = {"type": "array", "items": {"type": ["number", "null"]}, "description": description}
    if n is not None:
        out["minItems"] = out["maxItems"] = n
    return out


# the fields of the nav state (fusion.state.NavState.to_dict, plus what the daemon adds),
# so that a reader of a log or of the bus knows them without the source
NAV_STATE_FIELDS = {
    "t_s": _num("data time of validity, s"),
    "pos_n_m": _vec(3, "position north, east, down of the mission origin, m"),
    "vel_n_m_s": _vec(3, "velocity north, east, down, m/s"),
    "q_nb": _vec(4, "attitude body (FRD) to NED, quaternion w, x, y, z"),
    "euler_rad": _vec(3, "roll, pitch, yaw (ZYX), rad"),
    "bias_acc_b_m_s2": _vec(3, "accelerometer bias, body, m/s²"),
    "bias_gyro_b_rad_s": _vec(3, "gyro bias, body, rad/s"),
    "current_n_m_s": _vec(None, "sea current north, east, m/s"),
    "k_speed": _num("speed-scale state of the learned velocity, –"),
    "cov": _vec(18 * 18, "error-state covariance 18×18, row-major (fusion/state.py order: pos, vel, att, "
                         "bias_acc, bias_gyro, current, k_speed)"),
    "valid": {"type": "boolean", "description": "usable for navigation"},
    "reset_counter": {"type": "integer", "description": "steps on every discontinuity"},
    "lat_deg": _num("latitude, deg (WGS-84, from the mission origin)"),
    "lon_deg": _num("longitude, deg"),
    "alt_m": _num("altitude, m (negative below the surface)"),
}


def _schema(kind: str, description: str) -> dict:
    props: dict = {"type": {"const": kind}, "schema_version": {"const": SCHEMA_VERSION}}
    if kind == "nav_state":
        props.update(NAV_STATE_FIELDS)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"adaptnav.{kind}",
        "description": description,
        "type": "object",
        "properties": props,
        "required": ["type", "schema_version"],
    }


@dataclass(frozen=True)
class BusMessage:
    """A service message as read back from the bus or a log: its kind, data time, JSON body.

    It has ``KIND`` and ``t_s`` like a sample, so the codec and MCAP logs handle it;
    the estimator ignores it.
    """

    KIND: str
    t_s: float
    body: dict


def _decode_as(kind: str) -> Callable[[dict], BusMessage]:
    def decode(data: dict) -> BusMessage:
        if data.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"{kind}: schema_version {data.get('schema_version')!r} not supported")
        t_s = data.get("t_s")
        return BusMessage(kind, float(t_s) if isinstance(t_s, (int, float)) else math.nan, data)
    return decode


def _register_service_kinds() -> None:
    for kind, (topic, description) in SERVICE_KINDS.items():
        codec.register(kind, lambda m: m.body, _decode_as(kind), _schema(kind, description), topic)


_register_service_kinds()


def encode_sample(sample: Any) -> bytes:
    return codec.encode(sample)


def decode_sample(payload: bytes) -> Any:
    """Bytes → sample; :class:`SampleError` on anything malformed."""
    try:
        return codec.decode(payload)
    except SampleError:
        raise
    except (ValueError, TypeError, KeyError, UnicodeDecodeError) as e:
        raise SampleError(f"malformed payload: {e}") from e


class Bus:
    """One Zenoh session with the adaptnav key space of one vehicle.

    Parameters
    ----------
    cfg : ZenohConfig
        Mode, endpoints, scouting.
    vehicle : str
        Vehicle name for the key expressions.
    """

    def __init__(self, cfg: ZenohConfig, vehicle: str) -> None:
        self.keys = Keys(vehicle)
        os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)  # before the process's first session
        self.session = zenoh.open(zenoh_config(cfg))
        self.malformed: Counter[str] = Counter()  # by key expression suffix
        self._lock = threading.Lock()
        self._publishers: dict[str, Any] = {}
        self._declared: list[Any] = []

    # -- publishing ------------------------------------------------------------------
    def _publisher(self, key: str):
        pub = self._publishers.get(key)
        if pub is None:
            with self._lock:
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self._publishers[key] = self.session.declare_publisher(key, **self._qos(key))
        return pub

    def _qos(self, key: str, waits: bool | None = None) -> dict[str, Any]:
        """How every publisher on ``key`` is declared: its schema, whether it waits or drops
        when congested (``waits``, by default :meth:`Keys.lossless`), and whether it is sent
        at once (:meth:`Keys.express`) — only where it waits: a droppable message sent on its
        own is what a starved link drops (:meth:`Keys.express`)."""
        keys = self.keys
        waits = keys.lossless(key) if waits is None else waits
        return {"encoding": json_encoding(keys.schema_of(key)), "express": waits and keys.express(key),
                "congestion_control": zenoh.CongestionControl.BLOCK if waits else zenoh.CongestionControl.DROP}

    def put(self, key: str, payload: bytes) -> None:
        self._publisher(key).put(payload)

    def publish_sample_to_others(self, sample: Any) -> bool:
        """Publish a sample that did not come over the bus (e.g. from MAVLink) for the other
        nodes only — recorders, a remote calibrator — never back to this session's own
        subscribers (it would be fused twice). False, with nothing encoded, while no other
        node subscribes to its key: encoding every autopilot sample for nobody was a third of
        the daemon's work on an ArduSub vehicle. Whether one does is Zenoh's matching status,
        kept by a listener (a call into Zenoh per sample would wait for the GIL)."""
        key = self.keys.sensor(sample.KIND)
        entry = self._publishers.get(("remote", key))
        if entry is None:
            with self._lock:
                entry = self._publishers.get(("remote", key))
                if entry is None:
                    # dropping when congested: the daemon that forwards must never wait for a
                    # slow recorder
                    entry = self._publishers[("remote", key)] = _RemotePublisher(
                        self.session, key, self._qos(key, waits=False))
        if not entry.matching:
            return False
        entry.publisher.put(encode_sample(sample))
        return True

    def publish_sample(self, sample: Any) -> None:
        self.put(self.keys.sensor(sample.KIND), encode_sample(sample))

    def publish(self, key: str, kind: str, body: dict[str, Any]) -> None:
        self.put(key, message(kind, body))

    # -- subscribing -----------------------------------------------------------------
    def subscribe_samples(self, enqueue: Callable[[Any], None], key: str | None = None,
                          kinds: frozenset[str] | set[str] | None = None) -> None:
        """Decode samples on ``key`` (default: all sensor topics) and ``enqueue`` them.

        ``enqueue`` must not block (e.g. ``queue.put_nowait`` wrapped to count overflow).
        Malformed payloads are counted in :attr:`malformed` and logged at debug level, and
        so is a message of another kind than its key says: on ``sensor/<kind>`` only
        samples of that kind, on ``key`` only ``kinds`` (when given) — a nav state or a
        release published on a sensor key must neither be fused, nor applied, nor become a
        "sensor" in health.
        """
        sensor_prefix = f"{self.keys.root}/sensor/"

        def on_sample(zsample: Any) -> None:
            topic = str(zsample.key_expr)
            suffix = topic.rsplit("/", 1)[-1]
            try:
                item = decode_sample(zsample.payload.to_bytes())
            except SampleError as e:
                self.malformed[suffix] += 1
                log.debug("malformed payload on %s: %s", topic, e)
                return
            kind = getattr(item, "KIND", None)
            if (kind != suffix if topic.startswith(sensor_prefix) else kinds is not None and kind not in kinds):
                self.malformed[f"{suffix}:{kind}"] += 1  # e.g. "imu:nav_state"
                log.debug("a %s message on %s: not taken", kind, topic)
                return
            enqueue(item)

        self._declared.append(self.session.declare_subscriber(key or self.keys.sensors, on_sample))

    def subscribe_raw(self, key: str, handler: Callable[[str, bytes], None]) -> None:
        """``handler(key, payload_bytes)`` for every message on ``key`` (must not block)."""
        self._declared.append(self.session.declare_subscriber(
            key, lambda s: handler(str(s.key_expr), s.payload.to_bytes())))

    def queryable(self, name: str, answer: Callable[[], bytes]) -> None:
        """Answer ``adaptnav/<v>/query/<name>`` with ``answer()`` (fast, non-blocking)."""
        key = self.keys.query(name)
        encoding = json_encoding(self.keys.schema_of(key))

        def on_query(query: Any) -> None:
            try:
                query.reply(key, answer(), encoding=encoding)
            except Exception as e:  # a queryable must never take the session down
                log.warning("query %s failed: %s", key, e)
                query.reply_err(str(e).encode())

        self._declared.append(self.session.declare_queryable(key, on_query))

    def get(self, name: str, timeout_s: float = 2.0) -> dict | None:
        """Ask a queryable of this vehicle; the first reply's JSON, or ``None``."""
        for reply in self.session.get(self.keys.query(name), timeout=timeout_s):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None

    # -- synchronisation -------------------------------------------------------------
    def wait_subscribed(self, key: str, timeout_s: float = 30.0) -> bool:
        """Block until a subscriber somewhere matches ``key`` (Zenoh matching status of
        this session's publisher on it); False after ``timeout_s``.

        What a program (or a test) waits on before publishing data that must not be
        lost to a subscription still propagating — instead of sleeping for a guess.
        """
        return _wait_matching(self._publisher(key), timeout_s)

    def wait_queryable(self, name: str, timeout_s: float = 30.0) -> bool:
        """Block until a queryable ``adaptnav/<v>/query/<name>`` is reachable; False after
        ``timeout_s``."""
        querier = self.session.declare_querier(self.keys.query(name))
        try:
            return _wait_matching(querier, timeout_s)
        finally:
            querier.undeclare()

    def close(self) -> None:
        for obj in self._declared:
            try:
                obj.undeclare()
            except Exception:  # already gone with a closing session
                pass
        self._declared.clear()
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except Exception:
                pass
        self._publishers.clear()
        self.session.close()


class _RemotePublisher:
    """A publisher to the other nodes only, and whether any of them subscribes (``matching``,
    kept current by a Zenoh matching listener)."""

    def __init__(self, session: Any, key: str, qos: dict[str, Any]) -> None:
        self.publisher = session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE, **qos)
        self.matching = False
        self.listener = self.publisher.declare_matching_listener(self._changed)
        self.matching = self.publisher.matching_status.matching

    def _changed(self, status: Any) -> None:
        self.matching = status.matching

    def undeclare(self) -> None:
        self.listener.undeclare()
        self.publisher.undeclare()


def _wait_matching(entity: Any, timeout_s: float) -> bool:
    """Poll a Zenoh publisher's or querier's ``matching_status`` until it matches."""
    import time

    deadline = time.monotonic() + timeout_s
    while not entity.matching_status.matching:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.005)
    return True


def nonblocking_enqueue(q: "queue.Queue[Any]", overflow: Counter, reason: str = "queue_overflow") -> Callable[[Any], None]:
    """An ``enqueue`` for :meth:`Bus.subscribe_samples` that drops (and counts) on a full queue."""

    def enqueue(item: Any) -> None:
        try:
            q.put_nowait(item)
        except queue.Full:
            overflow[reason] += 1

    return enqueue
