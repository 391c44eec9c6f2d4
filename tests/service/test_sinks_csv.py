"""The replay's CSV sinks write rows directly (not through csv.writer, issue 17's replay
cost): what they write must still be what a CSV reader reads back field for field, free
text with commas, quotes and line breaks included."""
from __future__ import annotations

import csv
import math

from adaptnav.fusion.status import AidStatus
from adaptnav.service.runtime.sinks import AidStatusCsvSink


def test_aid_status_rows_read_back_field_for_field_whatever_the_reason_text(tmp_path):
    statuses = [
        AidStatus(1.25, "dvl", (0.5, -0.25, 1e-7), (0.01, -0.02, 0.0), (1e-4, 1e-4, 2e-4), 0.3, True, ""),
        AidStatus(2.5, "usbl", (10.0, -3.0), (), (), math.nan, False, 'gate, "outlier"\nsecond line'),
        AidStatus(3.0, "odd,source", (1.0,), (0.1,), (0.01,), 2.0, False, "gate"),
    ]
    path = tmp_path / "aid_status.csv"
    sink = AidStatusCsvSink(path)
    sink.on_aid(statuses)
    sink.close()
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == list(AidStatusCsvSink.COLUMNS)
    assert len(rows) == 1 + len(statuses)
    for s, row in zip(statuses, rows[1:]):
        assert row[1] == s.source and row[2] == ("1" if s.fused else "0") and row[3] == s.reason
        assert float(row[0]) == s.t_s
        assert [float(v) for v in row[5].split(";") if v] == list(s.observation)
        assert [float(v) for v in row[6].split(";") if v] == list(s.innovation)
        assert (math.isnan(s.test_ratio) and row[4] == "nan") or float(row[4]) == s.test_ratio
