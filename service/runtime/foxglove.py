"""The navigation solution where robotics engineers look: Foxglove, live and in MCAP.

Conversion of the runner's outputs to Foxglove's *well-known schemas* (``foxglove-sdk``,
protobuf encoded) so that Foxglove opens them on its Map and 3D panels without any
configuration, plus a few JSON channels for plots and tables:

====================== ======================== ===========================================
topic                  schema                   content
====================== ======================== ===========================================
``/nav/location``      ``foxglove.LocationFix`` lat/lon (deg), altitude = −down, ENU
                                                position covariance (m²)
``/nav/pose``          ``foxglove.PoseInFrame`` pose of the body (FRD) in the ``ned`` frame
``/nav/odometry``      ``foxglove.Odometry``    the same with its 6×6 covariance
                                                (position, attitude error in ``ned``)
``/nav/uncertainty``   ``foxglove.SceneUpdate`` the 3σ position ellipsoid (3D panel)
``/tf``                ``foxglove.FrameTransforms`` ``world`` (ENU, z up) → ``ned`` →
                                                ``base_link`` (FRD); truth: → ``truth``
``/truth/location``    ``foxglove.LocationFix`` simulator ground truth (when present)
``/truth/pose``        ``foxglove.PoseInFrame`` idem
``/nav/state``         JSON ``adaptnav.nav_plot`` NED position, σ (m), error vs truth (m),
                                                k_speed, current — for Plot panels
``/nav/aid``           JSON ``adaptnav.aid_table`` latest status of every aid source and
                                                fused/rejected counts — for a Table panel
``/calibration/release`` JSON                   every calibrator release (accepted or not)
``/health``            JSON                     the daemon's health report (live)
``/log``               ``foxglove.Log``         lifecycle events (releases with their reason)
====================== ======================== ===========================================

One conversion (:class:`FoxgloveSink`, a runner sink) feeds either a live WebSocket server
(:func:`start_live`, the daemon's ``[foxglove]`` section) or an MCAP file
(:func:`open_mcap_sink`, ``adaptnav replay --mcap``); :func:`encoded_messages` gives the
same messages as (topic, schema, bytes) for writers that are not the SDK's
(``adaptnav record``).

Time: ``timestamp`` fields and MCAP log times are on a real clock (UNIX ns) through a
:class:`TimeBase`: live, the wall clock; in replay, the data time shifted to the mission's
real start (a simulated mission's ``start_utc``, a tlog's recording clock, else the time
of the run), so Foxglove's timeline shows the mission's date, not 1970.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import numpy as np

from adaptnav.service.runtime.sinks import Sink

WORLD_FRAME = "world"      # ENU, z up: what Foxglove's 3D view takes as "up"
NED_FRAME = "ned"          # the filter's local NED frame at the mission origin
BODY_FRAME = "base_link"   # body FRD
TRUTH_FRAME = "truth"      # the simulator's body frame

# world (ENU) ← ned: (n, e, d) ↦ (e, n, −d), a 180° turn about (1, 1, 0)/√2
_Q_WORLD_NED_XYZW = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)
_NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

NAV_PLOT_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "adaptnav.nav_plot",
    "description": "navigation solution for plots: local NED (m), 1-σ (m), error vs truth (m)",
    "type": "object",
    "properties": {
        "t_s": {"type": "number", "description": "data time, s"},
        "north_m": {"type": "number"}, "east_m": {"type": "number"}, "down_m": {"type": "number"},
        "lat_deg": {"type": "number"}, "lon_deg": {"type": "number"},
        "sigma_north_m": {"type": "number"}, "sigma_east_m": {"type": "number"},
        "sigma_down_m": {"type": "number"}, "sigma_horizontal_m": {"type": "number"},
        "three_sigma_horizontal_m": {"type": "number"},
        "speed_m_s": {"type": "number"}, "k_speed": {"type": "number"},
        "current_n_m_s": {"type": "number"}, "current_e_m_s": {"type": "number"},
        "horizontal_error_m": {"type": ["number", "null"], "description": "vs truth, when present"},
        "valid": {"type": "boolean"},
    },
}
AID_TABLE_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "adaptnav.aid_table",
    "description": "latest status of every aiding source, with fused/rejected counts",
    "type": "object",
    "properties": {"t_s": {"type": "number"}, "sources": {"type": "array", "items": {"type": "object"}}},
}
RELEASE_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "adaptnav.calibration_release",
    "description": "a calibrator release: parameters, accepted or not and why",
    "type": "object",
}
HEALTH_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "adaptnav.health",
    "description": "the daemon's health report",
    "type": "object",
}
JSON_SCHEMAS = {"/nav/state": NAV_PLOT_SCHEMA, "/nav/aid": AID_TABLE_SCHEMA,
                "/calibration/release": RELEASE_SCHEMA, "/health": HEALTH_SCHEMA}


@dataclass
class TimeBase:
    """Data time (s) → UNIX time (ns) for ``timestamp`` fields and log times.

    ``unix_at_data_s`` is the UNIX time (s) of data time ``data_s``; ``data_s = None``
    anchors it at the first data time seen. ``live=True``: the wall clock at each call.
    """

    unix_s: float = 0.0
    data_s: float | None = 0.0
    live: bool = False

    @classmethod
    def wall(cls) -> "TimeBase":
        return cls(live=True)

    def ns(self, t_s: float) -> int:
        if self.live:
            return time.time_ns()
        if self.data_s is None and math.isfinite(t_s):
            self.data_s = float(t_s)
        ref = self.data_s if self.data_s is not None else 0.0
        dt = t_s - ref if math.isfinite(t_s) else 0.0
        return max(0, int(round((self.unix_s + dt) * 1e9)))


def _timestamp(ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _quat_xyzw(q_wxyz: Any) -> Any:
    from foxglove.messages import Quaternion

    w, x, y, z = (float(v) for v in q_wxyz)
    return Quaternion(x=x, y=y, z=z, w=w)


def _vec3(v: Any) -> Any:
    from foxglove.messages import Vector3

    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose(pos: Any, q_wxyz: Any) -> Any:
    from foxglove.messages import Pose

    return Pose(position=_vec3(pos), orientation=_quat_xyzw(q_wxyz))


def _finite(x: Any, default: float = 0.0) -> float:
    x = float(x)
    return x if math.isfinite(x) else default


def _pos_cov(state: Any) -> np.ndarray:
    """3×3 NED position covariance (m²) of a NavState (its error-state covariance)."""
    from adaptnav.fusion.state import POS

    cov = np.asarray(state.cov, dtype=float)
    return cov[POS, POS]


def location_fix(pos_n_m: Any, origin: Any, ns: int, cov_ned: np.ndarray | None = None,
                 heading_rad: float | None = None, frame_id: str = BODY_FRAME) -> Any:
    """A ``foxglove.LocationFix`` of a NED position (``origin``: :class:`GeoOrigin`)."""
    from foxglove.messages import LocationFix, LocationFixPositionCovarianceType

    lat, lon, alt = origin.to_geodetic(np.asarray(pos_n_m, dtype=float))
    kwargs: dict[str, Any] = {}
    if cov_ned is not None and np.isfinite(cov_ned).all():
        cov_enu = _NED_TO_ENU @ cov_ned @ _NED_TO_ENU.T
        kwargs.update(position_covariance=[float(v) for v in cov_enu.ravel()],
                      position_covariance_type=LocationFixPositionCovarianceType.Known)
    if heading_rad is not None and math.isfinite(heading_rad):
        kwargs["heading"] = float(heading_rad) % (2.0 * math.pi)
    return LocationFix(timestamp=_timestamp(ns), frame_id=frame_id, latitude=math.degrees(float(lat)),
                       longitude=math.degrees(float(lon)), altitude=float(alt), **kwargs)


def _yaw(q_wxyz: Any) -> float:
    w, x, y, z = (float(v) for v in q_wxyz)
    return math.atan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z))


def _ellipsoid(state: Any, ns: int, n_sigma: float = 3.0) -> Any:
    """The ``n_sigma`` position ellipsoid as a ``foxglove.SceneUpdate`` in the ``ned`` frame."""
    from foxglove.messages import Color, SceneEntity, SceneUpdate, SpherePrimitive, Vector3
    from scipy.spatial.transform import Rotation

    cov = _pos_cov(state)
    if not np.isfinite(cov).all():
        cov = np.eye(3)
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    x, y, z, w = Rotation.from_matrix(vecs).as_quat()
    size = 2.0 * n_sigma * np.sqrt(np.clip(vals, 0.0, None))

    sphere = SpherePrimitive(pose=_pose(state.pos_n_m, (w, x, y, z)),
                             size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                             color=Color(r=0.2, g=0.6, b=1.0, a=0.35))
    return SceneUpdate(entities=[SceneEntity(timestamp=_timestamp(ns), frame_id=NED_FRAME,
                                             id="position_3sigma", spheres=[sphere])])


class FoxgloveConverter:
    """Runner outputs → (topic, message) pairs in Foxglove's schemas (no I/O here).

    ``message`` is a ``foxglove.messages`` object (protobuf, well-known schema) or a dict
    (JSON, schema in :data:`JSON_SCHEMAS`). Keeps the latest state (for the error against
    truth) and per-source aid counters (for the aid table).
    """

    def __init__(self, origin: Any, time_base: TimeBase, aid_period_s: float = 1.0) -> None:
        self.origin = origin
        self.time = time_base
        self.aid_period_s = aid_period_s
        self._last_state: Any = None
        self._aid_latest: dict[str, dict] = {}
        self._aid_counts: dict[str, list[int]] = {}
        self._next_aid_t = -math.inf

    # -- nav --------------------------------------------------------------------------
    def nav(self, state: Any) -> list[tuple[str, Any]]:
        from adaptnav.fusion.state import ATT, POS
        from foxglove.messages import FrameTransform, FrameTransforms, Odometry, PoseInFrame, Vector3

        self._last_state = state
        ns = self.time.ns(float(state.t_s))
        stamp = _timestamp(ns)
        cov = np.asarray(state.cov, dtype=float)
        pos_cov = cov[POS, POS]
        pose = _pose(state.pos_n_m, state.q_nb)
        ix = np.r_[np.arange(18)[POS], np.arange(18)[ATT]]
        pose_cov6 = np.nan_to_num(cov[np.ix_(ix, ix)])
        out: list[tuple[str, Any]] = [
            ("/nav/location", location_fix(state.pos_n_m, self.origin, ns, pos_cov, _yaw(state.q_nb))),
            ("/nav/pose", PoseInFrame(timestamp=stamp, frame_id=NED_FRAME, pose=pose)),
            ("/nav/odometry", Odometry(timestamp=stamp, frame_id=NED_FRAME, body_frame_id=BODY_FRAME, pose=pose,
                                       pose_covariance=[float(v) for v in pose_cov6.ravel()])),
            ("/nav/uncertainty", _ellipsoid(state, ns)),
            ("/tf", FrameTransforms(transforms=[
                FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=NED_FRAME,
                               translation=Vector3(x=0.0, y=0.0, z=0.0),
                               rotation=_quat_xyzw((_Q_WORLD_NED_XYZW[3], *_Q_WORLD_NED_XYZW[:3]))),
                FrameTransform(timestamp=stamp, parent_frame_id=NED_FRAME, child_frame_id=BODY_FRAME,
                               translation=_vec3(state.pos_n_m), rotation=_quat_xyzw(state.q_nb))])),
            ("/nav/state", self._plot_doc(state, pos_cov, None)),
        ]
        return out

    def _plot_doc(self, state: Any, pos_cov: np.ndarray, error_m: float | None) -> dict:
        p = np.asarray(state.pos_n_m, dtype=float)
        v = np.asarray(state.vel_n_m_s, dtype=float)
        lat, lon, _ = self.origin.to_geodetic(p)
        sig = np.sqrt(np.clip(np.diag(pos_cov), 0.0, None))
        sig_h = math.sqrt(max(float(pos_cov[0, 0] + pos_cov[1, 1]), 0.0))
        cur = np.asarray(state.current_n_m_s, dtype=float).ravel()
        return {"t_s": _finite(state.t_s), "north_m": _finite(p[0]), "east_m": _finite(p[1]),
                "down_m": _finite(p[2]), "lat_deg": _finite(math.degrees(float(lat))),
                "lon_deg": _finite(math.degrees(float(lon))),
                "sigma_north_m": _finite(sig[0]), "sigma_east_m": _finite(sig[1]), "sigma_down_m": _finite(sig[2]),
                "sigma_horizontal_m": _finite(sig_h), "three_sigma_horizontal_m": _finite(3.0 * sig_h),
                "speed_m_s": _finite(math.hypot(v[0], v[1])), "k_speed": _finite(state.k_speed),
                "current_n_m_s": _finite(cur[0]), "current_e_m_s": _finite(cur[1]),
                "horizontal_error_m": error_m, "valid": bool(state.valid)}

    # -- truth ------------------------------------------------------------------------
    def truth(self, sample: Any, max_age_s: float = 0.05) -> list[tuple[str, Any]]:
        """Truth location/pose, and ``/nav/error`` against the state of the same epoch."""
        from foxglove.messages import FrameTransform, FrameTransforms, PoseInFrame

        ns = self.time.ns(float(sample.t_s))
        stamp = _timestamp(ns)
        pose = _pose(sample.pos_n_m, sample.q_nb)
        out: list[tuple[str, Any]] = [
            ("/truth/location", location_fix(sample.pos_n_m, self.origin, ns, None, _yaw(sample.q_nb),
                                             frame_id=TRUTH_FRAME)),
            ("/truth/pose", PoseInFrame(timestamp=stamp, frame_id=NED_FRAME, pose=pose)),
            ("/tf", FrameTransforms(transforms=[FrameTransform(
                timestamp=stamp, parent_frame_id=NED_FRAME, child_frame_id=TRUTH_FRAME,
                translation=_vec3(sample.pos_n_m), rotation=_quat_xyzw(sample.q_nb))])),
        ]
        st = self._last_state
        if st is not None and abs(float(st.t_s) - float(sample.t_s)) <= max_age_s:
            d = np.asarray(st.pos_n_m, dtype=float) - np.asarray(sample.pos_n_m, dtype=float)
            doc = self._plot_doc(st, _pos_cov(st), _finite(math.hypot(d[0], d[1])))
            out.append(("/nav/error", doc))
        return out

    # -- aids, releases, health -------------------------------------------------------
    def aid(self, statuses: list) -> list[tuple[str, Any]]:
        t = None
        for s in statuses:  # AidStatus objects, or their dicts (read back from the bus)
            d = s if isinstance(s, dict) else s.to_dict()
            self._aid_latest[d["source"]] = d
            c = self._aid_counts.setdefault(d["source"], [0, 0])
            c[0 if d["fused"] else 1] += 1
            t = float(d["t_s"])
        if t is None or t < self._next_aid_t:
            return []
        self._next_aid_t = t + self.aid_period_s
        return [("/nav/aid", self.aid_table(t))]

    def aid_table(self, t_s: float) -> dict:
        rows = []
        for src in sorted(self._aid_latest):
            d = self._aid_latest[src]
            fused, rejected = self._aid_counts[src]
            rows.append({"source": src, "fused": d["fused"], "reason": d.get("reason") or "",
                         "test_ratio": d.get("test_ratio"), "fused_count": fused, "rejected_count": rejected,
                         "t_s": d["t_s"]})
        return {"t_s": t_s, "sources": rows}

    def release(self, release: Any) -> list[tuple[str, Any]]:
        from foxglove.messages import Log, LogLevel

        from adaptnav.service.transport.release import release_to_dict

        doc = release_to_dict(release)
        ns = self.time.ns(float(release.t_s))
        k_v = (doc.get("params") or {}).get("k_v")
        text = (f"calibrator release {'accepted' if release.accepted else 'rejected'}"
                + (f" (k_V {k_v:.4g})" if isinstance(k_v, float) else "")
                + (f": {release.reason}" if getattr(release, "reason", "") else ""))
        return [("/calibration/release", doc),
                ("/log", Log(timestamp=_timestamp(ns), level=LogLevel.Info if release.accepted else LogLevel.Warning,
                             message=text, name="adaptnav.calibrator"))]

    def health(self, report: dict) -> list[tuple[str, Any]]:
        from adaptnav.service.transport.bus import _strict

        return [("/health", _strict(report))]

    def event(self, text: str, t_s: float, warning: bool = False) -> list[tuple[str, Any]]:
        from foxglove.messages import Log, LogLevel

        return [("/log", Log(timestamp=_timestamp(self.time.ns(t_s)), level=LogLevel.Warning if warning
                             else LogLevel.Info, message=text, name="adaptnav"))]


def json_schema_for(topic: str) -> dict:
    return JSON_SCHEMAS.get(topic, NAV_PLOT_SCHEMA if topic == "/nav/error" else {"type": "object"})


# the live server's channels (truth has no live source), message type name or "json"
LIVE_TOPICS = {"/nav/location": "LocationFix", "/nav/pose": "PoseInFrame", "/nav/odometry": "Odometry",
               "/nav/uncertainty": "SceneUpdate", "/tf": "FrameTransforms", "/nav/state": "json",
               "/nav/aid": "json", "/calibration/release": "json", "/health": "json", "/log": "Log"}


class SdkWriter:
    """Logs (topic, message) pairs on ``foxglove`` SDK channels of one :class:`foxglove.Context`
    (its sinks: a WebSocket server, an MCAP file).

    ``topics`` (topic → message type name or ``"json"``) are declared at once: a server
    advertises them when a client connects. (A channel created while a client is
    connecting can be advertised before the server can take a subscription to it — the
    SDK then answers "unknown channel" and the client never gets its messages.)
    """

    def __init__(self, context: Any, topics: dict[str, str] | None = None) -> None:
        self.context = context
        self._channels: dict[str, Any] = {}
        for topic, type_name in (topics or {}).items():
            self._channels[topic] = self._make(topic, type_name)

    def _make(self, topic: str, type_name: str) -> Any:
        import foxglove
        from foxglove import channels

        if type_name == "json":
            return foxglove.Channel(topic, schema=json_schema_for(topic), context=self.context)
        return getattr(channels, f"{type_name}Channel")(topic, context=self.context)

    def _channel(self, topic: str, msg: Any) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = self._make(topic, "json" if isinstance(msg, dict) else type(msg).__name__)
        return ch

    def write(self, pairs: Iterable[tuple[str, Any]], log_time_ns: int | None) -> None:
        for topic, msg in pairs:
            ch = self._channel(topic, msg)
            if log_time_ns is None:
                ch.log(msg)
            else:
                ch.log(msg, log_time=log_time_ns)

    def close(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()


class FoxgloveSink(Sink):
    """Runner sink: every output, converted (:class:`FoxgloveConverter`), logged on the SDK
    channels of ``context``. ``truth_max_age_s``: a truth sample and a state this close in
    data time are the same epoch (``/nav/error``)."""

    def __init__(self, context: Any, origin: Any, time_base: TimeBase, truth_max_age_s: float = 0.05,
                 closers: tuple[Callable[[], None], ...] = (), topics: dict[str, str] | None = None) -> None:
        self.convert = FoxgloveConverter(origin, time_base)
        self.writer = SdkWriter(context, topics)
        self.truth_max_age_s = truth_max_age_s
        self._closers = closers
        self.messages = 0
        self._valid = False

    def _log(self, pairs: list, t_s: float) -> None:
        if pairs:
            tb = self.convert.time
            self.writer.write(pairs, None if tb.live else tb.ns(t_s))
            self.messages += len(pairs)

    def on_nav(self, state: Any) -> None:
        t_s = float(state.t_s)
        self._log(self.convert.nav(state), t_s)
        if state.valid != self._valid:  # the Log panel says when the solution becomes (in)valid
            self._valid = bool(state.valid)
            self._log(self.convert.event(f"solution {'valid' if state.valid else 'invalid'} at data time "
                                         f"{t_s:.1f} s", t_s, warning=not state.valid), t_s)

    sample_kinds = frozenset({"truth"})

    def on_sample(self, sample: Any) -> None:
        if sample.KIND == "truth":
            self._log(self.convert.truth(sample, self.truth_max_age_s), float(sample.t_s))

    def on_aid(self, statuses: list) -> None:
        if statuses:
            self._log(self.convert.aid(statuses), float(statuses[-1].t_s))

    def on_release(self, release: Any) -> None:
        self._log(self.convert.release(release), float(release.t_s))

    def on_health(self, report: dict) -> None:
        t = report.get("t_s")
        self._log(self.convert.health(report), float(t) if isinstance(t, (int, float)) else math.nan)

    def close(self) -> None:
        self.writer.close()
        for close in self._closers:
            close()


def open_mcap_sink(path: Any, origin: Any, time_base: TimeBase, truth_max_age_s: float = 0.05,
                   metadata: dict[str, str] | None = None) -> FoxgloveSink:
    """A :class:`FoxgloveSink` writing ``path`` (MCAP, overwritten) through the SDK."""
    import foxglove

    ctx = foxglove.Context()
    writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=ctx)
    if metadata:
        writer.write_metadata("adaptnav", {str(k): str(v) for k, v in metadata.items()})
    return FoxgloveSink(ctx, origin, time_base, truth_max_age_s, closers=(writer.close,))


class LiveServer:
    """The daemon's live Foxglove WebSocket server (``[foxglove]`` section) and its sink.

    Raises ``OSError`` (one line: address and why) when the port cannot be bound.
    """

    def __init__(self, host: str, port: int, origin: Any, name: str = "adaptnav") -> None:
        import foxglove

        self.context = foxglove.Context()
        self.sink = FoxgloveSink(self.context, origin, TimeBase.wall(), topics=LIVE_TOPICS)
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        except Exception as e:  # the SDK raises its own error type for a bind failure
            raise OSError(f"foxglove server on {host}:{port}: {e}") from None
        self.port = int(self.server.port)

    def stop(self) -> None:
        self.sink.close()
        self.server.stop()


def encoded(topic: str, msg: Any) -> tuple[str, str, str, bytes, str, bytes]:
    """(topic, schema name, schema encoding, schema data, message encoding, message bytes)
    of a converted message, for MCAP writers other than the SDK's."""
    import json

    if isinstance(msg, dict):
        schema = json_schema_for(topic)
        return (topic, schema.get("title", "adaptnav.json"), "jsonschema", json.dumps(schema).encode(),
                "json", json.dumps(msg, separators=(",", ":")).encode())
    s = type(msg).get_schema()
    return topic, s.name, s.encoding, bytes(s.data), s.encoding, bytes(msg.encode())


def tlog_start_unix_s(path: Any, max_messages: int = 2000) -> float | None:
    """The recording computer's clock (UNIX s) at the first message of a ``.tlog`` that
    carries one (pymavlink's ``_timestamp``), or ``None``."""
    from pymavlink import mavutil

    try:
        conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    except OSError:
        return None
    try:
        for _ in range(max_messages):
            msg = conn.recv_match(blocking=False)
            if msg is None:
                return None
            ts = getattr(msg, "_timestamp", None)
            if msg.get_type() != "BAD_DATA" and isinstance(ts, float) and ts > 1e9:
                return ts
    finally:
        conn.close()
    return None


def replay_time_base(inp: Any) -> TimeBase:
    """Real-clock time base of a replay input: a simulated mission starts at its scenario's
    ``start_utc`` (else now); a ``.tlog`` at its recording clock (first message); anything
    else at the time of the run."""
    scenario = getattr(inp, "scenario", None)
    if scenario is not None:
        from adaptnav.sim.scenario import start_unix_s

        start = getattr(scenario, "start_utc", "")
        return TimeBase(unix_s=start_unix_s(start) if start else float(int(time.time())), data_s=0.0)
    path = getattr(inp, "path", None)
    if path is not None and str(path).lower().endswith(".tlog"):
        t0 = tlog_start_unix_s(path)
        if t0 is not None:
            return TimeBase(unix_s=t0, data_s=None)
    return TimeBase(unix_s=float(int(time.time())), data_s=None)


def bus_message_encoder(origin: Any, time_base: TimeBase) -> Callable[[Any], list[tuple]]:
    """For :func:`adaptnav.service.transport.logs.write_mcap` (``extra``) in ``adaptnav record``
    and ``adaptnav simulate``: a bus message (nav state, aid status, release) or a truth sample
    → the same message in Foxglove's schemas, :func:`encoded`."""
    conv = FoxgloveConverter(origin, time_base)

    def extra(item: Any) -> list[tuple]:
        kind = getattr(item, "KIND", None)
        try:
            if kind == "nav_state":
                from adaptnav.service.tools.demo import nav_state_from_dict

                pairs = conv.nav(nav_state_from_dict(item.body))
            elif kind == "truth":
                pairs = conv.truth(item)
            elif kind == "aid_status":
                pairs = conv.aid([item.body])
            elif kind == "calibration_release":
                from adaptnav.service.transport.release import release_from_dict

                pairs = conv.release(release_from_dict(item.body))
            else:
                return []
        except (KeyError, TypeError, ValueError):  # a message of another version: kept as it is
            return []
        return [encoded(topic, msg) for topic, msg in pairs]

    return extra
