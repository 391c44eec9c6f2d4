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
        # a row's format is cached per source and reason: a '%' in them is text, not a conversion
        AidStatus(4.0, "dvl", (0.5, -0.25, 1e-7), (0.01, -0.02, 0.0), (1e-4, 1e-4, 2e-4), 1.5, False, "100% off"),
        AidStatus(4.5, "dvl", (0.25, 0.75, 2e-7), (0.02, -0.01, 0.5), (2e-4, 1e-4, 3e-4), 0.5, True, ""),
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


def test_series_recorder_track_holds_every_state_past_its_first_arrays():
    import numpy as np

    from adaptnav.fusion.state import NavState
    from adaptnav.service.runtime.sinks import SeriesRecorder

    rec = SeriesRecorder(aid_rows=False)
    n = 1500  # past the first 600 rows: the arrays grow twice
    for k in range(n):
        cov = np.diag(np.arange(1.0, 19.0)) * (1.0 + k)
        rec.on_nav(NavState(t_s=0.1 * k, pos_n_m=np.array([k, -k, 0.5 * k], dtype=float),
                            vel_n_m_s=np.array([1.0, 2.0, 3.0]) * k, q_nb=np.array([1.0, 0.0, 0.0, 0.0]),
                            bias_acc_b_m_s2=np.zeros(3), bias_gyro_b_rad_s=np.zeros(3),
                            current_n_m_s=np.array([0.1, -0.2]) * k, k_speed=1.0 + k, cov=cov, valid=True,
                            reset_counter=0))
    track = rec.track()
    k = np.arange(n, dtype=float)
    assert np.array_equal(track.t_s, 0.1 * k)
    assert np.array_equal(track.pos_n_m, np.stack([k, -k, 0.5 * k], axis=1))
    assert np.array_equal(track.vel_n_m_s, np.array([1.0, 2.0, 3.0]) * k[:, None])
    assert np.array_equal(track.current_n_m_s, np.array([0.1, -0.2]) * k[:, None])
    assert np.array_equal(track.cov_pva, np.diag(np.arange(1.0, 10.0))[None] * (1.0 + k)[:, None, None])
    assert track.q_nb.shape == (n, 4) and np.all(track.q_nb[:, 0] == 1.0)
