"""MCAP logs of every bus message (simulated or recorded), readable by Foxglove / ``mcap``.

Layout written by :func:`write_mcap`:

- one channel per stream: topic ``/adaptnav/sensor/<kind>`` for sensor kinds,
  ``/adaptnav/truth`` for ground truth (others as :func:`adaptnav.service.transport.codec.topic_for` says),
  ``message_encoding="json"``, schema encoding ``jsonschema`` with the kind's JSON Schema;
- message log time = publish time = sample ``t_s`` in integer nanoseconds; sequence =
  the message's index in the file;
- metadata record ``adaptnav`` written *before* the messages (so a truncated file keeps
  it): string values as given, other values JSON-encoded (their keys listed under
  ``_json_keys``) — e.g. the effective scenario config.

Messages are written in the order given (the replay order), and :func:`read_mcap`
reads them back sequentially in that order, one chunk in memory at a time. A truncated
or corrupted file yields everything before the damage and then one
:class:`TruncatedLogError`; an undecodable message yields a :class:`SampleError` and
reading goes on. :class:`ReadStats` counts both.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from adaptnav.fusion.samples import SCHEMA_VERSION, ImuBatch, SampleError
from adaptnav.service.transport import codec

METADATA_NAME = "adaptnav"
ADAPTNAV_TOPIC_PREFIX = "/adaptnav/"  # our messages; other topics (Foxglove's schemas) are skipped on reading
SKIPPED = "skipped"  # key of write_mcap's counts: messages that could not be written
log = logging.getLogger(__name__)


# metadata key saying what a log's message log times are; ``RECEPTION_WALL_CLOCK``: the
# recorder's wall clock at reception, a clock of its own beside the data's (``adaptnav
# record``), so replay can tell a dropout (both advance) from a step of the data's clock
LOG_CLOCK_KEY = "log_clock"
RECEPTION_WALL_CLOCK = "reception_wall_clock"


class LogError(Exception):
    """A problem with a log file as a whole (the message says what)."""


class TruncatedLogError(LogError):
    """The file ends (or is corrupt) before its footer; what came before was yielded."""


class DamagedChunkError(LogError):
    """A chunk of the file could not be read; reading went on at the next chunk."""


def resilient_records(stream: Any, path: Path) -> Iterator[Any]:
    """An MCAP file's records in file order (``mcap``'s StreamReader, CRCs checked). A chunk
    that cannot be read (bit errors, a bad block) does not end the file when its summary
    still lists the chunks: a :class:`DamagedChunkError` is yielded in its place and reading
    goes on at the next chunk, the summary's channels known (a channel record may have been
    in the lost chunk). Without a summary (a cut file) or past the last chunk, the parser's
    exception is raised, as StreamReader raises it."""
    records = StreamReader(stream, validate_crcs=True).records
    summary = None
    while True:
        try:
            yield from records
            return
        except Exception as e:  # noqa: BLE001 — damaged bytes: resume at the next chunk if any
            position = stream.tell()
            if summary is None:
                summary = _readable_summary(path)
            starts = sorted(c.chunk_start_offset for c in (summary.chunk_indexes if summary else ()))
            later = [s for s in starts if s >= position]
            if not later:
                raise
            damaged_from = max((s for s in starts if s < position), default=position)
            yield from summary.channels.values()
            yield DamagedChunkError(f"{path.name}: the chunk at bytes {damaged_from}–{later[0]} could not be read "
                                    f"({type(e).__name__}: {e}); its messages are lost, the next chunk is read")
            stream.seek(later[0])
            records = StreamReader(stream, skip_magic=True, validate_crcs=True).records


def _readable_summary(path: Path) -> Any:
    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 — no summary to resume from
        return None


@dataclass
class ReadStats:
    """Counters filled while :func:`read_mcap` iterates."""

    messages: int = 0
    decoded: int = 0
    bad_messages: int = 0
    truncated: bool = False
    truncation_reason: str = ""
    damaged_chunks: int = 0
    per_kind: dict[str, int] = field(default_factory=dict)


_MAX_NS = 2**64 - 1


def _ns(t_s: float) -> int:
    ns = t_s * 1e9
    if not math.isfinite(ns) or ns < 0 or ns > _MAX_NS:
        return 0  # MCAP times are unsigned 64-bit; such a sample is judged by whoever reads it
    return int(round(ns))


def _imu_rows(batch: ImuBatch) -> Iterator[tuple[float, bytes]]:
    """Fast encoding of an ImuBatch: the same JSON as ``codec.encode(ImuSample)``."""
    t = np.asarray(batch.t_s, dtype=float).tolist()
    f = np.asarray(batch.specific_force_b_m_s2, dtype=float)
    w = np.asarray(batch.omega_b_rad_s, dtype=float)
    finite = bool(np.isfinite(f).all() and np.isfinite(w).all())
    fl, wl = f.tolist(), w.tolist()
    dumps = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode
    source = batch.source
    for i, ti in enumerate(t):
        fi, wi = fl[i], wl[i]
        if not finite:
            fi = [x if math.isfinite(x) else None for x in fi]
            wi = [x if math.isfinite(x) else None for x in wi]
        d = {"type": "imu", "schema_version": SCHEMA_VERSION, "t_s": ti,
             "specific_force_b_m_s2": fi, "omega_b_rad_s": wi, "source": source}
        yield ti, dumps(d).encode("utf-8")


def write_mcap(path: str | Path, samples_iterable: Iterable[Any], metadata: dict | None = None,
               progress=None, log_time_ns: Callable[[float], int] | None = None,
               extra: Callable[[Any], Iterable[tuple]] | None = None) -> dict[str, int]:
    """Write messages to an MCAP file.

    Parameters
    ----------
    path : output file (overwritten)
    samples_iterable : messages in the order to store (any registered kind); an
        :class:`ImuBatch` is written as its individual IMU messages
    metadata : stored in the ``adaptnav`` metadata record
    progress : optional callable ``progress(n_messages_written_since_last_call)``
    log_time_ns : optional callable data time (s) → log time (UNIX ns), a real clock for
        Foxglove's timeline (default: the data time itself)
    extra : optional callable message → more messages to write beside it, as tuples
        ``(topic, schema_name, schema_encoding, schema_data, message_encoding, data)``
        (Foxglove's well-known schemas: :func:`adaptnav.service.runtime.foxglove.encoded`)

    Returns
    -------
    dict kind → number of messages written (``"skipped"``: messages that could not be
    encoded, skipped and logged; the file is finished properly even when the iterable
    raises, e.g. on SIGTERM, and each completed chunk is readable after a SIGKILL)
    """
    counts: dict[str, int] = {}
    channels: dict[str, int] = {}
    seq = 0
    log_ns = log_time_ns or _ns
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=512 * 1024)
        writer.start(profile="", library="adaptnav")
        meta = {} if metadata is None else dict(metadata)
        json_keys = [k for k, v in meta.items() if not isinstance(v, str)]
        record = {str(k): (v if isinstance(v, str) else json.dumps(v, sort_keys=True)) for k, v in meta.items()}
        if json_keys:
            record["_json_keys"] = json.dumps(json_keys)
        writer.add_metadata(METADATA_NAME, record)

        def channel(kind: str) -> int:
            if kind not in channels:
                schema = codec.schema_for(kind)
                sid = writer.register_schema(name=schema.get("title", f"adaptnav.{kind}"),
                                             encoding="jsonschema",
                                             data=json.dumps(schema).encode("utf-8"))
                channels[kind] = writer.register_channel(topic=codec.topic_for(kind),
                                                         message_encoding="json", schema_id=sid)
            return channels[kind]

        try:
            for item in samples_iterable:
                try:
                    if isinstance(item, ImuBatch):
                        cid = channel("imu")
                        n = 0
                        for t, data in _imu_rows(item):
                            ns = log_ns(t)
                            writer.add_message(cid, log_time=ns, data=data, publish_time=ns, sequence=seq)
                            seq += 1
                            n += 1
                        counts["imu"] = counts.get("imu", 0) + n
                    else:
                        kind = codec.kind_of(item)
                        data = codec.encode(item)
                        cid = channel(kind)
                        ns = log_ns(codec.time_of(item))
                        writer.add_message(cid, log_time=ns, data=data, publish_time=ns, sequence=seq)
                        seq += 1
                        n = 1
                        counts[kind] = counts.get(kind, 0) + 1
                        for topic, sname, senc, sdata, menc, xdata in (extra(item) if extra is not None else ()):
                            if topic not in channels:
                                sid = writer.register_schema(name=sname, encoding=senc, data=sdata)
                                channels[topic] = writer.register_channel(topic=topic, message_encoding=menc,
                                                                          schema_id=sid)
                            writer.add_message(channels[topic], log_time=ns, data=xdata, publish_time=ns,
                                               sequence=seq)
                            seq += 1
                except (SampleError, ValueError, TypeError, OverflowError) as e:
                    # one message that cannot be written must not lose the recording
                    counts[SKIPPED] = counts.get(SKIPPED, 0) + 1
                    if counts[SKIPPED] <= 10:
                        log.warning("%s: message skipped (%s: %s)", path, type(e).__name__, e)
                    continue
                stream.flush()  # a finished chunk goes to disk at once (readable after a SIGKILL); else a no-op
                if progress is not None:
                    progress(n)
        finally:  # also on an exception or a signal: a complete file with what was written
            writer.finish()
    return counts


def _decode_metadata(record: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = dict(record)
    keys = json.loads(out.pop("_json_keys", "[]"))
    for k in keys:
        if k in out:
            out[k] = json.loads(out[k])
    return out


class McapLog:
    """One pass over an MCAP log: an iterator of messages and errors (see :func:`read_mcap`).

    Attributes known before iterating: ``metadata`` (the ``adaptnav`` record, ``{}`` if
    none), ``scenario`` (the simulated :class:`adaptnav.sim.scenario.Scenario` rebuilt from the
    metadata, or ``None``), ``streams`` (kinds of the file's channels when its summary is
    readable, else ``None``). Filled while iterating: ``stats`` (:class:`ReadStats`) and
    ``counters`` (a dict: ``messages_read``, ``corrupt_frames``, ``decode_errors`` by kind),
    ``log_time_ns`` (the log time of the message last yielded).
    """

    def __init__(self, path: str | Path, stats: ReadStats | None = None) -> None:
        self.path = Path(path)
        self.stats = stats if stats is not None else ReadStats()
        self.decode_errors: dict[str, int] = {}
        try:
            self.metadata = read_mcap_metadata(self.path)
        except TruncatedLogError:
            self.metadata = {}
        self.scenario = _scenario_from(self.metadata)
        self.streams = _summary_streams(self.path)
        self.log_time_ns: int | None = None
        self._it: Iterator[Any] | None = None

    @property
    def counters(self) -> dict[str, Any]:
        return {"messages_read": self.stats.messages,
                "corrupt_frames": int(self.stats.truncated) + self.stats.damaged_chunks,
                "decode_errors": dict(self.decode_errors)}

    def __iter__(self) -> "McapLog":
        return self

    def __next__(self) -> Any:
        if self._it is None:
            self._it = self._records()
        return next(self._it)

    def _records(self) -> Iterator[Any]:
        stats, channels = self.stats, {}
        with open(self.path, "rb") as stream:
            records = resilient_records(stream, self.path)
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except Exception as e:  # noqa: BLE001 — any parser failure on damaged bytes ends the file
                    stats.truncated = True
                    stats.truncation_reason = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
                    yield TruncatedLogError(f"{self.path}: log ends early or is corrupt after {stats.messages} "
                                            f"messages ({stats.truncation_reason}); kept what came before")
                    return
                if isinstance(record, DamagedChunkError):
                    stats.damaged_chunks += 1
                    yield record
                    continue
                if isinstance(record, Message):
                    ch = channels.get(record.channel_id)
                    if ch is not None and not ch.topic.startswith(ADAPTNAV_TOPIC_PREFIX):
                        continue  # a viewer's channel beside ours (Foxglove well-known schemas)
                    stats.messages += 1
                    try:
                        if record.channel_id not in channels:
                            raise SampleError(f"message on unknown channel {record.channel_id}")
                        sample = codec.decode(record.data)
                    except SampleError as e:
                        stats.bad_messages += 1
                        ch = channels.get(record.channel_id)
                        kind = ch.topic.rsplit("/", 1)[-1] if ch is not None else "unknown"
                        self.decode_errors[kind] = self.decode_errors.get(kind, 0) + 1
                        yield e
                        continue
                    stats.decoded += 1
                    kind = codec.kind_of(sample)
                    stats.per_kind[kind] = stats.per_kind.get(kind, 0) + 1
                    self.log_time_ns = record.log_time
                    yield sample
                elif isinstance(record, Channel):
                    channels[record.id] = record


def _scenario_from(metadata: dict) -> Any:
    raw = metadata.get("scenario")
    if not isinstance(raw, dict):
        return None
    from adaptnav.fusion.typed_config import ConfigError, build
    from adaptnav.sim.scenario import Scenario

    try:
        return build(Scenario, raw)
    except ConfigError:
        return None  # a log from another version: the samples still replay


def _summary_streams(path: Path) -> list[str] | None:
    """Kinds of the channels listed in the summary section (None if unreadable)."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 — truncated/corrupt: the summary is simply unknown
        return None
    if summary is None:
        return None
    kinds = []
    for ch in summary.channels.values():
        if not ch.topic.startswith(ADAPTNAV_TOPIC_PREFIX):
            continue
        schema = summary.schemas.get(ch.schema_id)
        name = schema.name if schema is not None else ""
        kinds.append(name.split(".", 1)[1] if name.startswith("adaptnav.") else ch.topic.rsplit("/", 1)[-1])
    return sorted(set(kinds))


def read_mcap(path: str | Path, stats: ReadStats | None = None,
              metadata_out: dict | None = None) -> McapLog:
    """Messages of an MCAP log, in file order; errors are yielded, not raised.

    Yields
    ------
    a decoded message, or a :class:`SampleError` (an undecodable message, reading goes
    on), or finally one :class:`TruncatedLogError` if the file ends early or is corrupt.

    Parameters
    ----------
    stats : optional :class:`ReadStats` updated as messages are read
    metadata_out : optional dict filled with the ``adaptnav`` metadata

    Returns
    -------
    McapLog — an iterator that also carries ``metadata``, ``scenario``, ``streams``,
    ``stats`` and ``counters``.
    """
    log = McapLog(path, stats)
    if metadata_out is not None:
        metadata_out.update(log.metadata)
    return log


def read_mcap_metadata(path: str | Path) -> dict[str, Any]:
    """The ``adaptnav`` metadata of a log (read from the start; works on truncated files)."""
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Metadata) and record.name == METADATA_NAME:
                    return _decode_metadata(record.metadata)
                if isinstance(record, Message):
                    break
        except Exception as e:  # noqa: BLE001 — damaged file
            raise TruncatedLogError(f"{path}: no readable metadata ({type(e).__name__}: {e})") from None
    return {}
