"""`adaptnav bench soak --minutes N`: the daemon's memory over a long mission with learning.

A simulated survey (the reference survey of issue 2: IMU 200 Hz, DVL, depth, heading, RPM,
USBL; the water changes at 30 min, so the calibrator has something to learn) of ``N``
minutes of data time is pushed through the daemon (``adaptnav run`` in a subprocess,
calibrator child process on, as on a vehicle) at full speed, flow-controlled on the
daemon's queue depth. Every ``--sample-s`` of data time the resident set size (RSS) of the
daemon and of its calibrator child is read from ``/proc`` together with the calibrator's
releases so far (health), so the figures show memory *while learning happens*.

Figures: ``rss_samples`` (data s, wall s, daemon MB, calibrator MB, releases, releases
accepted), and the growth over the last half of the mission, in % of the RSS at half time:
``rss_growth_last_half_percent`` (daemon), ``rss_calibrator_growth_last_half_percent``,
``rss_total_growth_last_half_percent`` (both); as RSS moves by a few MB between samples,
also its range and least-squares trend over the last half (``rss_*_trend_last_half_mb_per_h``).
Target (issue 12): ≤ 5 % over 1 h simulated.
"""
from __future__ import annotations

import json
import math
import tempfile
import time
from typing import Any

import numpy as np

from adaptnav.service.tools.benchmarks import BenchArgsError

GOAL_GROWTH_PERCENT = 5.0


def add_arguments(parser) -> None:  # pragma: no cover - argparse wiring
    parser.add_argument("--minutes", type=float, default=None, metavar="N",
                        help="soak: minutes of simulated mission (data time; default 60, --quick 10)")
    parser.add_argument("--sample-s", type=float, default=None, metavar="S",
                        help="soak: RSS sampled every S seconds of data time (default 30)")


def _growth_percent(start: float, end: float) -> float:
    return 100.0 * (end - start) / start if start > 0 and math.isfinite(start) else math.nan


def soak(sim_s: float, sample_every_s: float = 30.0, max_queue: int = 8000,
         overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    """Push ``sim_s`` of simulated survey through a daemon at full speed; RSS over time.

    ``overrides``: more daemon settings (e.g. the MAVLink bridge on).
    Returns the figures of the module docstring plus the start RSS, the end RSS, the peak,
    the proportional set sizes at the end, the speed (data s per wall s) and what the
    daemon's health counted (rejections, calibrator restarts, releases).
    """
    from adaptnav.sim.scenario import load_scenario

    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.tools.benchmarks.service import (LIVE_OVERRIDES, LIVE_SCENARIO, _calibrator_pid,
                                                           _flatten, _free_port, _pss_mb, _rss_mb, _start_daemon,
                                                           _stop, _wait_up, simulate_blocks)
    from adaptnav.service.transport.bus import Bus

    scenario = load_scenario(LIVE_SCENARIO, LIVE_OVERRIDES + [f"duration_s={sim_s}"])
    port = _free_port()
    out: dict[str, Any] = {"soak_sim_s": sim_s}
    with tempfile.TemporaryDirectory(prefix="adaptnav-soak-") as tmp:
        proc = _start_daemon(scenario, port, tmp, overrides=overrides)
        bus = Bus(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=()), "bench")
        try:
            _wait_up(bus, proc)
            cal = _calibrator_pid(proc.pid)
            out["rss_daemon_mb_start"] = _rss_mb(proc.pid)
            out["rss_calibrator_mb_start"] = _rss_mb(cal) if cal else math.nan
            samples: list[list[float]] = []
            wall0 = time.perf_counter()

            def record(t_s: float) -> None:
                cal_pid = _calibrator_pid(proc.pid)
                cal_health = (bus.get("health", timeout_s=2.0) or {}).get("calibrator", {})
                samples.append([round(t_s, 1), round(time.perf_counter() - wall0, 2), round(_rss_mb(proc.pid), 2),
                                round(_rss_mb(cal_pid), 2) if cal_pid else math.nan,
                                cal_health.get("releases", 0), cal_health.get("releases_accepted", 0)])

            t0 = None
            next_sample = 0.0
            n = 0
            for sample in _flatten(simulate_blocks(scenario)):
                t0 = sample.t_s if t0 is None else t0
                bus.publish_sample(sample)
                n += 1
                if n % 2000 == 0:
                    while (bus.get("health", timeout_s=1.0) or {}).get("queue_depth", 0) >= max_queue:
                        time.sleep(0.01)
                    if sample.t_s - t0 >= next_sample:
                        next_sample += sample_every_s
                        record(sample.t_s - t0)
            while (bus.get("health", timeout_s=1.0) or {}).get("queue_depth", 0) > 0:
                time.sleep(0.05)
            wall_s = time.perf_counter() - wall0
            record(sim_s)
            health = bus.get("health") or {}
            cal = _calibrator_pid(proc.pid)
            pss = (_pss_mb(proc.pid), _pss_mb(cal))
        finally:
            bus.close()
            _stop(proc)
    half = next(s for s in samples if s[0] >= sim_s / 2)
    end = samples[-1]
    daemon_mb = [s[2] for s in samples]
    # RSS moves by a few MB between samples (the heap breathes with the queue and EM
    # windows): the trend over the last half, a least-squares line, tells growth from that
    last = np.array([s[:4] for s in samples if s[0] >= sim_s / 2], dtype=float)
    slope = (lambda col: float(np.polyfit(last[:, 0] / 3600.0, last[:, col], 1)[0]) if len(last) >= 3 else math.nan)
    out.update({
        "rss_samples": samples,
        "rss_samples_columns": ["data_s", "wall_s", "daemon_mb", "calibrator_mb", "releases", "releases_accepted"],
        "rss_daemon_mb_half": half[2], "rss_daemon_mb_end": end[2], "rss_daemon_mb_peak": max(daemon_mb),
        "rss_calibrator_mb_half": half[3], "rss_calibrator_mb_end": end[3],
        "rss_growth_last_half_percent": _growth_percent(half[2], end[2]),
        "rss_calibrator_growth_last_half_percent": _growth_percent(half[3], end[3]),
        "rss_total_growth_last_half_percent": _growth_percent(half[2] + half[3], end[2] + end[3]),
        "rss_daemon_mb_range_last_half": [float(last[:, 2].min()), float(last[:, 2].max())],
        "rss_daemon_trend_last_half_mb_per_h": slope(2),
        "rss_calibrator_trend_last_half_mb_per_h": slope(3),
        "rss_total_mb_end": end[2] + end[3],
        "pss_daemon_mb_end": pss[0], "pss_calibrator_mb_end": pss[1],
        "soak_wall_s": wall_s, "soak_realtime_factor": sim_s / wall_s,
        "releases": end[4], "releases_accepted": end[5],
        "releases_in_last_half": end[4] - half[4],
        "daemon_rejected": json.dumps(health.get("rejected", {}), sort_keys=True),
        "daemon_calibrator_restarts": health.get("calibrator", {}).get("restarts"),
        "daemon_memory_trims": health.get("memory_trims"),
        "goal_rss_growth_last_half_percent": GOAL_GROWTH_PERCENT,
    })
    return out


def run(args) -> dict:
    minutes = getattr(args, "minutes", None)
    minutes = float(minutes) if minutes is not None else (10.0 if getattr(args, "quick", False) else 60.0)
    if not 1.0 <= minutes <= 24 * 60:
        raise BenchArgsError(f"--minutes must be within [1, 1440], got {minutes:g}")
    sample_s = getattr(args, "sample_s", None)
    sample_s = 30.0 if sample_s is None else float(sample_s)
    if not 0.0 < sample_s <= minutes * 60.0:  # (0 or NaN was taken for 30 s without a word)
        raise BenchArgsError(f"--sample-s must be within (0, the soak's {minutes * 60.0:g} s], got {sample_s:g}")
    return soak(minutes * 60.0, sample_s)
