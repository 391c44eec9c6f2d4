"""A real ArduSub (SITL) writes its DataFlash log while a pilot drives it; the log is replayed.

The autopilot runs with its own defaults (``LOG_BITMASK`` of ``sub.parm``: IMU at 25 Hz, ATT at
10 Hz) as a user's vehicle, no navigation daemon: :mod:`tests.sitl.bin_drive` arms, dives, drives
lanes and turns, surfaces, disarms, and keeps the ``.BIN``.  ``adaptnav replay`` then runs it
with the project's defaults and with the vehicle's profile; each is scored against the
simulator's truth in the log (``SIM`` records) by :func:`tests.fusion.freedrive.score`.

Figures go to ``$ADAPTNAV_SITL_OUT/bin/report.json`` (with the log and the ground station's
tlog of the same run); the asserts come last.  The recorded excerpt in ``tests/data``
(``test_dataflash_sitl_drive.py``) is a run of this drive.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from adaptnav.service.cli import main as cli_main

from ..fusion.freedrive import score
from .bin_drive import record

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(1800)]

PROFILE = Path(__file__).resolve().parents[2] / "deploy" / "vehicles" / "bluerov2-sitl.toml"


def test_a_moving_ardusub_s_dataflash_log_replays_and_navigates(tmp_path):
    out = Path(os.environ.get("ADAPTNAV_SITL_OUT", tmp_path)) / "bin"
    log = record(out)
    report: dict = {"log_bytes": log.stat().st_size}
    try:
        for name, config in (("defaults", []), ("profile", ["--config", str(PROFILE)])):
            d = out / f"replay-{name}"
            rc = cli_main(["replay", str(log), *config, "--out", str(d), "--no-progress", "--no-plots"])
            summary = json.loads((d / "summary.json").read_text())
            report[name] = {"exit_code": rc, **{k: round(v, 3) for k, v in score(d, log).items()},
                            "imu_grade": summary["filter"]["imu_grade"],
                            "unknown_message_types": summary["unknown_message_types"],
                            "unix_reference": summary["clock"]["unix_reference"]}
    finally:
        (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        print(json.dumps(report, indent=2))

    for name in ("defaults", "profile"):
        r = report[name]
        assert r["exit_code"] == 0 and r["unknown_message_types"] == [] and r["unix_reference"] == "GPS", r
        assert r["distance_travelled_m"] > 100.0 and r["max_error_submerged_m"] <= 15.0, r
    assert report["defaults"]["end_error_percent"] <= 5.0, report
    assert report["profile"]["end_error_percent"] <= 5.0 and report["profile"]["valid_fraction_submerged"] > 0.9, report
