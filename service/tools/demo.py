"""``adaptnav demo``: the whole live system on one machine, against the simulator.

One command (issue 5, item 6)::

    sim.simulate(demo.toml)                       (in memory, ground truth kept)
        │ samples, accelerated (SitlVehicle)           │ side-scan pings
        ▼                                              ▼
    MAVLink over UDP loopback (ArduSub-like)     Zenoh adaptnav/<v>/sensor/sonar
        │                                        (a second session: the sonar driver)
        ▼                                              │
    Daemon: bridge → runner (ESKF) ◄── releases ── calibrator process (EM over side-scan
        │  nav state → Zenoh adaptnav/<v>/nav/state        landmarks + USBL fixes)
        └─ ODOMETRY → MAVLink → SitlVehicle (counted)

The daemon runs in-process on an embedded Zenoh peer listening on ``tcp/127.0.0.1:<free
port>`` (multicast scouting off); the demo's own session connects to it and collects the
nav states and the calibrator's releases.  The *learned* row is that live run.  The
*static* (pre-change motion model, no calibrator) and *pure INS* (no velocity aiding)
rows replay the same simulated mission (same seed) through the same runner with
:func:`adaptnav.service.runtime.replay.replay`.  Metrics are :mod:`service.metrics` (horizontal error
against truth, % of distance travelled), plus the error at the end of each USBL gap after
the change (:func:`gap_end_errors`): the mission ends on a fix, so the final error alone
says little about the motion model; ``demo.toml`` loses USBL for the last 390 s so that
the motion model carries the navigation over a long gap.

Nothing of the live path is lost silently: the summary's ``nav_epochs`` compares the
epochs expected (10 Hz from the first state to the last IMU sample) with those the
daemon published and the demo's session received; ``reordered_at_daemon`` counts
samples the daemon held back because they overtook the IMU (side-scan pings on Zenoh
arrive before the MAVLink IMU samples of the same instant), ``mavlink_at_daemon`` the
link's losses (sequence gaps), ``rejected_at_daemon`` queue overflows.

Everything started here is stopped here (daemon, calibrator child, sessions, sockets),
also on errors and Ctrl-C.
"""
from __future__ import annotations

import json
import logging
import math
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

SCENARIO = "demo"
ROWS = (("pure_ins", "pure INS"), ("static", "static model"), ("learned", "learned model"))


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A free loopback port (TCP by default, ``socket.SOCK_DGRAM`` for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def scenario_overrides(sets: list[str] | tuple[str, ...]) -> list[str]:
    """``--set`` values → scenario overrides (an optional ``scenario.`` prefix is dropped)."""
    return [s[len("scenario."):] if s.startswith("scenario.") else s for s in sets]


def nav_state_from_dict(doc: dict) -> Any:
    """A ``nav_state`` JSON document (bus payload) → :class:`adaptnav.fusion.state.NavState`."""
    from adaptnav.fusion.state import NavState

    def arr(key, shape=None):
        a = np.array([math.nan if v is None else v for v in doc[key]], dtype=float)
        return a.reshape(shape) if shape else a

    return NavState(t_s=float(doc["t_s"]), pos_n_m=arr("pos_n_m"), vel_n_m_s=arr("vel_n_m_s"),
                    q_nb=arr("q_nb"), bias_acc_b_m_s2=arr("bias_acc_b_m_s2"),
                    bias_gyro_b_rad_s=arr("bias_gyro_b_rad_s"), current_n_m_s=arr("current_n_m_s"),
                    k_speed=float(doc["k_speed"]), cov=arr("cov", (18, 18)), valid=bool(doc["valid"]),
                    reset_counter=int(doc["reset_counter"]),
                    invalid_reasons=tuple(doc.get("invalid_reasons", ())))


class _Collector:
    """Zenoh subscriber side of the demo: nav states and releases (decode + append only)."""

    def __init__(self, bus: Any) -> None:
        self.nav: list[dict] = []
        self.releases: list[dict] = []
        self.malformed = 0
        self._lock = threading.Condition()
        bus.subscribe_raw(bus.keys.nav_state, self._appender(self.nav))
        bus.subscribe_raw(bus.keys.params, self._appender(self.releases))

    def _appender(self, into: list):
        def on_payload(key: str, payload: bytes) -> None:  # noqa: ARG001
            try:
                doc = json.loads(payload)
            except ValueError:
                self.malformed += 1
                return
            with self._lock:
                into.append(doc)
                self._lock.notify_all()
        return on_payload

    def wait_for_nav(self, count: int, timeout_s: float) -> bool:
        """Until ``count`` nav states have come (those published before a count was taken may
        still be on their way on a loaded machine), at most ``timeout_s``; False if not."""
        with self._lock:
            return self._lock.wait_for(lambda: len(self.nav) >= count, timeout_s)

    def last_t(self) -> float:
        with self._lock:
            return float(self.nav[-1]["t_s"]) if self.nav else -math.inf


def _backpressure(samples: Any, vehicle: Any, collector: _Collector, max_lag_s: float = 3.0,
                  max_wait_s: float = 10.0) -> Any:
    """``samples``, held back while the daemon's nav output lags the vehicle by more than
    ``max_lag_s`` of data time: the vehicle never runs ahead of what the daemon digests
    (no queue overflow, no UDP loss on a loaded machine). Runs in the vehicle's thread,
    which keeps serving its link (heartbeats, ODOMETRY) while it waits; a daemon that
    stops answering is waited for at most ``max_wait_s`` per stall."""
    for s in samples:
        v = vehicle()
        if v is not None and v.t_data_s is not None:
            waited = time.monotonic()
            next_hb = waited + 0.5
            while v.t_data_s - collector.last_t() > max_lag_s and math.isfinite(collector.last_t()):
                now = time.monotonic()
                if now - waited > max_wait_s:
                    log.warning("demo: daemon %.1f s of data behind for %.0f s; going on",
                                v.t_data_s - collector.last_t(), max_wait_s)
                    break
                if now >= next_hb:
                    v.heartbeat()
                    next_hb = now + 0.5
                v.poll()
                time.sleep(0.005)
        yield s


@dataclass
class LiveResult:
    """What the live run produced."""

    nav: list[dict]
    releases: list[dict]
    odometry_received: int
    vehicle_sent: dict
    sonar_published: int
    daemon_health: dict
    wall_s: float
    bridge_counters: dict = field(default_factory=dict)


def run_live(scenario: Any, result: Any, speed: float, progress: bool = True) -> LiveResult:
    """The live part: daemon + calibrator process + SITL vehicle + sonar publisher."""
    from adaptnav.service.transport.bus import Bus
    from adaptnav.service.config import ZenohConfig
    from adaptnav.service.daemon import Daemon
    from adaptnav.service.runtime.replay import build_config
    from adaptnav.service.tools.sitl_vehicle import SitlVehicle, SitlVehicleConfig

    zport, uport = free_port(), free_port(socket.SOCK_DGRAM)
    vehicle_name = "demo"
    state_dir = tempfile.TemporaryDirectory(prefix="adaptnav-demo-")
    cfg = build_config(scenario, None, [
        f'zenoh.listen=["tcp/127.0.0.1:{zport}"]', "zenoh.scouting=false", "zenoh.mode=peer",
        f"vehicle.name={vehicle_name}", f'state_dir="{state_dir.name}"',
        "mavlink.enabled=true", f'mavlink.url="udpin:127.0.0.1:{uport}"',
        # the simulated autopilot streams what we ask for: the IMU at its own rate, floats
        'mavlink.request_imu_message="HIGHRES_IMU"', f"mavlink.rates.imu_hz={scenario.imu.rate_hz}",
        "calibrator.enabled=true", 'calibrator.location="process"', "persistence.period_s=3600",
    ])
    peer = ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{zport}",), listen=(), scouting=False)
    daemon = Daemon(cfg)
    monitor = sonar_bus = vehicle = bar = None
    sonar_count = [0]
    wall0 = time.monotonic()
    try:
        daemon.start()
        monitor = Bus(peer, vehicle_name)
        collector = _Collector(monitor)
        sonar_bus = Bus(peer, vehicle_name)  # the sonar driver's own session

        def publish_sonar(sample: Any) -> None:
            if sample.KIND == "sonar":
                sonar_bus.publish_sample(sample)
                sonar_count[0] += 1

        time.sleep(0.3)  # let the sessions connect and the declarations propagate
        vehicle = SitlVehicle(_backpressure(result.iter_samples(), lambda: vehicle, collector),
                              SitlVehicleConfig(url=f"udpout:127.0.0.1:{uport}", speed=speed),
                              on_other_sample=publish_sonar)
        vehicle.start()
        duration = float(scenario.duration_s)
        if progress:
            from adaptnav.service.console import progress as progress_bar

            bar = progress_bar(round(duration), "live daemon", "s data", leave=False)
        last = 0.0
        while not vehicle.done.wait(0.25):
            t = collector.last_t()
            if bar is not None and math.isfinite(t) and t > last:
                bar.update(round(t - last, 1))
                last = t
        if vehicle.error is not None:
            raise RuntimeError(f"simulated vehicle failed: {vehicle.error}") from vehicle.error
        # the daemon drains its queue; then serve the last ODOMETRY messages
        end_t = vehicle.t_data_s or duration
        deadline = time.monotonic() + 30.0
        # until the last epoch is out, the daemon's input is empty and every published ping and
        # every USBL fix sent has been taken in (one still on the wire, or held for data order,
        # arrives within its hold time; on a loaded machine that can be after the last epoch —
        # the last fix comes with the data's last second): the counts below are final
        def taken_in(kind: str) -> int:
            sensors = daemon._health_report().get("sensors", {}) if daemon.bus is not None else {}
            return int(sensors.get(kind, {}).get("count") or 0)

        def all_taken_in() -> bool:
            return (taken_in("sonar") >= sonar_count[0]
                    and taken_in("usbl") >= int(vehicle.sent.get("GPS_INPUT", 0)))

        while ((collector.last_t() < end_t - 0.5 or daemon.source.qsize() > 0 or not all_taken_in())
               and time.monotonic() < deadline):
            vehicle.run(linger_s=0.25)  # the samples are exhausted: heartbeats + ODOMETRY only
        vehicle.run(linger_s=0.3)
        health = daemon._health_report() if daemon.bus is not None else {}
        # the states the daemon counted as published, received before the count is compared:
        # one published as the count was taken was still in flight (1777 of 1779 received
        # with the machine at load 5); one Zenoh lost does not come in these seconds either
        collector.wait_for_nav(int(health.get("nav_states") or 0), 5.0)
        bridge_counters = dict(getattr(daemon.bridge, "counters", {}) or {})
    finally:
        if bar is not None:
            bar.close()
        if vehicle is not None:
            vehicle.close()
        for b in (sonar_bus, monitor):
            if b is not None:
                b.close()
        daemon.stop()
        state_dir.cleanup()
    # ODOMETRY, or the pose alone (VISION_POSITION_ESTIMATE) while the velocity is unconstrained
    return LiveResult(collector.nav, collector.releases,
                      int(vehicle.received["odometry"]) + int(vehicle.received["pose_only"]),
                      {k: v for k, v in vehicle.sent.items()}, sonar_count[0], health,
                      time.monotonic() - wall0, bridge_counters)


def nav_epoch_counts(nav: list[dict], result: Any, duration_s: float, published: int | None,
                     rate_hz: float = 10.0) -> dict:
    """Where nav epochs went: ``expected`` (epochs ``k / rate`` from the first state to the
    last IMU sample: the epoch after the last sample is never complete live), ``published``
    by the daemon, ``received`` over Zenoh (distinct epochs), ``missing`` = expected −
    received."""
    t_imu = np.asarray(result.imu.t_s, dtype=float) if getattr(result, "imu", None) is not None else np.array([])
    t_end = float(t_imu[-1]) if t_imu.size else float(duration_s)
    t = sorted({round(float(d["t_s"]) * rate_hz) for d in nav if d.get("t_s") is not None})
    if not t:
        return {"expected": None, "published": published, "received": 0, "missing": None}
    expected = int(math.floor(t_end * rate_hz + 1e-9)) - t[0] + 1
    return {"expected": expected, "published": published, "received": len(t),
            "missing": expected - len(t)}


def live_recorder(live: LiveResult, result: Any, params0: Any) -> Any:
    """A :class:`adaptnav.service.runtime.sinks.SeriesRecorder` filled with the live run and the truth."""
    from adaptnav.service.transport.release import release_from_dict
    from adaptnav.service.runtime.sinks import SeriesRecorder

    rec = SeriesRecorder(initial_params=params0)
    for s in result.samples.get("truth", []):
        rec.on_sample(s)
    last = -math.inf
    for doc in sorted(live.nav, key=lambda d: d["t_s"]):
        if doc["t_s"] > last and doc.get("valid", True):
            rec.on_nav(nav_state_from_dict(doc))
            last = doc["t_s"]
    for doc in live.releases:
        try:
            rec.on_release(release_from_dict(doc))
        except ValueError:
            pass
    # USBL fixes the live filter fused: their times come with the truth-side samples
    usbl = [s.t_s for s in result.samples.get("usbl", []) if s.t_s <= last]
    rec.last_fix_t_s = max(usbl) if usbl else None
    return rec


def row(metrics: dict, **extra: Any) -> dict:
    """A summary row: the three headline figures first, then the rest."""
    out = {"final_error_m": metrics.get("final_horizontal_error_m"),
           "rms_error_m": metrics.get("rms_horizontal_error_m"),
           "percent_dt": metrics.get("percent_distance_travelled"),
           "distance_travelled_m": metrics.get("distance_travelled_m")}
    out.update(extra)
    return out


def gap_end_errors(t_s: np.ndarray, ne_m: np.ndarray, truth: Any, fix_t_s: list[float],
                   after_s: float = -math.inf) -> dict:
    """Horizontal error at the end of each fix gap (the estimate just before a fix).

    The final error right after a USBL fix (the demo ends on one) says little about the
    motion model; the error accumulated over a gap does. Returns ``gap_end_error_m`` (mean
    over the fixes after ``after_s``), ``gap_end_error_max_m`` and ``gaps`` (count).
    """
    t_s, ne_m = np.asarray(t_s, float), np.asarray(ne_m, float).reshape(-1, 2)
    tq = np.array([f for f in fix_t_s if f > after_s and f > t_s[0] + 1.0]) if len(t_s) else np.array([])
    if tq.size == 0:
        return {"gap_end_error_m": None, "gap_end_error_max_m": None, "gaps": 0}
    # the last output strictly before the fix (outputs at 10 Hz): the filter has not fused it yet
    i = np.clip(np.searchsorted(t_s, tq - 1e-6) - 1, 0, len(t_s) - 1)
    tt = t_s[i]
    tn = np.interp(tt, truth.t_s, truth.pos_n_m[:, 0])
    te = np.interp(tt, truth.t_s, truth.pos_n_m[:, 1])
    e = np.hypot(ne_m[i, 0] - tn, ne_m[i, 1] - te)
    return {"gap_end_error_m": float(e.mean()), "gap_end_error_max_m": float(e.max()), "gaps": int(e.size)}


def format_demo_table(summary: dict) -> str:
    head = ("run", "final err (m)", "RMS err (m)", "% DT", "err before fix (m)", "max before fix (m)")
    lines = [head]
    for key, name in ROWS:
        r = summary.get(key, {})
        cells = [name] + ["–" if r.get(k) is None else f"{r[k]:.3g}"
                          for k in ("final_error_m", "rms_error_m", "percent_dt", "gap_end_error_m",
                                    "gap_end_error_max_m")]
        lines.append(tuple(cells))
    w = [max(len(r[i]) for r in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w[i]) if i == 0 else c.rjust(w[i]) for i, c in enumerate(r)) for r in lines)


def _track_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_s, north/east (N, 2)) of a replay's ``trajectory.csv``."""
    a = np.genfromtxt(path, delimiter=",", names=True)
    return np.atleast_1d(a["t_s"]), np.column_stack([np.atleast_1d(a["north_m"]), np.atleast_1d(a["east_m"])])


def plot_demo(out: Path, rec: Any, tracks: dict[str, Path], scenario: Any) -> list[str]:
    """``demo_track.png`` (three tracks vs truth), ``demo_error.png`` (horizontal error vs
    time), ``demo_params.png`` (learned parameters vs truth over time)."""
    from adaptnav.service.tools.plots import headless_pyplot, save_figure

    plt = headless_pyplot()
    truth = rec.truth()
    live = rec.track()
    series = {k: _track_csv(p) for k, p in tracks.items()}
    series["learned"] = (live.t_s, live.pos_n_m[:, :2])
    names = dict(ROWS)
    files = []

    # the view is set by the truth and the aided runs: pure INS drifts by hundreds of metres
    # and would shrink static vs learned to one line; it is drawn clipped, its size said
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(truth.pos_n_m[:, 1], truth.pos_n_m[:, 0], "k--", lw=1.2, label="truth")
    aided = [truth.pos_n_m[:, :2]] + [series[k][1] for k, _ in ROWS if k != "pure_ins" and len(series[k][1])]
    lo, hi = np.min([a.min(axis=0) for a in aided], axis=0), np.max([a.max(axis=0) for a in aided], axis=0)
    pad = 0.08 * max(float(np.max(hi - lo)), 10.0)
    for key, _ in ROWS:
        t, ne = series[key]
        label = names[key]
        if key == "pure_ins" and len(t):
            end_err = float(np.hypot(*(ne[-1] - np.array([np.interp(t[-1], truth.t_s, truth.pos_n_m[:, i])
                                                         for i in (0, 1)]))))
            label += f" (clipped; {end_err:.0f} m off at the end)"
        ax.plot(ne[:, 1], ne[:, 0], lw=1.0, label=label)
    ax.set_xlim(lo[1] - pad, hi[1] + pad)
    ax.set_ylim(lo[0] - pad, hi[0] + pad)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="box")
    ax.legend(loc="best")
    ax.set_title(f"adaptnav demo: track vs truth ({scenario.duration_s:.0f} s)")
    save_figure(fig, out / "demo_track.png", dpi=110)
    files.append("demo_track.png")

    fig, ax = plt.subplots(figsize=(10, 4.5))
    errors = {}
    for key, _ in ROWS:
        t, ne = series[key]
        if len(t) == 0:
            continue
        tn = np.interp(t, truth.t_s, truth.pos_n_m[:, 0])
        te = np.interp(t, truth.t_s, truth.pos_n_m[:, 1])
        errors[key] = (t, np.hypot(ne[:, 0] - tn, ne[:, 1] - te))
    # the y scale is the aided runs' (pure INS would flatten them to zero); pure INS is
    # clipped at the top, its maximum said in its label
    top = max([float(np.nanmax(e)) for k, (_, e) in errors.items() if k != "pure_ins" and len(e)] + [1.0]) * 1.3
    for key, (t, e) in errors.items():
        label = names[key]
        if key == "pure_ins" and float(np.nanmax(e)) > top:
            label += f" (clipped; up to {float(np.nanmax(e)):.0f} m)"
        ax.plot(t, e, lw=1.0, label=label)
    ax.set_ylim(0.0, top)
    ax.axvline(scenario.environment.change_at_s, color="grey", ls=":", label="environment change")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.legend(loc="best")
    save_figure(fig, out / "demo_error.png", dpi=110)
    files.append("demo_error.png")

    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    t_end = float(scenario.duration_s)
    t_true = np.array([0.0, scenario.environment.change_at_s, scenario.environment.change_at_s, t_end])
    before, after = scenario.params_before(), scenario.params_after()
    rel = [r for r in rec.releases if r.accepted and r.params is not None]
    t_rel = np.array([0.0] + [r.t_s for r in rel] + [t_end])
    p_rel = [rec.initial_params] + [r.params for r in rel]
    p_rel.append(p_rel[-1])
    ax0.step(t_true, [before.k_v, before.k_v, after.k_v, after.k_v], "k--", where="post", label="truth k_V")
    ax0.step(t_rel, [p.k_v for p in p_rel], where="post", label="learned k_V (releases)")
    if len(live.t_s):
        ax0.plot(live.t_s, np.asarray(rec.nav_k_speed), lw=0.8, alpha=0.7, label="filter k_speed")
    ax0.set_ylabel("k_V")
    ax0.legend(loc="best")
    for name, label in (("var_vv", "σ_Vv"), ("var_ww", "σ_Ww")):
        line = ax1.step(t_rel, [math.sqrt(getattr(p, name)) for p in p_rel], where="post", label=f"learned {label}")
        ax1.step(t_true, [math.sqrt(getattr(q, name)) for q in (before, before, after, after)], ls="--",
                 where="post", color=line[0].get_color(), label=f"truth {label}")
    ax1.set_xlabel("t (s)")
    ax1.set_ylabel("σ")
    ax1.legend(loc="best")
    save_figure(fig, out / "demo_params.png", dpi=110)
    files.append("demo_params.png")
    return files


def run_demo(overrides: list[str] | tuple[str, ...] = (), out_dir: str | Path = "out", speed: float = 20.0,
             progress: bool = True, plots: bool = True) -> dict:
    """The whole demo; returns the summary (rows ``pure_ins``, ``static``, ``learned``).

    Parameters
    ----------
    overrides : list of str
        Scenario overrides ``key=value`` on ``sim/scenarios/demo.toml``.
    out_dir : path
        Plots, per-run replay outputs and ``demo_summary.json``.
    speed : float
        Data seconds per wall second of the live run.
    progress, plots : bool
    """
    from adaptnav.sim.scenario import load_scenario

    from adaptnav.service.runtime.replay import ReplayInput, build_config, replay, variant_config
    from adaptnav.service.runtime.sources import SimSource, simulate

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_wall = time.monotonic()
    scenario = load_scenario(SCENARIO, list(overrides))
    if progress:
        print(f"simulating {scenario.name}: {scenario.duration_s:.0f} s ...", file=sys.stderr)
    result = simulate(scenario)

    live = run_live(scenario, result, speed, progress)

    cfg = build_config(scenario)
    rows_metrics: dict[str, dict] = {}
    replays: dict[str, Any] = {}
    for key, variant in (("static", "given"), ("pure_ins", "pure_ins")):
        inp = ReplayInput(SimSource(scenario, result), scenario, f"{key}", scenario.duration_s)
        r = replay(inp, variant_config(cfg, variant), out / key, calibrate=False, progress=progress,
                   title=key, plots=False)
        replays[key] = r
        rows_metrics[key] = r.metrics
    rec = live_recorder(live, result, cfg.motion.params0)
    rows_metrics["learned"] = rec.metrics()

    # error at the end of each USBL gap (just before the fix) after the change: fairer
    # than the final error, which the last fix resets
    truth = rec.truth()
    fixes = sorted(s.t_s for s in result.samples.get("usbl", []))
    live_track = rec.track()
    gap_series = {k: _track_csv(replays[k].out_dir / "trajectory.csv") for k in ("static", "pure_ins")}
    gap_series["learned"] = (live_track.t_s, live_track.pos_n_m[:, :2])
    gaps = {k: gap_end_errors(*gap_series[k], truth, fixes, after_s=scenario.environment.change_at_s)
            for k in gap_series}

    accepted = [d for d in live.releases if d.get("accepted")]
    summary = {
        "pure_ins": row(rows_metrics["pure_ins"], **gaps["pure_ins"]),
        "static": row(rows_metrics["static"], **gaps["static"]),
        "learned": row(rows_metrics["learned"], **gaps["learned"], releases=len(live.releases), releases_accepted=len(accepted),
                       odometry_received_by_vehicle=live.odometry_received,
                       nav_epochs=nav_epoch_counts(live.nav, result, scenario.duration_s,
                                                   live.daemon_health.get("nav_states")),
                       nav_states_received=len(live.nav), sonar_pings_published=live.sonar_published,
                       reordered_at_daemon=live.daemon_health.get("reordered", {}),
                       mavlink_at_daemon=live.daemon_health.get("mavlink", {}),
                       samples_at_daemon={k: v.get("count") for k, v in
                                          live.daemon_health.get("sensors", {}).items()},
                       rejected_at_daemon=live.daemon_health.get("rejected", {}),
                       calibrator_dropped_samples=live.daemon_health.get("calibrator", {}).get("dropped_samples"),
                       calibrator_restarts=live.daemon_health.get("calibrator", {}).get("restarts"),
                       # releases and side-scan objects back after their due time (the demo runs at
                       # 20x real time: a busy machine shows here, the solution then not a replay's)
                       calibrator_late=live.daemon_health.get("calibrator", {}).get("late"),
                       final_params=accepted[-1]["params"] if accepted else None,
                       live_wall_s=live.wall_s),
        "scenario": {"name": scenario.name, "duration_s": scenario.duration_s, "seed": scenario.seed,
                     "change_at_s": scenario.environment.change_at_s,
                     "params_before": scenario.params_before().to_dict(),
                     "params_after": scenario.params_after().to_dict()},
        "speed": speed,
        "wall_s": None,
    }
    if plots:
        tracks = {"pure_ins": replays["pure_ins"].out_dir / "trajectory.csv",
                  "static": replays["static"].out_dir / "trajectory.csv"}
        summary["plots"] = plot_demo(out, rec, tracks, scenario)
    summary["wall_s"] = time.monotonic() - t_wall
    (out / "demo_summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    return summary
