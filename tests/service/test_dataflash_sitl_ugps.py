"""A real autopilot's DataFlash log with an underwater GPS: what a BlueROV2 with a Water Linked
UGPS and BlueOS writes, replayed deterministically with the defaults.

``tests/data/ardusub-4.7-sitl-ugps.BIN`` (ours, 2.2 MB) is the excerpt
(``python -m tests.sitl.bin_drive --excerpt``) of the log ArduSub V4.7.0-dev SITL
(``../shared/sitl``, ``--model vectored``, default ``LOG_BITMASK``) wrote during
``python -m tests.sitl.bin_drive OUT --ugps-hz 2``: the drive of ``ardusub-4.7-sitl-drive.BIN``
with ``GPS1_TYPE`` 14 and an underwater GPS on the companion
(:class:`tests.sitl.ardusub.UgpsDriver`: GPS_INPUT at 2 Hz from component 220, ``time_usec`` 0,
no GPS time, the truth's position with 1 m of noise per axis) in place of the simulated GPS.
ArduSub logs each fix as a GPS record — at any depth, with a 3D fix: an acoustic fix, which a
replay must not refuse as a radio GPS under water. The excerpt replays to the byte-identical
trajectory of the full log.

Before the autopilot's GPS type was read (``gps_raw_int_source = "auto"``), this log's fixes
were refused under water and it ended 9.95 % of its 140 m off (13.9 m).
"""
import json
from pathlib import Path

import pytest

from adaptnav.service.cli import main as cli_main

from ..fusion.freedrive import score

# its module fixtures' replays made once: its tests on one worker
pytestmark = pytest.mark.xdist_group("dataflash_sitl_ugps")

DRIVE = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-ugps.BIN"


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    out = tmp_path_factory.mktemp("bin_ugps")
    assert cli_main(["replay", str(DRIVE), "--out", str(out), "--no-progress", "--no-plots"]) == 0
    return json.loads((out / "summary.json").read_text()), out


def test_the_autopilot_s_mavlink_gps_is_taken_as_an_underwater_gps(replayed):
    summary, _ = replayed
    assert summary["gps_fixes"]["taken_as"] == "acoustic" and "14" in summary["gps_fixes"]["why"]
    gps = summary["message_types"]["GPS"]
    assert gps["status"] == "used" and gps["samples"] == gps["messages"] and gps["rate_hz"] == pytest.approx(2.0, rel=0.02)


def test_with_the_defaults_the_fixes_hold_the_solution_under_water(replayed):
    _, out = replayed
    s = score(out, DRIVE)
    assert s["distance_travelled_m"] > 130.0
    # the fixes' own noise is 1 m per axis: the solution stays within a few of them
    assert s["end_error_m"] <= 1.5 and s["max_error_submerged_m"] <= 2.5 and s["rms_error_submerged_m"] <= 1.0, s
    # σ from the fixes' HDOP (1.0) at the underwater GPS's 1 m per HDOP, as its GPS_INPUT would
    # give: about 1 % of the valid epochs beyond their 99 % ellipse is a consistent filter
    assert s["valid_fraction_submerged"] >= 0.95 and s["valid_outside_99_fraction"] <= 0.03, s
