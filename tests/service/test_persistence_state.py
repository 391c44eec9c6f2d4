"""Persistence: atomic round trip; corrupt, truncated or foreign files are ignored."""
from __future__ import annotations

import json
import math
import os

import pytest

from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.runtime.persistence import FILENAME, load_state, save_state

SLOW = {"bias_acc_b_m_s2": [0.01, -0.02, 0.003], "var_bias_acc": [1e-6, 1e-6, 1e-6],
        "current_n_m_s": [0.1, -0.05], "var_current": [1e-3, 1e-3], "k_speed": 1.07,
        "var_k_speed": 1e-4, "nan_entry": math.nan}


def test_round_trip(tmp_path):
    params = MotionParams(var_vv=0.003, k_v=1.13, b_w=0.002)
    path = save_state(tmp_path / "state", 1234.5, params, SLOW, "auv7")
    assert path.exists() and not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]
    got = load_state(tmp_path / "state")
    assert got.params == params
    assert got.t_s == 1234.5
    assert got.slow_states["k_speed"] == 1.07
    assert got.slow_states["current_n_m_s"] == [0.1, -0.05]
    assert got.slow_states["nan_entry"] is None  # strict JSON on disk
    json.loads(path.read_text())  # parses as strict JSON


def test_absent_is_none(tmp_path):
    assert load_state(tmp_path) is None


def test_overwrite_keeps_one_file(tmp_path):
    save_state(tmp_path, 1.0, MotionParams(k_v=1.1), SLOW)
    save_state(tmp_path, 2.0, MotionParams(k_v=1.2), SLOW)
    assert load_state(tmp_path).params.k_v == 1.2
    assert sorted(os.listdir(tmp_path)) == [FILENAME]


@pytest.mark.parametrize("content", [
    b"", b"{\"schema_version\": 1, \"params\": {\"k_v\"", b"\x00\x01garbage", b"[]",
    b'{"schema_version": 99, "params": null, "slow_states": {}}',
    b'{"schema_version": 1, "t_s": 0, "params": {"k_v": -1.0}, "slow_states": {}}',
    b'{"schema_version": 1, "t_s": 0, "params": {"warp": 1.0}, "slow_states": {}}',
    b'{"schema_version": 1, "t_s": 0, "params": null, "slow_states": [1, 2]}',
])
def test_corrupt_file_ignored(tmp_path, content, caplog):
    (tmp_path / FILENAME).write_bytes(content)
    with caplog.at_level("WARNING"):
        assert load_state(tmp_path) is None
    assert "ignoring persisted state" in caplog.text
