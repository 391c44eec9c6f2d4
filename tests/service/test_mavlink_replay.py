"""`adaptnav replay` of MAVLink logs: one exit rule for every reader, loud warnings, every
message type accounted for, and the clock/geodetic columns of trajectory.csv."""
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from adaptnav.service.cli import main as cli_main

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mavlink"
REAL_LOGS = ("ardusub-4.1.0-corrupt-frames.tlog", "ardusub-4.1.0-small.BIN", "ardusub-4.1.1-bluerov2-ugps.tlog",
             "ardusub-4.1.2-bench.tlog", "ardusub-sitl-freedrive.tlog")


def replay(path, out, *extra):
    return cli_main(["replay", str(path), "--out", str(out), "--no-progress", "--no-plots", *extra])


@pytest.mark.realdata
@pytest.mark.parametrize("name", REAL_LOGS)
def test_every_real_log_exits_0_and_says_when_it_produced_no_valid_position(name, tmp_path, capsys):
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    assert replay(path, tmp_path / "out") == 0  # something usable was read: never non-zero
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    err = capsys.readouterr().err
    rows = list(csv.DictReader(open(tmp_path / "out" / "trajectory.csv")))
    n_valid = sum(r["valid"] == "1" for r in rows)
    assert summary["valid_fraction"] == pytest.approx(n_valid / len(rows))
    if n_valid == 0:
        assert any("NO VALID POSITION" in w for w in summary["warnings"])
        assert "WARNING: NO VALID POSITION" in err
    else:
        assert not any("NO VALID POSITION" in w for w in summary["warnings"])
    # an attitude-driven track nothing measured says why, and what would make it a solution
    # (the bench and corrupt-frames logs: RAW_IMU at 2 Hz, no fix, the embedded thrust table)
    if "no_motion_measurement" in summary["filter"]["invalid_reasons_at_end"]:
        assert summary["filter"]["imu_grade"] == "attitude"
        assert any("vehicle profile" in w for w in summary["warnings"]) and "vehicle profile" in err
    # every message type read is accounted for: used, rejected, ignored with a why, or unknown
    types = summary["message_types"]
    assert sum(t["messages"] for t in types.values()) == summary["messages_read"]
    assert all(t["status"] in ("used", "rejected", "ignored", "unknown") for t in types.values())
    assert all(t.get("why") for t in types.values() if t["status"] != "used")
    assert summary["unknown_message_types"] == sorted(k for k, t in types.items() if t["status"] == "unknown")
    if name.endswith(".tlog"):
        # the tlog's receive stamps are a wall-clock reference: every row carries UNIX time
        assert summary["clock"]["unix_offset_s"] is not None
        assert all(r["t_unix_s"] for r in rows)
        # (the offset follows the receive clock over a sliding window: ms, not more, over a log)
        assert abs(float(rows[0]["t_unix_s"]) - float(rows[0]["t_s"]) - summary["clock"]["unix_offset_s"]) < 0.05
    if summary["origin"]["from"].startswith("first"):
        lat0 = summary["origin"]["lat_deg"]
        assert all(r["lat_deg"] for r in rows)
        # lat/lon are the NED position around the origin (1 m ≈ 9e-6 °)
        r = rows[len(rows) // 2]
        assert float(r["lat_deg"]) - lat0 == pytest.approx(float(r["north_m"]) / 111_200.0, rel=5e-3, abs=2e-7)


@pytest.mark.parametrize("content", [b"", b"\x00" * 5000, bytes(range(256)) * 40])
def test_nothing_usable_exits_1_with_the_reason(content, tmp_path, capsys):
    p = tmp_path / "broken.tlog"
    p.write_bytes(content)
    assert replay(p, tmp_path / "out") == 1
    err = capsys.readouterr().err
    assert "WARNING: nothing could be read" in err or "WARNING: no usable sample" in err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["warnings"]


def test_missing_log_exits_1(tmp_path, capsys):
    assert replay(tmp_path / "absent.tlog", tmp_path / "out") == 1
    assert "not found" in capsys.readouterr().err


def test_a_fix_only_log_without_an_imu_is_usable_but_not_valid(tmp_path, capsys):
    """A log that has samples but can never give a position exits 0, loudly."""
    import struct

    from adaptnav.service.transport.mavlink_convert import mavlink2

    mav = mavlink2.MAVLink(None, 1, 1)
    frames = [mav.heartbeat_encode(mavlink2.MAV_TYPE_SUBMARINE, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)]
    frames += [mav.scaled_pressure2_encode(1000 + 100 * k, 1100.0 + 0.01 * k, 0.0, 1500) for k in range(50)]
    p = tmp_path / "depth_only.tlog"
    with open(p, "wb") as f:
        for k, m in enumerate(frames):
            f.write(struct.pack(">Q", 1_760_000_000_000_000 + k * 100_000) + bytes(m.pack(mav)))
    assert replay(p, tmp_path / "out") == 0
    assert "WARNING: NO VALID POSITION" in capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["samples_used"] == 50 and not summary["valid_fraction"]
    assert math.isfinite(summary["clock"]["unix_offset_s"])


def test_a_mavlink1_tlog_replays_as_its_mavlink2_twin(tmp_path):
    """An older autopilot or ground station frames MAVLink 1: no extension fields — SIM_STATE
    without ``lat_int``/``lon_int``, whose float ``lat``/``lon`` ArduPilot fills with degE7
    (read as degrees, the truth was 35 million degrees off; now scaled, to a float32's ~2 m)."""
    from .mavlink_wire import as_mavlink1

    session = Path(__file__).resolve().parents[1] / "data" / "ardusub-sitl-session.tlog"
    v1 = as_mavlink1(session, tmp_path / "v1.tlog")
    out = {}
    for name, path in (("v2", session), ("v1", v1)):
        assert cli_main(["replay", str(path), "--out", str(tmp_path / name), "--no-progress", "--no-plots"]) == 0
        out[name] = json.loads((tmp_path / name / "summary.json").read_text())
    traj = [np.loadtxt(tmp_path / n / "trajectory.csv", delimiter=",", skiprows=1, usecols=range(16)) for n in ("v2", "v1")]
    np.testing.assert_array_equal(traj[0], traj[1])
    assert "truth_invalid" not in out["v1"]["rejected_samples"]
    assert out["v1"]["metrics"]["final_horizontal_error_m"] == pytest.approx(
        out["v2"]["metrics"]["final_horizontal_error_m"], abs=2.5)


def test_the_water_sensor_is_the_barometer_arduSub_made_primary(tmp_path):
    """On a board with two barometers of its own the Bar30 is ArduSub's third (SCALED_PRESSURE3);
    ArduSub picks the first water-type sensor as primary and saves BARO_PRIMARY. Read from the
    log's PARAM_VALUE, the depth is that sensor's: the replay is the original's, row for row.
    Without the parameter the second sensor (the enclosure's air) is taken, as before."""
    from .mavlink_wire import water_sensor_on_third_baro

    session = Path(__file__).resolve().parents[1] / "data" / "ardusub-sitl-session.tlog"
    out = {}
    for name, path in (("original", session),
                       ("third", water_sensor_on_third_baro(session, tmp_path / "third.tlog")),
                       ("unsaid", water_sensor_on_third_baro(session, tmp_path / "unsaid.tlog", say_baro_primary=False))):
        assert cli_main(["replay", str(path), "--out", str(tmp_path / name), "--no-progress", "--no-plots"]) == 0
        out[name] = (json.loads((tmp_path / name / "summary.json").read_text()),
                     np.loadtxt(tmp_path / name / "trajectory.csv", delimiter=",", skiprows=1, usecols=range(16)))
    np.testing.assert_array_equal(out["third"][1], out["original"][1])
    assert out["third"][0]["message_types"]["SCALED_PRESSURE3"]["status"] == "used"
    assert out["third"][0]["message_types"]["SCALED_PRESSURE2"]["status"] != "used"
    depth_unsaid = out["unsaid"][1][:, 3]
    assert np.nanmax(depth_unsaid) < 1.0 < np.nanmax(out["original"][1][:, 3])  # the air: no dive
