"""Every reader gives one line on an empty, truncated or foreign file, never a traceback
(issue 12 item 7), and replay does not take a mis-placed first fix for the map origin."""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from adaptnav.service.cli import main

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "mavlink"


def _cli(capsys, *argv):
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse
        code = e.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


@pytest.mark.parametrize("name, content", [
    ("short17.tlog", None), ("empty.BIN", b""), ("empty.tlog", b""), ("random.BIN", "random"),
    ("random.tlog", "random"), ("empty.mcap", b""), ("random.mcap", "random"), ("empty.log", b""),
    ("random.log", "random")])
@pytest.mark.timeout(120)  # a random ".log" once kept a reader failing in one place for ever
def test_a_damaged_or_foreign_log_replays_without_a_traceback(tmp_path, capsys, name, content):
    path = tmp_path / name
    if content is None:  # the first 17 bytes of a real tlog
        real = DATA / "ardusub-4.1.2-bench.tlog"
        if not real.is_file():
            pytest.skip("real data absent")
        content = real.read_bytes()[:17]
    elif content == "random":
        content = np.random.default_rng(1).bytes(5000)
    path.write_bytes(content)
    code, err = _cli(capsys, "replay", str(path), "--out", str(tmp_path / "out"), "--no-plots", "--no-progress")
    assert code in (0, 1, 2)


@pytest.mark.parametrize("verb", ["replay", "run"])
def test_a_foreign_config_file_is_one_line_naming_it(tmp_path, capsys, verb):
    cfg = tmp_path / "random.toml"
    cfg.write_bytes(np.random.default_rng(2).bytes(3000))
    log = tmp_path / "x.tlog"
    log.write_bytes(b"")
    argv = ["replay", str(log), "--out", str(tmp_path / "o")] if verb == "replay" else ["run"]
    code, err = _cli(capsys, *argv, "--config", str(cfg))
    assert code == 2
    assert "random.toml" in err and len(err.strip().splitlines()) == 1, err


def test_a_misplaced_first_fix_does_not_move_the_origin(tmp_path, capsys):
    """One first fix 4,755 km off (a mis-stamped sample) used to become the NED origin."""
    from adaptnav.service.runtime.sources import simulate
    from adaptnav.service.transport.logs import write_mcap
    from adaptnav.sim.scenario import load_scenario

    scenario = load_scenario("short", ["duration_s=60"])
    items = list(simulate(scenario).iter_blocks())
    fixes = [i for i in items if getattr(i, "KIND", "") in ("gnss", "usbl")]
    assert len(fixes) >= 2
    bad = replace(fixes[0], lat_rad=fixes[0].lat_rad + 4.755e6 / 6.371e6)
    items = [bad if i is fixes[0] else i for i in items if getattr(i, "KIND", "") != "truth"]
    write_mcap(tmp_path / "m.mcap", items)  # no scenario metadata: the origin comes from the fixes
    code, _ = _cli(capsys, "replay", str(tmp_path / "m.mcap"), "--out", str(tmp_path / "out"),
                   "--no-plots", "--no-progress")
    assert code == 0
    origin = json.loads((tmp_path / "out" / "config.json").read_text())["origin"]
    assert origin["lat_deg"] == pytest.approx(math.degrees(fixes[1].lat_rad), abs=1e-4)


TEST_DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.mark.parametrize("name, tail, cut_says", [
    ("ardusub-sitl-session.tlog", None, "ends inside a frame"),
    ("ardusub-4.7-sitl-drive.BIN", None, "ends inside a record"),
    ("ardusub-sitl-session.tlog", b"", None),
    ("ardusub-4.7-sitl-drive.BIN", b"", None),
    ("ardusub-4.7-sitl-drive.BIN", b"\xff" * 700, None)])  # a card's unwritten space is not a cut
def test_a_log_cut_off_inside_a_message_says_so_and_keeps_the_rest(tmp_path, name, tail, cut_says):
    """A recording cut off (power lost, a copy stopped early) ends inside a message: counted as a
    corrupt frame, said in the counters, everything before it read; a whole log says nothing."""
    from adaptnav.service.transport.tlog_source import TlogSource

    data = (TEST_DATA / name).read_bytes()
    whole = TlogSource(TEST_DATA / name)
    n_whole = len(list(whole))
    assert not whole.counters.get("truncated")
    path = tmp_path / name
    # a cut 40 % in, at a byte that is not a message's first (a frame's or record's start byte)
    cut = int(len(data) * 0.4)
    while data[cut] in (0xFD, 0xFE, 0xA3):
        cut += 1
    path.write_bytes(data[:cut] if tail is None else data + tail)
    src = TlogSource(path)
    n = len(list(src))
    if cut_says is None:
        assert not src.counters.get("truncated") and n == n_whole
        assert src.counters["corrupt_frames"] == whole.counters["corrupt_frames"]
    else:
        assert cut_says in src.counters["truncated"] and name in src.counters["truncated"]
        assert src.counters["corrupt_frames"] == whole.counters["corrupt_frames"] + 1
        assert 0.3 * n_whole < n < 0.5 * n_whole


def test_a_damaged_truth_record_is_rejected_not_scored(tmp_path, capsys):
    """A simulator's SIM record zeroed after its time stamp (a card's bad block) read as a
    pose with a zero quaternion at 0°/0°, and the metrics' attitude error raised on it."""
    from pymavlink import DFReader

    src = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-dvl.BIN"
    data = bytearray(src.read_bytes())
    reader = DFReader.DFReader_binary(str(src))
    sim = reader.name_to_id["SIM"]
    ofs, length = reader.offsets[sim][100], reader.formats[sim].len
    data[ofs + 3 + 8: ofs + length] = bytes(length - 3 - 8)  # header and TimeUS kept
    path = tmp_path / "zeroed-sim.BIN"
    path.write_bytes(bytes(data))
    code, err = _cli(capsys, "replay", str(path), "--out", str(tmp_path / "out"), "--no-plots", "--no-progress")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["rejected_samples"]["truth_invalid"] == 1
    assert (tmp_path / "out" / "metrics.json").is_file()


def _damage_one_chunk(path: Path, k: int) -> tuple[bytes, int]:
    """The file with the k-th chunk's compressed bytes garbled in place (a bad block): its
    header and the summary at the end intact; and the number of chunks."""
    from mcap.reader import make_reader

    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    c = chunks[k]
    middle = c.chunk_start_offset + c.chunk_length // 2
    data[middle: middle + 200] = np.random.default_rng(3).bytes(200)
    return bytes(data), len(chunks)


def test_a_damaged_chunk_of_an_mcap_log_loses_only_its_messages(tmp_path, capsys):
    """One garbled chunk (bit errors, a bad block) in the middle of a log used to end the
    replay there ("log ends early or is corrupt"): now reading goes on at the next chunk the
    summary lists, and only that chunk's messages are lost."""
    from adaptnav.service.runtime.sources import simulate
    from adaptnav.service.transport.logs import write_mcap
    from adaptnav.fusion.typed_config import as_dict
    from adaptnav.sim.scenario import load_scenario

    scenario = load_scenario("short", ["duration_s=120"])
    whole = tmp_path / "whole.mcap"
    write_mcap(whole, simulate(scenario).iter_blocks(), metadata={"scenario": as_dict(scenario)})
    data, n_chunks = _damage_one_chunk(whole, 1)
    assert n_chunks >= 4
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data)
    results = {}
    for name in ("whole", "damaged"):
        code, err = _cli(capsys, "replay", str(tmp_path / f"{name}.mcap"), "--out", str(tmp_path / name),
                         "--no-plots", "--no-progress")
        assert code == 0
        results[name] = json.loads((tmp_path / name / "summary.json").read_text())
    w, d = results["whole"], results["damaged"]
    assert d["corrupt_frames"] == 1 and not d.get("truncated")
    assert d["duration_s"] == pytest.approx(w["duration_s"], abs=0.5)  # read to the end
    lost = w["messages_read"] - d["messages_read"]
    assert 0 < lost < 1.5 * w["messages_read"] / n_chunks
    # the chunk's seconds are data missing, coasted through: taken for a step of the clock
    # and re-based, the filter left the vehicle's motion meanwhile out (411 m at the end)
    assert d["clock_jumps_s"] == [] and len(d["data_gaps_s"]) == 1, (d["clock_jumps_s"], d["data_gaps_s"])
    metrics = json.loads((tmp_path / "damaged" / "metrics.json").read_text())
    assert metrics["max_horizontal_error_m"] < 30.0 and metrics["nees_fraction_in_95"] > 0.8, metrics


def test_a_damaged_chunk_of_a_blueos_recording_loses_only_its_messages(tmp_path):
    from adaptnav.service.transport.tlog_source import TlogSource

    from .mavlink_wire import write_blueos_mcap

    whole = write_blueos_mcap(TEST_DATA / "ardusub-sitl-session.tlog", tmp_path / "whole.mcap")
    data, n_chunks = _damage_one_chunk(whole, 2)
    (tmp_path / "damaged.mcap").write_bytes(data)
    src_whole, src = TlogSource(whole), TlogSource(tmp_path / "damaged.mcap")
    t_whole, t = [s.t_s for s in src_whole], [s.t_s for s in src]
    assert src.counters["corrupt_frames"] == 1 and not src.counters.get("truncated")
    assert src.counters["rejected"]["damaged_chunk"] == 1
    assert t[-1] == t_whole[-1]
    lost = src_whole.counters["messages_read"] - src.counters["messages_read"]
    assert 0 < lost < 1.5 * src_whole.counters["messages_read"] / n_chunks


def _with_format_damaged(data: bytes, name: str, letters: str) -> bytes:
    """The log with one letter of one FMT record's format replaced by a byte no format uses
    (a flipped bit on the card)."""
    at = data.index(name.encode().ljust(4, b"\0") + letters.encode()) + 4 + 1  # its second letter
    return data[:at] + b"\\" + data[at + 1:]


@pytest.mark.parametrize("name, letters, lost", [
    ("GRXS", "QddfBBBHBBBBB", None),     # a type nothing reads: nothing lost
    ("FMT", "BBnNZ", None),              # FMT's own record: the reader's built-in declaration reads
    ("GPS", "QBBIHBcLLeffffB", "gnss")])  # the position fixes' type: only they are lost
def test_a_damaged_record_format_loses_only_its_records(tmp_path, name, letters, lost):
    """pymavlink's DataFlash index raised on one damaged FMT record and the whole log was
    'not a readable log' (found by mutating the public BIN): the type is now skipped, said and
    counted, and every other record reads as from the whole log."""
    from collections import Counter

    from adaptnav.service.transport.tlog_source import TlogSource

    log_name = "ardusub-4.7-sitl-drive.BIN"
    whole = TlogSource(TEST_DATA / log_name)
    kinds_whole = Counter(getattr(s, "KIND", "") for s in whole)
    path = tmp_path / log_name
    path.write_bytes(_with_format_damaged((TEST_DATA / log_name).read_bytes(), name, letters))
    src = TlogSource(path)
    kinds = Counter(getattr(s, "KIND", "") for s in src)
    assert src.counters["rejected"][f"damaged_format:{name}"] == 1
    assert src.counters["corrupt_frames"] == whole.counters["corrupt_frames"] + 1
    # (without position fixes there is no NED origin to place the simulator's truth in)
    gone = {lost} | ({"truth"} if lost == "gnss" else set())
    expected = Counter({k: n for k, n in kinds_whole.items() if k not in gone})
    assert kinds == expected and kinds["imu"] + kinds["imu_batch"] > 1000
    if lost is not None:
        assert kinds_whole[lost] > 0


def _damaged_gps_format(tmp_path, change) -> Path:
    """The SITL drive's DataFlash log with ``change(data, at)`` applied, ``at`` the offset of
    the GPS record format's length byte (its letters follow the name, 5 bytes on)."""
    log_name = "ardusub-4.7-sitl-drive.BIN"
    data = bytearray((TEST_DATA / log_name).read_bytes())
    at = bytes(data).index(b"GPS\0QBBIHBcLLeffffB") - 1  # the FMT record's length byte, before the name
    assert data[at] == 51
    change(data, at)
    path = tmp_path / log_name
    path.write_bytes(bytes(data))
    return path


def _kinds(src):
    from collections import Counter

    return Counter(getattr(s, "KIND", "") for s in src)


def _nothing_printed(capfd):
    printed = capfd.readouterr()  # (our own one-line warnings may quote the first complaint)
    return not [line for line in (printed.err + printed.out).splitlines()
                if line.startswith(("bad header", "Failed to parse", "bad msg"))]


def test_a_damaged_record_length_is_repaired(tmp_path, capfd):
    """One bit of GPS's declared length flipped (51 → 55 bytes): pymavlink's reader failed on
    every GPS record and the one after it, printed 142,221 lines to the terminal, its compiled
    indexer 116,622 more, and the records it lost were counted nowhere (corrupt frames 0). The
    letters' size and GPS's own records say 51: the byte is repaired and the log reads whole."""
    from adaptnav.service.transport.tlog_source import TlogSource

    path = _damaged_gps_format(tmp_path, lambda data, at: data.__setitem__(at, data[at] ^ 0x04))
    whole = TlogSource(TEST_DATA / path.name)
    kinds_whole = _kinds(whole)
    src = TlogSource(path)
    assert _kinds(src) == kinds_whole and kinds_whole["gnss"] > 1000
    assert src.counters["rejected"]["repaired_format_length:GPS"] == 1
    assert src.counters["corrupt_frames"] == whole.counters["corrupt_frames"] + 1
    assert _nothing_printed(capfd)


def test_a_format_letter_a_flipped_bit_made_unknown_is_repaired(tmp_path, capfd):
    """One bit of a GPS format letter flipped ('L' → '\\', a letter DFReader does not know):
    the type was skipped whole, every fix and the truth with it. One letter a bit away makes
    the declared length, and the records agree with that length: the letter is repaired and
    the log reads whole."""
    from adaptnav.service.transport.tlog_source import TlogSource

    def change(data, at):
        k = at + 5 + bytes(data[at + 5:at + 21]).index(b"L")
        data[k] ^= 0x10  # 'L' → '\\'

    path = _damaged_gps_format(tmp_path, change)
    whole = TlogSource(TEST_DATA / path.name)
    src = TlogSource(path)
    assert _kinds(src) == _kinds(whole)
    assert src.counters["rejected"]["repaired_format_letters:GPS"] == 1
    assert src.counters["corrupt_frames"] == whole.counters["corrupt_frames"] + 1
    assert _nothing_printed(capfd)


def test_format_letters_that_disagree_with_the_length_lose_only_their_type(tmp_path, capfd):
    """One letter of GPS's format changed to another of a different size ('f', 4 bytes → 'd',
    8): the length byte and the records say 51, so the letters are what is damaged; every GPS
    record failed to parse. The type is skipped whole and said; the rest reads as from the
    whole log."""
    from adaptnav.service.transport.tlog_source import TlogSource

    def change(data, at):
        k = at + 5 + bytes(data[at + 5:at + 21]).index(b"f")
        data[k] = ord("d")

    path = _damaged_gps_format(tmp_path, change)
    whole = TlogSource(TEST_DATA / path.name)
    kinds_whole = _kinds(whole)
    src = TlogSource(path)
    assert _kinds(src) == {k: n for k, n in kinds_whole.items() if k not in ("gnss", "truth")}
    assert src.counters["rejected"]["damaged_format:GPS"] == 1
    assert "reader_parse_failure" not in src.counters["rejected"]
    assert _nothing_printed(capfd)


def test_damaged_record_headers_are_counted_not_printed(tmp_path, capfd):
    """Forty records' header bytes zeroed in the middle of the log (bit errors on the card):
    pymavlink's indexer printed a line per resynchronisation. They are counted as corrupt
    frames (``indexer_bad_header``), nothing is printed, and at most those records are lost."""
    from adaptnav.service.transport.tlog_source import TlogSource

    log_name = "ardusub-4.7-sitl-drive.BIN"
    data = bytearray((TEST_DATA / log_name).read_bytes())
    hits, at = 0, len(data) // 2
    while hits < 40:
        at = bytes(data).index(b"\xa3\x95", at + 5000)
        data[at] = 0
        hits += 1
    path = tmp_path / log_name
    path.write_bytes(bytes(data))
    whole = TlogSource(TEST_DATA / log_name)
    n_whole = sum(_kinds(whole).values())
    src = TlogSource(path)
    n = sum(_kinds(src).values())
    assert n_whole - 40 <= n <= n_whole
    assert src.counters["rejected"]["indexer_bad_header"] >= 40
    assert src.counters["corrupt_frames"] >= whole.counters["corrupt_frames"] + 40
    assert _nothing_printed(capfd)


def _tlog_without(src: Path, dst: Path, t_from_s: float, span_s: float) -> None:
    """``src`` with the messages of ``[t_from_s, t_from_s + span_s)`` (from its first
    message's reception time) left out: a telemetry dropout as the ground station recorded it."""
    import struct

    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(src), dialect="ardupilotmega")
    t0 = None
    with open(dst, "wb") as f:
        while (msg := conn.recv_match()) is not None:
            t = msg._timestamp
            t0 = t if t0 is None else t0
            if msg.get_type() != "BAD_DATA" and not t_from_s <= t - t0 < t_from_s + span_s:
                f.write(struct.pack(">Q", int(t * 1e6)) + msg.get_msgbuf())
    conn.close()


def _moved_across(rows, t_before, t_after, prefix=""):
    def row_at(t):
        return min(rows, key=lambda r: abs(float(r["t_s"]) - t))
    a, b = row_at(t_before), row_at(t_after)
    return np.array([float(b[prefix + "north_m"]) - float(a[prefix + "north_m"]),
                     float(b[prefix + "east_m"]) - float(a[prefix + "east_m"])])


def test_a_telemetry_dropout_is_coasted_through_not_taken_for_a_clock_step(tmp_path, capsys):
    """12 s of a tlog missing (the link dropped) read as a clock that stepped forward: the
    filter was re-based "as if no time had passed" and left the 6 m the vehicle moved
    meanwhile out of its position, its covariance none the wiser. On an autopilot's boot
    clock a later time is data missing: the filter coasts through the gap."""
    import csv

    log = tmp_path / "dropout.tlog"
    _tlog_without(TEST_DATA / "ardusub-sitl-session.tlog", log, 150.0, 12.0)
    code, _ = _cli(capsys, "replay", str(log), "--out", str(tmp_path / "out"), "--no-plots", "--no-progress")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["clock_jumps_s"] == []
    (gap,) = summary["data_gaps_s"]
    assert 11.0 < gap[1] - gap[0] < 13.0
    with open(tmp_path / "out" / "trajectory.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["truth_north_m"]]
    before, after = gap[0] - 0.5, gap[1] + 0.5
    truth = _moved_across(rows, before, after, "truth_")
    ours = _moved_across(rows, before, after)
    assert np.linalg.norm(truth) > 3.0  # the vehicle moved through the gap (5.2 m)
    # the filter's position moved with it: coasting at the velocity before the gap, 8.2 m
    # along the 5.2 (re-based: 0.7 m)
    assert ours @ truth / np.linalg.norm(truth) > 0.5 * np.linalg.norm(truth), (ours, truth)
    # and 20 s on the error is back to where it was (1.45 m; re-based it kept 4.4 m)
    late = min(rows, key=lambda r: abs(float(r["t_s"]) - (after + 20.0)))
    assert np.hypot(float(late["north_m"]) - float(late["truth_north_m"]),
                    float(late["east_m"]) - float(late["truth_east_m"])) < 2.5


@pytest.fixture(scope="module")
def mission_60s():
    from adaptnav.service.runtime.sources import simulate
    from adaptnav.sim.scenario import load_scenario

    return [i for i in simulate(load_scenario("short", ["duration_s=60"])).iter_blocks()
            if getattr(i, "KIND", "") != "truth"]


def _timed(item, t_from_s: float, shift_s: float):
    """``item`` with its samples from ``t_from_s`` on stamped ``shift_s`` later."""
    from adaptnav.fusion.samples import ImuBatch

    if isinstance(item, ImuBatch):
        t = np.asarray(item.t_s, dtype=float)
        return ImuBatch(np.where(t >= t_from_s, t + shift_s, t), item.specific_force_b_m_s2, item.omega_b_rad_s)
    return replace(item, t_s=item.t_s + shift_s) if item.t_s >= t_from_s else item


@pytest.mark.parametrize("case", ["dropout", "step"])
def test_a_recording_tells_a_dropout_from_a_step_by_its_log_clock(tmp_path, capsys, mission_60s, case):
    """In a bus recording (``adaptnav record``) log times are the recorder's wall clock. When
    the data goes on 12 s later, the log clock says which it was, as the live daemon's wall
    clock did: advanced with the data — nothing arrived for 12 s (a dropout: coasted
    through); not advanced — the data's clock was set forward (a step: re-based)."""
    from adaptnav.service.transport.logs import LOG_CLOCK_KEY, RECEPTION_WALL_CLOCK, write_mcap

    t_from, span = 25.0, 12.0
    if case == "dropout":  # the messages of [25, 37) s never arrived
        items = [i for i in mission_60s if not (t_from <= float(np.min(i.t_s)) < t_from + span)]
        wall_ns = lambda t: int((1.8e9 + t) * 1e9)  # noqa: E731 — the recorder's clock ran with the data
    else:  # from 25 s on the data is stamped 12 s later; the recorder's clock did not jump
        items = [_timed(i, t_from, span) for i in mission_60s]
        wall_ns = lambda t: int((1.8e9 + (t - span if t >= t_from + span else t)) * 1e9)  # noqa: E731
    log = tmp_path / f"{case}.mcap"
    write_mcap(log, items, metadata={"recorded_by": "adaptnav record", LOG_CLOCK_KEY: RECEPTION_WALL_CLOCK},
               log_time_ns=wall_ns)
    code, _ = _cli(capsys, "replay", str(log), "--out", str(tmp_path / "out"), "--no-plots", "--no-progress")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    if case == "dropout":
        assert summary["clock_jumps_s"] == [], summary["clock_jumps_s"]
        (gap,) = summary["data_gaps_s"]
        assert span - 1.0 < gap[1] - gap[0] < span + 1.0
    else:
        assert summary["data_gaps_s"] == [], summary["data_gaps_s"]
        (jump,) = summary["clock_jumps_s"]
        assert jump == pytest.approx(span, abs=1.0)


def _dataflash_index(data: bytes):
    """pymavlink's index of a binary DataFlash log: (name → type id, type id → record offsets,
    type id → record length)."""
    import tempfile

    from pymavlink import DFReader

    with tempfile.NamedTemporaryFile(suffix=".BIN") as f:
        f.write(data)
        f.flush()
        r = DFReader.DFReader_binary(f.name, zero_time_base=False)
        return dict(r.name_to_id), [list(o) for o in r.offsets], {t: f.len for t, f in r.formats.items()}


def _sitl_drive_changed(tmp_path, change) -> tuple[Path, Path]:
    """(the SITL drive's DataFlash log, a copy with ``change(data, names, offsets, lengths)``
    applied)."""
    log_name = "ardusub-4.7-sitl-drive.BIN"
    whole = TEST_DATA / log_name
    data = bytearray(whole.read_bytes())
    change(data, *_dataflash_index(bytes(data)))
    path = tmp_path / log_name
    path.write_bytes(bytes(data))
    return whole, path


@pytest.mark.parametrize("lost, skipped", [("XKV1", 600), ("VER", 1)])
def test_a_type_whose_format_record_is_lost_loses_nothing_else(tmp_path, capfd, lost, skipped):
    """A block of zeros over one FMT record of a type nothing reads (XKV1's: 666 records; VER's:
    one, before the first SIM record): pymavlink's index stops at the type's first record
    (``unknown msg type``), and 85 % of the log was lost without a word — with VER, the
    simulator's truth too. The rest is now read record by record, said, and every sample and
    truth is the whole log's."""
    from adaptnav.service.transport.tlog_source import TlogSource

    def change(data, names, offsets, lengths):
        fmt_at = next(o for o in offsets[names["FMT"]] if data[o + 3] == names[lost])
        data[fmt_at:fmt_at + lengths[names["FMT"]]] = bytes(lengths[names["FMT"]])
        assert offsets[names[lost]][0] < len(data) // 2  # (the index stopped early: most of the log)

    whole_path, path = _sitl_drive_changed(tmp_path, change)
    whole = TlogSource(whole_path)
    samples_whole = [(s.KIND, s.t_s) for s in whole]
    src = TlogSource(path)
    samples = [(s.KIND, s.t_s) for s in src]
    assert samples == samples_whole and len(samples) > 10000
    assert src.has_truth and any(kind == "truth" for kind, _ in samples)
    assert src.counters["rejected"]["reader_skipped_bytes"] >= skipped  # the type's records, skipped
    assert _nothing_printed(capfd)


def test_one_damaged_record_header_loses_that_record_only(tmp_path, capfd):
    """One bit of a record header's type byte flipped in the log's first quarter, to a type no
    format declares: the index ended there and the rest of the log with it. Now that record is
    lost, and at most it."""
    from adaptnav.service.transport.tlog_source import TlogSource

    def change(data, names, offsets, lengths):
        imu = offsets[names["IMU"]]
        at = imu[len(imu) // 4]
        data[at + 2] ^= 0x40  # IMU's id 163 → 227, which no FMT record declares
        assert data[at + 2] not in names.values()

    whole_path, path = _sitl_drive_changed(tmp_path, change)
    kinds_whole = _kinds(TlogSource(whole_path))
    src = TlogSource(path)
    kinds = _kinds(src)
    assert {k: kinds_whole[k] - n for k, n in kinds.items()} in ({"imu": 1} | {k: 0 for k in kinds if k != "imu"},
                                                                 {k: 0 for k in kinds})
    assert set(kinds) == set(kinds_whole)
    assert _nothing_printed(capfd)


@pytest.mark.parametrize("damage", ["zeroed", "high bit"])
def test_a_damaged_record_time_is_refused_not_taken_for_a_reboot(tmp_path, damage):
    """One ATT record's TimeUS damaged mid-log: zeroed (a block of zeros over the record's
    body) or a high bit flipped. The mission clock took the first for a reboot and moved every
    later sample on by the log's age (a public log replayed as 295 s of data, not 24). A log is
    one boot: the record is refused (``time_damaged``), the clock sees no reboot and every
    other sample keeps its time."""
    from adaptnav.service.transport.tlog_source import TlogSource

    def change(data, names, offsets, lengths):
        att = offsets[names["ATT"]]
        at = att[len(att) // 2] + 3  # the record's TimeUS, its first field (little-endian Q)
        if damage == "zeroed":
            data[at:at + 8] = bytes(8)
        else:
            data[at + 5] ^= 0x10  # +2^44 µs

    whole_path, path = _sitl_drive_changed(tmp_path, change)
    samples_whole = [(s.KIND, s.t_s) for s in TlogSource(whole_path)]
    src = TlogSource(path)
    samples = [(s.KIND, s.t_s) for s in src]
    assert src.converter.time.reboots == 0
    kept = set(samples)
    missing = [s for s in samples_whole if s not in kept]
    assert len(samples) == len(samples_whole) - 1 and len(missing) == 1 and missing[0][0] == "attitude"
    assert src.counters["rejected"]["time_damaged"] == 1
