"""What the calibrator and the filter learn from side-scan landmarks, through the service path.

The landmark survey of :mod:`adaptnav.service.tools.landmarks_experiment` (reciprocal
lawnmower legs, USBL lost after 20 min, no DVL, the water changes at 30 min: k_V 1.0 → 0.9)
run as the daemon and replay run it: the runner, the estimator of
:func:`adaptnav.service.compose.make_estimator` (loop closures from the side-scan objects,
:mod:`adaptnav.service.loop_closures`) and the online calibrator (replay's lagged calibrator,
in this process), which detects the objects and learns from the pairs the filter associated
(:mod:`adaptnav.calibration.sidescan`). After the USBL fixes stop, its only teachers are the
landmarks and the IMU (and the heading aid).

Measured (:func:`run`), at ``t = change + after_s`` (default 10 min after the change):

* ``k_speed_error_percent_10min_after_change``: |k_V − k_V true| / k_V true of the
  calibrator's latest accepted release computed from data up to then, %;
* ``filter_speed_scale_error_percent_10min_after_change``: the same for the filter's speed
  scale ``k_speed · k_V`` at that time (it also learns from the closures it fuses);
* ``drift_percent_with_landmarks_and_calibrator``: horizontal error at the end / distance
  since the last USBL fix, %;
* ``teachers_after_change``: the teachers of the calibrator's releases after the change.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np


class _Collector:
    """Sink: releases, loop-closure statuses, the filter's speed scale at ``t_eval_s``."""

    def __init__(self, estimator: Any, t_eval_s: float) -> None:
        self.estimator = estimator
        self.t_eval_s = t_eval_s
        self.releases: list = []
        self.closures = 0
        self.closures_fused = 0
        self.speed_scale_at_eval = math.nan

    def on_nav(self, state: Any) -> None:
        if state.t_s <= self.t_eval_s:
            self.speed_scale_at_eval = float(state.k_speed) * float(self.estimator.motion_params.k_v)

    def on_aid(self, statuses: list) -> None:
        for s in statuses:
            if s.source == "loop_closure":
                self.closures += 1
                self.closures_fused += int(s.fused)

    def on_release(self, release: Any) -> None:
        self.releases.append(release)


def run(scenario: Any, *, after_s: float = 600.0, location: str = "inline") -> dict[str, Any]:
    """Simulate ``scenario`` and run it through the runner with the calibrator (module docstring)."""
    from adaptnav.service.compose import make_estimator, make_lagged_calibrator
    from adaptnav.service.runtime.clock import LogClock
    from adaptnav.service.runtime.replay import build_config
    from adaptnav.service.runtime.runner import default_release_gate
    from adaptnav.service.runtime.runner import run as run_loop
    from adaptnav.sim.simulator import simulate

    res = simulate(scenario)
    cfg = build_config(scenario)
    t_change = scenario.change_at_s
    t_eval = t_change + after_s if math.isfinite(t_change) else math.nan
    if not t_eval <= scenario.duration_s:  # no change, or the run ends before it is scored: no k_V figures
        t_eval = math.nan
    k_true = scenario.params_after().k_v
    est = make_estimator(cfg)
    cal = make_lagged_calibrator(cfg, cfg.motion.params0, location)
    sink = _Collector(est, t_eval)
    try:
        run_loop(res.iter_blocks(), est, [sink], LogClock(), cal,
                 release_gate=default_release_gate(cfg.calibrator.online))
    finally:
        cal.close()
    accepted = [r for r in sink.releases if r.accepted and r.t_s <= t_eval]
    k_cal = accepted[-1].params.k_v if accepted else math.nan
    teachers = sorted({t for r in sink.releases if r.accepted and t_change < r.t_s <= t_eval for t in r.teachers})

    dense = res.dense
    t_fix = scenario.usbl.lost_after_s if scenario.usbl.enabled and scenario.usbl.lost_after_s else 0.0
    i0 = int(np.searchsorted(dense.t_s, t_fix))
    dist = float(np.sum(np.linalg.norm(np.diff(dense.pos_n_m[i0:, :2], axis=0), axis=1)))
    ns = est.nav_state()
    k = min(int(np.searchsorted(dense.t_s, ns.t_s)), dense.t_s.size - 1)
    err = float(np.linalg.norm(ns.pos_n_m[:2] - dense.pos_n_m[k, :2]))

    def pct(x: float) -> float | None:
        return 100.0 * abs(x - k_true) / k_true if math.isfinite(x) else None

    return {
        "k_speed_error_percent_10min_after_change": pct(k_cal),
        "k_v_calibrator_10min_after_change": k_cal if math.isfinite(k_cal) else None,
        "k_v_true_after_change": k_true,
        "filter_speed_scale_error_percent_10min_after_change": pct(sink.speed_scale_at_eval),
        "teachers_after_change": teachers,
        "drift_percent_with_landmarks_and_calibrator": 100.0 * err / dist if dist > 0 else None,
        "calibrator_loop_closures": sink.closures,
        "calibrator_loop_closures_fused": sink.closures_fused,
    }
