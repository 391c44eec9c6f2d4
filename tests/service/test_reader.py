"""A MAVLink log read in a child process (:mod:`adaptnav.service.runtime.reader`) replays to the
same bytes as one read in the replaying process; the child's warnings, its exceptions and its
end are this process's."""
from __future__ import annotations

import csv
import json
import logging
import multiprocessing as mp
import os
import signal
import threading
from pathlib import Path

import pytest

from adaptnav.service.runtime.reader import CHILD_MIN_BYTES, wants_child
from adaptnav.service.runtime.replay import build_config, open_log, replay

SESSION = Path(__file__).resolve().parents[1] / "data" / "ardusub-sitl-session.tlog"
OUTPUTS = ("trajectory.csv", "aid_status.csv", "params.csv")


def _replay(path: Path, out: Path, reader: str):
    return replay(open_log(path), build_config(None, None), out, progress=False, plots=False, reader=reader)


def _summary(out: Path) -> dict:
    doc = json.loads((out / "summary.json").read_text())
    for key in ("wall_s", "realtime_factor"):  # the run's own time
        doc.pop(key)
    return doc


def test_a_log_read_in_a_child_replays_to_the_same_bytes(tmp_path):
    inline, child = tmp_path / "inline", tmp_path / "child"
    _replay(SESSION, inline, "inline")
    _replay(SESSION, child, "process")
    for name in OUTPUTS:
        assert (child / name).read_bytes() == (inline / name).read_bytes(), name
    assert _summary(child) == _summary(inline)
    # the UNIX time of each state is what the source had learnt by then: mirrored from the child
    with open(child / "trajectory.csv") as f:
        unix = [row["t_unix_s"] for row in csv.DictReader(f)]
    assert len(unix) > 1000 and all(unix[-500:])


def test_the_childs_warnings_are_logged_here_and_its_counts_reported(tmp_path, caplog):
    data = SESSION.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 7])  # the recording cut mid-frame
    with caplog.at_level(logging.WARNING, logger="adaptnav.service.transport.tlog_source"):
        _replay(cut, tmp_path / "child", "process")
    said = [r.getMessage() for r in caplog.records if r.name == "adaptnav.service.transport.tlog_source"]
    assert any("incomplete message" in text for text in said), said
    _replay(cut, tmp_path / "inline", "inline")
    child, inline = _summary(tmp_path / "child"), _summary(tmp_path / "inline")
    assert child["truncated"] and child == inline


def test_the_childs_exception_is_raised_here(tmp_path):
    log = tmp_path / "gone.tlog"
    log.write_bytes(SESSION.read_bytes())
    inp = open_log(log)
    inp.source.read_in_child = True
    log.unlink()  # gone before the child opens it
    with pytest.raises(FileNotFoundError, match="not found"):
        next(iter(inp.source))


@pytest.mark.timeout(120)  # (the old code waited for the reader for ever)
@pytest.mark.parametrize("parent_sigterm", ["default", "sets_an_event"])
def test_a_replay_that_stops_early_ends_its_reader(parent_sigterm):
    """Also when this process has a SIGTERM handler that only sets an event (``adaptnav
    record`` left one; a program that embeds the replay may have one): the forked reader
    inherited it, so ``terminate`` did not end it, and it waited on a full pipe whose other end
    it held itself: the replay's end never came (seen once in `make test` on a slow machine)."""
    previous = signal.getsignal(signal.SIGTERM)
    if parent_sigterm == "sets_an_event":
        stop = threading.Event()
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        inp = open_log(SESSION)
        inp.source.read_in_child = True
        items = iter(inp.source)
        first = [next(items) for _ in range(10)]
        assert all(hasattr(item, "KIND") for item in first)
        readers = [p for p in mp.active_children() if p.name == "adaptnav-log-reader"]
        assert len(readers) == 1
        items.close()  # the runner let go of the source (an exception, a stop)
        assert not readers[0].is_alive()
        assert not [p for p in mp.active_children() if p.name == "adaptnav-log-reader"]
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_where_a_log_is_read(tmp_path):
    small, big = tmp_path / "small.tlog", tmp_path / "big.tlog"
    small.write_bytes(b"\0" * (CHILD_MIN_BYTES - 1))
    big.write_bytes(b"\0" * CHILD_MIN_BYTES)
    assert wants_child(small, "process") and not wants_child(big, "inline")
    assert not wants_child(small, "auto")
    assert wants_child(big, "auto") == ((os.cpu_count() or 1) >= 2)
    assert not wants_child(tmp_path / "absent.tlog", "auto")
    with pytest.raises(ValueError, match="auto, process, inline"):
        wants_child(big, "thread")


def test_a_reader_that_dies_is_an_error_here_not_a_short_log():
    import signal

    inp = open_log(SESSION)
    inp.source.read_in_child = True
    items = iter(inp.source)
    next(items)
    (reader,) = [p for p in mp.active_children() if p.name == "adaptnav-log-reader"]
    os.kill(reader.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="log reader process ended without finishing"):
        for _ in items:  # what was handed over before it died, then the error
            pass


def test_a_blueos_recording_read_in_a_child_replays_to_the_same_bytes(tmp_path):
    from .mavlink_wire import write_blueos_mcap

    mcap = write_blueos_mcap(SESSION, tmp_path / "session.mcap")
    _replay(mcap, tmp_path / "inline", "inline")
    _replay(mcap, tmp_path / "child", "process")
    for name in OUTPUTS:
        assert (tmp_path / "child" / name).read_bytes() == (tmp_path / "inline" / name).read_bytes(), name
    assert _summary(tmp_path / "child") == _summary(tmp_path / "inline")


def test_a_damaged_log_s_warnings_are_said_once_either_way(tmp_path, caplog):
    """Opening a damaged DataFlash log says what its index lacks; the parent opens the log
    before the child does, and the child's words were logged here too: every warning twice.
    Read in a child, the warnings are those of the same log read here, once each."""
    import struct

    from pymavlink import DFReader

    src = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-drive.BIN"
    data = bytearray(src.read_bytes())
    index = DFReader.DFReader_binary(str(src), zero_time_base=False)
    fmt = index.name_to_id["FMT"]
    at = next(o for o in index.offsets[fmt] if data[o + 3] == index.name_to_id["XKV1"])
    data[at:at + index.formats[fmt].len] = bytes(index.formats[fmt].len)  # a format record lost
    imu = index.offsets[index.name_to_id["IMU"]]
    struct.pack_into("<H", data, imu[len(imu) // 3], 0)  # a record header zeroed
    damaged = tmp_path / "damaged.BIN"
    damaged.write_bytes(bytes(data))
    said = {}
    for reader in ("inline", "process"):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="adaptnav.service.transport.tlog_source"):
            _replay(damaged, tmp_path / reader, reader)
        said[reader] = [rec.getMessage() for rec in caplog.records
                        if rec.name == "adaptnav.service.transport.tlog_source"]
    assert any("index ends" in text for text in said["inline"])
    assert any("no record header" in text for text in said["inline"])
    assert sorted(said["process"]) == sorted(said["inline"])
