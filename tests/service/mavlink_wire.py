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
