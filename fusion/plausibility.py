r"""Plausibility at the door: every sample is checked against physical bounds and against
the data clock before it reaches the filter (or health, or the output epochs).

Why a door in front of the filter: a finite but absurd value (an IMU sample of 1e6 m/s²,
a gyro of 1e4 rad/s, a fix 4,000 km away) passes every finiteness test and wrecks the
state in one step; a single sample stamped 20 s (or 80 years) in the future would move the
runner's output epochs and the health clock with it. Bounds are physical, per kind:

- ``imu``: every axis of the specific force within ``max_specific_force_m_s2`` and of the
  rate within ``max_rate_rad_s`` (the full scale of the IMU: a value beyond it is not a
  measurement);
- ``rpm`` within ``max_rpm``; ``dvl`` velocity axes within ``max_speed_m_s``;
- ``depth``: the pressure's depth within [``min_depth_m``, ``max_depth_m``];
- ``heading``/``attitude``: angles within one turn (roll/pitch within ±π);
- ``gnss``/``usbl``: σ positive and below ``max_fix_sigma_m``, position within
  ``max_distance_from_origin_m`` of the mission origin (when one is set);
- ``truth`` passes untouched (it is never fused).

Time. The door keeps the data clock ``D`` (the latest accepted sample time, any stream).
A sample more than ``max_ahead_s`` after ``D`` or more than ``max_behind_s`` before it is
rejected (``time_ahead`` / ``time_behind``) — a single outlier stamp is never taken for a
clock jump. A *jump* is a stream that continues consistently from a new time:
``jump_confirm_samples`` samples in a row of one stream, increasing, each within
``max_ahead_s`` of the previous, all on the far side of ``D``, and no other stream going
on at ``D`` meanwhile — if one does, the clock did not jump: the stream is stamped by a clock
of its own (a driver's clock off) and stays refused (it re-based the whole filter, and the
IMU, still on ``D``, then came too late to be used). Then the jump is accepted:
``D`` moves to the new time, the jump is counted (``clock_jump``) and recorded in
:attr:`Door.jumps` as ``(kind, from_s, to_s)``, and :meth:`Door.check` returns the size of
the jump so that the caller re-bases what depends on time (the estimator's clock,
:meth:`adaptnav.fusion.eskf.Estimator.shift_time`) — right for a clock that *steps* (a
companion computer's clock set by NTP or GNSS after boot). But a forward jump may instead be
data *missing* — a telemetry dropout, a damaged block of a log, a link that stalled — during
which the vehicle moved. The caller that can tell them apart gives ``forward_jump_is_gap``,
asked ``(from_s, to_s)`` for each confirmed forward jump: an autopilot's boot clock cannot step
forward (tlogs, DataFlash logs: always a gap); live, the wall clock tells (it advanced with
the data across a dropout, not across a step); a recording's log clock likewise. For a gap
``D`` moves on, ``data_gap`` is counted and recorded in :attr:`Door.gaps`, and nothing is
re-based (the filter coasts through the gap, its covariance growing).

Non-finite numbers are not judged here: the estimator rejects and counts them
(``non_finite``). Pure functions of the samples: no clock, no I/O.
"""
from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .frames import GRAVITY_M_S2, GeoOrigin
from .strapdown import imu_run_in_bounds


@dataclass(frozen=True)
class PlausibilityConfig:
    """Bounds of the door (see the module docstring).

    The IMU bounds are full-scale ranges: 16 g and 2000 °/s cover consumer MEMS parts
    (ArduSub's, e.g. ICM-20602/MPU-6000 at their widest range) and tactical units
    (HG1120: 16 g, 2000 °/s); nothing an AUV does comes near them.
    """

    enabled: bool = True
    max_specific_force_m_s2: float = 16.0 * GRAVITY_M_S2
    max_rate_rad_s: float = math.radians(2000.0)
    max_rpm: float = 20000.0
    max_speed_m_s: float = 15.0                # DVL velocity per axis (DVLs read ≤ ~10 m/s)
    min_depth_m: float = -50.0                 # above the surface: a pressure sensor in air
    max_depth_m: float = 11000.0
    max_fix_sigma_m: float = 10000.0
    max_distance_from_origin_m: float = 200000.0
    max_ahead_s: float = 5.0                   # ahead of the data clock: outlier (or a jump)
    max_behind_s: float = 30.0                 # behind it: outlier (the estimator's own late window is shorter)
    jump_confirm_samples: int = 5              # a stream continuing this many samples from a new time: a jump

    def validate(self) -> None:
        for name in ("max_specific_force_m_s2", "max_rate_rad_s", "max_rpm", "max_speed_m_s",
                     "max_fix_sigma_m", "max_distance_from_origin_m", "max_ahead_s", "max_behind_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"plausibility.{name} must be > 0")
        if not self.min_depth_m < self.max_depth_m:
            raise ValueError("plausibility.min_depth_m must be < max_depth_m")
        if not 2 <= self.jump_confirm_samples <= 1000:
            raise ValueError("plausibility.jump_confirm_samples must be within [2, 1000]")


class _Candidate:
    __slots__ = ("t_first", "t_prev", "n")

    def __init__(self, t: float) -> None:
        self.t_first = self.t_prev = t
        self.n = 1


class Door:
    """The plausibility check (module docstring).

    Parameters
    ----------
    config : PlausibilityConfig
    origin : GeoOrigin
        Mission origin; a zero origin (lat = lon = 0) means "not set" and disables the
        distance bound.
    water_density_kg_m3, atmospheric_pressure_pa : float
        For the pressure → depth bound.
    forward_jump_is_gap : callable ``(from_s, to_s) -> bool``, optional
        Whether a confirmed forward jump of the data clock is data missing (coasted through)
        rather than a step of the clock (re-based); None: always a step.
    """

    def __init__(self, config: PlausibilityConfig, origin: GeoOrigin | None = None,
                 water_density_kg_m3: float = 1025.0, atmospheric_pressure_pa: float = 101325.0,
                 forward_jump_is_gap: Callable[[float, float], bool] | None = None) -> None:
        self.config = config
        # whether a confirmed forward jump from_s → to_s is data missing rather than a new
        # time base (module docstring); None: every jump is a clock step
        self.forward_jump_is_gap = forward_jump_is_gap
        self.gaps: list[tuple[str, float, float]] = []
        self.origin = origin
        self._origin_set = origin is not None and (origin.lat_rad != 0.0 or origin.lon_rad != 0.0)
        self._rho_g = water_density_kg_m3 * GRAVITY_M_S2
        self._p_atm = atmospheric_pressure_pa
        self.rejected: Counter = Counter()   # by reason (``door:<reason>`` when merged)
        self.jumps: list[tuple[str, float, float]] = []
        self.t_data_s = -math.inf
        self._cand: dict[str, _Candidate] = {}
        # what check() reads of the (frozen) config with every sample
        self._enabled = config.enabled
        self._max_behind_s, self._max_ahead_s = config.max_behind_s, config.max_ahead_s

    # -- time ------------------------------------------------------------------------------
    def _time(self, kind: str, t: float) -> tuple[str | None, float]:
        """``(reason or None, jump size s)`` for a sample of ``kind`` at ``t``."""
        c = self.config
        d = self.t_data_s
        # within the window of the data clock (the commonest case, tested first: False for a
        # non-finite stamp and before the first one)
        in_window = d - c.max_behind_s <= t <= d + c.max_ahead_s
        if not in_window:
            if not math.isfinite(t):
                return None, 0.0  # the source/estimator count non-finite stamps
            in_window = d == -math.inf
        if in_window:
            if self._cand:
                self._stream_on_time(kind)
            if t > d:
                self.t_data_s = t
            return None, 0.0
        reason = "time_ahead" if t > d else "time_behind"
        cand = self._cand.get(kind)
        if cand is not None and 0.0 < t - cand.t_prev <= c.max_ahead_s:
            cand.n += 1
            cand.t_prev = t
        else:
            cand = self._cand[kind] = _Candidate(t)
        if cand.n < c.jump_confirm_samples:
            self.rejected[reason] += 1
            return reason, 0.0
        del self._cand[kind]
        self._cand.clear()
        if t > d and self.forward_jump_is_gap is not None and self.forward_jump_is_gap(d, t):
            # data missing (a dropout, a damaged block): time passed, the filter coasts through
            self.gaps.append((kind, d, t))
            self.rejected["data_gap"] += 1
            self.t_data_s = t
            return None, 0.0
        # a stream that continues consistently from a new time: a clock jump
        self.jumps.append((kind, d, t))
        self.rejected["clock_jump"] += 1
        self.t_data_s = t
        return None, t - d

    def _stream_on_time(self, kind: str) -> None:
        """A sample of ``kind`` within the window of the data clock: its own candidate jump
        ends, and every other stream's starts over — the clock did not jump while this stream
        goes on at it; a stream that continues from another time is stamped by a clock of its
        own (a driver's clock off), and its samples stay refused."""
        self._cand.pop(kind, None)
        for cand in self._cand.values():
            cand.n = 0

    # -- values ----------------------------------------------------------------------------
    def _value(self, s) -> str | None:
        c = self.config
        kind = s.KIND
        if kind == "imu":
            if _over(s.specific_force_b_m_s2, c.max_specific_force_m_s2):
                return "imu_acc_range"
            if _over(s.omega_b_rad_s, c.max_rate_rad_s):
                return "imu_rate_range"
        elif kind == "rpm":
            if abs(s.rpm) > c.max_rpm:
                return "rpm_range"
        elif kind == "dvl":
            if _over(s.vel_d_m_s, c.max_speed_m_s):
                return "dvl_speed_range"
        elif kind == "depth":
            depth = (s.pressure_pa - self._p_atm) / self._rho_g
            if depth < c.min_depth_m or depth > c.max_depth_m:
                return "depth_range"
        elif kind == "heading":
            if abs(s.yaw_rad) > 2.0 * math.pi + 0.1:
                return "angle_range"
        elif kind == "attitude":
            if abs(s.roll_rad) > math.pi + 0.1 or abs(s.pitch_rad) > math.pi + 0.1 \
                    or abs(s.yaw_rad) > 2.0 * math.pi + 0.1:
                return "angle_range"
        elif kind in ("gnss", "usbl"):
            if abs(s.lat_rad) > math.pi / 2 or abs(s.lon_rad) > 2.0 * math.pi:
                return "fix_position_range"
            if s.sigma_h_m <= 0.0 or s.sigma_h_m > c.max_fix_sigma_m:
                return "fix_sigma_range"
            if kind == "usbl" and (s.depth_m < c.min_depth_m or s.depth_m > c.max_depth_m):
                return "depth_range"
            if self._origin_set and math.isfinite(s.lat_rad) and math.isfinite(s.lon_rad):
                ne = self.origin.to_ned(s.lat_rad, s.lon_rad)[:2]
                if math.hypot(float(ne[0]), float(ne[1])) > c.max_distance_from_origin_m:
                    return "fix_far_from_origin"
        return None

    # -- the door --------------------------------------------------------------------------
    def check(self, sample) -> tuple[bool, float]:
        """Judge one sample: ``(accepted, clock jump s)``; a rejection is counted by reason."""
        kind = sample.KIND
        if kind == "truth" or not self._enabled:
            return True, 0.0
        reason = self._value(sample)
        if reason is not None:
            self.rejected[reason] += 1
            return False, 0.0
        t = float(sample.t_s)
        # _time's commonest case first, without its call (every live sample): within the window
        # of the data clock, no stream on a candidate jump
        d = self.t_data_s
        if d - self._max_behind_s <= t <= d + self._max_ahead_s and not self._cand:
            if t > d:
                self.t_data_s = t
            return True, 0.0
        reason, jump = self._time(kind, t)
        return reason is None, jump

    def check_batch(self, t_s: np.ndarray, f_b: np.ndarray, w_b: np.ndarray) -> tuple[np.ndarray | None, float]:
        """Judge an IMU run: ``(keep mask or None for all, clock jump s)``.

        Fast path: every value within range, the first stamp within the window of the data
        clock and every step positive and short — one vectorised test. Otherwise sample by
        sample (rare).
        """
        c = self.config
        if not c.enabled or t_s.size == 0:
            return None, 0.0
        d = self.t_data_s
        # one compiled test (the replay's every IMU batch; a NaN fails it too)
        t_lo, t_hi = (-math.inf, math.inf) if d == -math.inf else (d - c.max_behind_s, d + c.max_ahead_s)
        if imu_run_in_bounds(t_s, f_b, w_b, c.max_specific_force_m_s2, c.max_rate_rad_s, t_lo, t_hi,
                             c.max_ahead_s):
            if self._cand:
                self._stream_on_time("imu")
            if t_s[-1] > d:
                self.t_data_s = float(t_s[-1])
            return None, 0.0
        keep = np.ones(t_s.size, dtype=bool)
        jump = 0.0
        for i in range(t_s.size):
            with np.errstate(invalid="ignore"):
                if np.any(np.abs(f_b[i]) > c.max_specific_force_m_s2):
                    self.rejected["imu_acc_range"] += 1
                    keep[i] = False
                    continue
                if np.any(np.abs(w_b[i]) > c.max_rate_rad_s):
                    self.rejected["imu_rate_range"] += 1
                    keep[i] = False
                    continue
            reason, j = self._time("imu", float(t_s[i]))
            if reason is not None:
                keep[i] = False
            jump += j
        return keep, jump


def _over(vec, bound: float) -> bool:
    """Any component of the sequence ``vec`` (a sample's tuple, list or array) beyond ``bound``
    in magnitude (NaN is not judged here)."""
    try:  # three components (the door's every vector): the tests written out, no loop
        v0, v1, v2 = vec
    except (TypeError, ValueError):
        for v in vec:  # a loop, not any(<generator>): the door runs on every live sample
            if abs(v) > bound:
                return True
        return False
    return abs(v0) > bound or abs(v1) > bound or abs(v2) > bound
