"""`adaptnav experiment thesis` and `adaptnav bench calibration` end to end (small sizes)."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
KEYS = {"sigma_dd_initial", "sigma_tr_initial", "sigma_dd_changed", "sigma_tr_changed", "sensor_noise",
        "static_error_m", "learned_error_m", "learned_sigma_dd", "learned_sigma_tr", "seeds"}


def _adaptnav(*args):
    out = subprocess.run([sys.executable, "-m", "adaptnav.service.cli", *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_experiment_custom_row_json_and_plot(tmp_path):
    text = _adaptnav("experiment", "thesis", "--seeds", "2", "--initial", "0.05,0.05", "--changed", "0.5,0.05",
                     "--sensor-noise", "2.0", "--change-step", "3", "--steps", "25", "--landmarks", "4",
                     "--json", "--plots", str(tmp_path))
    rows = json.loads(text)
    assert len(rows) == 1 and KEYS <= set(rows[0])
    r = rows[0]
    assert r["seeds"] == 2 and r["sigma_dd_changed"] == 0.5 and r["sensor_noise"] == 2.0
    # a ten-fold change of σ_Dd: the static filter must be clearly worse than the learned one
    assert r["learned_error_m"] < r["static_error_m"]
    assert list(tmp_path.glob("*.png"))


def test_experiment_output_does_not_depend_on_the_worker_count():
    row = ("--initial", "0.05,0.05", "--changed", "0.2,0.05", "--sensor-noise", "3.0", "--steps", "20")
    serial = json.loads(_adaptnav("experiment", "thesis", "--seeds", "3", "--first-seed", "11", *row, "--jobs", "1",
                                  "--json"))
    parallel = json.loads(_adaptnav("experiment", "thesis", "--seeds", "3", "--first-seed", "11", *row, "--jobs", "2",
                                    "--json"))
    assert serial == parallel and serial[0]["seeds"] == 3


def test_experiment_rejects_bad_custom_row():
    out = subprocess.run([sys.executable, "-m", "adaptnav.service.cli", "experiment", "thesis", "--changed", "0.5"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "SDD,STR" in (out.stderr + out.stdout)


def test_bench_calibration_quick():
    figures = json.loads(_adaptnav("bench", "calibration", "--quick", "--json"))
    for key in ("em_iteration_s", "em_iteration_exact_smoother_s", "em_iteration_speedup", "smoother_speedup"):
        assert figures[key] > 0
