"""Clocks of the runner loop: the only thing (with the source and sinks) that differs
between live operation and replay (DESIGN.md "Service").

A clock is asked, before each item is processed, to :meth:`wait_until` the item's data
time ``t_s``; it also tells the data time "now" (:meth:`now_data_s`, used by health to
flag silent sensors) and wall time (:meth:`wall_s`, for statistics only).

- :class:`LogClock` — replay as fast as the CPU allows: never waits; "now" is the last
  data time seen.
- :class:`RealtimeClock` — replay paced at ``speed`` × real time: waits until
  ``(t_s − t0_s) / speed`` monotonic seconds have passed since the first item.
- :class:`LiveClock` — live: data arrives in real time from the bus, so it never waits;
  "now" advances with :func:`time.monotonic`, anchored to the first sample's data time,
  so a sensor that stops sending is seen as silent even if nothing else arrives. It also
  tells a dropout from a step of the data's clock (:meth:`LiveClock.forward_jump_is_gap`).

Only ``service/`` reads a wall clock (DESIGN.md layout rules); all take ``time.monotonic``.
"""
from __future__ import annotations

import math
import time
from typing import Any, Protocol


class Clock(Protocol):
    """What the runner needs from a clock."""

    def wait_until(self, t_s: float, stop: Any = None) -> None:
        """Block until data time ``t_s`` may be processed (or ``stop`` is set)."""

    def now_data_s(self) -> float:
        """Current data time (s); NaN before the first item."""

    def wall_s(self) -> float:
        """Monotonic wall seconds since the clock was created."""


class _WallMixin:
    def _init_wall(self) -> None:
        self._wall0 = time.monotonic()

    def wall_s(self) -> float:
        return time.monotonic() - self._wall0


class LogClock(_WallMixin):
    """As fast as possible: :meth:`wait_until` only records the data time."""

    def __init__(self) -> None:
        self._init_wall()
        self._t_s = math.nan

    def wait_until(self, t_s: float, stop: Any = None) -> None:
        if not (t_s <= self._t_s):  # also true while _t_s is NaN
            self._t_s = t_s

    def now_data_s(self) -> float:
        return self._t_s

    def shift_time(self, delta_s: float) -> None:
        """The input's clock jumped by ``delta_s`` (the runner re-bases)."""
        self._t_s += delta_s


def _stopped(stop: Any) -> bool:
    if stop is None:
        return False
    is_set = getattr(stop, "is_set", None)
    return bool(is_set() if callable(is_set) else stop())


class RealtimeClock(_WallMixin):
    """Paces data time against :func:`time.monotonic` at ``speed`` × real time.

    Parameters
    ----------
    speed : float
        Data seconds per wall second (1.0 = real time, 10.0 = ten times faster). > 0.
    max_sleep_s : float
        Longest single sleep, so a ``stop`` request is honoured quickly.
    """

    def __init__(self, speed: float = 1.0, max_sleep_s: float = 0.1) -> None:
        if not (speed > 0.0 and math.isfinite(speed)):
            raise ValueError(f"RealtimeClock: speed must be a positive number, got {speed}")
        self._init_wall()
        self.speed = float(speed)
        self.max_sleep_s = max_sleep_s
        self._t0_s = math.nan
        self._wall_anchor = math.nan
        self._t_s = math.nan

    def wait_until(self, t_s: float, stop: Any = None) -> None:
        if math.isnan(self._t0_s):
            self._t0_s = t_s
            self._wall_anchor = time.monotonic()
        if not (t_s <= self._t_s):
            self._t_s = t_s
        due = self._wall_anchor + (t_s - self._t0_s) / self.speed
        while not _stopped(stop):
            remaining = due - time.monotonic()
            if remaining <= 0.0:
                return
            wait = getattr(stop, "wait", None)
            if callable(wait):  # threading.Event: wakes at once on stop
                wait(min(remaining, self.max_sleep_s))
            else:
                time.sleep(min(remaining, self.max_sleep_s))

    def now_data_s(self) -> float:
        if math.isnan(self._t0_s):
            return math.nan
        return self._t0_s + (time.monotonic() - self._wall_anchor) * self.speed

    def shift_time(self, delta_s: float) -> None:
        """The input's clock jumped by ``delta_s``: pacing continues from the new time."""
        self._t0_s += delta_s
        self._t_s += delta_s


class LiveClock(_WallMixin):
    """Live data: never waits; data time "now" follows the monotonic clock.

    The first :meth:`wait_until` anchors data time to monotonic time; afterwards
    ``now_data_s() = t_first_s + (monotonic − monotonic_first)`` (never behind the latest
    data time seen, in case the sensor clock runs fast).
    """

    # a forward jump is a dropout when the wall clock advanced at least this fraction of it
    GAP_WALL_FRACTION = 0.5

    def __init__(self) -> None:
        self._init_wall()
        self._offset_s = math.nan
        self._t_s = math.nan
        self._t_wall_s = math.nan  # monotonic time at which the latest data time was seen

    def wait_until(self, t_s: float, stop: Any = None) -> None:
        now = time.monotonic()
        if math.isnan(self._offset_s):
            self._offset_s = t_s - now
        if not (t_s <= self._t_s):
            self._t_s = t_s
            self._t_wall_s = now

    def forward_jump_is_gap(self, from_s: float, to_s: float) -> bool:
        """A stream went on from data time ``to_s`` after ``from_s`` (the latest data time):
        data missing (a link that dropped, a driver that stalled — the vehicle moved
        meanwhile) when the wall clock advanced with it, at least half as much since
        ``from_s`` was seen; a step of the data's clock (NTP or GNSS setting a companion's
        clock) when it did not — a step comes with no wall time to match it."""
        if math.isnan(self._t_wall_s) or not self._t_s >= from_s - 1.0:
            return False  # not the data time this clock saw last: no evidence of a dropout
        return time.monotonic() - self._t_wall_s >= self.GAP_WALL_FRACTION * (to_s - from_s)

    def now_data_s(self) -> float:
        if math.isnan(self._offset_s):
            return math.nan
        return max(time.monotonic() + self._offset_s, self._t_s)

    def shift_time(self, delta_s: float) -> None:
        """The input's clock jumped by ``delta_s``: "now" follows the new time base."""
        self._offset_s += delta_s
        self._t_s += delta_s
