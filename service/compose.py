"""The composition root: where the system is wired. The daemon, replay, the demo and the
benchmarks build their estimator, calibrator and sinks here, from one
:class:`~adaptnav.service.config.ServiceConfig`, so each is built one way.

- :func:`make_estimator` — the ESKF (:class:`adaptnav.fusion.eskf.Estimator`; with side-scan
  loop closures :class:`adaptnav.service.loop_closures.SideScanEstimator`);
- :func:`make_calibrator` — the EM calibrator in this process
  (:class:`adaptnav.calibration.online.OnlineCalibrator`), as the child processes and the
  calibrator node run it;
- :func:`make_lagged_calibrator` — replay's calibrator with deterministic application
  (:mod:`adaptnav.service.calibrator.lagged`);
- :func:`make_live_calibrator` — the daemon's supervised child
  (:mod:`adaptnav.service.calibrator.live`).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.motion_model import MotionParams


def make_estimator(cfg: Any, params0: MotionParams | None = None, origin: GeoOrigin | None = None, *,
                   objects: bool = True):
    """The navigation filter from a ServiceConfig (``params0`` default
    ``cfg.motion.params0``; ``origin`` default ``cfg.origin``). It also takes side-scan pings
    and the object sightings the calibrator returns, and fuses leg-to-leg loop closures
    (``filter.loop_closure.enabled``; :class:`adaptnav.service.loop_closures.SideScanEstimator`);
    ``objects=False`` when no sightings can come (no calibrator in the runner): pings then
    cost nothing."""
    from adaptnav.service.loop_closures import SideScanEstimator

    return SideScanEstimator(cfg.filter, cfg.motion.params0 if params0 is None else params0, cfg.motion.rpm_table,
                             cfg.origin.geo() if origin is None else origin, objects=objects)


def make_calibrator(cfg: Any, params0: MotionParams, seed: int):
    """An :class:`~adaptnav.calibration.online.OnlineCalibrator` from a ServiceConfig.

    Without its own origin, the calibrator uses the service's mission origin, so its
    poses and the filter's share one NED frame.
    """
    from adaptnav.calibration.online import OnlineCalibrator

    online = cfg.calibrator.online
    if not (math.isfinite(online.origin_lat_deg) and math.isfinite(online.origin_lon_deg)):
        online = dataclasses.replace(online, origin_lat_deg=cfg.origin.lat_deg,
                                     origin_lon_deg=cfg.origin.lon_deg)
    dvl = cfg.filter.dvl  # the DVL teacher needs the head's mounting (calibration.dvl_teacher)
    return OnlineCalibrator(online, params0, cfg.motion.rpm_table, np.random.default_rng(seed),
                            dvl_mount=(dvl.lever_arm_b_m, dvl.rotation_bd_rpy_rad))


def make_lagged_calibrator(cfg: Any, params0: MotionParams, location: str = "process",
                           latency_s: float | None = None):
    """Replay's calibrator (:class:`~adaptnav.service.calibrator.lagged.LaggedCalibrator`):
    ``location`` ``"process"`` (child process) or ``"inline"``; ``latency_s`` default
    ``cfg.calibrator.latency_s``."""
    from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator, ProcessBackend

    lag = cfg.calibrator.latency_s if latency_s is None else latency_s
    product_lag = min(cfg.calibrator.product_latency_s, lag)
    seed = cfg.calibrator.seed
    if location == "inline":
        backend: Any = InlineBackend(make_calibrator(cfg, params0, seed))
    elif location == "process":
        backend = ProcessBackend(cfg, params0, seed)
    else:
        raise ValueError(f"calibrator location {location!r}: expected 'process' or 'inline'")
    return LaggedCalibrator(backend, lag, product_lag)


def make_live_calibrator(cfg: Any, params0: MotionParams, batch_s: float = 0.05):
    """The daemon's calibrator child (:class:`~adaptnav.service.calibrator.live.CalibratorProcess`),
    not yet started."""
    from adaptnav.service.calibrator.live import CalibratorProcess

    return CalibratorProcess(cfg, params0, batch_s=batch_s)
