"""MAVLink frames as real senders and loggers get them wrong (for the readers' tests)."""
from __future__ import annotations


def qgc_logged(msg, mav) -> bytes:
    """``msg`` as a sender that does not truncate (BlueOS's mavlink2rest) sends it and QGC's tlog
    writer stores it: the payload cut of its trailing zeros, the CRC of the whole payload kept."""
    import struct

    from pymavlink.generator.mavcrc import x25crc

    frame = msg.pack(mav)  # pymavlink truncates as the spec says, CRC over the cut payload
    n, full = frame[1], type(msg).unpacker.size
    assert n < full, "the test needs a message with trailing zeros"
    whole = bytearray(frame[:10 + n])
    whole[1] = full
    whole += bytes(full - n)
    crc = x25crc(bytes(whole[1:]))
    crc.accumulate(bytes((type(msg).crc_extra,)))
    return bytes(frame[:10 + n]) + struct.pack("<H", crc.crc)


def _extension_fields() -> dict[str, set[str]]:
    """Message name → its MAVLink 2 extension fields (pymavlink's own XML definitions)."""
    from adaptnav.service.transport.mavlink_frames import message_definitions

    out = {}
    for m in message_definitions():
        start = m.extensions_start if m.extensions_start is not None else len(m.fields)
        out[m.name] = {f.name for f in m.fields[start:]}
    return out


def bitflags_text(value: int, flags: dict) -> str:
    """A bitmask as rust-mavlink's bitflags 2 write it in human-readable serde (newer
    mavlink2rest): the named flags it holds joined by ``" | "`` in the enum's order, the bits no
    flag names as one hex number (``"0x..."``), ``""`` for none."""
    parts, rest = [], int(value)
    for bit, entry in sorted(flags.items()):
        if bit and bit & rest == bit:
            parts.append(entry.name)
            rest &= ~bit
    if rest:
        parts.append(hex(rest))
    return " | ".join(parts)


def mavlink2rest_json(msg, drop_extensions: bool = False, extensions: dict | None = None,
                      bitmask_text: bool = False) -> dict:
    """``msg`` as BlueOS's mavlink-server writes it (mavlink2rest's JSON): ``type`` → ``mavtype``,
    enum values ``{"type": NAME}``, bitmasks ``{"bits": n}`` (or, ``bitmask_text``, as text:
    :func:`bitflags_text`), char arrays as text; the MAVLink 2 extension fields left out with
    ``drop_extensions`` (BlueOS 1.4's recordings)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    cls = type(msg)
    skip = (extensions or {}).get(cls.msgname, set()) if drop_extensions else set()
    body = {"type": cls.msgname}
    for field in cls.fieldnames:
        if field in skip:
            continue
        v = getattr(msg, field)
        enum = cls.fieldenums_by_name.get(field)
        if isinstance(v, bytes):
            v = v.decode("utf-8", "replace").split("\x00", 1)[0]
        elif enum and cls.fielddisplays_by_name.get(field) == "bitmask":
            v = bitflags_text(v, mav.enums.get(enum, {})) if bitmask_text else {"bits": int(v)}
        elif enum and isinstance(v, int) and v in mav.enums.get(enum, {}):
            v = {"type": mav.enums[enum][v].name}
        body["mavtype" if field == "type" else field] = v
    h = msg._header
    return {"header": {"system_id": h.srcSystem, "component_id": h.srcComponent, "sequence": h.seq},
            "message": body}


def write_blueos_mcap(tlog, out, drop_extensions: bool = False, per_type_topics: bool = False,
                      bitmask_text: bool = False):
    """A tlog's messages as a BlueOS recording (``mavlink/out``, or ``mavlink/<sys>/<comp>/<TYPE>``
    with ``per_type_topics``), each at its tlog stamp as the record's log time; bitmasks as
    text with ``bitmask_text`` (:func:`mavlink2rest_json`)."""
    import json

    from mcap.writer import Writer

    from adaptnav.service.transport.mavlink_frames import TlogReader

    extensions = _extension_fields() if drop_extensions else None
    channels: dict[str, int] = {}
    with open(out, "wb") as f:
        w = Writer(f)
        w.start()
        for msg in TlogReader(tlog):
            if isinstance(msg, Exception) or msg.get_type() == "BAD_DATA":
                continue
            h = msg._header
            topic = f"mavlink/{h.srcSystem}/{h.srcComponent}/{msg.get_type()}" if per_type_topics else "mavlink/out"
            if topic not in channels:
                channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=0)
            ns = int(round(msg._timestamp * 1e9))
            data = json.dumps(mavlink2rest_json(msg, drop_extensions, extensions, bitmask_text)).encode()
            w.add_message(channels[topic], log_time=ns, data=data, publish_time=ns)
        w.finish()
    return out


def as_mavlink1(tlog, out):
    """A tlog's messages re-framed as MAVLink 1 (an older autopilot or ground station): the
    extension fields dropped, messages with ids above 255 dropped, stamps kept."""
    import struct

    from pymavlink.dialects.v10 import ardupilotmega as v1

    from adaptnav.service.transport.mavlink_frames import TlogReader

    class _Nowhere:
        def write(self, _buf):
            pass

    reader = TlogReader(tlog)
    with open(out, "wb") as f:
        for msg in reader:
            if isinstance(msg, Exception) or msg.get_type() == "BAD_DATA":
                continue
            cls = v1.mavlink_map.get(msg.get_msgId())
            if cls is None:
                continue
            fields = [getattr(msg, name) for name in cls.fieldnames]
            mav = v1.MAVLink(_Nowhere(), srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
            mav.seq = msg.get_seq()
            frame = cls(*[v.encode() if isinstance(v, str) else v for v in fields]).pack(mav)
            f.write(struct.pack(">Q", int(round(msg._timestamp * 1e6))) + frame)
    reader.close()
    return out


def water_sensor_on_third_baro(tlog, out, say_baro_primary: bool = True):
    """A tlog as a vehicle whose board has two barometers of its own logs it: the water sensor
    is the third (SCALED_PRESSURE3: the original SCALED_PRESSURE2's readings), the second reads
    the air in the enclosure; ``say_baro_primary``: the autopilot's PARAM_VALUE BARO_PRIMARY = 2
    (what ArduSub saves when it picks that sensor) follows its first HEARTBEAT."""
    import struct

    from pymavlink.dialects.v20 import ardupilotmega as v2

    from adaptnav.service.transport.mavlink_frames import TlogReader

    class _Nowhere:
        def write(self, _buf):
            pass

    reader = TlogReader(tlog)
    said = not say_baro_primary
    with open(out, "wb") as f:
        def put(t_s, msg, sysid, compid):
            mav = v2.MAVLink(_Nowhere(), srcSystem=sysid, srcComponent=compid)
            f.write(struct.pack(">Q", int(round(t_s * 1e6))) + msg.pack(mav))

        for msg in reader:
            if isinstance(msg, Exception) or msg.get_type() == "BAD_DATA":
                continue
            t_s, sysid, compid = msg._timestamp, msg.get_srcSystem(), msg.get_srcComponent()
            if msg.get_type() == "SCALED_PRESSURE2":
                put(t_s, v2.MAVLink_scaled_pressure2_message(msg.time_boot_ms, 1013.25, 0.0, 2500), sysid, compid)
                put(t_s, v2.MAVLink_scaled_pressure3_message(msg.time_boot_ms, msg.press_abs, msg.press_diff,
                                                              msg.temperature), sysid, compid)
                continue
            if msg.get_type() == "SCALED_PRESSURE3":
                continue  # the simulator's absent third sensor (zeros)
            f.write(struct.pack(">Q", int(round(t_s * 1e6))) + msg.get_msgbuf())
            if not said and msg.get_type() == "HEARTBEAT" and compid == 1:
                put(t_s, v2.MAVLink_param_value_message(b"BARO_PRIMARY", 2.0, v2.MAV_PARAM_TYPE_INT8, 900, 50),
                    sysid, compid)
                said = True
    reader.close()
    return out


def dvl_as_odometry(tlog, out):
    """A tlog's VISION_POSITION_DELTA as the Water Linked DVL extension's ODOMETRY mode sends
    them (system 255, component 0): the body velocity (delta / Δt), x, y, z and q NaN,
    child frame BODY_FRD, the velocity variance (1 cm/s)² on the covariance diagonal, quality
    from the confidence, ``time_usec`` on the driver's own clock."""
    import math
    import struct

    from pymavlink.dialects.v20 import ardupilotmega as v2

    from adaptnav.service.transport.mavlink_frames import TlogReader

    class _Nowhere:
        def write(self, _buf):
            pass

    reader = TlogReader(tlog)
    mav = v2.MAVLink(_Nowhere(), srcSystem=255, srcComponent=0)
    t_first = None
    nan = math.nan
    with open(out, "wb") as f:
        for msg in reader:
            if isinstance(msg, Exception) or msg.get_type() == "BAD_DATA":
                continue
            if msg.get_type() != "VISION_POSITION_DELTA":
                f.write(struct.pack(">Q", int(round(msg._timestamp * 1e6))) + msg.get_msgbuf())
                continue
            t_first = msg._timestamp if t_first is None else t_first
            dt_s = msg.time_delta_usec * 1e-6
            vel = [d / dt_s for d in msg.position_delta]
            cov = [0.0] * 21
            cov[0] = cov[6] = cov[11] = 0.01 ** 2
            odo = v2.MAVLink_odometry_message(
                int((msg._timestamp - t_first) * 1e6), v2.MAV_FRAME_LOCAL_NED, v2.MAV_FRAME_BODY_FRD,
                nan, nan, nan, [nan] * 4, *vel, nan, nan, nan, [nan] + [0.0] * 20, cov, 0,
                v2.MAV_ESTIMATOR_TYPE_UNKNOWN, max(1, min(100, int(msg.confidence))))
            f.write(struct.pack(">Q", int(round(msg._timestamp * 1e6))) + odo.pack(mav))
    reader.close()
    return out
