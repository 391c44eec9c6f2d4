"""A drive of another shape than the one the defaults were measured on: stop and go.

``tests/data/ardusub-4.7-sitl-stops.BIN`` (ours, 2.6 MB) is an excerpt (``python -m
tests.sitl.bin_drive --excerpt``; the full 18 MB log replays to the byte-identical trajectory)
of what ArduSub V4.7.0-dev SITL (``../shared/sitl``, ``--model vectored``) logged with its
default ``LOG_BITMASK`` while ``python -m tests.sitl.bin_drive OUT --pattern stops`` drove it: a
dive, four 50 s lanes with 30 s hovers between them (thrust cut, the vehicle coasts to rest),
turns, surface. The defaults were once tuned on drives without stops: there the learned velocity
said "speed 0" the instant the thrust was cut while the vehicle coasted for seconds (0.55 →
0.35 / 0.17 / 0.06 m/s 1 / 2 / 5 s later), every stop cut k_speed by 4–8 % and moved the position
back 2–5 m: 13.7 % of the distance at the end, 16.1 m at most. Now an uncalibrated vehicle's
learned velocity carries the gap to a 2 s lag of the command as variance
(``filter.learned_velocity.transient_time_s``, ``motion.uncalibrated_transient_time_s``) and its
k_speed starts at σ 0.3 (the embedded table is another vehicle's), and a coast is observed
between the command and the lag (``filter.learned_velocity.coast_mean_fraction``); its heave is 0 ± the
vertical speed (``motion.uncalibrated_heave_sigma_per_vertical_speed``: it may change depth on
vertical thrusters).
"""
import json
from pathlib import Path

from adaptnav.service.cli import main as cli_main

from ..fusion.freedrive import score

STOPS = Path(__file__).resolve().parents[1] / "data" / "ardusub-4.7-sitl-stops.BIN"


def test_stop_and_go_stays_within_5_percent_of_distance_and_15_m_with_the_defaults(tmp_path):
    assert cli_main(["replay", str(STOPS), "--out", str(tmp_path), "--no-progress", "--no-plots"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["motion_prior"].startswith("uncalibrated")
    s = score(tmp_path, STOPS)
    assert s["distance_travelled_m"] > 100.0
    # issue 11's bounds (measured 1.43 % and 3.75 m; 1.95 % / 4.28 m through the vehicle's thruster
    # curve before the simulator's; before the transient variance 13.65 % / 16.1 m;
    # 1.43 % / 3.02 m before the coast's mean and the tilt's wander, which took the ground
    # station's tlog of another stops drive from 4.41 to 1.84 %: tests/service/test_mavlink_sitl_stops.py)
    assert s["end_error_percent"] <= 5.0 and s["max_error_submerged_m"] <= 15.0, s
    # and honest: the valid epochs' errors within their 99 % ellipse (a consistent filter: ~1 %)
    assert s["valid_outside_99_fraction"] <= 0.02, s
    # valid while it descends and climbs level on its vertical thrusters (measured 99 %; 91 %
    # while the learned velocity held its heave to 0 ± 0.05 m/s: the integrity test failed it
    # at every depth change)
    assert s["valid_fraction_submerged"] > 0.95, s
