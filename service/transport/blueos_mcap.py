"""BlueOS's own recordings of MAVLink (``.mcap``, written on the vehicle while it is armed).

BlueOS's mavlink-server publishes every MAVLink message it routes (the autopilot's and the
companion's: a DVL or underwater-GPS extension's) on Zenoh, and its recorder writes them to an
MCAP file: topic ``mavlink/out`` (every message) and ``mavlink/<system>/<component>/<TYPE>``,
each message a JSON text in mavlink2rest's form::

    {"header": {"system_id": 1, "component_id": 1, "sequence": 42},
     "message": {"type": "ATTITUDE", "time_boot_ms": 123456, "roll": 0.01, ...}}

where a field named ``type`` is ``mavtype``, an enum value is ``{"type": "MAV_..."}``, a
bitmask ``{"bits": n}`` or, as rust-mavlink's bitflags 2 write it, ``"FLAG_A | FLAG_B | 0x100"``
(the bits no flag names as one hex number, ``""`` for none), a char array text (or a list of characters
or codes), and non-finite floats are JSON5's ``NaN``/``Infinity``.  MAVLink 2 extension fields
may be missing (BlueOS 1.4, mavlink-server#213): they take their defaults.  The log time of a
record is the vehicle computer's UNIX clock at reception (as a tlog's stamp).

:class:`BlueOsMcapReader` yields each as the pymavlink message it was (header, fields,
``_timestamp``), so a BlueOS recording replays through the same converter and accounts as a
tlog (:class:`adaptnav.service.transport.tlog_source.TlogSource`).  The layout is the one the
public BlueOS tools read (mavlink-server's Zenoh topics, ``mcap_to_tlog`` in
clydemcqueen/ardusub_log_tools); a message that does not follow it is counted as malformed,
never guessed at.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Iterator

from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from adaptnav.service.transport.logs import DamagedChunkError, resilient_records

ALL_TOPIC = "mavlink/out"
_PER_TYPE_TOPIC = re.compile(r"^mavlink/\d+/\d+/[A-Z0-9_]+$")
_SCAN_RECORDS = 5000  # a file without its summary (cut off): its first records say what it is


def mavlink_layout(path: str | Path) -> str | None:
    """How ``path`` carries MAVLink: ``"out"`` (every message on ``mavlink/out``, read only
    there), ``"per_type"`` (only ``mavlink/<sys>/<comp>/<TYPE>``), or None (not a BlueOS
    recording). From the summary; a file cut off before it (recording at power loss, or
    downloaded while open) by its first records."""
    topics: set[str] = set()
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is not None:
            topics = {c.topic for c in summary.channels.values()}
    except Exception:  # noqa: BLE001 — not an MCAP file, or damaged before its summary
        summary = None
    if summary is None:
        try:
            with open(path, "rb") as f:
                for i, record in enumerate(StreamReader(f, validate_crcs=False).records):
                    if isinstance(record, Channel):
                        topics.add(record.topic)
                    if i >= _SCAN_RECORDS or ALL_TOPIC in topics:
                        break
        except Exception:  # noqa: BLE001 — what was read before the damage decides
            pass
    if ALL_TOPIC in topics:
        return "out"
    return "per_type" if any(_PER_TYPE_TOPIC.match(t) for t in topics) else None


class MalformedMessage(ValueError):
    """A record that is not a MAVLink message in mavlink2rest's form."""


class BlueOsMcapReader:
    """Iterate a BlueOS MCAP recording as pymavlink messages.

    Yields a message, or for a record that cannot be one a :class:`MalformedMessage`, or for
    a message type the dialect does not know its name (a ``str``) — the caller counts both.
    """

    def __init__(self, path: str | Path):
        from pymavlink.dialects.v20 import ardupilotmega

        self.path = Path(path)
        self.layout = mavlink_layout(self.path)
        self.damaged_chunks: list[str] = []  # what records() could not read and went past
        self._mav = ardupilotmega
        self._classes = {cls.msgname: cls for cls in ardupilotmega.mavlink_map.values()}

    def _wanted(self, topic: str) -> bool:
        return topic == ALL_TOPIC if self.layout == "out" else bool(_PER_TYPE_TOPIC.match(topic))

    def records(self) -> Iterator[tuple[bytes, float]]:
        """The MAVLink records as ``(JSON bytes, log time in UNIX s)``, in file order (as
        recorded); the file read sequentially, so a file cut off yields everything before the
        cut, then raises (the caller says so)."""
        if self.layout is None:
            return
        wanted: dict[int, bool] = {}
        with open(self.path, "rb") as f:
            for record in resilient_records(f, self.path):
                if isinstance(record, DamagedChunkError):  # the next chunk is read
                    self.damaged_chunks.append(str(record))
                elif isinstance(record, Channel):
                    wanted[record.id] = self._wanted(record.topic)
                elif isinstance(record, Message) and wanted.get(record.channel_id):
                    yield record.data, record.log_time / 1e9

    def __iter__(self) -> Iterator[Any]:
        """:meth:`records` as pymavlink messages (or what :meth:`message` says instead)."""
        for data, t_unix_s in self.records():
            try:
                yield self.message(data, t_unix_s)
            except MalformedMessage as e:
                yield e

    def message(self, data: bytes, t_unix_s: float) -> Any:
        """One record's JSON as a pymavlink message (its type name when the dialect lacks it)."""
        try:
            doc = json.loads(data)
            header, body = doc.get("header") or {}, dict(doc["message"])
            name = body.pop("type")
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            raise MalformedMessage(f"not a MAVLink JSON record: {type(e).__name__}") from None
        cls = self._classes.get(name)
        if cls is None:
            return str(name)
        kwargs = {}
        for field, ftype in zip(cls.fieldnames, cls.fieldtypes):
            key = "mavtype" if field == "type" else field
            if key in body:
                kwargs[field] = self._value(body[key], ftype, name, field)
        try:
            msg = cls(**kwargs)  # a missing extension field takes its default; a base field cannot
        except TypeError as e:
            raise MalformedMessage(f"{name}: {e}") from None
        msg._header = self._mav.MAVLink_header(cls.id, seq=int(header.get("sequence", 0) or 0) & 0xFF,
                                               srcSystem=int(header.get("system_id", 0) or 0),
                                               srcComponent=int(header.get("component_id", 0) or 0))
        msg._timestamp = t_unix_s
        return msg

    def _value(self, v: Any, ftype: str, name: str, field: str) -> Any:
        if ftype == "char":
            if isinstance(v, list):
                v = "".join(c if isinstance(c, str) else chr(int(c)) for c in v)
            return str(v).split("\x00", 1)[0].encode("utf-8")  # pymavlink's constructors take bytes
        if isinstance(v, list):
            return [self._value(x, ftype, name, field) for x in v]
        if isinstance(v, dict):
            if "bits" in v:
                return int(v["bits"])
            if "type" in v:
                return self._constant(str(v["type"]), name, field)
            raise MalformedMessage(f"{name}.{field}: {v!r}")
        if isinstance(v, str):  # a bitmask written out ("A | B | 0x100"), a constant, or empty
            bits = 0
            for part in filter(None, (p.strip() for p in v.split("|"))):
                bits |= self._constant(part, name, field)
            return bits
        if v is None:  # JSON's null for a non-finite float
            return math.nan if ftype in ("float", "double") else 0
        return v

    def _constant(self, constant: str, name: str, field: str) -> int:
        """A name of the dialect, or the number bitflags 2 writes for bits no flag names
        (``0x100``; decimal too). A name the dialect lacks (a newer sender) cannot be turned
        into bits: the message is malformed rather than read with a guess."""
        if constant[:1].isdigit():
            try:
                return int(constant, 0)
            except ValueError:
                raise MalformedMessage(f"{name}.{field}: not a number {constant!r}") from None
        value = getattr(self._mav, constant, None)
        if not isinstance(value, int):
            raise MalformedMessage(f"{name}.{field}: unknown constant {constant!r}")
        return value

