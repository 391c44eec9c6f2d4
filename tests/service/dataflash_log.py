"""Write small ArduPilot DataFlash logs (``.BIN``) for tests: FMT records, then records.

The binary format as ArduPilot writes it (``libraries/AP_Logger/LogStructure.h``): every record
is ``0xA3 0x95 <type id>`` and its fields packed little-endian by the format's letters; an FMT
record (type 128) declares each type.  pymavlink's DFReader reads the result as it reads a
vehicle's log (``L``: latitude/longitude as int32 degE7, read back in degrees).
"""
from __future__ import annotations

import struct
from pathlib import Path

_STRUCT = {"B": "B", "b": "b", "H": "H", "h": "h", "I": "I", "i": "i", "Q": "Q", "q": "q", "f": "f", "d": "d",
           "n": "4s", "N": "16s", "Z": "64s", "L": "i", "M": "B"}
HEAD = b"\xa3\x95"


class DataflashWriter:
    """``fmt(name, form, labels)`` declares a record type, ``write(name, *values)`` writes one."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._f = open(self.path, "wb")
        self._types: dict[str, tuple[int, str]] = {}
        self._f.write(self._fmt_record(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))

    @staticmethod
    def _length(form: str) -> int:
        return 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in form))

    def _fmt_record(self, type_id: int, name: str, form: str, labels: str) -> bytes:
        return HEAD + struct.pack("<BBB4s16s64s", 128, type_id, self._length(form), name.encode(), form.encode(),
                                  labels.encode())

    def fmt(self, name: str, form: str, labels: str) -> "DataflashWriter":
        type_id = 129 + len(self._types)
        self._types[name] = (type_id, form)
        self._f.write(self._fmt_record(type_id, name, form, labels))
        return self

    def write(self, name: str, *values) -> None:
        type_id, form = self._types[name]
        vals = [v.encode() if isinstance(v, str) else v for v in values]
        vals = [round(v * 1e7) if c == "L" else v for c, v in zip(form, vals)]
        self._f.write(HEAD + struct.pack("<B" + "".join(_STRUCT[c] for c in form), type_id, *vals))

    def close(self) -> Path:
        self._f.close()
        return self.path


def ardusub_formats(w: DataflashWriter) -> DataflashWriter:
    """The record types of an ArduSub 4.7 log that the replay reads (their 4.7 layouts, the
    fields the replay needs), and two it ignores."""
    w.fmt("IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    w.fmt("ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    w.fmt("BARO", "QBfff", "TimeUS,I,Alt,Press,Temp")
    w.fmt("RCOU", "QHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6")
    w.fmt("GPS", "QBBIHBfLLff", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd")
    w.fmt("GPA", "QBfffff", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc")
    w.fmt("SIM", "QfffLLfffff", "TimeUS,Roll,Pitch,Yaw,Lat,Lng,Alt,Q1,Q2,Q3,Q4")
    w.fmt("SIM2", "Qdddfff", "TimeUS,PN,PE,PD,VN,VE,VD")
    w.fmt("MSG", "QZ", "TimeUS,Message")
    w.fmt("XKF1", "QBffffff", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD")
    w.fmt("PARM", "QNf", "TimeUS,Name,Value")
    return w


def text_log_from_bin(bin_path: Path, log_path: Path, newline: str = "\r\n") -> Path:
    """Write a ``.BIN`` as Mission Planner's "convert .bin to .log" writes it: one line per
    record in the file's order (FMT lines where the FMT records are), ``NAME, v1, v2, ...``,
    values as the format's letters scale them (``c`` centi-units, ``L`` degrees); CRLF."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(bin_path), zero_time_base=False)
    with open(log_path, "w", newline="") as out:
        while (m := reader.recv_msg()) is not None:
            if m.get_type() == "FMT":
                values = [m.Type, m.Length, m.Name, m.Format, m.Columns]
            else:
                values = []
                for name in m._fieldnames:
                    v = getattr(m, name)
                    values.append(v.decode("ascii", "replace").rstrip("\0") if isinstance(v, bytes) else v)
            out.write(", ".join([m.get_type()] + [repr(v) if isinstance(v, float) else str(v) for v in values])
                      + newline)
    return Path(log_path)
