"""Replay source for MAVLink telemetry logs (``.tlog``), BlueOS's MAVLink recordings
(``.mcap``, :mod:`adaptnav.service.transport.blueos_mcap`) and ArduPilot DataFlash (``.BIN``).

pymavlink opens a log with the same ``mavutil.mavlink_connection`` API as a live link,
so the messages go through the same :class:`adaptnav.service.transport.mavlink_convert.MavlinkConverter`
as the bridge; a DataFlash log's records (DFReader) through
:class:`adaptnav.service.transport.dataflash.DataflashConverter` on the same clock and accounts.  Data time comes from the autopilot's ``time_boot_ms``/``time_usec``
(the tlog's own ``_timestamp`` is the wall clock of the recording computer and is not
used).  Samples are released in the deterministic replay order
``(t_s, source priority, seq)`` through a bounded re-order buffer of
``reorder_window_s`` (messages of one autopilot arrive slightly out of order: ATTITUDE
is stamped before the RAW_IMU sent just ahead of it).

Corrupt frames (CRC failures, truncated packets) are reported by pymavlink's robust
parser as ``BAD_DATA`` pseudo-messages; they are counted in ``counters["corrupt_frames"]``
and skipped — except the frames a ground station logged with their payload's trailing zeros
cut after the CRC (a QGroundControl tlog of a BlueOS vehicle:
:mod:`adaptnav.service.transport.mavlink_frames`), which are restored and used: they stay
counted as corrupt (the file holds them so) and are also counted, by type, in
``counters["repaired_frames"]``.  ``missing`` says, in words, what the log cannot give the estimator —
e.g. an IMU stream too slow for strapdown (real ArduSub streams RAW_IMU at 2 Hz unless
asked for more), in which case the IMU samples are withheld and attitude is used.
"""
from __future__ import annotations

import heapq
import logging
import math
import statistics
import tempfile
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator

from adaptnav.service.transport.mavlink_convert import (  # sets MAVLINK20 before pymavlink loads
    ConvertConfig,
    MavlinkConverter,
)
from adaptnav.service.transport.dataflash import IGNORED_WHY as DATAFLASH_IGNORED_WHY
from adaptnav.service.transport.dataflash import READ as DATAFLASH_READ
from adaptnav.service.transport.dataflash import USED as DATAFLASH_USED
from adaptnav.service.transport.dataflash import (DataflashConverter, SimTruth, format_repairs,
                                                  indexer_complaints, reader_complaints, tolerant_formats)
from adaptnav.service.transport.blueos_mcap import BlueOsMcapReader, MalformedMessage
from adaptnav.service.transport.mavlink_frames import GPS_GLOBAL_ORIGIN_ID, SIM_STATE_ID, TlogReader, untruncated
from adaptnav.fusion.alignment import IMU_RATE_WINDOW, imu_too_slow
from adaptnav.fusion.config import AlignmentConfig
from adaptnav.fusion.frames import GeoOrigin
from adaptnav.fusion.samples import ImuSample, TruthSample, replay_order_key

# a DataFlash record's first two bytes (ArduPilot's HEAD_BYTE1, HEAD_BYTE2)
_DATAFLASH_HEADER = bytes((0xA3, 0x95))

log = logging.getLogger(__name__)

from pymavlink import mavutil  # noqa: E402


@dataclass(frozen=True)
class TlogConfig:
    """``[replay.mavlink]``: how a MAVLink log becomes a sample stream."""

    convert: ConvertConfig = field(default_factory=ConvertConfig)
    # slower IMU streams are withheld: the estimator's own rule (filter.alignment.min_imu_rate_hz)
    min_imu_rate_hz: float = AlignmentConfig.min_imu_rate_hz
    drop_slow_imu: bool = True
    reorder_window_s: float = 2.0
    # the water pressure sensor's BARO instance in a DataFlash log (None: the one ArduSub made
    # primary, PARM BARO_PRIMARY 1 or 2, else 1 — a BlueROV2's Bar30)
    dataflash_baro_instance: int | None = None

    def validate(self) -> None:
        if self.min_imu_rate_hz <= 0 or self.reorder_window_s < 0:
            raise ValueError("min_imu_rate_hz must be > 0 and reorder_window_s ≥ 0")


_TEXT_FIELD_FORMATS = frozenset("nNZaM")  # DataFlash format characters read as text


def _clean_text_dataflash(data: bytes) -> tuple[bytes, int]:
    """The lines of a text DataFlash log that are records of its formats: ASCII, a known
    record name, as many fields as its ``FMT`` says, numbers where it says numbers.
    Returns (the kept lines, the number of non-empty lines dropped). A last line without
    its newline (the file was cut there) is left out and not counted: the reader's end
    says so (:meth:`TlogSource._note_cut_off`)."""
    delimiter = b", " if b"FMT, " in data[:8000] else b","
    formats: dict[bytes, str] = {}
    kept: list[bytes] = []
    dropped = 0
    for line in data.split(b"\n")[:-1]:
        line = line.rstrip(b"\r")
        if not line.strip():
            continue
        if max(line) > 0x7E or min(line) < 0x20:
            dropped += 1
            continue
        parts = line.split(delimiter)
        name = parts[0].strip()
        if name == b"FMT" and len(parts) >= 5 and parts[1].strip().isdigit() and parts[2].strip().isdigit():
            formats[parts[3].strip()] = parts[4].strip().decode()
            kept.append(line)
            continue
        fmt = formats.get(name)
        if fmt is None or len(parts) - 1 != len(fmt) or not all(
                kind in _TEXT_FIELD_FORMATS or _is_number(value) for kind, value in zip(fmt, parts[1:])):
            dropped += 1
            continue
        kept.append(line)
    return b"\n".join(kept) + b"\n", dropped


def _is_number(text: bytes) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _plausible_truth(t: SimTruth) -> bool:
    values = (t.t_s, t.lat_deg, t.lon_deg, t.alt_m, *t.vel_n_m_s, *t.q_nb)
    return (all(map(math.isfinite, values)) and abs(math.hypot(*t.q_nb) - 1.0) < 0.01
            and abs(t.lat_deg) <= 90.0 and abs(t.lon_deg) <= 180.0 and (t.lat_deg, t.lon_deg) != (0.0, 0.0))


def _is_text_dataflash(path: Path) -> bool:
    """A text DataFlash log names its record formats (``FMT,``) in its first lines."""
    try:
        with open(path, "rb") as f:
            return b"FMT," in f.read(8000)
    except OSError:
        return False


class TlogSource:
    """Iterate the samples of a ``.tlog`` (or ``.BIN``) in replay order.

    Parameters
    ----------
    path : str or Path
        The log file.
    config : TlogConfig, optional

    Attributes
    ----------
    counters : dict
        ``messages_read`` (decoded messages), ``corrupt_frames`` (BAD_DATA),
        ``repaired_frames`` (of those, restored and used, by message type),
        ``samples_by_kind``, ``rejected`` (by reason: conversion failures, ``late``,
        ``duplicate_time``, ``imu_too_slow``...), ``late_samples`` (outside the re-order
        window), ``reboots`` (autopilot clock restarts), ``duration_s`` (data time span).
    missing : list of str
        What the estimator will lack, in words; complete once iteration has finished.
    """

    def __init__(self, path: str | Path, config: TlogConfig | None = None, origin: GeoOrigin | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"MAVLink log not found: {self.path}")
        self.config = config or TlogConfig()
        self.converter = MavlinkConverter(self.config.convert, origin)
        self.truth_origin: GeoOrigin | None = origin
        self._truth_held: list[tuple[Any, float]] = []
        self.counters: dict[str, Any] = {
            "messages_read": 0, "corrupt_frames": 0, "repaired_frames": {}, "samples_by_kind": {}, "rejected": {},
            "late_samples": 0, "duration_s": 0.0,
        }
        self.missing: list[str] = []
        self._imu_dt: list[float] = []
        self._imu_last_t: float | None = None
        self._imu_type: str | None = None
        self._imu_switches = 0
        suffix = self.path.suffix.lower()
        # ".log" is a DataFlash log as text (Mission Planner's "convert .bin to .log") when it
        # holds format records, else telemetry as a tlog holds it (as pymavlink decides)
        self._text_dataflash = suffix == ".log" and _is_text_dataflash(self.path)
        self._dataflash = suffix == ".bin" or self._text_dataflash
        self._index_said = False
        # a binary DataFlash log whose index stops short (pymavlink's indexers stop at a record of
        # a type no format declares): the offset of that record, where the rest is read from
        self._index_ends_at: int | None = None
        self._format_repairs: list | None = None  # a binary DataFlash log's damaged FMT bytes (found once)
        self._tlog = suffix == ".tlog" or (suffix == ".log" and not self._text_dataflash)
        self._text_lines_dropped_said = False
        self._text_log_clean = False  # a text log checked line by line and found whole
        self._blueos = self.path.suffix.lower() == ".mcap"  # BlueOS's recording (blueos_mcap)
        self.dataflash = DataflashConverter(self.converter, self.config.dataflash_baro_instance)
        self.has_truth = self._scan_truth()
        self._simulator_thrusters()
        if origin is None and self._tlog:
            self.converter.origin_lookup = self._ekf_origin_in_log

    # --------------------------------------------------------------------- helpers
    def _reject(self, reason: str, n: int = 1) -> None:
        rej = self.counters["rejected"]
        rej[reason] = rej.get(reason, 0) + n

    def _keep_imu(self, sample: ImuSample) -> bool:
        """Track the IMU rate; withhold samples of a stream too slow for strapdown."""
        if self._imu_last_t is not None and sample.t_s > self._imu_last_t:
            self._imu_dt.append(sample.t_s - self._imu_last_t)
        self._imu_last_t = sample.t_s
        if not self.config.drop_slow_imu:
            return True
        if imu_too_slow(self._imu_dt[-IMU_RATE_WINDOW:], self.config.min_imu_rate_hz):
            self._reject("imu_too_slow")
            return False
        return True

    def _convert(self, msg: Any) -> list:
        if self._dataflash:
            samples, truths = self.dataflash.convert(msg)
            if samples and isinstance(samples[0], ImuSample):
                self._imu_type = f"IMU[{self.dataflash.imu_instance}]"
        else:
            samples = self.converter.convert(msg)
            if samples and isinstance(samples[0], ImuSample):
                self._imu_type = self.converter.imu_message
                if self.converter.imu_switches != self._imu_switches:  # a better stream: its own rate
                    self._imu_switches = self.converter.imu_switches
                    self._imu_dt, self._imu_last_t = [], None
            truths = self._sim_state(msg) if msg.get_type() == "SIM_STATE" else []
        if truths:
            samples = samples + self._truth(truths)
        elif self.truth_origin is None and self._truth_held:
            fix = next((x for x in samples if x.KIND in ("gnss", "usbl") and math.isfinite(x.lat_rad)), None)
            if fix is not None:  # the replay's rule: the first position fix is the NED origin
                self.truth_origin = GeoOrigin(fix.lat_rad, fix.lon_rad, 0.0)
                held, self._truth_held = self._truth_held, []
                samples = samples + [self._truth_sample(t) for t in held]
        return samples

    def set_convert(self, convert: ConvertConfig, min_imu_rate_hz: float | None = None) -> None:
        """How messages become samples (the service's ``[mavlink.convert]``, as the live
        bridge uses it) and the slowest IMU stream kept for strapdown (the filter's
        ``alignment.min_imu_rate_hz``; None: as configured); before iteration only."""
        if self.counters["messages_read"]:
            raise RuntimeError("set_convert after the log has been read")
        self.config = replace(self.config, convert=convert)
        if min_imu_rate_hz is not None:
            self.config = replace(self.config, min_imu_rate_hz=min_imu_rate_hz)
            self.config.validate()
        old = self.converter  # its origin: configured, or none yet (then the log's, when needed)
        self.converter = MavlinkConverter(convert, old.origin)
        self.converter.origin_from, self.converter.origin_lookup = old.origin_from, old.origin_lookup
        self.dataflash = DataflashConverter(self.converter, self.config.dataflash_baro_instance)
        self._simulator_thrusters()

    def _simulator_thrusters(self) -> None:
        """A log with a simulator's truth is ArduPilot's simulator's: its thrusters through the
        simulator's curve from the first record (live, the converter switches on the truth's
        first message; here the scan knows before any thrust is read)."""
        if self.has_truth:
            self.converter.take_simulator("its SIM records" if self._dataflash else "SIM_STATE in the log")

    def set_origin(self, origin: GeoOrigin) -> None:
        """The NED origin the replay uses (a configured one); truth is placed around it."""
        self.truth_origin = origin
        self.converter.origin, self.converter.origin_from = origin, "config"

    def _sim_state(self, msg: Any) -> list[SimTruth]:
        """SIM_STATE (a simulator's ground truth; no time field: its receive time)."""
        t_s = self.converter.time.from_receive(getattr(msg, "_timestamp", None))
        if t_s is None:
            return []
        lat, lon = msg.lat_int * 1e-7, msg.lon_int * 1e-7
        if lat == 0.0 and lon == 0.0:  # older SIM_STATE, or MAVLink 1: without the integer fields
            lat, lon = msg.lat, msg.lon
            if abs(lat) > 90.0 or abs(lon) > 180.0:  # ArduPilot puts degE7 into these float fields
                lat, lon = lat * 1e-7, lon * 1e-7  # (a float32 holds degE7 to ±16: ~2 m of truth)
        return [SimTruth(t_s, lat, lon, float(msg.alt), (float(msg.vn), float(msg.ve), float(msg.vd)),
                         (float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4)))]

    def _truth(self, truths: list[SimTruth]) -> list:
        """A simulator's truth (SIM_STATE, DataFlash SIM) → TruthSample around the NED origin,
        held until the origin is known (the first fix, as the replay's). A record that cannot
        be a pose (not finite, not a unit quaternion, at 0°/0°: a damaged record) is rejected."""
        if not all(map(_plausible_truth, truths)):
            kept = [t for t in truths if _plausible_truth(t)]
            for _ in range(len(truths) - len(kept)):
                self._reject("truth_invalid")
            truths = kept
        if self.truth_origin is None:
            self._truth_held.extend(truths)
            return []
        return [self._truth_sample(t) for t in truths]

    def _truth_sample(self, t: SimTruth) -> TruthSample:
        pos = self.truth_origin.to_ned(math.radians(t.lat_deg), math.radians(t.lon_deg), t.alt_m)
        self.counters["truth_samples"] = self.counters.get("truth_samples", 0) + 1
        return TruthSample(t.t_s, tuple(float(v) for v in pos), t.vel_n_m_s, t.q_nb, (0.0, 0.0, 0.0), math.nan)

    def _ekf_origin_in_log(self, max_messages: int = 2_000_000) -> GeoOrigin | None:
        """The autopilot's EKF origin (GPS_GLOBAL_ORIGIN) wherever it is in the ``.tlog``: what
        places GLOBAL_VISION_POSITION_ESTIMATE's local positions (a USBL driver's fixes). Live,
        the bridge asks for it at link-up; a log may carry it only when something asked, after
        the first fixes (which were refused as ``no_origin`` and the replay had no position).
        The converter asks (``origin_lookup``) at the first such fix without an origin."""
        reader = TlogReader(self.path)
        try:
            msg = reader.first_message(GPS_GLOBAL_ORIGIN_ID, max_messages)
        finally:
            reader.close()
        if msg is None or not (msg.latitude or msg.longitude):
            return None
        return GeoOrigin(math.radians(msg.latitude * 1e-7), math.radians(msg.longitude * 1e-7), msg.altitude / 1000.0)

    def _scan_truth(self, max_messages: int = 20_000) -> bool:
        """Does the log carry a simulator's truth (SIM_STATE near its start; a DataFlash SIM record)?"""
        if self._tlog:
            reader = TlogReader(self.path)
            try:
                return reader.has_message(SIM_STATE_ID, max_messages)
            finally:
                reader.close()
        if self._blueos:  # the records' text, decoded only where it names SIM_STATE
            reader = BlueOsMcapReader(self.path)
            try:
                for i, (data, t_unix_s) in enumerate(reader.records()):
                    if i >= max_messages:
                        return False
                    if b"SIM_STATE" in data and getattr(reader.message(data, t_unix_s), "get_type",
                                                        lambda: "")() == "SIM_STATE":
                        return True
            except Exception:  # noqa: BLE001 — a damaged file or record: the reading pass reports it
                pass
            return False
        with reader_complaints():  # pymavlink's: the reading pass counts and says them
            try:
                conn = self._connect()
            except Exception:  # pymavlink's tlog index chokes on a truncated file; the reading pass reports it
                return False
            try:
                truth_type, next_message = "SIM_STATE", conn.recv_match
                if self._dataflash:  # DFReader indexes the file by record type: no scan
                    try:
                        found = conn.recv_match(type="SIM") is not None
                    except Exception:  # a damaged log: the reading pass reports it
                        return False
                    if found or self._index_ends_at is None:
                        return found
                    self._past_index(conn)  # an index that ends early: the records after it, scanned
                    truth_type, next_message = "SIM", conn.recv_msg
                for _ in range(max_messages):
                    try:
                        m = next_message()
                    except Exception:
                        continue
                    if m is None:
                        return False
                    if m.get_type() == truth_type:
                        return True
                return False
            finally:
                conn.close()

    def _connect(self) -> Any:
        """pymavlink's reader of the file. A text DataFlash log is checked line by line first
        (:func:`_clean_text_dataflash`): pymavlink's text reader gives up on the whole log at
        one bad line (a byte that is not UTF-8, garbage where it looks for a new record type),
        skips a line of too few fields or an unknown name without a word, and reads a line
        that a block of zeros merged with the next as one record of wrong values. A log with
        such lines is read from a copy without them, each counted as a corrupt frame and said.
        A binary one is read from a copy when a record format's length byte needs repair
        (:meth:`_open_binary_dataflash`)."""
        if self._dataflash and not self._text_dataflash:
            return self._open_binary_dataflash()
        if not self._text_dataflash or self._text_log_clean:
            return self._open(self.path)
        clean, dropped = _clean_text_dataflash(self.path.read_bytes())
        if not dropped:
            self._text_log_clean = True  # the next opening (the truth scan's, the replay's) trusts it
            return self._open(self.path)
        if not self._text_lines_dropped_said:
            self._text_lines_dropped_said = True
            self.counters["corrupt_frames"] += dropped
            log.warning("%s: %d lines are not records of the log's formats (garbage, lines merged "
                        "by a block of zeros, non-text bytes); the rest is read", self.path.name, dropped)
        return self._open_copy(clean, ".log")

    def _open_binary_dataflash(self) -> Any:
        """A binary DataFlash log, read from a copy with its damaged FMT record bytes repaired
        when it has some (:func:`~adaptnav.service.transport.dataflash.format_repairs`),
        each counted as a corrupt frame and said once."""
        import mmap

        if self._format_repairs is None:
            try:
                with open(self.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                    self._format_repairs = format_repairs(data)
            except (OSError, ValueError):  # empty or unreadable: the reader says so
                self._format_repairs = []
            for r in self._format_repairs:
                self.counters["corrupt_frames"] += 1
                self._reject(f"repaired_format_{r.what}:{r.name}")
                log.warning("%s: record format %s: its %s (%s) damaged, its records agree on one repair: "
                            "repaired", self.path.name, r.name, r.what, r.was)
        if not self._format_repairs:
            return self._open(self.path)
        data = bytearray(self.path.read_bytes())
        for r in self._format_repairs:
            data[r.offset] = r.value
        return self._open_copy(data, ".bin")

    def _open_copy(self, data: bytes | bytearray, suffix: str) -> Any:
        """pymavlink's reader of ``data`` (a mended copy of the log) from a temporary file."""
        with tempfile.NamedTemporaryFile(prefix="adaptnav-", suffix=suffix) as copy:
            copy.write(data)
            copy.flush()
            return self._open(Path(copy.name))  # mapped: outlives the name

    def _open(self, path: Path) -> Any:
        """pymavlink's reader; a text DataFlash log's directly (pymavlink takes only a
        lower-case ``.log`` for one: ``FILE.LOG`` was read as telemetry)."""
        if self._text_dataflash:
            from pymavlink import DFReader

            return DFReader.DFReader_text(str(path), zero_time_base=False)
        if not self._dataflash:
            return mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
        with tolerant_formats() as damaged, indexer_complaints() as indexer:
            conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
        if self._index_said:  # opened more than once (the truth scan): said and counted once
            return conn
        self._index_said = True
        self._index_ends_at = indexer["index_ends_at"]
        if self._index_ends_at is not None:
            log.warning("%s: the log's index ends at byte %d of %d, at a record of a type no format declares "
                        "(its format record lost, or the record's header damaged): the rest is read record by "
                        "record", self.path.name, self._index_ends_at, int(getattr(conn, "data_len", 0)))
        if damaged:
            self.counters["corrupt_frames"] += len(damaged)
            for name in damaged:
                self._reject(f"damaged_format:{name}")
            log.warning("%s: %d record format(s) damaged (%s): their records are skipped, the rest is read",
                        self.path.name, len(damaged), ", ".join(damaged))
        bad = indexer["bad_headers"]
        if bad:  # positions where no record header was found: damaged bytes, skipped
            self.counters["corrupt_frames"] += bad
            self._reject("indexer_bad_header", bad)
            log.warning("%s: pymavlink's indexer found no record header at %d position(s) (the first: %s): "
                        "damaged bytes skipped", self.path.name, bad, indexer["first"])
        return conn

    # --------------------------------------------------------------------- iteration
    def _messages(self) -> Iterator[Any]:
        if self._tlog:
            yield from self._tlog_messages()
            return
        if self._blueos:
            yield from self._blueos_messages()
            return
        if self._dataflash:
            with reader_complaints() as said:
                yield from self._reader_messages()
            self.dataflash.finish()  # (a record held for a jump of its time that no record confirmed)
            if said["lines"]:
                failed = said["parse_failures"]  # records dropped (a record may fail more than once)
                # damaged bytes, or records of a type no format declares, skipped to the next
                # record (only where the index did not reach: it leads to records only)
                skips = said["skips"]
                self.counters["corrupt_frames"] += failed + skips
                if failed:
                    self._reject("reader_parse_failure", failed)
                if skips:
                    self._reject("reader_skipped_bytes", skips)
                log.warning("%s: pymavlink's reader failed to parse records %d time(s) and skipped damaged bytes "
                            "%d time(s) (%d complaint(s), the first: %s)", self.path.name, failed, skips,
                            said["lines"], said["first"][:200])
            return
        yield from self._reader_messages()

    def _reader_messages(self) -> Iterator[Any]:
        """The messages of pymavlink's reader of the file (a DataFlash log, or telemetry of a
        kind our own readers do not take)."""
        try:
            conn = self._connect()
        except Exception as e:  # noqa: BLE001 — empty or foreign file (DFReader mmaps it): nothing to read
            self._reject(f"unreadable:{type(e).__name__}")
            log.warning("%s: not a readable MAVLink/DataFlash log (%s: %s)", self.path.name, type(e).__name__, e)
            return
        try:
            if not self._dataflash:
                if (yield from self._read_all(conn, conn.recv_match)):
                    self._note_cut_off(conn)
                return
            # a DataFlash log: only the records the replay reads are decoded (DFReader skips to
            # them through its index); the others are counted from the index
            if not (yield from self._read_all(conn, lambda: conn.recv_match(type=DATAFLASH_READ, strict=True))):
                return
            self._count_unread(conn)
            if self._index_ends_at is not None and not (yield from self._unindexed_rest(conn)):
                return
            self._note_cut_off(conn)
        finally:
            conn.close()

    def _read_all(self, conn: Any, next_message: Any) -> Iterator[Any]:
        """The messages ``next_message()`` gives until it gives None, as read (:meth:`_as_read`);
        an exception of the reader is counted as a corrupt frame and the reading goes on.
        Returns False when the reader failed twice in one place (the rest is not read, and said)."""
        stuck_at = None  # the reader's position at its last error
        while True:
            try:
                msg = next_message()
            except Exception as e:  # a reader bug on garbage must not end the replay
                self.counters["corrupt_frames"] += 1
                self._reject(f"reader_error:{type(e).__name__}")
                position = getattr(conn, "offset", None)
                if position is not None and position == stuck_at:  # it failed twice in one place
                    self._reject("unreadable_rest")
                    log.warning("%s: the reader cannot go past byte %d (%s: %s); the rest is not read",
                                self.path.name, position, type(e).__name__, e)
                    return False
                stuck_at = position
                continue
            stuck_at = None
            if msg is None:
                return True
            msg = self._as_read(msg, getattr(conn, "mav", None))  # a DataFlash reader has no parser
            if msg is not None:
                yield msg

    def _past_index(self, conn: Any) -> None:
        """DFReader set to parse on from where its index ends (:attr:`_index_ends_at`)."""
        conn.offset = self._index_ends_at
        conn.remaining = conn.data_len - conn.offset

    def _unindexed_rest(self, conn: Any) -> Iterator[Any]:
        """A binary DataFlash log's records after the end of its index (:attr:`_index_ends_at`),
        read one after the other by DFReader's own parser, which skips what it cannot read to
        the next record it knows (counted in :meth:`_messages`): those of the types the replay
        reads, the others counted as unread. Without it one record of a type no format declares
        — a zeroed block over a format record, one damaged header byte — lost the whole log
        after it. Returns as :meth:`_read_all`."""
        self._past_index(conn)
        unread: Counter[str] = Counter()

        def next_read() -> Any:
            while True:
                msg = conn.recv_msg()
                if msg is None or msg.get_type() in DATAFLASH_READ:
                    return msg
                unread[msg.get_type()] += 1

        whole = yield from self._read_all(conn, next_read)
        self.dataflash.count_unread(dict(unread))
        self.counters["messages_read"] += sum(unread.values())
        return whole

    def _count_unread(self, conn: Any) -> None:
        """A DataFlash log's records of the types not read, from DFReader's index."""
        indexed = getattr(conn, "counts", ())
        # a .BIN's index counts by type id, a text .log's (Mission Planner's conversion) by name
        by_name = (indexed.items() if isinstance(indexed, dict)
                   else ((conn.id_to_name.get(i), n) for i, n in enumerate(indexed)))
        counts = {name: int(n) for name, n in by_name if n and name and name not in DATAFLASH_READ}
        self.dataflash.count_unread(counts)
        self.counters["messages_read"] += sum(counts.values())

    def _as_read(self, msg: Any, mav: Any) -> Any | None:
        """A message as read, counted (None: a corrupt frame, counted as one); a frame a
        logger only cut the trailing zeros of is restored (``mav``: the parser's dialect)."""
        counters = self.counters
        if msg.get_type() == "BAD_DATA":
            counters["corrupt_frames"] += 1
            msg = untruncated(msg, mav) if mav is not None else None
            if msg is None:
                return None
            repaired = counters["repaired_frames"]
            repaired[msg.get_type()] = repaired.get(msg.get_type(), 0) + 1
        counters["messages_read"] += 1
        return msg

    def _tlog_messages(self) -> Iterator[Any]:
        """A ``.tlog``'s messages (:class:`TlogReader`); corrupt frames counted, restored
        where a logger only cut their trailing zeros."""
        reader = TlogReader(self.path)
        counters = self.counters
        try:
            for msg in reader:
                if isinstance(msg, Exception):  # the parser raised on garbage: count, go on
                    counters["corrupt_frames"] += 1
                    self._reject(f"reader_error:{type(msg).__name__}")
                    continue
                msg = self._as_read(msg, reader.mav)
                if msg is not None:
                    yield msg
            self._note_cut_off(reader)
        finally:
            reader.close()

    def _blueos_messages(self) -> Iterator[Any]:
        """A BlueOS recording's messages (:class:`BlueOsMcapReader`): a record that is not a
        MAVLink message is a corrupt frame; a type the dialect lacks is accounted as unknown."""
        reader = BlueOsMcapReader(self.path)
        if reader.layout is None:
            self._reject("unreadable:no_mavlink_topics")
            log.warning("%s: no MAVLink topics (mavlink/out, mavlink/<sys>/<comp>/<TYPE>): not a BlueOS "
                        "recording", self.path.name)
            return
        try:
            for msg in reader:
                if isinstance(msg, MalformedMessage):
                    self.counters["corrupt_frames"] += 1
                    self._reject("malformed_json")
                    continue
                self.counters["messages_read"] += 1
                if isinstance(msg, str):  # a type this dialect does not know: accounted as unknown
                    self.converter.count_unknown(msg)
                    continue
                yield msg
                self._note_damaged_chunks(reader)
            self._note_damaged_chunks(reader)
        except Exception as e:  # noqa: BLE001 — a damaged file: what came before was read
            self.counters["corrupt_frames"] += 1
            why = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
            self.counters["truncated"] = (f"{self.path.name} ends early or is damaged after "
                                          f"{self.counters['messages_read']} messages ({why}); everything "
                                          "before was replayed")
            log.warning("%s", self.counters["truncated"])

    def _note_damaged_chunks(self, reader: BlueOsMcapReader) -> None:
        while reader.damaged_chunks:
            self.counters["corrupt_frames"] += 1
            self._reject("damaged_chunk")
            log.warning("%s", reader.damaged_chunks.pop(0))

    def _note_cut_off(self, conn: Any) -> None:
        """At the end of the file: a last message cut off (the recorder lost power, a copy
        stopped early) is counted as a corrupt frame and said in ``counters["truncated"]`` —
        everything before it was read. A tlog's parser holds the cut frame's bytes; a
        DataFlash log ends with a record header and too few bytes after it (zeros or 0xFF
        after the last record are a card's unwritten space, not a cut)."""
        if self._text_dataflash:
            with open(self.path, "rb") as f:  # a text log's last line ends with its newline
                f.seek(0, 2)
                size = f.tell()
                f.seek(max(0, size - 4096))
                tail = f.read()
            left = len(tail) - (tail.rfind(b"\n") + 1)
            cut, what = left > 0 and tail.strip(b"\x00\xff \r\n\t") != b"", "line"
        elif self._dataflash:
            offset, end = int(getattr(conn, "offset", 0)), int(getattr(conn, "data_len", 0))
            data = getattr(conn, "data_map", None)
            left = end - offset
            cut = False
            if left > 0 and data is not None:
                if offset >= 3 and bytes(data[offset - 3:offset - 1]) == _DATAFLASH_HEADER:
                    cut, left = True, left + 3  # DFReader stops past the header of a record too short
                else:  # fewer than 3 bytes left, the start of a header
                    cut = bytes(data[offset:offset + 2]) == _DATAFLASH_HEADER[:left]
            what = "record"
        else:
            left = int(conn.mav.buf_len()) if getattr(conn, "mav", None) is not None else 0
            cut, what = left > 0, "frame"
        if cut:
            self.counters["corrupt_frames"] += 1
            self.counters["truncated"] = (f"{self.path.name} ends inside a {what}: its last {left} bytes are an "
                                          "incomplete message (the recording was cut off); everything before "
                                          "them was replayed")
            log.warning("%s", self.counters["truncated"])

    def __iter__(self) -> Iterator[Any]:
        heap: list[tuple] = []
        seq = 0
        released_t = -math.inf
        t_first = t_last = None
        by_kind = self.counters["samples_by_kind"]
        window = self.config.reorder_window_s

        last_t_by_kind: dict[str, float] = {}

        def release(upto: float):
            nonlocal released_t, t_first, t_last
            while heap and heap[0][0][0] <= upto:
                _, sample = heapq.heappop(heap)
                if last_t_by_kind.get(sample.KIND) == sample.t_s:
                    self._reject("duplicate_time")  # same message logged twice (two links)
                    continue
                last_t_by_kind[sample.KIND] = sample.t_s
                released_t = sample.t_s
                t_first = sample.t_s if t_first is None else t_first
                t_last = sample.t_s
                by_kind[sample.KIND] = by_kind.get(sample.KIND, 0) + 1
                yield sample

        def push(samples: list):
            nonlocal seq
            for sample in samples:
                if isinstance(sample, ImuSample) and not self._keep_imu(sample):
                    continue
                if sample.t_s < released_t:
                    self.counters["late_samples"] += 1
                    self._reject("late")
                    continue
                heapq.heappush(heap, (replay_order_key(sample, seq), sample))
                seq += 1

        for msg in self._messages():
            samples = self._convert(msg)
            if samples:
                push(samples)
                yield from release(max(s.t_s for s in samples) - window)
        push(self.converter.flush())
        yield from release(math.inf)
        for reason, n in self.converter.rejected.items():
            self.counters["rejected"][reason] = self.counters["rejected"].get(reason, 0) + n
        self.counters["duration_s"] = 0.0 if t_first is None else t_last - t_first
        self.counters["reboots"] = self.converter.time.reboots
        self.counters["message_types"] = (self.converter.accounting(DATAFLASH_USED, DATAFLASH_IGNORED_WHY)
                                          if self._dataflash else self.converter.accounting())
        self.counters["clock"] = self.converter.clock_report()
        self.counters["gps_fixes"] = self.converter.gps_report()
        self.counters["thrusters"] = self.converter.thruster_report()
        if not self._dataflash:
            self.counters["imu_stream"] = {"integrated": self.converter.integrated_imu_stream(),
                                           "switches": self.converter.imu_switches}
        self.missing = self._diagnose()

    def _diagnose(self) -> list[str]:
        by_kind = self.counters["samples_by_kind"]
        out = []
        if not by_kind.get("imu"):
            if self._imu_dt:
                rate = 1.0 / statistics.median(self._imu_dt)
                fallback = "using ATTITUDE" if by_kind.get("attitude") else "and no ATTITUDE either"
                out.append(f"no usable IMU stream: {self._imu_type or 'IMU'} at {rate:.1f} Hz is too slow "
                           f"for strapdown (< {self.config.min_imu_rate_hz:g} Hz); {fallback}")
            else:
                out.append("no IMU stream")
        df = self._dataflash  # the records' names in a DataFlash log, the messages' in a tlog
        if not by_kind.get("attitude"):
            out.append("no attitude (ATT)" if df else "no attitude (ATTITUDE)")
        if not by_kind.get("depth"):
            out.append(f"no depth (BARO[{self.dataflash.baro_instance}] absent or invalid)" if df
                       else f"no depth ({self.converter.depth_message} absent or invalid)")
        if not by_kind.get("rpm"):
            out.append("no thruster RPM (RCOU)" if df else "no thruster RPM (SERVO_OUTPUT_RAW)")
        if not (by_kind.get("usbl") or by_kind.get("gnss")):
            out.append("no position fixes (GPS with a 3D fix)" if df
                       else "no position fixes (GPS_INPUT / GPS_RAW_INT with a fix)")
        return out
