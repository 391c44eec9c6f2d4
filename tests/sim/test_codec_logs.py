"""Wire codec, MCAP logs (round trip, truncation, foreign readers) and `adaptnav simulate`."""
import json
import math

import numpy as np
import pytest
from mcap.reader import make_reader

from adaptnav.fusion.samples import (SAMPLE_TYPES, DvlSample, ImuBatch, ImuSample, RangeSample, SampleError,
                            TruthSample, UsblSample, VisualMotionSample)
from adaptnav.fusion.typed_config import as_dict
from adaptnav.service.transport import codec
from adaptnav.service.cli import main as cli_main
from adaptnav.service.transport.logs import ReadStats, TruncatedLogError, read_mcap, read_mcap_metadata, write_mcap
from adaptnav.sim.scenario import load_scenario
from adaptnav.sim.simulator import simulate
from adaptnav.sonar.ping import SonarPing


@pytest.fixture(scope="module")
def sim30():
    return simulate(load_scenario("short", ["duration_s=30", "dvl.enabled=true", "beacons.enabled=true"]))


def _examples():
    return [
        ImuSample(0.01, (0.1, -0.2, -9.81), (1e-3, 0.0, -2e-3)),
        ImuSample(0.02, (0.1, -0.2, -9.81), (1e-3, 0.0, -2e-3), "autopilot"),
        DvlSample(1.0, (1.5, 0.01, -0.02), False, math.nan),
        UsblSample(60.0, 0.75, 0.1, 20.0, 2.0),
        RangeSample(2.0, 3, (10.0, 20.0, 30.0), 45.5, 2.0),
        VisualMotionSample(3.0, 2.0, 1.2, -0.1, 0.01, tuple(float(i) for i in range(9))),
        TruthSample(0.1, (1.0, 2.0, 3.0), (1.5, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.1, 0.1, 0.0), 0.9),
    ]


def _same(xs, ys):
    """Element-wise equality by repr (NaN fields make == false; repr is exact for floats)."""
    return len(xs) == len(ys) and all(repr(x) == repr(y) for x, y in zip(xs, ys))


def test_codec_round_trip_every_kind():
    for s in _examples():
        back = codec.decode(codec.encode(s))
        assert repr(back) == repr(s)  # repr: NaN != NaN but prints the same
    ping = SonarPing(5.0, np.array([0.0, 1.5, 2.25], np.float32), np.array([3.0, math.nan, 1.0], np.float32), 30.0)
    back = codec.decode(codec.encode(ping))
    assert back.t_s == 5.0 and np.array_equal(back.port, ping.port)
    assert math.isnan(back.starboard[1]) and back.starboard[2] == 1.0
    payload = json.loads(codec.encode(ping))
    assert payload["type"] == "sonar" and payload["schema_version"] == 1


def test_codec_schemas_describe_the_payloads():
    for kind in list(SAMPLE_TYPES) + ["sonar"]:
        schema = codec.schema_for(kind)
        assert schema["type"] == "object" and schema["properties"]["type"] == {"const": kind}
    for s in _examples():
        payload = json.loads(codec.encode(s))
        schema = codec.schema_for(s.KIND)
        assert set(schema["required"]) <= set(payload) <= set(schema["properties"])


@pytest.mark.parametrize("payload", [
    b"\xff\xfe not utf8",
    b"{not json",
    b"[1, 2, 3]",
    b'"imu"',
    b'{"type": "warp_drive", "schema_version": 1}',
    b'{"schema_version": 1, "t_s": 0}',
    b'{"type": [1], "schema_version": 1}',
    b'{"type": "imu", "schema_version": 1, "t_s": 0.5, "specific_force_b_m_s2": [0.0, 0.0, true], "omega_b_rad_s": [0.0, 0.0, 0.0]}',
    b'{"type": "imu", "schema_version": 1, "t_s": "noon", "specific_force_b_m_s2": [0,0,0], "omega_b_rad_s": [0,0,0]}',
    b'{"type": "imu", "schema_version": 1, "t_s": 0, "specific_force_b_m_s2": [0,0], "omega_b_rad_s": [0,0,0]}',
    b'{"type": "imu", "schema_version": 9, "t_s": 0, "specific_force_b_m_s2": [0,0,0], "omega_b_rad_s": [0,0,0]}',
    b'{"type": "dvl", "schema_version": 1, "t_s": 0, "vel_d_m_s": [0,0,0], "valid": "yes"}',
    b'{"type": "range", "schema_version": 1, "t_s": 0, "beacon_id": 1.5, "beacon_pos_n_m": [0,0,0], "range_m": 1, "sigma_m": 1}',
    b'{"type": "sonar", "schema_version": 1, "t_s": 0, "port": [1, "x"], "starboard": [1, 2], "slant_range_m": 30}',
    b'{"type": "sonar", "schema_version": 1, "t_s": 0, "port": [1], "starboard": [1, 2], "slant_range_m": 30}',
    b'{"type": "sonar", "schema_version": 1, "t_s": 0, "port": {"a": 1}, "starboard": [1], "slant_range_m": 30}',
    b"[" * 100000,
    12345,
])
def test_codec_rejects_malformed_payloads_with_sample_error(payload):
    with pytest.raises(SampleError):
        codec.decode(payload)


def test_payloads_only_the_lenient_parser_reads_decode_as_before():
    """The bus decodes with orjson; what it refuses but Python's json reads (a NaN literal,
    an integer beyond 64 bits, from a third-party publisher) decodes as it always did —
    the estimator or the door judges the values, the payload is not "malformed"."""
    nan = codec.decode(b'{"type": "imu", "schema_version": 1, "t_s": 1.5, '
                       b'"specific_force_b_m_s2": [NaN, 0.0, -9.8], "omega_b_rad_s": [0.0, 0.0, 0.0]}')
    assert isinstance(nan, ImuSample) and nan.t_s == 1.5 and math.isnan(nan.specific_force_b_m_s2[0])
    big = codec.decode(b'{"type": "range", "schema_version": 1, "t_s": 2.0, "beacon_id": 123456789012345678901234, '
                       b'"beacon_pos_n_m": [0.0, 0.0, 0.0], "range_m": 10.0, "sigma_m": 1.0}')
    assert big.beacon_id == 123456789012345678901234
    same = codec.encode(ImuSample(0.25, (0.1, 0.2, -9.8), (0.01, 0.0, 0.0)))
    assert codec.decode(same) == codec.decode(same.decode()) == ImuSample(0.25, (0.1, 0.2, -9.8), (0.01, 0.0, 0.0))


def test_registry_adds_kinds():
    codec.register("test_note", lambda o: {"type": "test_note", "schema_version": 1, "t_s": o[0]},
                   lambda d: ("note", float(d["t_s"])), {"type": "object"}, topic="/adaptnav/test/note")
    assert codec.decode(b'{"type": "test_note", "schema_version": 1, "t_s": 2}') == ("note", 2.0)
    with pytest.raises(SampleError):
        codec.decode(b'{"type": "test_note", "schema_version": 1}')  # KeyError → SampleError
    assert codec.topic_for("test_note") == "/adaptnav/test/note"


def test_mcap_round_trip(sim30, tmp_path):
    path = tmp_path / "sim.mcap"
    meta = {"scenario": as_dict(sim30.scenario), "note": "hello"}
    counts = write_mcap(path, sim30.iter_blocks(), meta)
    assert counts == sim30.counts()
    stats, got_meta = ReadStats(), {}
    back = list(read_mcap(path, stats, got_meta))
    expected = list(sim30.iter_samples())
    assert len(back) == len(expected) and stats.decoded == len(expected) and not stats.truncated
    assert _same(back, expected)  # exact floats (repr round trip), same order
    assert got_meta == meta == read_mcap_metadata(path)
    # a foreign reader (the mcap library's indexed reader) sees the documented layout
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {ch.topic: ch for ch in summary.channels.values()}
        assert "/adaptnav/truth" in topics and "/adaptnav/sensor/imu" in topics and "/adaptnav/sensor/dvl" in topics
        for ch in topics.values():
            assert ch.message_encoding == "json"
            assert summary.schemas[ch.schema_id].encoding == "jsonschema"
        first = next(reader.iter_messages(topics=["/adaptnav/sensor/imu"]))
        assert first[2].log_time == int(round(sim30.imu.t_s[0] * 1e9))


def test_mcap_keeps_who_measured_the_imu(tmp_path):
    """A recording keeps ImuSample.source (the auto IMU grade's prior): a batch written on the
    fast path and single samples read back with their source, runs split where it changes."""
    from adaptnav.service.runtime.sources import SourceCounters, order_and_batch

    path = tmp_path / "imu.mcap"
    t = np.arange(1, 6) * 0.01
    f = np.tile([0.0, 0.0, -9.81], (5, 1))
    w = np.zeros((5, 3))
    write_mcap(path, [ImuBatch(t, f, w, "autopilot"), ImuSample(0.06, (0.0, 0.0, -9.81), (0.0, 0.0, 0.0), "dedicated"),
                      ImuSample(0.07, (0.0, 0.0, -9.81), (0.0, 0.0, 0.0))])
    back = list(read_mcap(path, ReadStats()))
    assert [s.source for s in back] == ["autopilot"] * 5 + ["dedicated", ""]
    runs = list(order_and_batch(back, SourceCounters()))
    assert [(len(r), r.source) for r in runs] == [(5, "autopilot"), (1, "dedicated"), (1, "")]


def test_truncated_mcap_yields_the_prefix_then_an_error(sim30, tmp_path):
    path = tmp_path / "full.mcap"
    write_mcap(path, sim30.iter_blocks(), {"scenario": "short"})
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    stats = ReadStats()
    items = list(read_mcap(cut, stats))
    assert isinstance(items[-1], TruncatedLogError) and stats.truncated
    good = items[:-1]
    assert not any(isinstance(x, Exception) for x in good)
    expected = list(sim30.iter_samples())
    assert 0 < len(good) < len(expected) and _same(good, expected[: len(good)])
    assert read_mcap_metadata(cut) == {"scenario": "short"}


def test_bad_message_is_reported_and_reading_goes_on(tmp_path):
    path = tmp_path / "bad.mcap"
    good = [ImuSample(0.01 * i, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0)) for i in range(1, 4)]
    # a nan-laden sample is representable; a sample with a wrong field is not
    from mcap.writer import Writer
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("adaptnav.imu", "jsonschema", json.dumps(codec.schema_for("imu")).encode())
        cid = w.register_channel("/adaptnav/sensor/imu", "json", sid)
        for i, s in enumerate(good):
            w.add_message(cid, i, codec.encode(s), i)
            if i == 0:
                w.add_message(cid, i, b'{"type": "imu", "schema_version": 1, "t_s": "x"}', i)
        w.finish()
    stats = ReadStats()
    items = list(read_mcap(path, stats))
    assert [type(x) for x in items] == [ImuSample, SampleError, ImuSample, ImuSample]
    assert stats.bad_messages == 1 and stats.decoded == 3


def test_nan_imu_batch_is_written_as_null(tmp_path):
    batch = ImuBatch(np.array([0.01, 0.02]), np.array([[np.nan, 0, 0], [0, 0, -9.8]]), np.zeros((2, 3)))
    path = tmp_path / "nan.mcap"
    write_mcap(path, [batch], {})
    back = list(read_mcap(path))
    assert math.isnan(back[0].specific_force_b_m_s2[0]) and back[1].specific_force_b_m_s2[2] == -9.8


def test_simulate_command(tmp_path, capsys):
    out = tmp_path / "s.mcap"
    rc = cli_main(["simulate", "short", "--set", "duration_s=10", "--set", "usbl.period_s=5.0",
                   "--set", "usbl.start_s=5.0", "--out", str(out), "--no-progress"])
    assert rc == 0
    line = capsys.readouterr().out
    assert "imu=1000" in line and "usbl=2" in line
    kinds = {s.KIND for s in read_mcap(out)}
    assert {"imu", "rpm", "heading", "depth", "usbl", "truth", "gnss"} <= kinds
    assert read_mcap_metadata(out)["scenario"]["usbl"]["period_s"] == 5.0
    rc = cli_main(["simulate", "short", "--set", "usbl.nope=1", "--out", str(out)])
    assert rc == 2 and "usbl" in capsys.readouterr().err


def test_not_an_mcap_file_is_one_clear_error(tmp_path):
    path = tmp_path / "junk.mcap"
    path.write_bytes(b"this is not an mcap file at all")
    log = read_mcap(path)
    items = list(log)
    assert len(items) == 1 and isinstance(items[0], TruncatedLogError) and "invalid magic" in str(items[0])
    assert log.counters["corrupt_frames"] == 1 and log.metadata == {} and log.scenario is None


def test_log_reader_knows_scenario_and_streams(sim30, tmp_path):
    path = tmp_path / "sim.mcap"
    write_mcap(path, sim30.iter_blocks(), {"scenario": as_dict(sim30.scenario)})
    log = read_mcap(path)
    assert log.scenario == sim30.scenario
    assert log.streams == sorted(sim30.counts())


def test_kinds_carried_as_dicts_go_through_logs(tmp_path):
    # service kinds (nav state, health ...) are registered with dict in / dict out
    codec.register("test_state", lambda d: d, lambda d: d,
                   {"type": "object", "title": "adaptnav.test_state"}, topic="/adaptnav/test/state")
    msgs = [{"type": "test_state", "schema_version": 1, "t_s": 0.5, "x": [1.0, None]},
            ImuSample(0.6, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))]
    path = tmp_path / "state.mcap"
    assert write_mcap(path, msgs, {}) == {"test_state": 1, "imu": 1}
    log = read_mcap(path)
    back = list(log)
    assert back == msgs and log.stats.per_kind == {"test_state": 1, "imu": 1}
    with open(path, "rb") as f:
        first = next(make_reader(f).iter_messages(topics=["/adaptnav/test/state"]))
    assert first[2].log_time == 500_000_000


def test_every_logged_message_validates_against_its_channel_schema(sim30, tmp_path):
    # what Foxglove / third-party tools rely on: the channel schema describes the payloads
    jsonschema = pytest.importorskip("jsonschema")
    path = tmp_path / "sim.mcap"
    ping = SonarPing(1.0, np.array([0.0, math.nan], np.float32), np.array([1.0, 2.0], np.float32), 30.0)
    write_mcap(path, list(sim30.iter_samples())[::7] + [ping], {})
    validators = {}
    n = 0
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.id not in validators:
                doc = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(doc)
                validators[channel.id] = jsonschema.Draft202012Validator(doc)
            validators[channel.id].validate(json.loads(message.data))
            n += 1
    assert n > 600 and len(validators) >= 8
    # and a payload that breaks the contract does not validate
    bad = json.loads(codec.encode(_examples()[0]))
    bad["omega_b_rad_s"] = [0.0, 0.0]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, codec.schema_for("imu"))
