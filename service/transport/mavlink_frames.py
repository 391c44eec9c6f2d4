"""MAVLink 2 frames that fail their CRC only because a logger cut their payload's trailing zeros.

MAVLink 2 senders must drop a payload's trailing zero bytes *before* computing the CRC
(the spec's payload truncation); receivers must accept an untruncated frame too.  BlueOS
extensions send through mavlink2rest / rust-mavlink, which do not truncate (mavlink2rest#80,
rust-mavlink#188): the Ping echosounder's ``DISTANCE_SENSOR``, the Water Linked UGPS
extension's ``GPS_INPUT`` (its ``yaw`` extension is 0), commands.  The autopilot accepts them
(the CRC covers the whole payload), but QGroundControl's tlog writer serialises each frame
anew with ``mavlink_msg_to_send_buffer``, which truncates the payload and keeps the CRC of
the whole one (pymavlink#237, BlueOS#1740): in a QGC tlog of a BlueOS vehicle these frames
read as ``BAD_DATA`` "invalid MAVLink CRC" — an underwater-GPS fix, an altitude, lost.

:func:`untruncated` restores such a frame: it pads the payload with zeros back to the
message's length without and with its extension fields and accepts the frame only when the
CRC then matches (the sender's exact bytes; a garbled frame matches by chance with
probability 2/65536).  Anything else stays a corrupt frame.
"""
from __future__ import annotations

import contextlib
import functools
import io
import os
import struct
from typing import Any

_V2_MAGIC = 0xFD
_V2_HEADER = 10  # magic, len, incompat, compat, seq, sysid, compid, msgid (3 bytes)
_IFLAG_SIGNED = 0x01


@functools.cache
def message_definitions() -> tuple[Any, ...]:
    """The messages of the ardupilotmega dialect with its includes, as pymavlink's own XML
    definitions describe them (``mavparse.MAVType``: fields, extensions, wire lengths)."""
    from pymavlink.generator import mavparse
    import pymavlink.dialects.v20 as dialects

    folder = os.path.dirname(dialects.__file__)
    parsed: dict[str, Any] = {}

    def load(name: str) -> None:
        if name in parsed:
            return
        with contextlib.redirect_stdout(io.StringIO()):  # mavparse prints its enum warnings
            parsed[name] = mavparse.MAVXML(os.path.join(folder, name), mavparse.PROTOCOL_2_0)
        for include in parsed[name].include:
            load(include)

    load("ardupilotmega.xml")
    return tuple(m for x in parsed.values() for m in x.message)


@functools.cache
def _lengths_by_msgid() -> dict[int, tuple[int, ...]]:
    """Wire payload lengths of each message: without its extension fields, and with them."""
    return {m.id: tuple(sorted({m.wire_min_length, m.wire_length})) for m in message_definitions()}


def untruncated(bad: Any, mav: Any) -> Any | None:
    """The message a ``BAD_DATA`` pseudo-message ``bad`` was, when its frame fails the CRC only
    because its payload's trailing zeros were cut after the CRC was computed; else None.

    ``mav`` is the connection's ``MAVLink`` parser (ardupilotmega, as everywhere here: it decodes
    the restored frame).
    The restored message keeps ``bad``'s receive stamp (``_timestamp``: a tlog's recording time).
    """
    if "CRC" not in str(getattr(bad, "reason", "")):
        return None
    frame = bytes(getattr(bad, "data", b""))
    if len(frame) < _V2_HEADER + 2 or frame[0] != _V2_MAGIC or frame[2] & _IFLAG_SIGNED:
        return None
    n = frame[1]
    if len(frame) != _V2_HEADER + n + 2:
        return None
    msgid = frame[7] | frame[8] << 8 | frame[9] << 16
    from pymavlink.dialects.v20 import ardupilotmega
    from pymavlink.generator.mavcrc import x25crc

    msg_class = ardupilotmega.mavlink_map.get(msgid)
    if msg_class is None:
        return None
    (crc_sent,) = struct.unpack_from("<H", frame, _V2_HEADER + n)
    for full in _lengths_by_msgid().get(msgid, ()):
        if full <= n:
            continue
        restored = bytearray(frame[:_V2_HEADER + n])
        restored[1] = full
        restored += bytes(full - n)
        crc = x25crc(restored[1:])
        crc.accumulate(bytes((msg_class.crc_extra,)))
        if crc.crc != crc_sent:
            continue
        restored += struct.pack("<H", crc_sent)
        try:
            msg = mav.decode(restored)
        except Exception:  # noqa: BLE001 — a frame the dialect cannot decode stays corrupt
            return None
        msg._timestamp = getattr(bad, "_timestamp", None)
        return msg
    return None


# --------------------------------------------------------------------------- .tlog files
_STAMP = struct.Struct(">Q")
_V1_MAGIC = 0xFE
SIM_STATE_ID = 108
GPS_GLOBAL_ORIGIN_ID = 49


class TlogReader:
    """The messages of a ``.tlog``: records of an 8-byte big-endian µs stamp (the recorder's
    wall clock) and one MAVLink frame.

    Frames go through pymavlink's own parser (robust: a damaged frame is a ``BAD_DATA``
    pseudo-message, ``_timestamp`` the record's stamp) in the order pymavlink's log reader
    feeds it — the same messages — without that reader's per-message bookkeeping (per-system
    message tables, sequence statistics, progress, a whole-file index at open), which a replay
    never reads and which cost it a third of its time on a busy log.

    ``mav`` is the parser: after iteration ``mav.buf_len()`` says how many bytes of a last,
    incomplete frame it holds. An exception of the parser is yielded in the frame's place (the
    next record is read after it): a reader bug on garbage must not end the log.
    """

    def __init__(self, path: str | os.PathLike):
        import mmap

        from pymavlink.dialects.v20 import ardupilotmega

        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            self._data: Any = mmap.mmap(f.fileno(), size, access=mmap.ACCESS_READ) if size else b""
        self.mav = ardupilotmega.MAVLink(None)
        self.mav.robust_parsing = True

    def close(self) -> None:
        if hasattr(self._data, "close"):
            self._data.close()

    def __iter__(self):
        from pymavlink.dialects.v20.ardupilotmega import MAVError, MAVLink_bad_data

        data, end = self._data, len(self._data)
        mav = self.mav
        parse, needed, unpack = mav.parse_char, mav.bytes_needed, _STAMP.unpack_from
        decode, held = mav.decode, mav.buf_len
        pos, t_s = 0, None
        while True:
            if pos + 8 <= end:
                t_s = unpack(data, pos)[0] * 1e-6
            pos = min(pos + 8, end)  # a short stamp at the end is read and dropped, as pymavlink does
            # a whole frame with nothing held by the parser: decoded at once, as parse_char
            # would decode it after staging its header and body (the same message, or the same
            # BAD_DATA) — its byte-wise staging was a tenth of a tlog's replay. Only where the
            # parser's first read (bytes_needed) would not reach past the frame; anything else
            # (no magic byte, unknown incompat flags, a frame cut by the file's end) goes the
            # parser's way below
            if pos + 3 <= end and not held():
                magic, n, flags = data[pos], data[pos + 1], data[pos + 2]
                if magic == _V2_MAGIC and not flags & ~_IFLAG_SIGNED:
                    size = _V2_HEADER + n + 2 + (13 if flags & _IFLAG_SIGNED else 0)
                elif magic == _V1_MAGIC:
                    size = 6 + n + 2
                else:
                    size = 0
                if size and pos + size <= end and needed() <= size:
                    frame = bytearray(data[pos:pos + size])
                    pos += size
                    try:
                        msg = decode(frame)
                    except MAVError as e:  # robust parsing's answer to a frame it cannot decode
                        msg = MAVLink_bad_data(frame, e.message)
                    except Exception as e:  # noqa: BLE001 — said to the caller, which counts it
                        yield e
                        continue
                    msg._timestamp = t_s
                    yield msg
                    continue
            while True:
                chunk = data[pos:pos + needed()]
                pos += len(chunk)
                try:
                    msg = parse(chunk)
                except Exception as e:  # noqa: BLE001 — said to the caller, which counts it
                    yield e
                    break
                if msg is not None:
                    msg._timestamp = t_s
                    yield msg
                    break
                if not chunk:
                    return

    def has_message(self, msgid: int, max_records: int = 20_000) -> bool:
        """Is a message ``msgid`` among the first ``max_records`` records (a walk over the
        frame headers, nothing decoded)?"""
        return self._find(msgid, max_records) is not None

    def first_message(self, msgid: int, max_records: int = 20_000) -> Any:
        """The first message ``msgid`` among the first ``max_records`` records, decoded (None:
        none there, or it does not decode)."""
        found = self._find(msgid, max_records)
        if found is None:
            return None
        from pymavlink.dialects.v20 import ardupilotmega

        pos, size = found
        try:
            return ardupilotmega.MAVLink(None).decode(bytearray(self._data[pos + 8:pos + size]))
        except Exception:  # noqa: BLE001 — a damaged frame: the reading pass counts it
            return None

    def _find(self, msgid: int, max_records: int) -> tuple[int, int] | None:
        """(record offset, record size) of the first frame ``msgid`` (a walk over the headers)."""
        data, end = self._data, len(self._data)
        pos = records = 0
        while pos + 18 <= end and records < max_records:
            magic, n = data[pos + 8], data[pos + 9]
            if magic == _V2_MAGIC:
                found = data[pos + 15] | data[pos + 16] << 8 | data[pos + 17] << 16
                size = 8 + _V2_HEADER + n + 2 + (13 if data[pos + 10] & _IFLAG_SIGNED else 0)
            elif magic == _V1_MAGIC:
                found, size = data[pos + 13], 8 + 6 + n + 2
            else:  # out of step (a damaged record): look for the next frame
                pos += 1
                continue
            if found == msgid:
                return pos, size
            pos += size
            records += 1
        return None
