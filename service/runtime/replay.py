"""Replay harness: a recorded mission (MCAP, ``.tlog``/``.BIN``) or a scenario simulated
in memory, through the *same* runner as the live daemon (:func:`adaptnav.service.runtime.runner.run`),
with a log/simulator source, a log (or real-time) clock and file sinks.

Configuration is the daemon's :class:`service.config.ServiceConfig` (one typed tree),
built with this precedence: defaults < what a simulated log says about itself (the
scenario: IMU grade → filter noises, sensor noises, water density, DVL mounting, RPM
table, the *pre-change* motion parameters, origin) < ``--config FILE`` < overrides.

Outputs in ``DIR``: ``trajectory.csv``, ``aid_status.csv``, ``params.csv``,
``metrics.json`` (with truth), ``track.png``, ``params.png``, ``innovations.png``,
``summary.json`` and the effective ``config.json`` (+ ``scenario.json`` for simulations).

With ``calibrate=True`` the online calibrator runs in a child process (the second core;
``calibrator_location="inline"``: in this process, same output) and a release it computed
at data time τ is applied once the runner's data time reaches τ + ``calibrator.latency_s``,
the runner waiting for the child's progress: the output is deterministic
(:class:`adaptnav.service.calibrator.lagged.LaggedCalibrator`).

Comparisons (the navigation-core targets): ``aiding="none"`` is pure INS (learned
velocity, DVL and visual motion off; the other aids stay), ``k_v_error`` a static,
wrong motion model (``k_V·(1 + error)``, no calibrator); :func:`compare` runs pure INS /
static wrong model / as given side by side.
"""
from __future__ import annotations

import csv
import gc
import itertools
import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from adaptnav.fusion.aiding import FIX_KINDS
from adaptnav.fusion.typed_config import apply_overrides, as_dict, build

from adaptnav.service.runtime.clock import LogClock, RealtimeClock
from adaptnav.service.runtime.events import LifecycleLog
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.runner import RunSummary, default_release_gate, door_for, run
from adaptnav.service.runtime.sinks import (AidStatusCsvSink, DeferredSinks, MetricsSink, ParamsCsvSink, PlotSink,
                                            SeriesRecorder, Sink, TrajectoryCsvSink)
from adaptnav.service.runtime.sources import McapSource, SimSource, simulate, tlog_source  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

VELOCITY_AIDS_OFF = ("filter.learned_velocity.enabled=false", "filter.dvl.enabled=false",
                     "filter.visual_motion.enabled=false")


# -- configuration from a scenario --------------------------------------------------------
def _imu_filter_raw(grade: str) -> dict:
    """Filter IMU noise densities matching a simulator IMU grade (sim/imu.py).

    Bias 1-σ = sqrt(turn-on² + instability²); bias random-walk density ≥ the Gauss–Markov
    driving density ``σ_GM·sqrt(2/τ)`` (the filter models biases as random walks).
    Floors keep a "perfect" IMU's filter well conditioned.
    """
    from adaptnav.sim.imu import IMU_GRADES

    g = IMU_GRADES[grade]

    def rw(m):
        return max(m.random_walk_density, m.instability_sigma * math.sqrt(2.0 / m.correlation_time_s))

    return {
        "acc_noise_m_s2_rthz": max(g.accel.white_density, 1e-6),
        "gyro_noise_rad_s_rthz": max(g.gyro.white_density, 1e-8),
        "acc_bias_sigma_m_s2": max(math.hypot(g.accel.turn_on_sigma, g.accel.instability_sigma), 1e-5),
        "gyro_bias_sigma_rad_s": max(math.hypot(g.gyro.turn_on_sigma, g.gyro.instability_sigma), 1e-8),
        "acc_bias_rw_m_s3_rthz": max(rw(g.accel), 1e-8),
        "gyro_bias_rw_rad_s2_rthz": max(rw(g.gyro), 1e-10),
    }


def config_raw_from_scenario(scenario: Any) -> dict:
    """ServiceConfig sections (raw dict) that a simulated mission determines."""
    sc = scenario
    return {
        "origin": {"lat_deg": sc.origin.lat_deg, "lon_deg": sc.origin.lon_deg},
        "motion": {
            "rpm_table": {"rpm": list(sc.rpm.table_rpm), "speed_m_s": list(sc.rpm.table_speed_m_s)},
            # the filter is given the pre-change model (learning it is the calibrator's job)
            "params0": sc.params_before().to_dict(),
            # the simulated vehicle's own table and variances, also when its thrust reaches the
            # daemon as an autopilot's PWM (the demo's simulated ArduSub)
            "prior": "calibrated",
        },
        "filter": {
            "imu": _imu_filter_raw(sc.imu.grade),
            "heading": {"sigma_rad": math.radians(sc.heading.sigma_deg)},
            "depth": {"sigma_m": sc.depth.sigma_m, "water_density_kg_m3": sc.environment.density_kg_m3,
                      "density_sigma_kg_m3": sc.depth.density_sigma_kg_m3,
                      "atmospheric_pressure_pa": sc.environment.atmospheric_pressure_pa},
            # the DVL's σ stays the filter's (fusion/config.py: its long-term errors dominate)
            "dvl": {"water_track_sigma_m_s": sc.dvl.water_track_sigma_m_s, "lever_arm_b_m": list(sc.dvl.lever_arm_b_m),
                    "lever_arm_sigma_m": 0.0,  # the simulated head is where the scenario says
                    "rotation_bd_rpy_rad": [math.radians(v) for v in sc.dvl.mount_rpy_deg]},
            "gnss": {"max_depth_m": sc.gnss.max_depth_m},
        },
        # the calibrator's NED frame is the filter's
        "calibrator": {"online": {"origin_lat_deg": sc.origin.lat_deg, "origin_lon_deg": sc.origin.lon_deg}},
    }


def _merge(base: dict, top: dict) -> dict:
    out = dict(base)
    for k, v in top.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def build_config(scenario: Any = None, config_path: str | Path | None = None,
                 overrides: list[str] | tuple[str, ...] = ()) -> Any:
    """Effective :class:`ServiceConfig` (precedence in the module docstring)."""
    from adaptnav.service.config import ServiceConfig, read_config_file

    raw: dict = config_raw_from_scenario(scenario) if scenario is not None else {}
    if config_path is not None:
        raw = _merge(raw, read_config_file(config_path))
    return build(ServiceConfig, apply_overrides(raw, list(overrides)))


# -- inputs -------------------------------------------------------------------------------
@dataclass
class ReplayInput:
    """An opened input: the source and what it says about itself."""

    source: Any
    scenario: Any = None            # sim.scenario.Scenario when the input is a simulation
    label: str = ""
    duration_s: float | None = None
    reopen: Any = None              # callable → a fresh source over the same data
    path: Path | None = None        # the log file, when the input is one

    @property
    def has_truth(self) -> bool:
        return bool(getattr(self.source, "has_truth", False))


def open_scenario(name: str, overrides: list[str] | tuple[str, ...] = ()) -> ReplayInput:
    """Simulate scenario ``name`` (or a .toml path) in memory."""
    from adaptnav.sim.scenario import load_scenario

    scenario = load_scenario(name, list(overrides))
    result = simulate(scenario)
    return ReplayInput(SimSource(scenario, result), scenario, f"scenario {scenario.name}",
                       scenario.duration_s, reopen=lambda: SimSource(scenario, result))


def open_log(path: str | Path) -> ReplayInput:
    """Open ``.mcap`` (our logs, or BlueOS's MAVLink recordings) or ``.tlog``/``.bin``
    (MAVLink/DataFlash) for replay."""
    path = Path(path)
    if path.is_dir():  # (a folder of logs: each is replayed on its own)
        raise IsADirectoryError(f"{path} is a folder, not a log: give one of its .mcap, .tlog or .bin files")
    if not path.is_file():
        raise FileNotFoundError(f"log not found: {path}")
    suffix = path.suffix.lower()
    if suffix in (".tlog", ".bin", ".log"):
        return ReplayInput(tlog_source(path), None, path.name, None, reopen=lambda: tlog_source(path), path=path)
    if suffix == ".mcap":
        from adaptnav.service.transport.blueos_mcap import mavlink_layout

        if mavlink_layout(path):  # BlueOS's recording of the vehicle's MAVLink, not one of ours
            return ReplayInput(tlog_source(path), None, path.name, None, reopen=lambda: tlog_source(path), path=path)
        src = McapSource(path)
        return ReplayInput(src, src.scenario, path.name, src.duration_s, reopen=lambda: McapSource(path), path=path)
    raise ValueError(f"{path}: unknown log type {suffix!r} (expected .mcap, .tlog or .bin)")


# -- one replay ----------------------------------------------------------------------------
@dataclass
class ReplayResult:
    out_dir: Path
    summary: dict
    metrics: dict
    run: RunSummary
    files: list[str] = field(default_factory=list)


def _progress_bar(total_s: float | None, label: str, enabled: bool):
    from adaptnav.service.console import progress as progress_bar

    # a bar on a terminal, a line every 10 s elsewhere (stderr), nothing when disabled/quiet
    bar = progress_bar(round(total_s, 1) if total_s else None, label[:30], "s data", enabled, leave=False,
                       mininterval=0.5)
    if bar is None:
        return None, None
    state = {"t0": None, "done": 0.0}

    def progress(t_s: float) -> None:
        if state["t0"] is None:
            state["t0"] = t_s
        done = t_s - state["t0"]
        if done - state["done"] >= 1.0:
            bar.update(round(done - state["done"], 1))
            state["done"] = done

    return bar, progress


# the collector's young-generation threshold (net new container objects) during a run: at
# CPython's 700 a calibrated hour took ~220 collections (~0.12 s of the replaying process,
# issue 17), each scanning what is alive for a while — the deferred sinks' queued states, the
# calibrator's batches —, all of it freed by reference counts; ~5 at this threshold
_REPLAY_GC_YOUNG_OBJECTS = 20_000


def replay(inp: ReplayInput, cfg: Any, out_dir: str | Path, *, calibrate: bool = False,
           realtime: float | None = None, progress: bool = True, title: str = "",
           plots: bool = True, calibrator_location: str = "process",
           mcap: str | Path | None = None, report: str | Path | None = None,
           reader: str = "auto") -> ReplayResult:
    """Run one replay of ``inp`` with config ``cfg`` into ``out_dir`` (see module docstring).

    Parameters
    ----------
    inp : ReplayInput
    cfg : ServiceConfig
    out_dir : path, created if needed
    calibrate : bool
        Run the online calibrator; its releases are applied at data time τ +
        ``cfg.calibrator.latency_s`` (deterministic: :class:`adaptnav.service.calibrator.lagged.LaggedCalibrator`).
    calibrator_location : {"process", "inline"}
        The calibrator in a child process (the second core) or in this process; both
        give the same output.
    realtime : float, optional
        Pace at this many times real time (``None``: as fast as possible).
    progress : bool
        Show a progress bar over data time.
    plots : bool
        Write the PNG plots.
    mcap : path, optional
        Also write the solution (and the truth) to this MCAP file in Foxglove's
        well-known schemas, log times on a real clock (:mod:`adaptnav.service.runtime.foxglove`).
    report : path, optional
        Also write a self-contained HTML report here (:mod:`adaptnav.service.tools.report`).
    reader : {"auto", "process", "inline"}
        Where a MAVLink log is read (decoded, converted, ordered): a child process
        (:mod:`adaptnav.service.runtime.reader`; the same items, the same outputs), this
        process, or ``auto``: a child for a log of a few MB on a machine with two cores.
    """
    from adaptnav.service.compose import make_estimator

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    origin_configured = cfg.origin.lat_deg != 0.0 or cfg.origin.lon_deg != 0.0
    # the thrust is an autopilot's PWM: a MAVLink or DataFlash log, or a recording of a daemon
    # whose MAVLink bridge was on (replayed with its config: the daemon's own rule)
    autopilot_thrust = hasattr(inp.source, "set_convert") or cfg.mavlink.enabled
    cfg = cfg.resolved(autopilot_thrust)
    if hasattr(inp.source, "set_convert"):  # a MAVLink log: converted as the live bridge converts,
        # its slow IMU streams withheld by the filter's rule (as the motion prior decides it)
        inp.source.set_convert(cfg.mavlink.convert, cfg.filter.alignment.min_imu_rate_hz)
    if origin_configured and hasattr(inp.source, "set_origin"):
        inp.source.set_origin(cfg.origin.geo())
    if hasattr(inp.source, "read_in_child"):  # a MAVLink log
        from adaptnav.service.runtime.reader import wants_child

        inp.source.read_in_child = wants_child(inp.source.tlog.path, reader)
    items: Any = iter(inp.source)
    origin_note = None
    origin_is_start = True  # the vehicle starts at the origin within initial.sigma_pos_m
    origin_warnings: list[str] = []  # a first fix passed over, or an unconfirmed one taken
    if inp.scenario is None and cfg.origin.lat_deg == 0.0 and cfg.origin.lon_deg == 0.0:
        # no origin configured (real logs): the first position fix is the NED origin
        head, fix, origin_warnings, t_first = _read_until_fix(items)
        items = itertools.chain(head, items)
        if fix is not None:
            cfg = replace(cfg, origin=replace(cfg.origin, lat_deg=math.degrees(fix.lat_rad),
                                              lon_deg=math.degrees(fix.lon_rad)))
            origin_note = f"first {fix.KIND} fix at t={fix.t_s:.3f} s"
            # a fix this long after the data starts is not where the vehicle started
            origin_is_start = t_first is None or fix.t_s - t_first <= ORIGIN_FIX_AT_START_S
            log.info("NED origin from the %s", origin_note)
    params0, motion_prior = cfg.motion.initial_params(autopilot_thrust)
    log.info("motion model: %s", motion_prior)
    estimator = make_estimator(cfg, params0, objects=calibrate)  # sightings come from the calibrator
    estimator.origin_is_start = origin_is_start
    if getattr(inp.source, "in_time_order", False):  # no sample can be late: no history for them
        estimator.keep_history = False
    calibrator = None
    if calibrate:
        from adaptnav.service.compose import make_lagged_calibrator

        calibrator = make_lagged_calibrator(cfg, params0, calibrator_location)
    health = Health(silent_after_s=cfg.health.sensor_timeout_s)
    truth = inp.has_truth
    recorder = SeriesRecorder(initial_params=params0, aid_rows=plots or report is not None)
    metrics_sink = MetricsSink(recorder, out / "metrics.json")
    validity = ValidityCounter()
    consistency = AidConsistency(cfg.filter.gate_threshold)
    origin_known = inp.scenario is not None or origin_configured or origin_note is not None
    sinks = [TrajectoryCsvSink(out / "trajectory.csv", truth=truth,
                               truth_max_age_s=0.5 / cfg.outputs.nav_rate_hz,
                               unix_of=getattr(inp.source, "unix_of", None),
                               origin=cfg.origin.geo() if origin_known else None),
             validity, consistency,
             AidStatusCsvSink(out / "aid_status.csv"),
             ParamsCsvSink(out / "params.csv", params0),
             recorder, metrics_sink, LifecycleLog(warnings=False)]  # lifecycle events at INFO (`adaptnav -v replay`)
    # the source tells data missing from a step of its clock where it can (a boot clock, a log clock)
    door = door_for(estimator, getattr(inp.source, "forward_jump_is_gap", None))
    if plots:
        sinks.append(PlotSink(recorder, out, title or inp.label, gaps=door.gaps if door is not None else ()))
    if mcap is not None:
        from adaptnav.service.runtime.foxglove import open_mcap_sink, replay_time_base

        sinks.append(open_mcap_sink(mcap, cfg.origin.geo(), replay_time_base(inp),
                                    truth_max_age_s=0.5 / cfg.outputs.nav_rate_hz,
                                    metadata={"input": inp.label}))
    backend = getattr(calibrator, "backend", None)
    if hasattr(backend, "idle"):
        # the files' sinks work while the runner waits for the calibrator child, not on top
        # (each sink sees its calls in their order; none reads another before closing)
        deferred = DeferredSinks([s for s in sinks if getattr(s, "deferrable", False)])
        backend.idle = deferred.work
        sinks = [deferred, *(s for s in sinks if not getattr(s, "deferrable", False))]
    clock = RealtimeClock(realtime) if realtime else LogClock()
    bar, prog = _progress_bar(inp.duration_s, title or inp.label, progress)
    wall0 = time.monotonic()
    # what exists now (a simulated mission held in memory is ~10⁵ objects per hour) is
    # left out of the garbage collector's full passes during the run: they rescanned all of
    # it a few times per replay for nothing (it is freed, if at all, by reference counts)
    gc.freeze()
    thresholds = gc.get_threshold()
    if 0 < thresholds[0] < _REPLAY_GC_YOUNG_OBJECTS:  # (0: the collector is off, left so)
        gc.set_threshold(_REPLAY_GC_YOUNG_OBJECTS, *thresholds[1:])
    try:
        summary = run(items, estimator, sinks, clock, calibrator,
                      output_rate_hz=cfg.outputs.nav_rate_hz, health=health, progress=prog,
                      release_gate=default_release_gate(cfg.calibrator.online), door=door)
    finally:
        gc.set_threshold(*thresholds)
        gc.unfreeze()
        if bar is not None:
            bar.close()
        if calibrator is not None:
            calibrator.close()
    wall_s = time.monotonic() - wall0
    placed = None
    if origin_note is not None and estimator.position_seeds:  # (a start the origin within σ_0 as well)
        # the earliest fix that placed it (a late fix re-fused may have placed it again: the last word)
        t_first = min(s[0] for s in estimator.position_seeds)
        seed = [s for s in estimator.position_seeds if s[0] == t_first][-1]
        placed = place_rows_before_the_first_fix(out / "trajectory.csv", seed, cfg.origin.geo())

    src = inp.source
    counters = src.report_counters()
    for reason, n in counters["rejected"].items():
        health.on_rejected(reason, n)
    rejected = health.rejected_by_reason()
    duration = summary.duration_s
    missing = list(getattr(src, "missing", []))
    doc = {
        "input": inp.label,
        "messages_read": counters["messages_read"],
        "samples_used": summary.samples_used,
        "corrupt_frames": counters["corrupt_frames"],
        "rejected_samples": rejected,
        "rejected_total": int(sum(rejected.values())),
        "late_samples": counters["late_samples"],
        "duration_s": duration,
        "wall_s": wall_s,
        "realtime_factor": duration / wall_s if wall_s > 0 else None,
        "missing_streams": missing,
        "nav_states": summary.nav_states,
        "imu_samples": summary.imu_samples,
        "releases": summary.releases,
        "releases_accepted": summary.releases_accepted,
        "errors": dict(summary.errors),
        # position resets onto gated fixes (consistent evidence), with their size
        "position_resets": [{"t_s": t, "source": src, "size_m": size}
                            for t, src, size in getattr(estimator, "position_resets", [])],
        # the origin was a fix's, later than the start: the rows before that fix, placed by it
        "rows_placed_by_the_first_fix": placed,
        "clock_jumps_s": list(summary.clock_jumps),
        # data missing on a clock that cannot step (a dropout): (from, to) data times, s
        "data_gaps_s": [[d, t] for _, d, t in (door.gaps if door is not None else [])],
        "calibrate": bool(calibrate),
        "calibrator": ({"location": calibrator_location, "latency_s": calibrator.latency_s,
                        "wait_s": getattr(calibrator.backend, "wait_s", 0.0),
                        "process_cpu_s": _finite_or_none(getattr(calibrator.backend, "child_cpu_s", None)),
                        # what the calibrator's object front end made of the side-scan pings
                        "side_scan": getattr(calibrator.backend, "side_scan", None)}
                       if calibrator is not None else None),
        "origin": {"lat_deg": cfg.origin.lat_deg, "lon_deg": cfg.origin.lon_deg,
                   "from": origin_note or ("scenario" if inp.scenario is not None else "config")},
        "health": health.report(),
        "valid_fraction": validity.fraction,
        "first_valid_t_s": validity.first_valid_t_s,
        "filter": _filter_report(estimator),
        # each aid's attempts and what their innovations say of the covariance (no truth needed)
        "aid_consistency": consistency.report(),
        "motion_prior": motion_prior,
    }
    if getattr(estimator, "side_scan", None):  # side-scan loop closures (service.loop_closures)
        doc["side_scan"] = dict(estimator.side_scan)
    cal = getattr(estimator, "dvl_calibration", None)
    if cal is not None and doc["health"]["sensors"].get("dvl", {}).get("count", 0):
        doc["dvl_calibration"] = cal.report()  # "status": "prior" says the DVL was never calibrated
    if counters.get("message_types"):
        doc["message_types"] = counters["message_types"]
        doc["unknown_message_types"] = sorted(k for k, v in counters["message_types"].items()
                                              if v.get("status") == "unknown")
    if counters.get("clock"):
        doc["clock"] = counters["clock"]
    if counters.get("gps_fixes"):  # MAVLink/DataFlash: the autopilot's GPS taken as a GNSS or an underwater GPS
        doc["gps_fixes"] = counters["gps_fixes"]
    if counters.get("imu_stream"):  # MAVLink: which IMU stream was integrated, how often it changed
        doc["imu_stream"] = counters["imu_stream"]
    if counters.get("thrusters"):  # MAVLink/DataFlash: the vehicle's PWM → RPM curve or the simulator's
        doc["thrusters"] = counters["thrusters"]
    doc["warnings"] = origin_warnings + replay_warnings(doc)
    for w in doc["warnings"]:
        log.warning("%s", w)
    if counters.get("truncated"):
        doc["truncated"] = counters["truncated"]
    if counters.get("repaired_frames"):  # logged zero-truncated after their CRC: restored, used
        doc["repaired_frames"] = counters["repaired_frames"]
    if metrics_sink.metrics:
        doc["metrics"] = metrics_sink.metrics
    (out / "summary.json").write_text(json.dumps(doc, indent=2, sort_keys=True, default=_json_default) + "\n")
    (out / "config.json").write_text(json.dumps(as_dict(cfg), indent=2, sort_keys=True, default=_json_default) + "\n")
    if inp.scenario is not None:
        (out / "scenario.json").write_text(json.dumps(as_dict(inp.scenario), indent=2, sort_keys=True,
                                                      default=_json_default) + "\n")
    if report is not None:
        from adaptnav.service.tools.report import write_report

        write_report(recorder, doc, report, title or f"adaptnav replay: {inp.label}")
    files = sorted(p.name for p in out.iterdir() if p.is_file())
    return ReplayResult(out, doc, metrics_sink.metrics, summary, files)


class ValidityCounter(Sink):
    """Sink: how many nav states were output, how many of them valid, the first valid one."""

    deferrable = True

    def __init__(self) -> None:
        self.states = 0
        self.valid = 0
        self.first_valid_t_s: float | None = None

    def on_nav(self, state: Any) -> None:
        self.states += 1
        if state.valid:
            self.valid += 1
            if self.first_valid_t_s is None:
                self.first_valid_t_s = float(state.t_s)

    @property
    def fraction(self) -> float | None:
        return self.valid / self.states if self.states else None


class AidConsistency(Sink):
    """Sink: what each aid's attempts say of the filter without any truth — a real log's check
    of the covariance. Per source: attempts, fused, refused by reason, and over the attempts
    that reached the test (fused or gated) the normalised innovation squared per degree of
    freedom, ``ε/m`` (``ε = test_ratio × gate(m)``, the gate of ``filter.gate_sigma``): its
    mean (a consistent filter ≈ 1; well above, the covariance or the aid's σ too small; well
    below, the aid's σ too large) and the fraction of attempts within the χ²(m) 95 % quantile
    (≈ 0.95). An aid whose σ is chosen for errors that stay (the autopilot's ATTITUDE, fused at
    tens of Hz) sits far below 1 by design; above 1 is the failure that matters.
    ``gate_of_dof``: ``m -> gate`` (:meth:`FilterConfig.gate_threshold`)."""

    deferrable = True

    def __init__(self, gate_of_dof: Any) -> None:
        from adaptnav.fusion.integrity import chi2_quantile

        self._gate_of_dof, self._chi2 = gate_of_dof, chi2_quantile
        self._limits: dict[int, tuple[float, float]] = {}  # m → (gate, χ²(m) 95 % quantile)
        self._by_source: dict[str, _AidTally] = {}

    def on_aid(self, statuses: list) -> None:
        by_source, limits_of = self._by_source, self._limits
        for s in statuses:
            try:  # (subscripts, not get calls: ~130k statuses per data hour)
                a = by_source[s.source]
            except KeyError:
                a = by_source[s.source] = _AidTally()
            a.attempts += 1
            fused = s.fused
            if fused:
                a.fused += 1
            else:
                reason = s.reason or "unspecified"
                a.refused[reason] = a.refused.get(reason, 0) + 1
            m = len(s.innovation)
            test_ratio = s.test_ratio
            if not (fused or s.reason == "gate") or not m or not math.isfinite(test_ratio):
                continue
            try:
                gate, within = limits_of[m]
            except KeyError:
                gate, within = limits_of[m] = (float(self._gate_of_dof(m)), self._chi2(0.95, m))
            nis = test_ratio * gate
            a.tested += 1
            a.nis_per_dof_sum += nis / m
            a.within_95 += nis <= within

    def report(self) -> dict:
        """``{source: {attempts, fused, refused, tested, nis_per_dof_mean, within_95}}``
        (the last two None for a source never tested)."""
        out = {}
        for source, a in sorted(self._by_source.items()):
            n = a.tested
            out[source] = {"attempts": a.attempts, "fused": a.fused, "refused": dict(sorted(a.refused.items())),
                           "tested": n, "nis_per_dof_mean": a.nis_per_dof_sum / n if n else None,
                           "within_95": a.within_95 / n if n else None}
        return out


class _AidTally:
    """One source's counts in :class:`AidConsistency` (slots: ~130k statuses per data hour
    update them; a dict per source with string keys cost more)."""

    __slots__ = ("attempts", "fused", "refused", "tested", "nis_per_dof_sum", "within_95")

    def __init__(self) -> None:
        self.attempts = self.fused = self.tested = self.within_95 = 0
        self.refused: dict[str, int] = {}
        self.nis_per_dof_sum = 0.0


def _filter_report(estimator: Any) -> dict:
    """The filter's own account: the IMU model it chose, resets, zero-velocity updates."""
    imu = estimator.imu_model
    return {"imu_grade": imu.grade, "imu_grade_why": imu.why, "imu_source": imu.source,
            "imu_quantized": imu.quantized, "earth_rotation": imu.earth_rotation,
            "attitude_heading": estimator.heading_source_report(),
            "depth_noise": estimator.depth_noise.report(),
            "resets": dict(sorted(estimator.resets.items())),
            "zero_velocity_updates": estimator.zero_velocity_updates,
            "invalid_reasons_at_end": estimator.invalid_reasons()}


# a first fix is taken for the origin only when the next fix is within reach of it at
# this speed (+ 3σ): a mis-stamped or mis-placed first fix must not move the origin
_ORIGIN_CONFIRM_SPEED_M_S = 5.0


def _fixes_agree(a: Any, b: Any) -> bool:
    """Two fixes within reach of each other (great-circle distance on a sphere)."""
    d_m = 6.371e6 * math.hypot(b.lat_rad - a.lat_rad, (b.lon_rad - a.lon_rad) * math.cos(a.lat_rad))
    return d_m <= _ORIGIN_CONFIRM_SPEED_M_S * abs(b.t_s - a.t_s) + 3.0 * math.hypot(a.sigma_h_m, b.sigma_h_m)


def replay_warnings(summary: dict) -> list[str]:
    """What a user must not miss about a replay, one sentence each (summary ``warnings``)."""
    out = []
    if not summary.get("messages_read"):
        out.append("nothing could be read from the input (empty, unreadable or not a log)")
    elif not summary.get("samples_used"):
        out.append("no usable sample in the input: nothing was navigated")
    elif not summary.get("valid_fraction"):
        what = "no nav state at all" if summary.get("nav_states", 0) == 0 else \
            f"{summary.get('nav_states', 0)} nav states, none valid"
        reasons = ", ".join((summary.get("filter") or {}).get("invalid_reasons_at_end") or []) or "none"
        out.append(f"NO VALID POSITION was produced ({what}; last reasons: {reasons}): "
                   "trajectory.csv is not a navigation solution")
    if "no_motion_measurement" in ((summary.get("filter") or {}).get("invalid_reasons_at_end") or []):
        out.append("no IMU fast enough to integrate, so the attitude drives the strapdown, and at the end "
                   "nothing measured the motion (no recent fix or DVL, no thrust model calibrated for this "
                   "vehicle or by the fixes): its track is kept in trajectory.csv, not called valid — a "
                   "vehicle profile (--config with motion.rpm_table), fixes or a DVL make it a navigation "
                   "solution")
    jumps = summary.get("clock_jumps_s") or []
    if jumps:
        out.append(f"the input's time base jumped {len(jumps)} time(s) "
                   f"({', '.join(f'{j:+.3f} s' for j in jumps[:5])}{', ...' if len(jumps) > 5 else ''}): "
                   "navigation re-based each one; times in the outputs follow the input's")
    gaps = summary.get("data_gaps_s") or []
    if gaps:
        out.append(f"the input misses data {len(gaps)} time(s) "
                   f"({', '.join(f'{t - d:.1f} s at {d:.1f} s' for d, t in gaps[:5])}{', ...' if len(gaps) > 5 else ''}): "
                   "navigation coasted through each, its uncertainty growing")
    depth = (summary.get("filter") or {}).get("depth_noise") or {}
    if depth.get("fraction_at_bound"):
        out.append(f"the depth sensor was noisier than the bound of {depth['max_sigma_m']} m "
                   f"({100 * depth['fraction_at_bound']:.1f} % of depths, latest measured σ "
                   f"{depth['measured_sigma_m']:.3g} m): fused at the bound, "
                   "its innovations fail the integrity test (filter.depth.adaptive_max_sigma_m)")
    unknown = summary.get("unknown_message_types") or []
    if unknown:
        out.append(f"{len(unknown)} message type(s) not understood (counted, not used): {', '.join(unknown)}")
    return out


def place_rows_before_the_first_fix(path: Path, seed: tuple[float, float, float], origin: Any) -> dict:
    """``trajectory.csv``'s rows before the first fix, moved by what that fix moved the
    position (``seed``: its time and north/east shift, :attr:`Estimator.position_seeds`) —
    offline, the dead-reckoned track before a fix is placed by it as the track after it is
    (without, a fix 35 s into a log left 52 m on every earlier row: RMS 16 m where the rest
    was 2 m). Their ``valid`` flags and σ columns stay what they were when computed (a start
    more than ORIGIN_FIX_AT_START_S before the fix: not valid). Returns what was done, for
    ``summary.json``."""
    t_seed, d_north, d_east = seed
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    col = {name: k for k, name in enumerate(header)}
    moved = 0
    for row in body:
        if float(row[col["t_s"]]) >= t_seed:
            break
        north, east = float(row[col["north_m"]]) + d_north, float(row[col["east_m"]]) + d_east
        row[col["north_m"]], row[col["east_m"]] = "%.10g" % north, "%.10g" % east
        if row[col["lat_deg"]]:
            lat, lon = origin.to_geodetic_ne(north, east)
            row[col["lat_deg"]], row[col["lon_deg"]] = "%.9f" % math.degrees(lat), "%.9f" % math.degrees(lon)
        moved += 1
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    return {"t_s": t_seed, "shift_north_m": d_north, "shift_east_m": d_east, "rows": moved}


def nothing_usable(summary: dict) -> bool:
    """The one rule for a non-zero exit: nothing usable could be read."""
    return not summary.get("messages_read") or not summary.get("samples_used")


# An origin taken from a fix more than this long after the data starts is not the start: the
# vehicle may have gone anywhere before it (a fix 45 s in, 70 m from the start, was gated against
# the start's 10 m), so the start is "position unknown" until a fix places it. Sooner, the
# start is the origin within initial.sigma_pos_m — as for a simulator whose radio fix under
# water the filter refuses (surface_only) and whose origin is nevertheless the start.
ORIGIN_FIX_AT_START_S = 10.0


def _read_until_fix(items: Any, max_data_s: float = 600.0, max_items: int = 200_000):
    """Items read until a GNSS/USBL fix confirmed by the next one (both included), at most
    ``max_data_s`` of data or ``max_items``; returns (items read, the fix or None, warnings,
    the data's first time or None).
    A fix the next one does not confirm is passed over; with a single fix in the window,
    that one is taken — each said in ``warnings`` (for summary.json and the log)."""
    head: list = []
    warnings: list[str] = []
    t0 = None
    candidate = None
    for item in items:
        head.append(item)
        kind = getattr(item, "KIND", None)
        if kind in FIX_KINDS and math.isfinite(item.lat_rad) and math.isfinite(item.lon_rad) \
                and (item.lat_rad != 0.0 or item.lon_rad != 0.0) and math.isfinite(item.t_s):
            if candidate is None:
                candidate = item
            elif _fixes_agree(candidate, item):
                return head, candidate, warnings, t0
            else:
                warnings.append(f"origin: the {candidate.KIND} fix at t={candidate.t_s:.3f} s is not confirmed "
                                f"by the next one (t={item.t_s:.3f} s): not taken for the origin")
                candidate = item
        t = getattr(item, "t_s", None)
        if kind == "imu_batch":
            t = float(item.t_s[-1]) if len(item) else None
        if t is not None and math.isfinite(t):
            t0 = t if t0 is None else t0
            if t - t0 > max_data_s:
                break
        if len(head) >= max_items:
            break
    if candidate is not None:
        warnings.append(f"origin: from a single {candidate.KIND} fix at t={candidate.t_s:.3f} s, "
                        "not confirmed by another")
    return head, candidate, warnings, t0


def _finite_or_none(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _json_default(o: Any) -> Any:
    if hasattr(o, "to_dict"):
        return o.to_dict()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


# -- comparisons ----------------------------------------------------------------------------
VARIANTS = ("pure_ins", "static_wrong", "given")
# with a DVL that loses lock (the DVL-outage scenario): INS + DVL without the motion model,
# the static pre-change model, and the model the calibrator learns from the DVL
DVL_VARIANTS = ("pure_ins", "static", "learned")
MOTION_MODEL_OFF = ("filter.learned_velocity.enabled=false",)


def compare_plan(scenario: Any, calibrate: bool) -> list[tuple[str, str, bool]]:
    """``(row name, variant for variant_config, calibrator on)`` per row of ``--compare``.

    A simulated mission with a DVL whose lock comes and goes compares through the outage
    (:data:`DVL_VARIANTS`, the calibrator on for ``learned``); otherwise pure INS / static
    wrong model / as given (``learned`` with ``calibrate``).
    """
    if scenario is not None and getattr(getattr(scenario, "dvl", None), "enabled", False):
        return [("pure_ins", "motion_model_off", False), ("static", "given", False), ("learned", "given", True)]
    return [(("learned" if (v == "given" and calibrate) else v), v, calibrate and v == "given") for v in VARIANTS]


def variant_config(cfg: Any, variant: str, k_v_error: float = 0.1) -> Any:
    """``pure_ins`` (no velocity aiding), ``motion_model_off`` (no learned velocity; DVL and
    visual motion stay), ``static_wrong`` (k_V × (1 + k_v_error)), ``given``."""
    from adaptnav.service.config import ServiceConfig

    if variant == "given":
        return cfg
    raw = as_dict(cfg)
    if variant == "pure_ins":
        return build(ServiceConfig, apply_overrides(raw, list(VELOCITY_AIDS_OFF)))
    if variant == "motion_model_off":
        return build(ServiceConfig, apply_overrides(raw, list(MOTION_MODEL_OFF)))
    if variant == "static_wrong":
        return replace(cfg, motion=replace(cfg.motion, params0=replace(
            cfg.motion.params0, k_v=cfg.motion.params0.k_v * (1.0 + k_v_error))))
    raise ValueError(f"unknown variant {variant!r} (one of {VARIANTS})")


TABLE_KEYS = (("final_horizontal_error_m", "final err (m)"), ("rms_horizontal_error_m", "RMS err (m)"),
              ("drift_percent_since_fix", "% DT since fix"), ("percent_distance_travelled", "% DT"),
              ("current_error_at_last_fix_m_s", "cur err@fix (m/s)"), ("current_error_m_s", "cur err end"),
              ("nees_mean", "NEES mean"), ("nees_fraction_in_95", "NEES in 95%"),
              ("outage_drift_percent", "% DT outage"), ("recovery_correction_sigma", "recovery (σ)"))


def format_table(rows: dict[str, dict]) -> str:
    """Rows name → metrics as an aligned text table."""
    head = ["run"] + [h for _, h in TABLE_KEYS]
    lines = [head]
    for name, m in rows.items():
        cells = [name]
        for key, _ in TABLE_KEYS:
            v = m.get(key) if m else None
            cells.append("–" if v is None else f"{v:.4g}")
        lines.append(cells)
    widths = [max(len(r[i]) for r in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))
                     for r in lines)


def targets_text(metrics: dict) -> str:
    """The navigation-core target figures of one run, one per line."""
    if not metrics:
        return "no truth in the input: no metrics"
    lo, hi = metrics.get("nees_band_95", [math.nan, math.nan])

    def f(key, unit=""):
        v = metrics.get(key)
        return "–" if v is None else f"{v:.4g}{unit}"

    return "\n".join([
        f"drift_percent_since_fix        {f('drift_percent_since_fix', ' %')}  "
        f"(error at end / distance since last fused fix {f('distance_since_fix_m', ' m')})",
        f"final_horizontal_error_m       {f('final_horizontal_error_m', ' m')}",
        f"rms_horizontal_error_m         {f('rms_horizontal_error_m', ' m')}",
        f"distance_travelled_m           {f('distance_travelled_m', ' m')}",
        f"current_error at last fix      {f('current_error_at_last_fix_m_s', ' m/s')}",
        f"current_error_m_s (end)        {f('current_error_m_s', ' m/s')}",
        f"nees_mean (d={metrics.get('nees_dim')})            {f('nees_mean')}  (95 % band of χ²: {lo:.3g}–{hi:.3g})",
        f"nees_fraction_in_95            {f('nees_fraction_in_95')}",
    ])
