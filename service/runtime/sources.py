"""Sources of the runner loop for replay: logs and the simulator (Stone Soup style:
readers and simulators are interchangeable as sources). The live queue source is
the daemon's (``service.daemon.QueueSource``).

A source is an iterable of samples (:mod:`adaptnav.fusion.samples`), :class:`ImuBatch` runs and,
live, calibrator releases, in the deterministic replay order
``(t_s, source priority, seq)`` (:func:`adaptnav.fusion.samples.replay_order_key`). It also has

- ``counters`` — a :class:`SourceCounters` (messages read, decode errors, corrupt
  frames, samples with an unusable timestamp, late samples, ...),
- ``streams`` — the sample kinds the input holds (known up front where possible),
- ``missing`` — the streams a navigation run would want but the input lacks,
- ``metadata`` — what the input says about itself (e.g. the simulated scenario),
- ``report_counters()`` — the figures ``summary.json`` reports (messages read, corrupt
  frames, rejections by reason, late samples).

Sources here: :class:`SimSource` (a scenario simulated in memory), :class:`McapSource`
(our MCAP logs, scenario from the metadata), :class:`TlogReplaySource` (MAVLink
``.tlog``/DataFlash ``.bin`` through :class:`adaptnav.service.transport.tlog_source.TlogSource`) and
:class:`SampleStreamSource` (any iterable of samples).

:func:`order_and_batch` is the common core: a bounded re-ordering heap (``horizon_s`` of
data time — logs are nearly ordered; a global sort of a 1-h log would hold every sample
in memory) followed by grouping runs of consecutive, increasing, finite IMU samples into
:class:`ImuBatch` (the estimator's fast path). An IMU sample that is a duplicate, out of
order or not finite is passed on alone so the estimator judges (rejects and counts) it.
Samples whose ``t_s`` is not finite cannot be placed in time: they are dropped and
counted (``bad_timestamp``).
"""
from __future__ import annotations

import heapq
import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

from adaptnav.fusion.samples import ImuBatch, ImuSample, kinds, replay_order_key

log = logging.getLogger(__name__)

# streams navigation uses (``nav_stream`` in the sensor table); a log lacking one of
# these is reported in ``missing``
NAV_STREAMS = kinds(nav_stream=True)


@dataclass
class SourceCounters:
    """Counts of what a source read and refused (merged into ``summary.json``)."""

    messages_read: int = 0
    samples: int = 0
    decode_errors: Counter = field(default_factory=Counter)   # by reason
    corrupt_frames: int = 0
    bad_timestamp: int = 0
    late_samples: int = 0          # arrived after later samples were already released
    by_kind: Counter = field(default_factory=Counter)

    def rejected(self) -> dict[str, int]:
        """Source-side rejections by reason (for the health/summary merge)."""
        out: Counter = Counter({f"decode:{k}": v for k, v in self.decode_errors.items()})
        if self.corrupt_frames:
            out["corrupt_frame"] += self.corrupt_frames
        if self.bad_timestamp:
            out["bad_timestamp"] += self.bad_timestamp
        return dict(out)

    def to_dict(self) -> dict:
        return {
            "messages_read": self.messages_read,
            "samples": self.samples,
            "decode_errors": dict(sorted(self.decode_errors.items())),
            "corrupt_frames": self.corrupt_frames,
            "bad_timestamp": self.bad_timestamp,
            "late_samples": self.late_samples,
            "by_kind": dict(sorted(self.by_kind.items())),
        }


def _imu_ok(s: ImuSample) -> bool:
    return all(map(math.isfinite, s.specific_force_b_m_s2)) and all(map(math.isfinite, s.omega_b_rad_s))


def order_and_batch(samples: Iterable[Any], counters: SourceCounters, horizon_s: float = 5.0,
                    max_batch: int = 4096) -> Iterator[Any]:
    """Reorder ``samples`` within ``horizon_s`` and group IMU runs (module docstring).

    Parameters
    ----------
    samples : iterable of samples (any order; nearly ordered is cheap)
    counters : SourceCounters
        Updated in place (``samples``, ``by_kind``, ``bad_timestamp``, ``late_samples``).
    horizon_s : float
        Re-ordering window in data seconds.
    max_batch : int
        Longest :class:`ImuBatch` emitted.
    """
    heap: list[tuple] = []
    seq = 0
    newest = -math.inf
    released = -math.inf
    run: list[ImuSample] = []

    def release(item):
        nonlocal released
        if item.t_s < released:
            counters.late_samples += 1
        else:
            released = item.t_s
        if item.KIND == "imu":
            if run and item.source != run[0].source:  # a run is one stream (ImuBatch.source)
                yield ImuBatch.of(run)
                run.clear()
            if _imu_ok(item) and (not run or item.t_s > run[-1].t_s):
                run.append(item)
                if len(run) >= max_batch:
                    yield ImuBatch.of(run)
                    run.clear()
                return
            if run:
                yield ImuBatch.of(run)
                run.clear()
            yield item  # the estimator rejects and counts it
            return
        if run:
            yield ImuBatch.of(run)
            run.clear()
        yield item

    for s in samples:
        t = getattr(s, "t_s", math.nan)
        if not isinstance(t, (int, float)) or not math.isfinite(t):
            counters.bad_timestamp += 1
            continue
        counters.samples += 1
        counters.by_kind[s.KIND] += 1
        heapq.heappush(heap, (*replay_order_key(s, seq), s))
        seq += 1
        if t > newest:
            newest = t
        while heap and heap[0][0] < newest - horizon_s:
            yield from release(heapq.heappop(heap)[3])
    while heap:
        yield from release(heapq.heappop(heap)[3])
    if run:
        yield ImuBatch.of(run)


class SampleStreamSource:
    """Any iterable of samples (a reader) as an ordered, batched source.

    Parameters
    ----------
    samples : iterable
        Samples in (nearly) time order.
    streams : iterable of str, optional
        Kinds present, when the reader knows them up front.
    metadata : dict, optional
    horizon_s : float
        Re-ordering window (s).
    """

    def __init__(self, samples: Iterable[Any], streams: Iterable[str] | None = None,
                 metadata: dict | None = None, horizon_s: float = 5.0,
                 counters: SourceCounters | None = None) -> None:
        self._samples = samples
        self.streams = None if streams is None else sorted(set(streams))
        self.metadata = metadata or {}
        self.horizon_s = horizon_s
        self.counters = counters or SourceCounters()

    @property
    def missing(self) -> list[str]:
        seen = set(self.streams or ()) | set(self.counters.by_kind)
        return [k for k in NAV_STREAMS if k not in seen]

    @property
    def has_truth(self) -> bool:
        return "truth" in (self.streams or ()) or self.counters.by_kind.get("truth", 0) > 0

    def __iter__(self) -> Iterator[Any]:
        return order_and_batch(self._samples, self.counters, self.horizon_s)

    def report_counters(self) -> dict:
        c = self.counters
        return {"messages_read": c.messages_read or c.samples, "corrupt_frames": c.corrupt_frames,
                "rejected": c.rejected(), "late_samples": c.late_samples}


class SimSource:
    """A scenario simulated in memory as a source (``adaptnav.sim.simulate(scenario).iter_blocks()``).

    The simulator already yields :class:`ImuBatch` runs and other samples in replay order;
    they pass through, counted by how far each iteration got
    (:class:`adaptnav.sim.simulator.BlockProgress`: no count per item). ``metadata`` holds the
    scenario.
    """

    def __init__(self, scenario: Any, result: Any = None) -> None:
        self.scenario = scenario
        self.result = result if result is not None else simulate(scenario)
        self.metadata = {"scenario": scenario}
        self.streams = None
        self._progress: list[Any] = []  # one per iteration of a SimResult
        self._counted = SourceCounters()  # the items of another result's iter_blocks, counted one by one

    @property
    def counters(self) -> SourceCounters:
        """What the iterations so far handed out (every item is a message read)."""
        c = SourceCounters(by_kind=Counter(self._counted.by_kind))
        for progress in self._progress:
            c.by_kind.update(progress.by_kind())
        c.samples = c.messages_read = sum(c.by_kind.values())
        return c

    @property
    def missing(self) -> list[str]:
        by_kind = self.counters.by_kind
        return [k for k in NAV_STREAMS if k not in by_kind]

    has_truth = True
    # every sample comes after the IMU samples up to its time and none before them (the
    # simulator's replay order): the filter needs no history for late samples
    in_time_order = True

    def report_counters(self) -> dict:
        return {"messages_read": self.counters.messages_read, "corrupt_frames": 0, "rejected": {},
                "late_samples": 0}

    def __iter__(self) -> Iterator[Any]:
        from adaptnav.sim.simulator import BlockProgress, SimResult

        if not isinstance(self.result, SimResult):  # (a stand-in with an iter_blocks of its own)
            return self._count(self.result.iter_blocks())
        progress = BlockProgress()
        self._progress.append(progress)
        return self.result.iter_blocks(progress)

    def _count(self, items: Iterable[Any]) -> Iterator[Any]:
        by_kind = self._counted.by_kind
        for item in items:
            if isinstance(item, ImuBatch):
                by_kind["imu"] += len(item)
            else:
                by_kind[item.KIND] += 1
            yield item


def simulate(scenario: Any) -> Any:
    """Run the simulator on a scenario (``adaptnav.sim.simulator.simulate``)."""
    from adaptnav.sim.simulator import simulate as run_simulation

    return run_simulation(scenario)


class TlogReplaySource(SampleStreamSource):
    """A :class:`adaptnav.service.transport.tlog_source.TlogSource` batched for the estimator; its own
    counters (messages read, corrupt frames, what is missing) are the ones reported."""

    def __init__(self, tlog: Any) -> None:
        super().__init__(tlog)
        self.tlog = tlog
        # read in a child process (:mod:`adaptnav.service.runtime.reader`): the same items; the
        # configuration calls made before reading are recorded for it
        self.read_in_child = False
        self.calls: list[tuple[str, tuple]] = []

    def __iter__(self) -> Iterator[Any]:
        if self.read_in_child:  # the log's samples from the child, ordered and batched here
            from adaptnav.service.runtime.reader import read_in_child

            return order_and_batch(read_in_child(self), self.counters, self.horizon_s)
        return super().__iter__()

    @staticmethod
    def forward_jump_is_gap(from_s: float, to_s: float) -> bool:
        """Always: the samples are on the autopilot's boot clock, which does not step forward;
        a stream going on from a later time is data missing (a telemetry dropout)."""
        return True

    @property
    def missing(self) -> list[str]:
        return list(getattr(self.tlog, "missing", []) or [])

    def unix_of(self, t_s: float) -> float | None:
        """UNIX time of mission time ``t_s`` (None without a wall-clock reference in the log)."""
        return self.tlog.converter.time.unix_of(t_s)

    def set_origin(self, origin: Any) -> None:
        """The configured NED origin (places GLOBAL_VISION_POSITION_ESTIMATE and the truth)."""
        self.tlog.set_origin(origin)
        self.calls.append(("set_origin", (origin,)))

    def set_convert(self, convert: Any, min_imu_rate_hz: float | None = None) -> None:
        """The service's ``[mavlink.convert]`` (:class:`ConvertConfig`), as the live bridge uses
        it, and the filter's slowest IMU stream for strapdown (``filter.alignment.min_imu_rate_hz``)."""
        self.tlog.set_convert(convert, min_imu_rate_hz)
        self.calls.append(("set_convert", (convert, min_imu_rate_hz)))

    @property
    def has_truth(self) -> bool:
        """A simulator's SIM_STATE in the log: metrics against it."""
        return bool(self.tlog.has_truth)

    def report_counters(self) -> dict:
        c = self.tlog.counters
        rejected = dict(c.get("rejected", {}))
        lost = int(c.get("corrupt_frames", 0)) - sum(c.get("repaired_frames", {}).values())
        if lost:  # the corrupt frames not restored (mavlink_frames)
            rejected["corrupt_frame"] = rejected.get("corrupt_frame", 0) + lost
        return {"messages_read": int(c.get("messages_read", 0)),
                "corrupt_frames": int(c.get("corrupt_frames", 0)),
                "rejected": rejected,
                "late_samples": int(c.get("late_samples", 0)),
                "message_types": c.get("message_types", {}),
                "clock": c.get("clock", {}),
                "imu_stream": c.get("imu_stream", {}),
                "repaired_frames": dict(c.get("repaired_frames", {})),
                "gps_fixes": c.get("gps_fixes", {}),
                "thrusters": c.get("thrusters", {}),
                "truncated": c.get("truncated", "")}


def tlog_source(path: Path) -> Any:
    """A ``.tlog``/``.bin`` file, or a BlueOS ``.mcap`` recording of MAVLink, as a replay source."""
    from adaptnav.service.transport.tlog_source import TlogSource

    return TlogReplaySource(TlogSource(path))


class McapSource(SampleStreamSource):
    """Our MCAP logs (:func:`adaptnav.service.transport.logs.read_mcap`), with the scenario from the metadata.

    Undecodable messages are counted by reason (``decode:<field>``) and skipped; a
    truncated file replays up to the damage and says so in ``truncated``.

    A forward jump of the data's clock (:meth:`forward_jump_is_gap`) is data missing when a
    damaged chunk was lost there, or when the recording's log clock is the recorder's wall
    clock (``adaptnav record``) and it advanced with the data — as the live daemon judged it.
    """

    MAX_LOGGED = 10
    # (data time, log time) pairs kept for judging jumps: one per 50 ms of data and at every
    # jump; 4096 of them span minutes, far more than the reorder window reads ahead
    CLOCK_PAIRS = 4096
    CLOCK_PAIR_STEP_S = 0.05

    def __init__(self, path: Path) -> None:
        from adaptnav.service.transport import logs

        self.path = Path(path)
        self.stats = logs.ReadStats()
        self.truncated = ""
        self.reader = logs.read_mcap(self.path, self.stats)
        self.scenario = self.reader.scenario
        streams = self.reader.streams
        if streams is None and self.scenario is not None:
            streams = ["truth"]  # simulated logs carry truth; the summary is lost with truncation
        super().__init__(self._samples(), streams=streams, metadata=self.reader.metadata)
        self.duration_s = self.scenario.duration_s if self.scenario is not None else None
        self._log_clock_is_wall = (self.reader.metadata.get(logs.LOG_CLOCK_KEY) == logs.RECEPTION_WALL_CLOCK
                                   or self.reader.metadata.get("recorded_by") == "adaptnav record")
        self._clock_pairs: deque[tuple[float, float]] = deque(maxlen=self.CLOCK_PAIRS)
        self._damaged_after_s: list[float] = []  # data time of the last sample before each lost chunk

    def _samples(self):
        from adaptnav.fusion.samples import SampleError

        from adaptnav.service.transport import logs

        logged = 0
        t_last = -math.inf
        for item in self.reader:
            if isinstance(item, SampleError):
                reason = str(item).split(":")[0].strip() or "malformed"
                self.counters.decode_errors[reason] += 1
                if logged < self.MAX_LOGGED:
                    log.warning("%s: undecodable message skipped: %s", self.path.name, item)
                    logged += 1
                continue
            if isinstance(item, logs.DamagedChunkError):
                self.counters.decode_errors["damaged_chunk"] += 1
                self._damaged_after_s.append(t_last)
                log.warning("%s", item)
                continue
            if isinstance(item, logs.TruncatedLogError):
                self.truncated = str(item)
                self.counters.decode_errors["truncated"] += 1
                log.warning("%s", item)
                continue
            if getattr(item, "KIND", None) == "calibration_release":
                # what the live calibrator released is not re-applied: a replay runs its
                # own calibrator (--calibrate) or none
                self.counters.by_kind["calibration_release"] += 1
                continue
            t = getattr(item, "t_s", math.nan)
            if isinstance(t, float) and math.isfinite(t):
                t_last = t
                if self._log_clock_is_wall and self.reader.log_time_ns is not None:
                    pairs = self._clock_pairs
                    if not pairs or abs(t - pairs[-1][0]) >= self.CLOCK_PAIR_STEP_S:
                        pairs.append((t, self.reader.log_time_ns * 1e-9))
            yield item

    def forward_jump_is_gap(self, from_s: float, to_s: float) -> bool:
        """Whether the data going on at ``to_s`` after ``from_s`` is data missing (class docstring)."""
        if any(from_s - 2.0 <= t <= to_s for t in self._damaged_after_s):
            return True
        log_after = log_before = None
        middle = from_s + 0.5 * (to_s - from_s)
        for t, log_s in reversed(self._clock_pairs):  # newest first, read ahead of the door
            if t > middle:
                log_after = log_s  # ends as the first logged after the jump
            elif t <= from_s + self.CLOCK_PAIR_STEP_S:
                log_before = log_s
                break
        if log_after is None or log_before is None:
            return False  # no log clock to tell: a step, as before
        return log_after - log_before >= 0.5 * (to_s - from_s)

    def report_counters(self) -> dict:
        c = self.counters
        return {"messages_read": int(self.stats.messages),
                "corrupt_frames": int(self.stats.bad_messages) + int(self.stats.truncated) + self.stats.damaged_chunks,
                "rejected": c.rejected(), "late_samples": c.late_samples, "truncated": self.truncated}
