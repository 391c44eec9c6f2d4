"""Health accumulator of the runner: what the daemon publishes at 1 Hz on
``adaptnav/<v>/health`` and what replay writes into ``summary.json``.

It counts, per sensor kind, samples seen, the data time first/last seen and a recent
rate; rejected samples by reason (the estimator's own ``rejected`` counter, plus decode
errors, corrupt frames and processing errors reported by the service); the calibrator's
state and last release; the input queue depth. A sensor is *silent* when it has not
been seen for ``silent_after_s`` seconds of data time.

Recent rate: samples are counted in 1-s buckets of data time; the rate is the count over
the last ``rate_window_s`` complete buckets divided by the window (the mean rate since
first seen while less than a window has elapsed).
"""
from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Mapping


@dataclass(slots=True)
class _SensorStats:
    count: int = 0
    first_t_s: float = math.nan
    last_t_s: float = math.nan
    buckets: deque = field(default_factory=deque)  # (int second, count)
    # the latest bucket (buckets[-1]) and the second it ends at, for Health.on_sample's fast path
    # (-inf: no bucket)
    last_bucket: list | None = None
    last_bucket_end_s: float = -math.inf

    def add(self, t_s: float, n: int, keep_s: int) -> None:
        self.count += n
        if math.isnan(self.first_t_s) or t_s < self.first_t_s:
            self.first_t_s = t_s
        if math.isnan(self.last_t_s) or t_s > self.last_t_s:
            self.last_t_s = t_s
        sec = math.floor(t_s)
        if self.buckets and self.buckets[-1][0] == sec:
            self.buckets[-1][1] += n
        elif not self.buckets or sec > self.buckets[-1][0]:
            self.last_bucket = [sec, n]
            self.last_bucket_end_s = sec + 1
            self.buckets.append(self.last_bucket)
            while self.buckets and self.buckets[0][0] < sec - keep_s:
                self.buckets.popleft()
        # a late sample (older bucket) only counts in the totals: rates are approximate

    def clear_buckets(self) -> None:
        self.buckets.clear()
        self.last_bucket, self.last_bucket_end_s = None, -math.inf

    def rate_hz(self, now_s: float, window_s: int) -> float:
        if self.count == 0 or not math.isfinite(now_s) or math.isnan(self.first_t_s):
            return 0.0  # (only samples without a usable time seen: no rate)
        now_sec = math.floor(now_s)
        lo = now_sec - window_s
        n = sum(c for s, c in self.buckets if lo <= s < now_sec)
        span = now_sec - max(lo, math.floor(self.first_t_s))
        if span <= 0:
            span_s = max(self.last_t_s - self.first_t_s, 0.0)
            return (self.count - 1) / span_s if span_s > 0 else 0.0
        return n / span


class Health:
    """Counts and flags for the health report (see module docstring).

    Parameters
    ----------
    silent_after_s : float
        Data seconds without a sample after which a sensor is reported silent.
    rate_window_s : int
        Width of the recent-rate window (s).
    """

    def __init__(self, silent_after_s: float = 10.0, rate_window_s: int = 5) -> None:
        self.silent_after_s = float(silent_after_s)
        self.rate_window_s = int(rate_window_s)
        self._sensors: dict[str, _SensorStats] = {}
        self.rejected: Counter[str] = Counter()       # service-side: decode/corrupt/errors
        self.estimator_rejected: Mapping[str, int] | None = None  # live view of estimator.rejected
        self.door_rejected: Mapping[str, int] | None = None  # live view of the plausibility door's
        self.calibrator_state: str = "off"
        self.last_release: dict[str, Any] | None = None
        self.releases: int = 0
        self.releases_accepted: int = 0
        self.queue_depth: int = 0
        self.t_s: float = math.nan
        self.state_saves: int = 0           # learned state written (persistence)
        self.state_save_failures: int = 0   # ... and attempts that failed (disk full, read-only)
        self.state_save_error: str = ""     # why the last one failed ("" once a save succeeds)
        self.memory_trims: int = 0          # heap returned to the system after a burst drained

    # -- feeding ---------------------------------------------------------------------
    def on_sample(self, kind: str, t_s: float, n: int = 1) -> None:
        """``n`` samples of ``kind`` seen, the last at data time ``t_s``."""
        try:  # (a subscript, not a get call: every sample and IMU batch)
            stats = self._sensors[kind]
        except KeyError:
            stats = self._sensors[kind] = _SensorStats()
        # fast path (the common case): in order, same 1-s bucket as the last sample (NaN: not)
        if stats.last_t_s <= t_s < stats.last_bucket_end_s:
            stats.count += n
            stats.last_t_s = t_s
            stats.last_bucket[1] += n
        elif math.isfinite(t_s):
            stats.add(t_s, n, self.rate_window_s + 1)
        else:
            stats.count += n
            return
        if not (t_s <= self.t_s):
            self.t_s = t_s

    def shift_time(self, delta_s: float) -> None:
        """The input's clock jumped by ``delta_s`` (re-based by the runner): every sensor's
        times move with it, so none looks silent or far ahead (rates restart)."""
        for s in self._sensors.values():
            s.first_t_s += delta_s
            s.last_t_s += delta_s
            s.clear_buckets()
        self.t_s += delta_s

    def on_rejected(self, reason: str, n: int = 1) -> None:
        """Count ``n`` inputs the service itself refused (decode error, corrupt frame, ...)."""
        if n:
            self.rejected[reason] += n

    def on_state_saved(self, error: str = "") -> None:
        """A save of the learned state succeeded (``error`` empty) or failed (why)."""
        if error:
            self.state_save_failures += 1
        else:
            self.state_saves += 1
        self.state_save_error = error

    def on_release(self, release: Any) -> None:
        """A calibrator release (accepted or not)."""
        self.releases += 1
        accepted = bool(getattr(release, "accepted", False))
        self.releases_accepted += int(accepted)
        params = getattr(release, "params", None)
        to_dict = getattr(params, "to_dict", None)
        self.last_release = {
            "t_s": float(getattr(release, "t_s", math.nan)),
            "accepted": accepted,
            "reason": str(getattr(release, "reason", "")),
            "log_likelihood": float(getattr(release, "log_likelihood", math.nan)),
            "params": to_dict() if callable(to_dict) else None,
        }

    # -- reading ---------------------------------------------------------------------
    def rejected_by_reason(self) -> dict[str, int]:
        """Estimator rejections and service-side rejections, merged, sorted by reason."""
        total: Counter[str] = Counter(self.rejected)
        for view in (self.estimator_rejected, self.door_rejected):
            if view:
                total.update(dict(view))
        return {k: int(total[k]) for k in sorted(total) if total[k]}

    def silent_sensors(self, now_s: float | None = None) -> list[str]:
        now = self.t_s if now_s is None else now_s
        return sorted(k for k, s in self._sensors.items()
                      if math.isfinite(now) and (math.isnan(s.last_t_s)
                                                 or now - s.last_t_s > self.silent_after_s))

    def report(self, now_s: float | None = None) -> dict[str, Any]:
        """JSON-ready health dict at data time ``now_s`` (default: latest data time seen)."""
        now = self.t_s if now_s is None or not math.isfinite(now_s) else now_s
        sensors = {}
        for kind in sorted(self._sensors):
            s = self._sensors[kind]
            silent = math.isfinite(now) and (math.isnan(s.last_t_s)
                                             or now - s.last_t_s > self.silent_after_s)
            sensors[kind] = {
                "count": s.count,
                "rate_hz": round(s.rate_hz(now, self.rate_window_s), 6),
                "last_seen_t_s": None if math.isnan(s.last_t_s) else s.last_t_s,
                "age_s": None if math.isnan(s.last_t_s) or not math.isfinite(now) else now - s.last_t_s,
                "silent": bool(silent),
            }
        return {
            "t_s": None if not math.isfinite(now) else now,
            "sensors": sensors,
            "silent": [k for k, v in sensors.items() if v["silent"]],
            "rejected": self.rejected_by_reason(),
            "calibrator": {
                "state": self.calibrator_state,
                "releases": self.releases,
                "releases_accepted": self.releases_accepted,
                "last_release": self.last_release,
            },
            "queue_depth": int(self.queue_depth),
            "persistence": {"saves": self.state_saves, "failures": self.state_save_failures,
                            "last_error": self.state_save_error or None},
            "memory_trims": self.memory_trims,
        }
