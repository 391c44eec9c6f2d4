"""The daemon's voice: lifecycle events of the navigation, logged once each at INFO.

:class:`LifecycleLog` is a runner sink (:mod:`adaptnav.service.runtime.sinks`) that turns the
stream of states, aid statuses and releases into the few lines an operator wants to read
in ``journalctl`` — not one line per sample:

- ``aligned``: the first state (the filter initialised), with where and when;
- ``solution valid`` / ``solution invalid`` on each change (with the horizontal σ);
- ``reset``: each discontinuity (``reset_counter`` stepped: alignment, IMU gap, position reset);
- position fixes (USBL, GNSS): the first accepted one; a *burst* of rejections is one line
  when it starts (with the reason) and one when it ends (how many, how long);
- calibrator releases: accepted (with k_V) or rejected, and why.

Each line also carries a structured ``event`` dict (``extra``), which ``--log-json`` writes
as fields (journald / log collectors can filter on ``event``).
"""
from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from adaptnav.fusion.state import POS_NE
from adaptnav.service.runtime.sinks import Sink

log = logging.getLogger("adaptnav.events")

FIX_SOURCES = ("usbl", "gnss")


def emit(event: str, message: str, *args: Any, level: int = logging.INFO, **fields: Any) -> None:
    """Log ``message % args`` with ``extra={"event": {"event": event, **fields}}``."""
    log.log(level, message, *args, extra={"event": {"event": event, **fields}})


class LifecycleLog(Sink):
    """Runner sink logging lifecycle events (module docstring). ``warnings=False`` (replay):
    every event at INFO — a replay reports its findings in its summary, not as warnings."""

    def __init__(self, warnings: bool = True) -> None:
        self._warn = logging.WARNING if warnings else logging.INFO
        self._aligned = False
        self._valid: bool | None = None
        self._reset_counter: int | None = None
        self._fix_accepted: set[str] = set()
        self._burst: dict[str, dict] = {}   # source → {n, t0_s, reason} while rejections run

    def on_nav(self, state: Any) -> None:
        t = float(state.t_s)
        if self._aligned and state.valid == self._valid:  # nothing to say (every state but a few)
            rc = int(state.reset_counter)
            if rc != self._reset_counter:
                self._on_reset(rc, t)
            return
        cov = state.cov
        sigma_h = math.sqrt(max(float(np.sum(np.diag(np.asarray(cov))[POS_NE])), 0.0))
        if not self._aligned:
            self._aligned = True
            p = state.pos_n_m
            emit("aligned", "aligned: first state at data time %.2f s (depth %.1f m, σ horizontal %.1f m)",
                 t, float(p[2]), sigma_h, t_s=t)
        if state.valid != self._valid:
            if self._valid is not None or state.valid:
                reasons = list(getattr(state, "invalid_reasons", ()) or ())
                why = f"; why: {', '.join(reasons)}" if reasons else ""
                emit("solution_valid" if state.valid else "solution_invalid",
                     "solution %s at data time %.2f s (σ horizontal %.1f m%s)",
                     "valid" if state.valid else "INVALID", t, sigma_h, why,
                     level=logging.INFO if state.valid else self._warn, t_s=t, sigma_h_m=sigma_h,
                     invalid_reasons=reasons)
            self._valid = bool(state.valid)
        rc = int(state.reset_counter)
        if rc != self._reset_counter:
            self._on_reset(rc, t)

    def _on_reset(self, rc: int, t: float) -> None:
        if self._reset_counter is not None:
            emit("reset", "filter reset #%d at data time %.2f s", rc, t, level=self._warn, t_s=t,
                 reset_counter=rc)
        self._reset_counter = rc

    def on_aid(self, statuses: list) -> None:
        for s in statuses:
            if s.source not in FIX_SOURCES:
                continue
            t = float(s.t_s)
            burst = self._burst.get(s.source)
            if s.fused:
                if burst is not None:
                    del self._burst[s.source]
                    emit("fix_rejections_end", "%s fixes accepted again at data time %.2f s after %d rejected "
                         "over %.0f s", s.source, t, burst["n"], t - burst["t0_s"], t_s=t, source=s.source,
                         rejected=burst["n"])
                if s.source not in self._fix_accepted:
                    self._fix_accepted.add(s.source)
                    emit("fix_accepted", "first %s fix accepted at data time %.2f s (test ratio %.2f)",
                         s.source, t, float(s.test_ratio), t_s=t, source=s.source)
            elif burst is None:
                self._burst[s.source] = {"n": 1, "t0_s": t, "reason": s.reason}
                emit("fix_rejections_start", "%s fix rejected at data time %.2f s: %s (test ratio %.2f)",
                     s.source, t, s.reason or "?", float(s.test_ratio), level=self._warn, t_s=t,
                     source=s.source, reason=s.reason)
            else:
                burst["n"] += 1

    def on_release(self, release: Any) -> None:
        t = float(release.t_s)
        k_v = getattr(getattr(release, "params", None), "k_v", math.nan)
        if release.accepted:
            emit("release_accepted", "calibrator release accepted at data time %.1f s: k_V %.4g%s", t, k_v,
                 f" ({release.reason})" if release.reason else "", t_s=t, k_v=k_v, reason=release.reason)
        else:
            emit("release_rejected", "calibrator release rejected at data time %.1f s: %s", t,
                 release.reason or "no reason given", level=self._warn, t_s=t, reason=release.reason)

    def close(self) -> None:
        for src, burst in self._burst.items():
            emit("fix_rejections_open", "%s: %d fixes rejected since data time %.2f s (%s), none accepted since",
                 src, burst["n"], burst["t0_s"], burst["reason"], level=self._warn, source=src,
                 rejected=burst["n"])
