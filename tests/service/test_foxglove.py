"""Foxglove: the live WebSocket view of the daemon, read by a real client speaking the
``foxglove.sdk.v1`` subprotocol (the SDK server's name for the Foxglove WebSocket protocol), and the MCAP of a replay read back — channels in
Foxglove's well-known schemas (protobuf, decoded with the schema the file/server gives),
log times on a real clock."""
from __future__ import annotations

import base64
import json
import math
import struct
import time
from datetime import datetime, timezone
from pathlib import Path

import pytest

from adaptnav.service.daemon import Daemon

from .test_daemon_support import Feeder, daemon_config, free_port, peer

pytestmark = pytest.mark.timeout(180)

pb = pytest.importorskip("google.protobuf", reason="protobuf decodes Foxglove's schemas (test extra)")


def message_class(schema_name: str, descriptor_set: bytes):
    """The protobuf class of ``schema_name`` from a serialized FileDescriptorSet (what
    Foxglove's MCAP schemas and WebSocket advertisements carry)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # dependencies first, whatever the set's order
        for fd in list(pending):
            try:
                pool.Add(fd)
                pending.remove(fd)
            except TypeError:
                continue
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def layout_topics(node) -> list[str]:
    """Every topic a Foxglove layout names (``/topic`` or ``/topic.field`` strings and keys)."""
    out: list[str] = []
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("followTopic", "topicToRender", "topicPath", "value") and isinstance(v, str):
                out.append(v.split(".", 1)[0])
            elif k in ("topics", "topicColors") and isinstance(v, dict):
                out += list(v)
            else:
                out += layout_topics(v)
    elif isinstance(node, list):
        for v in node:
            out += layout_topics(v)
    return out


def stamp_s(ts) -> float:
    return ts.seconds + ts.nanos * 1e-9


# -- live ----------------------------------------------------------------------------------
def test_live_websocket_client_subscribes_and_decodes(tmp_path):
    from websockets.sync.client import connect

    zport = free_port()
    cfg = daemon_config(zport, tmp_path / "state", "calibrator.enabled=false", "foxglove.enabled=true",
                        "foxglove.port=0", "origin.lat_deg=43.0", "origin.lon_deg=5.9")
    assert cfg.foxglove.host == "127.0.0.1"  # loopback unless configured
    daemon = Daemon(cfg)
    daemon.start()
    bus = peer(zport)
    feeder = Feeder(bus)
    feeder.start()
    want = {"/nav/location", "/nav/pose", "/nav/state", "/health", "/tf"}
    got: dict[str, list] = {}
    try:
        url = f"ws://127.0.0.1:{daemon.foxglove.port}"
        with connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            channels: dict[int, dict] = {}
            subs: dict[int, dict] = {}
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not (want <= {t for t, v in got.items() if len(v) >= 3}):
                frame = ws.recv(timeout=5)
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op.get("op") == "advertise":
                        new = []
                        for ch in op["channels"]:
                            channels[ch["id"]] = ch
                            if ch["topic"] in want:
                                sub_id = len(subs) + 1
                                subs[sub_id] = ch
                                new.append({"id": sub_id, "channelId": ch["id"]})
                        if new:
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    continue
                assert frame[0] == 0x01  # MessageData
                sub_id, log_ns = struct.unpack_from("<IQ", frame, 1)
                got.setdefault(subs[sub_id]["topic"], []).append((log_ns, bytes(frame[13:]), subs[sub_id]))
    finally:
        feeder.stop()
        bus.close()
        daemon.stop()
    assert want <= set(got), f"topics received: {sorted(got)}"
    now_ns = time.time_ns()
    for topic, msgs in got.items():
        for log_ns, _, _ in msgs:  # a real clock: the last minutes, not 1970
            assert now_ns - 300e9 < log_ns <= now_ns, topic

    log_ns, payload, ch = got["/nav/location"][-1]
    assert ch["schemaName"] == "foxglove.LocationFix" and ch["encoding"] == "protobuf"
    fix = message_class(ch["schemaName"], base64.b64decode(ch["schema"])).FromString(payload)
    # the feeder's vehicle is at rest at 5 m depth at the origin
    assert fix.latitude == pytest.approx(43.0, abs=1e-4) and fix.longitude == pytest.approx(5.9, abs=1e-4)
    assert fix.altitude == pytest.approx(-5.0, abs=0.5)
    assert len(fix.position_covariance) == 9 and fix.position_covariance[0] > 0
    assert abs(stamp_s(fix.timestamp) * 1e9 - log_ns) < 5e9

    _, payload, ch = got["/nav/pose"][-1]
    assert ch["schemaName"] == "foxglove.PoseInFrame"
    pose = message_class(ch["schemaName"], base64.b64decode(ch["schema"])).FromString(payload)
    assert pose.frame_id == "ned" and pose.pose.position.z == pytest.approx(5.0, abs=0.5)
    q = pose.pose.orientation  # heading 0.3 rad from the feeder's heading sensor
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.3, abs=0.05)

    _, payload, ch = got["/nav/state"][-1]
    assert ch["encoding"] == "json"
    doc = json.loads(payload)
    assert doc["down_m"] == pytest.approx(5.0, abs=0.5) and doc["sigma_north_m"] > 0
    _, payload, _ = got["/health"][-1]
    assert json.loads(payload)["type"] == "health"


# -- replay MCAP ---------------------------------------------------------------------------
def test_replay_mcap_has_well_known_schemas_on_a_real_clock(tmp_path):
    from mcap.reader import make_reader

    from adaptnav.service.cli import main

    start = "2026-05-01T08:00:00Z"
    out = tmp_path / "nav.mcap"
    rc = main(["replay", "--scenario", "short", "--set", f"start_utc=\"{start}\"", "--set", "duration_s=120",
               "--out", str(tmp_path / "r"), "--mcap", str(out), "--no-plots", "--no-progress"])
    assert rc == 0
    start_ns = int(datetime(2026, 5, 1, 8, tzinfo=timezone.utc).timestamp() * 1e9)
    by_topic: dict[str, list] = {}
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        for schema, channel, message in reader.iter_messages():
            by_topic.setdefault(channel.topic, []).append((message.log_time, schema, message.data))
    assert schemas["/nav/location"] == "foxglove.LocationFix"
    assert schemas["/nav/pose"] == "foxglove.PoseInFrame"
    assert schemas["/truth/location"] == "foxglove.LocationFix"
    assert schemas["/tf"] == "foxglove.FrameTransforms"
    assert schemas["/nav/odometry"] == "foxglove.Odometry"
    # the deploy/ layout opens on what the file holds: every topic it names is a channel
    layout = json.loads((Path(__file__).resolve().parents[2] / "deploy" / "foxglove-layout.json").read_text())
    named = set(layout_topics(layout["configById"]))
    assert {"/nav/location", "/nav/error", "/nav/state", "/nav/aid", "/nav/pose"} <= named
    assert named <= set(schemas), f"layout names topics the replay does not write: {named - set(schemas)}"
    # log times: the scenario's start_utc + data time (120 s of data)
    times = [t for msgs in by_topic.values() for t, _, _ in msgs]
    assert start_ns <= min(times) < start_ns + 5e9
    assert start_ns + 100e9 < max(times) <= start_ns + 121e9

    loc = message_class("foxglove.LocationFix", by_topic["/nav/location"][0][1].data)
    truth = {t: loc.FromString(d) for t, _, d in by_topic["/truth/location"]}
    errors = []
    for t, _, d in by_topic["/nav/location"]:
        nav = loc.FromString(d)
        assert abs(stamp_s(nav.timestamp) * 1e9 - t) < 1e3
        tr = truth.get(t)
        if tr is not None:  # same epoch: the solution and the truth agree to the filter's accuracy
            dn = (nav.latitude - tr.latitude) * 111_000.0
            de = (nav.longitude - tr.longitude) * 111_000.0 * math.cos(math.radians(tr.latitude))
            errors.append(math.hypot(dn, de))
    assert len(errors) > 900
    assert max(errors) < 30.0 and sorted(errors)[len(errors) // 2] < 10.0
    # the error plot channel compares the same epochs
    err = [json.loads(d)["horizontal_error_m"] for _, _, d in by_topic["/nav/error"]]
    assert len(err) > 900 and max(err) < 30.0


def test_simulated_log_starts_at_start_utc_and_replays_unchanged(tmp_path):
    """``simulate`` writes log times from the scenario's start_utc and the truth in Foxglove's
    schemas beside the adaptnav channels; replay reads the adaptnav channels only."""
    from mcap.reader import make_reader

    from adaptnav.service.cli import main
    from adaptnav.service.transport.logs import read_mcap

    out = tmp_path / "sim.mcap"
    assert main(["simulate", "short", "--set", "duration_s=30", "--set", "start_utc=\"2026-05-01T08:00:00Z\"",
                 "--out", str(out), "--no-progress"]) == 0
    start_ns = int(datetime(2026, 5, 1, 8, tzinfo=timezone.utc).timestamp() * 1e9)
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    names = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert names["/truth/location"] == "foxglove.LocationFix"
    assert start_ns <= summary.statistics.message_start_time < start_ns + 1e9
    assert summary.statistics.message_end_time <= start_ns + 31e9
    log = read_mcap(out)
    items = list(log)
    assert not [x for x in items if isinstance(x, Exception)]
    assert "location" not in (log.streams or [])
    assert log.stats.messages == sum(n for ch_id, n in summary.statistics.channel_message_counts.items()
                                     if summary.channels[ch_id].topic.startswith("/adaptnav/"))
