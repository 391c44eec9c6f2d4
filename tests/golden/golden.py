"""Golden replays: a short simulated mission (with the calibrator) and a real ArduSub log
replayed through the product's replay path, their output reduced to a fingerprint and
compared with the committed reference ``tests/golden/<case>.json`` within tolerances —
a change that moves numbers is seen (as PX4's replay change indicator).

A change of behaviour made on purpose regenerates the references, one command::

    make golden        # = .venv/bin/python -m tests.golden.golden

and the commit says why the numbers moved (the diff of the JSON shows which).
"""
from __future__ import annotations

import csv
import json
import math
import sys
import tempfile
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
DATA = ROOT.parent / "shared" / "data"

# (case → how to open it); a log case whose file is absent is skipped
CASES = {
    "sim_short": {"scenario": "short", "overrides": ["duration_s=240"], "calibrate": True},
    "tlog_ugps": {"log": DATA / "mavlink" / "ardusub-4.1.1-bluerov2-ugps.tlog"},
}
TRAJECTORY_EVERY_S = 10.0   # one fingerprint row per this many data seconds
# tolerances by column (absolute): what a change in the last bits of floating point
# (another BLAS, another numba) may move, far below what a change of behaviour moves
TOLERANCE = {"_m": 1e-3, "_m_s": 1e-4, "_rad": 1e-5, "k_speed": 1e-5}
SUMMARY_KEYS = ("messages_read", "samples_used", "corrupt_frames", "rejected_samples", "late_samples",
                "nav_states", "imu_samples", "releases", "releases_accepted", "errors", "missing_streams",
                "origin")


def available(case: str) -> bool:
    spec = CASES[case]
    return "log" not in spec or Path(spec["log"]).is_file()


def run_case(case: str, out_dir: Path) -> dict:
    """Replay ``case`` into ``out_dir``; its fingerprint."""
    from adaptnav.service.runtime import replay as rp

    spec = CASES[case]
    if "scenario" in spec:
        inp = rp.open_scenario(spec["scenario"], spec["overrides"])
        cfg = rp.build_config(inp.scenario, None, [])
    else:
        inp = rp.open_log(spec["log"])
        cfg = rp.build_config(None, None, [])
    res = rp.replay(inp, cfg, out_dir, calibrate=spec.get("calibrate", False), progress=False, plots=False,
                    calibrator_location="inline")
    return fingerprint(out_dir, res.summary)


def fingerprint(out_dir: Path, summary: dict) -> dict:
    """Run counters, aid statuses counted by (source, fused, reason), the trajectory every
    ``TRAJECTORY_EVERY_S``, the parameter releases and (simulations) the metrics."""
    with open(out_dir / "trajectory.csv") as fh:
        rows = list(csv.DictReader(fh))
    cols = [c for c in rows[0] if not c.startswith("truth_") and c not in ("t_s", "valid")] if rows else []
    traj, next_t = [], -math.inf
    for r in rows:
        t = float(r["t_s"])
        if t >= next_t:
            traj.append({"t_s": t, "valid": r["valid"], **{c: _number(r[c]) for c in cols}})
            next_t = t + TRAJECTORY_EVERY_S
    if rows:
        last = rows[-1]
        traj.append({"t_s": float(last["t_s"]), "valid": last["valid"], **{c: _number(last[c]) for c in cols}})
    with open(out_dir / "aid_status.csv") as fh:
        aids = Counter(f"{r['source']}/{r['fused']}/{r['reason']}" for r in csv.DictReader(fh))
    with open(out_dir / "params.csv") as fh:
        params = [{k: _number(v) for k, v in r.items()} for r in csv.DictReader(fh)]
    doc = {"summary": {k: summary.get(k) for k in SUMMARY_KEYS}, "aid_status": dict(sorted(aids.items())),
           "trajectory": traj, "params": params}
    if summary.get("metrics"):
        doc["metrics"] = summary["metrics"]
    return json.loads(json.dumps(doc, default=str))  # as it reads back from the file


def _number(text: str):
    try:
        return float(text)
    except ValueError:
        return text


def _tolerance(key: str) -> float:
    for suffix, tol in TOLERANCE.items():
        if key.endswith(suffix):
            return tol
    return 1e-6


def differences(got, ref, path: str = "") -> list[str]:
    """Where ``got`` departs from ``ref`` beyond the tolerances (empty when it does not)."""
    if isinstance(ref, dict) and isinstance(got, dict):
        out = [f"{path}.{k}: missing (reference {ref[k]!r})" for k in ref if k not in got]
        out += [f"{path}.{k}: new (not in the reference)" for k in got if k not in ref]
        for k in ref:
            if k in got:
                out += differences(got[k], ref[k], f"{path}.{k}")
        return out
    if isinstance(ref, list) and isinstance(got, list):
        if len(ref) != len(got):
            return [f"{path}: {len(got)} entries, reference {len(ref)}"]
        return [d for i, (g, r) in enumerate(zip(got, ref)) for d in differences(g, r, f"{path}[{i}]")]
    if isinstance(ref, float) and isinstance(got, (int, float)) and not isinstance(got, bool):
        tol = _tolerance(path.rsplit(".", 1)[-1])
        if (math.isnan(ref) and math.isnan(got)) or abs(got - ref) <= tol:
            return []
        return [f"{path}: {got!r}, reference {ref!r} (tolerance {tol:g})"]
    return [] if got == ref else [f"{path}: {got!r}, reference {ref!r}"]


def reference_path(case: str) -> Path:
    return HERE / f"{case}.json"


def main(argv: list[str]) -> int:
    cases = argv or list(CASES)
    for case in cases:
        if not available(case):
            print(f"{case}: input absent, reference left as it is")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            doc = run_case(case, Path(tmp))
        reference_path(case).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
        print(f"{case}: reference written to {reference_path(case).relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
