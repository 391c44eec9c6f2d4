"""DataFlash logs as text (``.log``): what Mission Planner's "convert .bin to .log" writes and
what users often share instead of the ``.BIN``. pymavlink reads both; a text log must replay
as its ``.BIN`` does, say where it was cut off, and lose only the lines that are damaged
(pymavlink's text reader gives up on the whole file at one line of garbage).

Before: the replay of any text log ended in a traceback (DFReader's index of a text log is a
dict, the ``.BIN``'s a list); a ``.log`` without format lines was read as telemetry with the
DataFlash call and failed in one place for ever.
"""
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from adaptnav.service.cli import main as cli_main

from .dataflash_log import text_log_from_bin

# its module fixtures' replays made once: its tests on one worker
pytestmark = pytest.mark.xdist_group("dataflash_text")

DRIVE = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-dvl.BIN"


def _replay(path: Path, out: Path) -> tuple[int, dict, list[list[str]]]:
    code = cli_main(["replay", str(path), "--out", str(out), "--no-progress", "--no-plots"])
    summary = json.loads((out / "summary.json").read_text())
    rows = list(csv.reader(open(out / "trajectory.csv")))
    return code, summary, rows


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("text_log")
    text = text_log_from_bin(DRIVE, tmp / "drive.log")
    return tmp, text, _replay(DRIVE, tmp / "bin"), _replay(text, tmp / "text")


def test_a_text_log_replays_as_its_bin(logs):
    tmp, _, (code_bin, s_bin, rows_bin), (code_text, s_text, rows_text) = logs
    assert code_bin == code_text == 0
    assert rows_text == rows_bin and len(rows_bin) > 1000
    assert (tmp / "text" / "aid_status.csv").read_bytes() == (tmp / "bin" / "aid_status.csv").read_bytes()
    assert s_text["message_types"]["VISO"]["status"] == "used"
    assert s_text["message_types"] == s_bin["message_types"]
    assert s_text["corrupt_frames"] == 0 and not s_text.get("truncated")


def test_a_text_log_cut_off_inside_a_line_says_so_and_keeps_the_rest(logs):
    tmp, text, (_, _, rows_whole), _ = logs
    data = text.read_bytes()
    cut = tmp / "cut.log"
    cut.write_bytes(data[: int(0.6 * len(data))])
    assert not cut.read_bytes().endswith(b"\n")
    code, summary, rows = _replay(cut, tmp / "cut")
    assert code == 0
    assert "cut.log ends inside a line" in summary["truncated"] and summary["corrupt_frames"] == 1
    t_end = float(rows[-1][0])
    before = [r for r in rows_whole[1:] if float(r[0]) < t_end - 2.0]
    assert len(before) > 500 and rows[1:len(before) + 1] == before


def test_damaged_lines_in_a_text_log_are_counted_and_the_rest_is_read(logs):
    tmp, text, (_, _, rows_whole), _ = logs
    lines = text.read_bytes().split(b"\r\n")
    k = len(lines) // 2
    damaged = lines[:k] + [b"\xa3\x95\x80\xff garbage", b"IMU, 12, not-a-number"] + lines[k:]
    path = tmp / "damaged.log"
    path.write_bytes(b"\r\n".join(damaged))
    code, summary, rows = _replay(path, tmp / "damaged")
    assert code == 0
    assert summary["corrupt_frames"] == 2, summary["corrupt_frames"]
    # only those two lines are lost: the trajectory is the whole log's
    end = np.array([float(x) for x in rows[-1][1:3]])
    end_whole = np.array([float(x) for x in rows_whole[-1][1:3]])
    assert rows[0] == rows_whole[0] and len(rows) == len(rows_whole)
    assert np.linalg.norm(end - end_whole) < 0.05


def test_a_block_of_zeros_inside_a_text_log_is_counted_not_read_as_records(logs):
    """A card's or a copy's block of zeros across line ends: pymavlink's text reader skipped
    what became a line without fields and read the line the zeros merged as one record of
    the first line's name with the fields of both, without a word."""
    tmp, text, (_, _, rows_whole), _ = logs
    data = bytearray(text.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 300] = bytes(300)
    path = tmp / "zeros.log"
    path.write_bytes(bytes(data))
    code, summary, rows = _replay(path, tmp / "zeros")
    assert code == 0
    # the lines the block touched, each counted; no others
    touched = bytes(data[:middle]).rsplit(b"\n", 1)[-1] + bytes(data[middle:middle + 300])
    assert 1 <= summary["corrupt_frames"] <= touched.count(b"\n") + 2 and not summary.get("truncated")
    end = np.array([float(x) for x in rows[-1][1:3]])
    end_whole = np.array([float(x) for x in rows_whole[-1][1:3]])
    assert len(rows) == len(rows_whole) and np.linalg.norm(end - end_whole) < 0.05


def test_an_upper_case_log_name_is_a_text_log_too(logs):
    """``FILE.LOG`` (a Windows copy): pymavlink takes only ``.log`` for a text DataFlash log and
    read this one as telemetry — nothing replayed."""
    tmp, text, (_, _, rows_bin), _ = logs
    upper = tmp / "DRIVE.LOG"
    upper.write_bytes(text.read_bytes())
    code, summary, rows = _replay(upper, tmp / "upper")
    assert code == 0 and rows == rows_bin and summary["corrupt_frames"] == 0
