"""`adaptnav experiment landmarks` end to end on a short survey (2 short reciprocal legs)."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# three 200 m legs; USBL every 20 s for 5 min keeps the navigation's gate a few metres wide
SHORT = ["--set", "duration_s=500", "--set", "usbl.lost_after_s=300", "--set", "usbl.period_s=20",
         "--set", "trajectory.leg_length_m=200", "--set", "sonar.objects_per_hectare=50"]


def _adaptnav(*args):
    out = subprocess.run([sys.executable, "-m", "adaptnav.service.cli", *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    return out


def test_landmarks_experiment_prints_one_json_object_with_the_scores():
    out = _adaptnav("experiment", "landmarks", *SHORT, "--set", "seed=3", "--json")
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout)
    for key in ("objects_in_common_swath", "objects_reassociated_fraction", "false_link_fraction", "links_per_km",
                "drift_percent_with_landmarks", "drift_percent_without_landmarks",
                "drift_percent_with_landmarks_filter_only"):
        assert key in r, key
    # with landmarks = in the filter and the calibrator (issue 14): the calibrator's run took them too
    assert r["calibrator_loop_closures_fused"] > 0
    # the run ends before the change of water + 10 min: no k_V figure rather than one against a change never made
    assert r["k_speed_error_percent_10min_after_change"] is None
    assert r["seed"] == 3
    assert r["objects_in_common_swath"] >= 20
    assert 0.1 < r["objects_reassociated_fraction"] <= 1.0 and r["links_per_km"] > 0
    assert r["false_link_fraction"] <= 0.1
    # most sightings are on real objects (the detector's precision)
    assert r["sightings_on_objects"] >= 0.8 * r["sightings"]


def test_landmarks_experiment_rejects_unknown_keys():
    out = _adaptnav("experiment", "landmarks", "--set", "no_such_key=1", "--json")
    assert out.returncode != 0 and "no_such_key" in out.stderr


def test_landmarks_experiment_without_the_calibrator_says_so_by_leaving_its_keys_out():
    out = _adaptnav("experiment", "landmarks", *SHORT, "--set", "seed=3", "--json", "--no-calibrator")
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout)
    assert "drift_percent_with_landmarks" not in r and "calibrator_loop_closures" not in r
    assert r["drift_percent_with_landmarks_filter_only"] >= 0.0
