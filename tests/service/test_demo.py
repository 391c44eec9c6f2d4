"""`adaptnav demo`, shortened, end to end through the real path: simulated ArduSub
vehicle → UDP MAVLink → bridge, side-scan pings on a second Zenoh session → daemon with
its calibrator process → nav states on Zenoh and ODOMETRY back to the vehicle."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[2]
# 5 s of data after the last USBL fix (at 180 s): a fix in the data's last sample reached the
# daemon's count or not as the machine's load had it (2 of 3 once in a fresh clone's make test)
DURATION_S = 185


def _children(pid: int) -> set[int]:
    """Child processes, except multiprocessing's resource tracker (one per interpreter,
    started with the first spawn context and ending with the interpreter, by design)."""
    out = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and "resource_tracker" not in cmd:
            out.add(int(entry.name))
    return out


def test_short_demo_end_to_end_json(tmp_path):
    from adaptnav.service.tools.demo import run_demo

    before = _children(os.getpid())
    # 3 min with the change at 60 s: USBL fixes at 60, 120, 180 s, side-scan throughout
    summary = run_demo([f"duration_s={DURATION_S}", "environment.change_at_s=60"], tmp_path / "out", speed=30.0,
                       progress=False, plots=True)
    rows = {k: summary[k] for k in ("pure_ins", "static", "learned")}
    for name, r in rows.items():
        for key in ("final_error_m", "rms_error_m", "percent_dt"):
            assert r[key] is not None and math.isfinite(r[key]), (name, key, r)
    learned = rows["learned"]
    # the live path delivers every nav epoch (10 Hz of data time) over Zenoh: the first
    # seconds are alignment (levelling, and the autopilot's ATTITUDE yaw must settle for
    # filter.alignment.yaw_settle_s), nothing else may be missing — the daemon holds samples that
    # overtake the IMU across transports (side-scan pings on Zenoh vs MAVLink) so the
    # runner sees data order, and nothing is dropped on the way
    assert learned["nav_states_received"] >= DURATION_S * 10 - 30
    assert learned["nav_epochs"]["received"] == learned["nav_states_received"]  # no duplicates
    assert learned["nav_epochs"]["published"] == learned["nav_states_received"]  # Zenoh lost none
    assert learned["reordered_at_daemon"].get("held", 0) > 0  # pings did overtake: the case is exercised
    assert learned["mavlink_at_daemon"]["packets_lost"] == 0
    assert "queue_overflow" not in learned["rejected_at_daemon"]
    # ODOMETRY back over MAVLink at the bridge's 10 Hz (quality-0 states during alignment are not sent)
    assert learned["odometry_received_by_vehicle"] >= DURATION_S * 10 - 30  # alignment: see above
    assert learned["sonar_pings_published"] >= DURATION_S * 4
    # every ping published by the sonar driver's session reached the daemon (and from
    # there the calibrator, whose front end turns them into landmark sightings)
    assert learned["samples_at_daemon"]["sonar"] == learned["sonar_pings_published"]
    assert learned["samples_at_daemon"]["usbl"] >= 3
    # the calibrator process keeps up: samples are batched across the process boundary
    # (dropped ones would be counted here, never lost silently)
    assert learned["calibrator_dropped_samples"] == 0
    # what came back after its due time is reported (how much depends on the machine's pace)
    assert set(learned["calibrator_late"]) == {"releases", "products", "max_s"}
    # error at the end of each USBL gap after the change (fixes at 120 and 180 s)
    for name, r in rows.items():
        assert r["gaps"] == 2 and math.isfinite(r["gap_end_error_m"]), (name, r)
    assert rows["pure_ins"]["gap_end_error_m"] > rows["static"]["gap_end_error_m"]
    # velocity aiding beats pure INS between fixes, for the static and the learned model
    assert rows["pure_ins"]["rms_error_m"] > 2.0 * rows["static"]["rms_error_m"]
    assert rows["pure_ins"]["rms_error_m"] > 2.0 * learned["rms_error_m"]
    assert {"demo_track.png", "demo_error.png", "demo_params.png"} <= {p.name for p in (tmp_path / "out").iterdir()}
    json.loads((tmp_path / "out" / "demo_summary.json").read_text())
    # clean shutdown: no calibrator child (or any other) left behind
    assert _children(os.getpid()) <= before


def test_cli_rejects_bad_scenario_key(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "adaptnav.service.cli", "demo", "--json", "--no-progress",
                           "--out", str(tmp_path), "--set", "no_such_key=1"],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert proc.returncode == 2
    assert "no_such_key" in proc.stderr and proc.stdout == ""
