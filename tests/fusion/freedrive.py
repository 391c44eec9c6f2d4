"""Score a replay of the real ArduSub SITL log against its truth (``SIM_STATE``), submerged only.

The log (``../shared/data/mavlink/ardusub-sitl-freedrive.tlog``) carries the simulator's
truth as ``SIM_STATE`` (``lat_int``/``lon_int`` degE7 — the float ``lat``/``lon`` hold degE7
in float32, quantised to ~0.4 m —, ``alt`` m up, negative under water), which has no
time field: each is stamped with the autopilot boot time of the latest message that has
one (ATTITUDE at 50 Hz, so ≤ 20 ms late). A surface GNSS fix at the end hides drift, so
the score covers the submerged part only: the horizontal error at the last epoch with the
truth deeper than ``submerged_depth_m`` and the largest error while submerged; distance
travelled is the truth's horizontal path length from the log's start to that epoch.

Usage (the figures quoted in the README)::

    adaptnav replay ../shared/data/mavlink/ardusub-sitl-freedrive.tlog --out OUT
    python -m tests.fusion.freedrive OUT [LOG]

``LOG`` (default: that tlog) may be an ArduSub DataFlash ``.BIN`` of the simulator: its truth
is then the ``SIM`` records (``TimeUS`` boot time, ``Lat``/``Lng`` degrees, ``Alt`` m up).
"""
from __future__ import annotations

import csv
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

FREEDRIVE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mavlink" / "ardusub-sitl-freedrive.tlog"


def sim_state_truth(tlog: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_s (M,), lat_rad (M,), lon_rad (M,), depth_m (M,)) of the log's SIM_STATE — or, for a
    DataFlash ``.BIN``, of its ``SIM`` records (stamped by their own ``TimeUS``, boot time)."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    rows, boot_s = [], None
    dataflash = Path(tlog).suffix.lower() in (".bin", ".log")
    try:
        while dataflash and (msg := conn.recv_match(type="SIM")) is not None:
            # SIM: Lat/Lng in degrees (DFReader applies the format's 1e-7), Alt m up
            rows.append((msg.TimeUS / 1e6, math.radians(msg.Lat), math.radians(msg.Lng), -float(msg.Alt)))
        while not dataflash and (msg := conn.recv_match()) is not None:
            if msg.get_srcComponent() != 1:
                continue
            if hasattr(msg, "time_boot_ms"):
                boot_s = msg.time_boot_ms / 1000.0
            elif msg.get_type() == "SIM_STATE" and boot_s is not None:
                lat = getattr(msg, "lat_int", 0) or msg.lat
                lon = getattr(msg, "lon_int", 0) or msg.lon
                rows.append((boot_s, math.radians(lat * 1e-7), math.radians(lon * 1e-7), -float(msg.alt)))
    finally:
        conn.close()
    a = np.array(rows)
    _, keep = np.unique(a[:, 0], return_index=True)  # one truth per stamp
    a = a[keep]
    return a[:, 0], a[:, 1], a[:, 2], a[:, 3]


def score(out_dir: str | Path, tlog: Path = FREEDRIVE, submerged_depth_m: float = 1.0) -> dict:
    """Submerged scores of the replay written to ``out_dir`` (trajectory.csv, summary.json)."""
    from adaptnav.fusion.frames import GeoOrigin

    out = Path(out_dir)
    summary = json.loads((out / "summary.json").read_text())
    o = summary["origin"]
    origin = GeoOrigin(math.radians(o["lat_deg"]), math.radians(o["lon_deg"]))
    t_true, lat, lon, depth = sim_state_truth(tlog)
    ned = np.array([origin.to_ned(la, lo) for la, lo in zip(lat, lon)])
    with open(out / "trajectory.csv") as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(r["t_s"]) for r in rows])
    est = np.array([[float(r["north_m"]), float(r["east_m"])] for r in rows])
    sigma = np.array([[float(r["sigma_north_m"]), float(r["sigma_east_m"])] for r in rows])
    valid = np.array([r["valid"] in ("1", "True", "true") for r in rows])
    inside = (t >= t_true[0]) & (t <= t_true[-1])
    t, est, sigma, valid = t[inside], est[inside], sigma[inside], valid[inside]
    true_ne = np.stack([np.interp(t, t_true, ned[:, 0]), np.interp(t, t_true, ned[:, 1])], axis=1)
    sub = np.interp(t, t_true, depth) > submerged_depth_m
    if not sub.any():
        raise ValueError("the truth is never submerged")
    err = np.hypot(*(est - true_ne).T)
    # the error normalised by the published north/east σ (the CSV has no cross term): beyond
    # χ²₂'s 99 % point while valid, the solution claimed a position it did not have
    q = np.sum(((est - true_ne) / sigma) ** 2, axis=1)
    valid_sub = valid & sub
    k_last = int(np.flatnonzero(sub)[-1])
    steps = np.hypot(np.diff(ned[:, 0]), np.diff(ned[:, 1]))
    path = np.concatenate([[0.0], np.cumsum(steps)])
    distance = float(np.interp(t[k_last], t_true, path))
    return {
        "distance_travelled_m": distance,
        "end_error_m": float(err[k_last]),
        "end_error_percent": 100.0 * float(err[k_last]) / distance,
        "max_error_submerged_m": float(err[sub].max()),
        "rms_error_submerged_m": float(np.sqrt(np.mean(err[sub] ** 2))),
        "valid_fraction_submerged": float(valid[sub].mean()),
        "valid_outside_99_fraction": float(np.mean(q[valid_sub] > 9.21)) if valid_sub.any() else 0.0,
        "t_last_submerged_s": float(t[k_last]),
    }


if __name__ == "__main__":
    print(json.dumps(score(sys.argv[1], *(Path(a) for a in sys.argv[2:3])), indent=2))
