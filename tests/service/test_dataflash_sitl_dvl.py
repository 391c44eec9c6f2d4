"""A real autopilot's DataFlash log with a DVL: what a BlueROV2 with a Water Linked DVL and
BlueOS writes, replayed deterministically with the defaults.

``tests/data/ardusub-4.7-sitl-dvl.BIN`` (ours, 2.3 MB) is the excerpt
(``python -m tests.sitl.bin_drive --excerpt``) of the log ArduSub V4.7.0-dev SITL
(``../shared/sitl``, ``--model vectored``, default ``LOG_BITMASK``) wrote during
``python -m tests.sitl.bin_drive OUT --dvl-hz 5``: the drive of ``ardusub-4.7-sitl-drive.BIN``
(arm at the surface, dive to 5 m, four 60 s lanes and three turns under depth hold, 20 s
sideways, surface) with ``VISO_TYPE`` 1 and a DVL driver on the companion
(:class:`tests.sitl.ardusub.DvlDriver`: VISION_POSITION_DELTA at 5 Hz from component 197,
``time_usec`` 0, the truth's body velocity with a 0.3 % scale error and 1 cm/s noise).
ArduSub logs each delta it receives as a VISO record (rotated by ``VISO_ORIENT``, stamped on
arrival): 4.6 Hz of them here (the driver starts when the autopilot's port first speaks).
The excerpt replays to the byte-identical trajectory of the full 15.7 MB log.

Before VISO was read (``service/transport/dataflash.py``), this log ended 3.72 % of its 140 m
off (5.2 m, max 5.2 m): the DVL a user's log carries was ignored as an unknown record.
"""
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from adaptnav.service.cli import main as cli_main

from ..fusion.freedrive import score

from pymavlink import mavutil

# its module fixtures' replays made once: its tests on one worker
pytestmark = pytest.mark.xdist_group("dataflash_sitl_dvl")

DRIVE = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-dvl.BIN"


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    out = tmp_path_factory.mktemp("bin_dvl")
    assert cli_main(["replay", str(DRIVE), "--out", str(out), "--no-progress", "--no-plots"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    aids = list(csv.DictReader(open(out / "aid_status.csv")))
    return summary, aids, out


def test_the_dvl_the_autopilot_logged_is_used(replayed):
    summary, aids, _ = replayed
    viso = summary["message_types"]["VISO"]
    assert viso["status"] == "used" and viso["rate_hz"] == pytest.approx(4.6, rel=0.05), viso
    assert viso["samples"] == viso["messages"]
    assert summary["unknown_message_types"] == []
    dvl = [a for a in aids if a["source"] == "dvl"]
    accepted = sum(a["fused"] == "1" for a in dvl)
    assert len(dvl) >= 0.95 * viso["samples"] and accepted >= 0.9 * len(dvl), (len(dvl), accepted)


def test_the_dvl_samples_are_the_truth_s_body_velocity_at_their_time():
    """The conversion's frame, units and time: each DVL sample read from the log against the
    simulator's truth (SIM attitude, SIM2 NED velocity, straight from the file) rotated into
    the body frame at the sample's time."""
    from adaptnav.fusion.frames import quat_to_dcm
    from adaptnav.service.transport.tlog_source import TlogSource

    dvl = [s for s in TlogSource(DRIVE) if s.KIND == "dvl"]
    log = mavutil.mavlink_connection(str(DRIVE))
    sim, sim2 = [], []
    while (m := log.recv_match(type=["SIM", "SIM2"])) is not None:
        (sim if m.get_type() == "SIM" else sim2).append(m)
    # the replay's clock is the boot clock from the log's first record: compare on TimeUS
    t0_s = min(m.TimeUS for m in sim) / 1e6 - min(s.t_s for s in TlogSource(DRIVE) if s.KIND == "truth")
    t_s = np.array([m.TimeUS / 1e6 for m in sim]) - t0_s
    q = np.array([[m.Q1, m.Q2, m.Q3, m.Q4] for m in sim])
    t_2 = np.array([m.TimeUS / 1e6 for m in sim2]) - t0_s
    v_n = np.array([[m.VN, m.VE, m.VD] for m in sim2])
    err, speed = [], []
    for d in dvl:
        i = min(np.searchsorted(t_s, d.t_s), len(t_s) - 1)
        vn = np.array([np.interp(d.t_s, t_2, v_n[:, k]) for k in range(3)])
        err.append(np.asarray(d.vel_d_m_s) - quat_to_dcm(q[i]).T @ vn)
        speed.append(np.linalg.norm(vn))
    err, moving = np.array(err), np.array(speed) > 0.2
    assert len(dvl) > 1500 and moving.sum() > 600
    # the driver's noise (1 cm/s), its 0.3 % scale and the age of the truth it read (≤ 20 ms)
    assert np.median(np.abs(err[moving]), axis=0) == pytest.approx([0.0, 0.0, 0.0], abs=0.02)


def test_with_the_defaults_the_dvl_log_ends_within_1_percent(replayed):
    summary, _, out = replayed
    s = score(out, DRIVE)
    assert s["distance_travelled_m"] > 130.0
    assert s["end_error_percent"] <= 1.0 and s["max_error_submerged_m"] <= 2.0, s
    assert s["valid_fraction_submerged"] >= 0.95 and s["valid_outside_99_fraction"] <= 0.01, s
