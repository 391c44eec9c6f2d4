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


def replay_scored(log: Path, out: Path, *sets: str, config: Path | None = None) -> dict:
    """``adaptnav replay LOG --out OUT [--config CONFIG] [--set ...]`` (else the defaults), then
    :func:`score`."""
    from adaptnav.service.cli import main as cli_main

    args = ["replay", str(log), "--out", str(out), "--no-progress", "--no-plots"]
    if config is not None:
        args += ["--config", str(config)]
    for s in sets:
        args += ["--set", s]
    assert cli_main(args) == 0
    return score(out, log)


def replayed_with_defaults(log: Path):
    """A module-scoped fixture: ``log`` replayed once with the defaults (:func:`replay_scored`),
    as ``(output folder, score)``, for the tests of a module that read that replay."""
    import pytest

    @pytest.fixture(scope="module")
    def defaults(tmp_path_factory) -> tuple[Path, dict]:
        out = tmp_path_factory.mktemp(f"{log.stem}-defaults")
        return out, replay_scored(log, out)

    return defaults


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


# what a real BlueROV2's telemetry log carries at ArduSub's default stream rates
# (../shared/data/mavlink/ardusub-4.1.1-bluerov2-ugps.tlog: RAW_IMU, SCALED_IMU2 and
# SERVO_OUTPUT_RAW at 2.0 Hz, SCALED_PRESSURE2 at 2.4 Hz, ATTITUDE at 19.9 Hz — taken at 10 Hz
# here, its SR*_EXTRA1 default); every other message as logged
DEFAULT_RATES_HZ = {"RAW_IMU": 2.0, "SCALED_IMU": 2.0, "SCALED_IMU2": 2.0, "SCALED_IMU3": 2.0, "HIGHRES_IMU": 2.0,
                    "ATTITUDE": 10.0, "SERVO_OUTPUT_RAW": 2.0, "SCALED_PRESSURE": 2.0, "SCALED_PRESSURE2": 2.0}


def at_default_rates(tlog: Path, out: Path, ugps_period_s: float | None = None, ugps_sigma_m: float = 1.0,
                     ugps_gap_s: tuple[float, float] = (math.inf, math.inf), dvl_period_s: float | None = None,
                     dvl_sigma_m_s: float = 0.01, seed: int = 1, rates_hz: dict[str, float] | None = None) -> Path:
    """A copy of ``tlog`` as a ground station logs it at ArduSub's default stream rates
    (:data:`DEFAULT_RATES_HZ`, updated with ``rates_hz``: each stream thinned on its receive
    stamps), optionally with an
    underwater GPS's fixes made from the simulator's truth — ``GPS_INPUT`` from system 255 (as
    BlueOS's UGPS extension sends it) every ``ugps_period_s`` while the truth is below 0.5 m,
    0.3 s after its epoch, ``ugps_sigma_m`` of white noise per axis, none within ``ugps_gap_s``
    (s since the log's start) — and a DVL's: ``VISION_POSITION_DELTA`` from system 255 (BlueOS's
    DVL extension: the body-frame velocity of its latest ping × the time since the previous one,
    ``time_usec`` 0, confidence 90 %) every ``dvl_period_s`` under water, 50 ms after its epoch,
    the truth's velocity in the truth's body axes plus ``dvl_sigma_m_s`` of white noise."""
    import struct

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from adaptnav.fusion.frames import quat_to_dcm

    rng = np.random.default_rng(seed)
    rates = {**DEFAULT_RATES_HZ, **(rates_hz or {})}
    ugps = mavlink2.MAVLink(None, 255, 0)  # BlueOS's extensions: system 255
    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    last: dict[tuple, float] = {}
    t0 = t_fix = t_dvl = None
    try:
        with open(out, "wb") as f:
            while (msg := conn.recv_match()) is not None:
                mtype = msg.get_type()
                if mtype == "BAD_DATA":
                    continue
                t = msg._timestamp
                t0 = t if t0 is None else t0
                rate = rates.get(mtype)
                key = (mtype, msg.get_srcSystem(), msg.get_srcComponent())
                if rate is not None and key in last and t - last[key] < 1.0 / rate - 1e-3:
                    continue
                last[key] = t
                f.write(struct.pack(">Q", int(round(t * 1e6))) + msg.get_msgbuf())
                if mtype != "SIM_STATE" or -float(msg.alt) < 0.5:
                    continue
                if dvl_period_s is not None and (t_dvl is None or t - t_dvl >= dvl_period_s):
                    dt, t_dvl = (dvl_period_s if t_dvl is None else t - t_dvl), t
                    R_nb = quat_to_dcm(np.array([msg.q1, msg.q2, msg.q3, msg.q4]))
                    v_b = R_nb.T @ np.array([msg.vn, msg.ve, msg.vd]) + rng.normal(0.0, dvl_sigma_m_s, 3)
                    ping = ugps.vision_position_delta_encode(0, int(round(dt * 1e6)), [0.0, 0.0, 0.0],
                                                             [float(v) * dt for v in v_b], 90.0)
                    f.write(struct.pack(">Q", int(round((t + 0.05) * 1e6))) + ping.pack(ugps))
                if ugps_period_s is None:
                    continue
                if (t_fix is not None and t - t_fix < ugps_period_s) or ugps_gap_s[0] <= t - t0 <= ugps_gap_s[1]:
                    continue
                t_fix = t
                lat = (getattr(msg, "lat_int", 0) or msg.lat) * 1e-7
                lon = (getattr(msg, "lon_int", 0) or msg.lon) * 1e-7
                dn, de = rng.normal(0.0, ugps_sigma_m, 2)
                lat += math.degrees(dn / 6_378_137.0)
                lon += math.degrees(de / (6_378_137.0 * math.cos(math.radians(lat))))
                fix = ugps.gps_input_encode(0, 0, 253, 0, 0, 3, int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0,
                                            ugps_sigma_m, 65535, 0, 0, 0, 0, 0, 0, 12, 0)
                f.write(struct.pack(">Q", int(round((t + 0.3) * 1e6))) + fix.pack(ugps))
    finally:
        conn.close()
    return out


if __name__ == "__main__":
    print(json.dumps(score(sys.argv[1], *(Path(a) for a in sys.argv[2:3])), indent=2))
