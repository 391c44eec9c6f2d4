"""BlueOS's own MCAP recordings of the vehicle's MAVLink replay as the same messages in a tlog do.

No BlueOS recording is public; these are made from real telemetry (the SITL session tlog with
its truth, the real BlueROV2 UGPS tlog) in the form BlueOS's mavlink-server publishes and
records (mavlink2rest's JSON on ``mavlink/out`` or ``mavlink/<sys>/<comp>/<TYPE>``; the layout
the public BlueOS tools read, :mod:`adaptnav.service.transport.blueos_mcap`).
"""
import csv
import json
from pathlib import Path

import pytest

from adaptnav.service.cli import main as cli_main

from .mavlink_wire import write_blueos_mcap

DATA = Path(__file__).resolve().parents[1] / "data"
SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mavlink"


def _replay(path, out):
    assert cli_main(["replay", str(path), "--out", str(out), "--no-progress", "--no-plots"]) == 0
    return json.loads((out / "summary.json").read_text()), (out / "trajectory.csv").read_bytes()


@pytest.fixture(scope="module")
def session_tlog_replayed(tmp_path_factory):
    """The session's tlog replayed (summary, trajectory.csv's bytes): what each recording of it
    must give, replayed once."""
    return _replay(DATA / "ardusub-sitl-session.tlog", tmp_path_factory.mktemp("session_tlog"))


@pytest.mark.xdist_group("blueos_session")  # (the tlog's replay made once: these on one worker)
@pytest.mark.parametrize("per_type_topics, bitmask_text", [(False, False), (True, False), (False, True)])
def test_a_blueos_recording_replays_to_the_tlog_s_solution(tmp_path, session_tlog_replayed, per_type_topics,
                                                           bitmask_text):
    """Also with the bitmasks as newer mavlink2rest writes them (text: HIGHRES_IMU's
    ``fields_updated`` says which of its fields are fresh)."""
    mcap = write_blueos_mcap(DATA / "ardusub-sitl-session.tlog", tmp_path / "session.mcap",
                             per_type_topics=per_type_topics, bitmask_text=bitmask_text)
    s_tlog, traj_tlog = session_tlog_replayed
    s_mcap, traj_mcap = _replay(mcap, tmp_path / "mcap")
    assert traj_mcap == traj_tlog  # every row, every digit
    assert s_mcap["messages_read"] == s_tlog["messages_read"] and s_mcap["corrupt_frames"] == 0
    assert s_mcap["message_types"] == s_tlog["message_types"]
    # the truth (SIM_STATE) is placed at its reception: the log time in integer ns, not the tlog's µs float
    assert s_mcap["metrics"]["final_horizontal_error_m"] == pytest.approx(s_tlog["metrics"]["final_horizontal_error_m"],
                                                                          rel=1e-9)


def test_without_the_extension_fields_blueos_1_4_left_out_it_still_navigates(tmp_path):
    """BlueOS 1.4's recordings lack MAVLink 2 extension fields (mavlink-server#213): they take
    their defaults (GPS_RAW_INT without h_acc: σ from HDOP)."""
    path = SHARED / "ardusub-4.1.1-bluerov2-ugps.tlog"
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    mcap = write_blueos_mcap(path, tmp_path / "ugps.mcap", drop_extensions=True)
    s_tlog, _ = _replay(path, tmp_path / "tlog")
    s_mcap, _ = _replay(mcap, tmp_path / "mcap")
    assert s_mcap["message_types"]["GPS_INPUT"]["samples"] == s_tlog["message_types"]["GPS_INPUT"]["samples"] > 140
    assert s_mcap["valid_fraction"] == pytest.approx(s_tlog["valid_fraction"], abs=0.01) and s_mcap["valid_fraction"] > 0.99
    rows = list(csv.DictReader(open(tmp_path / "mcap" / "trajectory.csv")))
    ref = list(csv.DictReader(open(tmp_path / "tlog" / "trajectory.csv")))
    assert abs(float(rows[-1]["north_m"]) - float(ref[-1]["north_m"])) < 0.5


def test_a_record_that_is_not_mavlink_json_is_counted_and_skipped(tmp_path):
    from mcap.writer import Writer

    out = tmp_path / "bad.mcap"
    good = {"header": {"system_id": 1, "component_id": 1, "sequence": 0},
            "message": {"type": "ATTITUDE", "time_boot_ms": 1000, "roll": 0.1, "pitch": 0.0, "yaw": 0.2,
                        "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0}}
    with open(out, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel(topic="mavlink/out", message_encoding="json", schema_id=0)
        for i, data in enumerate([json.dumps(good).encode(), b"{not json", json.dumps({"message": {}}).encode(),
                                  json.dumps({**good, "message": {"type": "ATTITUDE", "roll": 0.1}}).encode(),
                                  json.dumps({**good, "message": {"type": "NOT_A_MAVLINK_TYPE"}}).encode()]):
            w.add_message(ch, log_time=(1_700_000_000 + i) * 10**9, data=data, publish_time=0)
        w.finish()
    s, _ = _replay(out, tmp_path / "r")
    assert s["corrupt_frames"] == 3  # not JSON, no type, a base field missing
    assert s["message_types"]["ATTITUDE"]["messages"] == 1
    assert s["message_types"]["NOT_A_MAVLINK_TYPE"]["status"] == "unknown"


def test_a_recording_cut_off_replays_what_it_holds_and_says_so(tmp_path):
    """BlueOS writes while armed: a power loss, or a download of the open file, leaves an MCAP
    without its summary — recognised by its first records, read up to the cut."""
    tlog = DATA / "ardusub-sitl-session.tlog"
    whole = write_blueos_mcap(tlog, tmp_path / "whole.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole[: len(whole) // 2])
    s, traj = _replay(cut, tmp_path / "r")
    assert "ends early" in s["truncated"] and s["corrupt_frames"] == 1
    s_whole, traj_whole = _replay(tmp_path / "whole.mcap", tmp_path / "w")
    assert 0.3 * s_whole["messages_read"] < s["messages_read"] < 0.7 * s_whole["messages_read"]
    rows, rows_whole = traj.splitlines(), traj_whole.splitlines()
    # the same solution up to the cut (the last rows' truth columns wait for truth after the cut)
    keep = int(0.9 * len(rows))
    assert len(rows) > 100 and rows[:keep] == rows_whole[:keep]


def test_a_bitmask_as_text_keeps_the_bits_no_flag_names(tmp_path):
    """rust-mavlink's bitflags 2 write the bits their dialect has no name for as one hex number
    (``"A | B | 0x100"``): those bits are kept, not the record lost; a flag name our dialect
    lacks cannot be turned into bits, so that record is counted malformed, never guessed at."""
    from mcap.writer import Writer

    from adaptnav.service.transport.blueos_mcap import BlueOsMcapReader, MalformedMessage

    fix = {"time_usec": 0, "gps_id": 0, "time_week_ms": 0, "time_week": 0, "fix_type": 3, "lat": 473977420,
           "lon": 85455940, "alt": -2.0, "hdop": 1.5, "vdop": 1.0, "vn": 0.0, "ve": 0.0, "vd": 0.0,
           "speed_accuracy": 0.0, "horiz_accuracy": 1.2, "vert_accuracy": 0.0, "satellites_visible": 8}
    flags = ["GPS_INPUT_IGNORE_FLAG_VEL_HORIZ | GPS_INPUT_IGNORE_FLAG_VEL_VERT | 0x100", "",
             "GPS_INPUT_IGNORE_FLAG_ALT|24", "GPS_INPUT_IGNORE_FLAG_FROM_THE_FUTURE | GPS_INPUT_IGNORE_FLAG_ALT"]
    out = tmp_path / "flags.mcap"
    with open(out, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel(topic="mavlink/out", message_encoding="json", schema_id=0)
        for i, text in enumerate(flags):
            doc = {"header": {"system_id": 1, "component_id": 220, "sequence": i},
                   "message": {"type": "GPS_INPUT", "ignore_flags": text, **fix}}
            w.add_message(ch, log_time=(i + 1) * 10**9, data=json.dumps(doc).encode(), publish_time=(i + 1) * 10**9)
        w.finish()
    got = list(BlueOsMcapReader(out))
    assert [m.ignore_flags for m in got[:3]] == [8 | 16 | 0x100, 0, 1 | 24]
    assert got[0].horiz_accuracy == pytest.approx(1.2) and got[0].get_srcComponent() == 220
    assert isinstance(got[3], MalformedMessage) and "GPS_INPUT_IGNORE_FLAG_FROM_THE_FUTURE" in str(got[3])
