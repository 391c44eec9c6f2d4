"""ArduPilot DataFlash logs (``.BIN``, read with pymavlink's DFReader): records → samples.

A DataFlash log is the autopilot's own record, written on board while armed (ArduSub's
``LOG_DISARMED`` is 0): every record carries ``TimeUS``, the boot clock in µs, so it needs no
reception stamps.  DFReader applies each format's multipliers: values are SI apart from
degrees (``Lat``/``Lng`` in degrees, attitude in degrees).  Records used (ArduSub 4.1–4.7):

======  ====================================================  =========================================
record  fields → sample                                       notes
======  ====================================================  =========================================
IMU     AccX..Z [m/s²], GyrX..Z [rad/s] → ImuSample            instance ``I`` 0 only (one stream is
                                                              integrated); 25 Hz with the default
                                                              ``LOG_BITMASK`` (MASK_LOG_IMU), the loop
                                                              rate with IMU_FAST
ATT     Roll, Pitch, Yaw [deg] → AttitudeSample                10 Hz (ATTITUDE_MED); withheld while the
                                                              EKF's word (MSG) says it is not aligned
BARO    Press [Pa] → DepthSample                              instance ``baro_instance`` (default: the
                                                              water sensor ArduSub made primary,
                                                              BARO_PRIMARY 1 or 2; else 1)
RCOU    C1..C14 [µs] → RpmSample                              as SERVO_OUTPUT_RAW
GPS     Lat, Lng [deg], Status → GnssSample                   instance 0, Status ≥ 3D fix; σ from the
                                                              latest GPA's HAcc [m], else HDop; GWk/GMS
                                                              (GPS time) give the log's UNIX time; an
                                                              underwater GPS's fixes (UsblSample) when
                                                              PARM GPS_TYPE/GPS1_TYPE is 14 (MAVLink)
RFND    Dist [m], Orient, Stat → AltitudeSample                downward (orientation 25), status Good
SIM     Lat, Lng [deg], Alt [m up], Q1..Q4 → truth             a simulator's ground truth, never fused;
                                                              the velocity from the latest SIM2
VISO    dt [s], PosDX..Z [m], AngDX..Z [rad], conf [%]         a DVL's VISION_POSITION_DELTA as the
        → DvlSample                                           autopilot received it (rotated by
                                                              VISO_ORIENT, stamped on arrival): as
                                                              the tlog's (dvl_from_vision_position_delta)
VISV    VX..Z [m/s] → DvlSample                               VISION_SPEED_ESTIMATE as received, at its
                                                              corrected time CTimeMS; frame as the
                                                              tlog's (``vision_speed_frame``)
======  ====================================================  =========================================

Every other record type is accounted for: ignored with the reason in :data:`IGNORED_WHY`, or
``unknown`` (a type this table does not know).
"""
from __future__ import annotations

import contextlib
import math
import re
import struct
import sys
import threading
from types import SimpleNamespace
from typing import Any, Iterator, NamedTuple

from adaptnav.fusion.frames import wrap_angle
from adaptnav.fusion.samples import AltitudeSample, AttitudeSample, DepthSample, GnssSample, ImuSample

from .mavlink_convert import (ConversionError, ConvertConfig, MavlinkConverter, TypeAccount, _WindowMin,
                              attitude_word_from_text, dvl_from_vision_position_delta, dvl_from_vision_speed,
                              rpm_from_pwm)

# GPS time (GWk, GMS) → UNIX: the GPS epoch 1980-01-06 in UNIX seconds, and GPS − UTC
# (18 s since 2017-01-01, IERS Bulletin C; no leap second announced since)
GPS_EPOCH_UNIX_S = 315_964_800.0
GPS_WEEK_S = 604_800.0
GPS_UTC_LEAP_S = 18.0
GPS_TIME_WINDOW_S = 10.0  # the least-delayed fix of this span pairs GPS time with the boot clock
RFND_STATUS_GOOD = 4  # AP_RangeFinder::Status::Good
DOWNWARD = 25  # ROTATION_PITCH_270

USED = ("IMU", "ATT", "BARO", "RCOU", "GPS", "GPA", "RFND", "SIM", "SIM2", "MSG", "VISO", "VISV")
# the records a replay reads (decodes); the others are only counted, from the reader's index
READ = frozenset(USED) | {"PARM"}

_FORMATS_PATCH_LOCK = threading.Lock()
_STDERR_PATCH_LOCK = threading.Lock()  # fd 2 redirected by one reader at a time


def _opaque_format(n_bytes: int) -> str:
    """Format letters of exactly ``n_bytes`` bytes of text fields (64, 16, 4, 1 bytes each)."""
    out = []
    for letter, size in (("Z", 64), ("N", 16), ("n", 4), ("B", 1)):
        k, n_bytes = divmod(max(n_bytes, 0), size)
        out.append(letter * k)
    return "".join(out)


_FMT_HEADER = b"\xa3\x95\x80"  # a record header and the FMT type (128)
_FMT_RECORD_LEN = 89           # 3 + Type B, Length B, Name 4s, Format 16s, Columns 64s
_LENGTH_VOTES = 200            # records of a type looked at to tell which of the two is right


def _letters_size(letters: bytes) -> int | None:
    """Bytes of a record body of these format letters (None: a letter DFReader does not know)."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    size = 0
    for c in letters.decode("ascii", "replace"):
        spec = FORMAT_TO_STRUCT.get(c)
        if spec is None:
            return None
        size += struct.calcsize("<" + spec[0])
    return size


class FormatRepair(NamedTuple):
    """One byte of a damaged FMT record set right (:func:`format_repairs`)."""

    offset: int      # of the byte in the file
    value: int       # what it is set to
    name: str        # the record type's name
    what: str        # "length" or "letters"
    was: str         # the damaged value, for the message


def _header_votes(data: Any, mtype: int, after: int, lengths) -> tuple[int, dict[int, int]]:
    """``(records looked at, {length: records followed by a header at that length})`` for up
    to ``_LENGTH_VOTES`` records of type ``mtype`` after offset ``after``."""
    votes = {length: 0 for length in lengths}
    seen = 0
    rec = data.find(b"\xa3\x95" + bytes([mtype]), after)
    while rec >= 0 and seen < _LENGTH_VOTES:
        seen += 1
        for length in votes:
            if data[rec + length:rec + length + 2] == b"\xa3\x95":
                votes[length] += 1
        rec = data.find(b"\xa3\x95" + bytes([mtype]), rec + 3)
    return seen, votes


def format_repairs(data: Any) -> list[FormatRepair]:
    """The bytes of a binary DataFlash log's FMT records that a single damaged byte or bit
    made wrong, and what they were.

    A record's declared length is always its letters' size + 3 in a whole log (ArduSub 4.1
    and 4.7 alike). When they disagree, one of the two was damaged: the records of the type
    say which — a header follows each record at the length that is right. The length is
    repaired when its letters' length puts a header after most of its records and the
    declared one does not. A letter DFReader does not know (a flipped bit) is repaired when
    exactly one letter a bit away from it gives the declared length (and the records agree
    with that length). Otherwise :func:`tolerant_formats` skips the type whole. With
    pymavlink's reader a wrong length lost every record of the type and the record after
    each, and sent its indexer resynchronising through the log (116,622 complaints for one
    flipped bit of GPS's length); a wrong letter lost the whole log or every record of its
    type. A letter changed into another of the same size cannot be told from the right one."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    repairs: list[FormatRepair] = []
    at = data.find(_FMT_HEADER)
    while at >= 0 and at + _FMT_RECORD_LEN <= len(data):
        mtype, declared = data[at + 3], data[at + 4]
        letters = bytes(data[at + 9:at + 25]).split(b"\0", 1)[0]
        name = bytes(data[at + 5:at + 9]).split(b"\0", 1)[0].decode("ascii", "replace")
        size = _letters_size(letters)
        if size is not None and declared != size + 3:
            expected = size + 3
            seen, votes = _header_votes(data, mtype, at + _FMT_RECORD_LEN, (declared, expected))
            if seen >= 3 and votes[expected] >= 0.8 * seen and votes[declared] < 0.5 * votes[expected]:
                repairs.append(FormatRepair(at + 4, expected, name, "length", str(declared)))
        elif size is None:
            unknown = [k for k, c in enumerate(letters) if chr(c) not in FORMAT_TO_STRUCT]
            if len(unknown) == 1:
                k = unknown[0]
                rest = _letters_size(letters[:k] + letters[k + 1:])
                near = (letters[k] ^ (1 << b) for b in range(8))  # the letters a bit away
                fits = [c for c in near if chr(c) in FORMAT_TO_STRUCT and rest is not None
                        and rest + _letters_size(bytes([c])) + 3 == declared]
                if len(fits) == 1:
                    seen, votes = _header_votes(data, mtype, at + _FMT_RECORD_LEN, (declared,))
                    if seen == 0 or votes[declared] >= 0.8 * seen:
                        repairs.append(FormatRepair(at + 9 + k, fits[0], name, "letters",
                                                    letters.decode("ascii", "replace")))
        at = data.find(_FMT_HEADER, at + 3)
    return repairs


@contextlib.contextmanager
def tolerant_formats() -> Iterator[list[str]]:
    """While pymavlink's binary DataFlash reader indexes a log: an FMT record whose format
    letters are damaged (a flipped byte), or whose letters' size disagrees with its declared
    length, declares its record type as opaque bytes of the declared length, instead of
    raising — DFReader's index gives up on the whole log at one such record (e.g.
    ``Unsupported format char: '\\' in message GRXS``), though every
    other type still reads. Yields the names of the types so declared (their records are
    skipped whole, as a type ``<name>_damaged``; if one is a type the replay reads, its
    samples are lost and said)."""
    from pymavlink import DFReader

    damaged: list[str] = []
    original = DFReader.DFFormat

    class _Tolerant(original):  # type: ignore[misc, valid-type]
        opaque = False

        def __init__(self, type, name, flen, format, columns, oldfmt=None):  # noqa: A002 - DFReader's names
            try:
                super().__init__(type, name, flen, format, columns, oldfmt)
                if struct.calcsize(self.msg_struct) != int(flen) - 3:
                    # letters and length disagree (one of them damaged, the length not
                    # repairable: format_repairs): every record would fail to parse
                    raise ValueError("format letters and length disagree")
            except Exception:  # noqa: BLE001 - DFReader raises a bare Exception
                label = DFReader.null_term(name) if isinstance(name, str) else repr(name)
                if label not in damaged:  # the index may build a type's format twice
                    damaged.append(label)
                letters = _opaque_format(int(flen) - 3)
                # renamed: nothing that reads the type by its name (the replay, DFReader's
                # clock from GPS records) takes its bytes for fields
                super().__init__(type, f"{label}_damaged", flen, letters,
                                 ",".join(f"_{i}" for i in range(len(letters))), oldfmt)
                self.opaque = True

        # the log's units and multipliers (FMTU) are for the declared columns, not the bytes
        def set_unit_ids(self, unit_ids, unit_lookup):
            if not self.opaque:
                super().set_unit_ids(unit_ids, unit_lookup)

        def set_mult_ids(self, mult_ids, mult_lookup):
            if not self.opaque:
                super().set_mult_ids(mult_ids, mult_lookup)

    with _FORMATS_PATCH_LOCK:
        DFReader.DFFormat = _Tolerant
        try:
            yield damaged
        finally:
            DFReader.DFFormat = original


@contextlib.contextmanager
def indexer_complaints() -> Iterator[dict[str, Any]]:
    """While pymavlink's compiled DataFlash indexer runs (it builds a binary log's index when
    the log is opened): its complaints are counted, not printed. On a damaged log it prints
    ``bad header 0x… at <offset>`` to the C stderr for every position it resynchronises at —
    116,622 lines for one flipped length byte. Yields ``{"bad_headers": n, "first": text,
    "index_ends_at": offset or None}`` (``0xffff``, erased flash — a card's unwritten space
    after the log — is not counted). ``index_ends_at``: where the indexer met a record of a
    type no format declares (its format record lost, or a damaged header's type byte) and
    stopped: nothing after it is in the index (``unknown msg type 0x… (n) at <offset>``, the
    legacy indexer's the same).

    The process's file descriptor 2 is redirected to a temporary file meanwhile (the only way
    to catch a C library's ``fprintf``); whatever else was written to it then — by another
    thread, say — is written back to stderr afterwards, in order, so nothing is lost."""
    import os
    import tempfile

    said: dict[str, Any] = {"bad_headers": 0, "first": "", "index_ends_at": None}
    sys.stderr.flush()
    with tempfile.TemporaryFile() as caught, _STDERR_PATCH_LOCK:
        real = os.dup(2)
        os.dup2(caught.fileno(), 2)
        try:
            yield said
        finally:
            sys.stderr.flush()
            os.dup2(real, 2)
            os.close(real)
            caught.seek(0)
            for line in caught:
                if line.startswith(b"bad header 0xffff"):
                    continue  # erased flash (a card's unwritten space after the log): not damage
                if line.startswith(b"bad header"):
                    said["bad_headers"] += 1
                    if not said["first"]:
                        said["first"] = line.decode("ascii", "replace").strip()
                elif (end := _UNKNOWN_TYPE_AT.match(line)) is not None:
                    if said["index_ends_at"] is None:  # (the indexer stops at the first)
                        said["index_ends_at"] = int(end.group(1))
                else:
                    os.write(2, line)


# pymavlink's indexers' last word on a record of a type no format declares (they stop there)
_UNKNOWN_TYPE_AT = re.compile(rb"unknown msg type 0x[0-9a-fA-F]+ \(\d+\) at (\d+)")

# what pymavlink's DataFlash reader prints when a record does not parse (it is dropped; the
# other complaints are the resync around one: bytes skipped)
_PARSE_FAILED = ("Failed to parse", "bad msg at offset")


@contextlib.contextmanager
def reader_complaints() -> Iterator[dict[str, Any]]:
    """While pymavlink's DataFlash reader runs: what it prints (a damaged log made it print a
    line per bad record and per resync — 142,221 lines for one damaged length byte — to the
    terminal of whoever replayed it, and the records it dropped so were counted nowhere) is
    counted instead. Yields ``{"lines": n, "parse_failures": n, "skips": n, "first": text}``
    (``skips``: the runs of bytes it skipped to the next record it knows); DFReader's
    module-level ``print`` is replaced meanwhile (only that module's: the compiled indexer
    writes to the C stderr, :func:`indexer_complaints`)."""
    from pymavlink import DFReader

    said: dict[str, Any] = {"lines": 0, "parse_failures": 0, "skips": 0, "first": ""}

    def complain(*args: Any, **kwargs: Any) -> None:  # noqa: ARG001 - print's signature
        said["lines"] += 1
        text = " ".join(str(a) for a in args)
        if not said["first"]:
            said["first"] = text
        if text.startswith(_PARSE_FAILED):
            said["parse_failures"] += 1
        elif text.startswith("Skipped "):
            said["skips"] += 1

    before = DFReader.__dict__.get("print")  # a use around this one (nested): put back after
    DFReader.print = complain
    try:
        yield said
    finally:
        if before is None:
            del DFReader.print
        else:
            DFReader.print = before


_WHY_ESTIMATE = "the autopilot's own estimate (an output of its EKF/AHRS, not a sensor)"
_WHY_CONTROL = "the autopilot's controllers, pilot input and modes (no navigation content)"
_WHY_HOUSEKEEPING = "log format / housekeeping (no navigation content)"
IGNORED_WHY: dict[str, str] = {
    **{r: _WHY_ESTIMATE for r in (
        "AHR2", "DCM", "EAHR", "POS", "ORGN", "XKF0", "XKF1", "XKF2", "XKF3", "XKF4", "XKF5", "XKFS", "XKFD",
        "XKFM", "XKQ", "XKT", "XKTV", "XKV1", "XKV2", "XKY0", "XKY1", "NKF1", "NKF2", "NKF3", "NKF4", "NKF5",
        "NKQ", "NKT", "NKV1", "NKV2", "NKY0", "NKY1", "EKF1", "EKF2", "EKF3", "EKF4", "AHRS", "TERR")},
    **{r: _WHY_CONTROL for r in (
        "ANG", "ATSC", "CTUN", "CTRL", "PIDA", "PIDP", "PIDR", "PIDY", "PIDN", "PIDE", "PSCD", "PSCN", "PSCE",
        "RATE", "RCIN", "RCI2", "MODE", "CMD", "MOTB", "MNT", "FTN", "FTN1", "FTN2", "ARM", "EV", "ERR",
        "MAVC", "GUIP", "JOYS")},
    **{r: _WHY_HOUSEKEEPING for r in (
        "FMT", "FMTU", "UNIT", "MULT", "PARM", "VER", "FILE", "DSF", "DU32", "PM", "MAV", "UART", "BAT", "POWR",
        "MCU", "VIBE", "RAD", "TSYN", "ESC", "ESCX", "SRTL", "PRX", "BCN", "DMS", "OFG", "MON", "STAK", "RALY",
        "SIMS", "SITL")},
    "MAG": "magnetometer: the heading comes from ATT (the autopilot's compass-aided attitude)",
    "GYR": "raw gyro at the sensor rate (IMU_RAW), before the autopilot's filters: IMU is integrated",
    "ACC": "raw accelerometer at the sensor rate (IMU_RAW), before the autopilot's filters: IMU is integrated",
    "ISBH": "IMU batch sampler (vibration analysis): IMU is integrated",
    "ISBD": "IMU batch sampler (vibration analysis): IMU is integrated",
    "RCO2": "servo outputs 15–32 (the thrusters are on RCOU)",
    "RCO3": "servo outputs 15–32 (the thrusters are on RCOU)",
    "GPA": "the GPS's accuracy: gives the σ of the next GPS fix, no sample of its own",
    "SIM2": "simulator truth (velocity): completes SIM's truth, never fused",
    "MSG": "text; the autopilot's EKF (re)start and yaw alignment gate ATT, no sample",
    "VISP": "VISION_POSITION_ESTIMATE as received: a pose in the sender's own frame (a DVL's or camera's "
            "odometry), not a position fix; its velocity comes as VISO/VISV",
}


class SimTruth(NamedTuple):
    """A simulator's ground truth as it is logged (geodetic), placed on the NED frame later."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float  # up
    vel_n_m_s: tuple[float, float, float]
    q_nb: tuple[float, float, float, float]  # w, x, y, z


class LogTimeGuard:
    """A DataFlash log's ``TimeUS``, judged before the mission clock takes it.

    A log holds one boot of the autopilot (a reboot starts a new file) and its records are
    written in time order, so a time more than ``back_s`` before the log's latest is no reboot:
    it is damage — a block of zeros over the record's time (``TimeUS`` 0), a flipped bit — and
    the mission clock took it for a reboot and moved every later sample on by the log's age
    (a public log with 20 blocks of 512 zero bytes replayed as 295 s of data, not 24). A time
    more than ``jump_s`` after the latest, or the log's first, is a logging pause or damage
    alike: its record is held until the next one says which (:meth:`judge`). A record alone
    between two such jumps cannot be told from damage and is refused with it."""

    def __init__(self, back_s: float = 1.0, jump_s: float = 5.0) -> None:
        self.back_s, self.jump_s = back_s, jump_s
        self.latest_s: float | None = None  # the log's time so far (two records agreed on it)
        self.held_s: float | None = None    # the time of the record held

    def near(self, t_s: float, level_s: float) -> bool:
        return level_s - self.back_s <= t_s <= level_s + self.jump_s

    def judge(self, t_s: float) -> tuple[str, bool]:
        """``(verdict, held record's fate)`` for a record of time ``t_s`` (s): verdict "take",
        "hold" (until the next record) or "refuse" (damaged); the record held before it, if
        any, is taken first when True, refused when False (no record held: False)."""
        held, latest = self.held_s, self.latest_s
        self.held_s = None
        if held is not None and self.near(t_s, held):  # the next record agrees: a new level
            self.latest_s = max(held, t_s)  # (held only ahead of the latest, or as the first)
            return "take", True
        if latest is not None and self.near(t_s, latest):
            self.latest_s = max(latest, t_s)
            return "take", False
        if latest is not None and t_s < latest - self.back_s:
            return "refuse", False
        self.held_s = t_s  # a jump forward, or the first time
        return "hold", False


class DataflashConverter:
    """DataFlash records → samples (module docstring), on the clock and accounts of ``mav``.

    Shares the :class:`MavlinkConverter`'s :class:`MissionClock` and its per-type accounts
    (``summary.json``'s ``message_types``) and its rejection counters. ``TimeUS`` is the boot
    clock; a log is one boot, so its jumps are judged first (:class:`LogTimeGuard`: a damaged
    time is refused as ``time_damaged``, never taken for a reboot).
    """

    def __init__(self, mav: MavlinkConverter, baro_instance: int | None = None):
        self.mav = mav
        self.config: ConvertConfig = mav.config
        self._baro_instance = baro_instance
        self._gps_h_acc_m: dict[int, float] = {}  # latest GPA HAcc per GPS instance
        self._sim_vel_n_m_s: tuple[float, float, float] | None = None
        # −(UNIX − t_s) of the recent fixes: a fix is logged when it arrives, after its time of
        # validity by the receiver's latency (≥ 0, jittering); the least delayed of a window is the best pair
        self._gps_delay = _WindowMin(GPS_TIME_WINDOW_S)
        self.imu_instance = 0
        self.time_guard = LogTimeGuard()
        self._held: tuple[Any, str, TypeAccount, float] | None = None  # the record the guard holds

    @property
    def baro_instance(self) -> int:
        """The water pressure sensor's BARO instance: as configured, else the autopilot's
        (:attr:`MavlinkConverter.water_baro_instance`, from its PARM BARO_PRIMARY)."""
        return self._baro_instance if self._baro_instance is not None else self.mav.water_baro_instance

    def convert(self, msg: Any) -> tuple[list, list[SimTruth]]:
        """``(samples, truths)`` of one record."""
        mtype = msg.get_type()
        acc = self.mav.types.setdefault(mtype, TypeAccount())
        acc.messages += 1
        t_us = getattr(msg, "TimeUS", None)
        if mtype not in USED:
            if mtype == "PARM":  # the autopilot's parameters, written at the log's start
                self.mav.note_parameter(str(getattr(msg, "Name", "")), float(getattr(msg, "Value", math.nan)))
            if mtype in IGNORED_WHY:
                self._ignore(acc, IGNORED_WHY[mtype])
            return [], []  # unknown: counted in messages, reported as such
        if t_us is None:
            self.mav._count_reject(acc, "no_time")
            return [], []
        # SIM2 is written on the simulator's physics step (hundreds of Hz), slightly out of
        # step with the others: it teaches the clock nothing, it only carries velocity
        if mtype == "SIM2":
            self._sim_vel_n_m_s = (float(msg.VN), float(msg.VE), float(msg.VD))
            self._ignore(acc, IGNORED_WHY[mtype])
            return [], []
        verdict, held_taken = self.time_guard.judge(t_us / 1e6)
        samples: list = []
        truths: list[SimTruth] = []
        held, self._held = self._held, None
        if held is not None:
            if held_taken:
                samples, truths = self._dated(*held)
            else:
                self.mav._count_reject(held[2], "time_damaged")
        if verdict == "hold":
            self._held = (msg, mtype, acc, t_us)
        elif verdict == "refuse":
            self.mav._count_reject(acc, "time_damaged")
        else:
            more, more_truths = self._dated(msg, mtype, acc, t_us)
            samples, truths = samples + more, truths + more_truths
        return samples, truths

    def finish(self) -> None:
        """The log ended: a record still held (a jump of time no record came after to confirm)
        is refused as damaged."""
        held, self._held = self._held, None
        if held is not None:
            self.mav._count_reject(held[2], "time_damaged")

    def _dated(self, msg: Any, mtype: str, acc: TypeAccount, t_us: float) -> tuple[list, list[SimTruth]]:
        """``(samples, truths)`` of a record whose ``TimeUS`` the guard took."""
        t_s = self.mav.time.map_boot_s(t_us / 1e6)
        try:
            if mtype == "SIM":
                self.mav.take_simulator("its SIM records")
                acc.stamp(t_s)
                self._ignore(acc, "simulator truth (never fused; the replay's metrics)")
                return [], [self._sim(msg, t_s)]
            out = self._samples(msg, mtype, t_s, acc)
        except ConversionError as e:
            self.mav._count_reject(acc, e.reason)
            return [], []
        except (AttributeError, TypeError, ValueError, OverflowError):
            self.mav._count_reject(acc, "malformed")
            return [], []
        if out:
            acc.stamp(t_s)
            acc.samples += len(out)
        return out, []

    def count_unread(self, counts: dict[str, int]) -> None:
        """Account for records not read (not in :data:`READ`), by type: ignored with their
        reason, or unknown."""
        for mtype, n in counts.items():
            acc = self.mav.types.setdefault(mtype, TypeAccount())
            acc.messages += n
            if mtype in IGNORED_WHY:
                acc.ignored[IGNORED_WHY[mtype]] = acc.ignored.get(IGNORED_WHY[mtype], 0) + n

    # ------------------------------------------------------------------ records
    def _ignore(self, acc: TypeAccount, why: str) -> list:
        acc.ignored[why] = acc.ignored.get(why, 0) + 1
        return []

    def _samples(self, msg: Any, mtype: str, t_s: float, acc: TypeAccount) -> list:
        if mtype == "IMU":
            if getattr(msg, "I", 0) != self.imu_instance:
                return self._ignore(acc, f"other instance (IMU {self.imu_instance} is integrated)")
            f = (msg.AccX, msg.AccY, msg.AccZ)
            w = (msg.GyrX, msg.GyrY, msg.GyrZ)
            if not all(math.isfinite(v) for v in (*f, *w)):
                raise ConversionError("non_finite", "IMU")
            # a DataFlash log's IMU is the flight controller's own (ImuSample.source)
            return [ImuSample(t_s, f, w, "autopilot")]
        if mtype == "ATT":
            if self.mav.autopilot_attitude_ok is False:
                raise ConversionError("attitude_not_aligned", "the autopilot's EKF says its attitude is not aligned")
            r, p, y = math.radians(msg.Roll), math.radians(msg.Pitch), math.radians(msg.Yaw)
            if not all(math.isfinite(v) for v in (r, p, y)):
                raise ConversionError("non_finite", "ATT")
            return [AttitudeSample(t_s, r, p, float(wrap_angle(y)))]
        if mtype == "BARO":
            if getattr(msg, "I", 0) != self.baro_instance:  # its PARM BARO_PRIMARY is read at the log's start
                return self._ignore(acc, f"other instance (BARO {self.baro_instance} is the water sensor)")
            if not msg.Press > 0:
                raise ConversionError("bad_pressure", f"Press={msg.Press}")
            return [DepthSample(t_s, float(msg.Press))]
        if mtype == "RCOU":  # forward and lateral RPM as from SERVO_OUTPUT_RAW
            return [rpm_from_pwm(lambda ch: getattr(msg, f"C{ch}", 0) or 0, t_s, self.mav.thrusters)]
        if mtype == "GPA":
            h_acc = float(getattr(msg, "HAcc", 0.0) or 0.0)
            if h_acc > 0 and math.isfinite(h_acc):
                self._gps_h_acc_m[int(getattr(msg, "I", 0))] = h_acc
            return self._ignore(acc, IGNORED_WHY["GPA"])
        if mtype == "GPS":
            return self._gps(msg, t_s, acc)
        if mtype == "RFND":
            if getattr(msg, "Orient", DOWNWARD) != DOWNWARD:
                raise ConversionError("distance_not_down", f"Orient={msg.Orient}")
            if getattr(msg, "Stat", RFND_STATUS_GOOD) != RFND_STATUS_GOOD:
                raise ConversionError("distance_invalid", f"Stat={msg.Stat}")
            return [AltitudeSample(t_s, float(msg.Dist))]
        if mtype == "VISO":  # the DVL driver's delta as the autopilot got it: no time of its own
            delta = SimpleNamespace(time_delta_usec=float(msg.dt) * 1e6, confidence=float(msg.conf),
                                    position_delta=(msg.PosDX, msg.PosDY, msg.PosDZ),
                                    angle_delta=(msg.AngDX, msg.AngDY, msg.AngDZ))
            return [dvl_from_vision_position_delta(delta, t_s, self.config, timed=False)]
        if mtype == "VISV":
            # CTimeMS: the autopilot's estimate of when it was measured (the sender's time,
            # jitter-corrected); the record itself is written on arrival
            age_s = float(msg.TimeUS) / 1e6 - float(getattr(msg, "CTimeMS", 0) or 0) / 1e3
            t_meas_s = t_s - age_s if 0.0 <= age_s <= 1.0 else t_s
            speed = SimpleNamespace(x=float(msg.VX), y=float(msg.VY), z=float(msg.VZ))
            return [dvl_from_vision_speed(speed, t_meas_s, self.config)]
        if mtype == "MSG":
            word = attitude_word_from_text(str(getattr(msg, "Message", "")))
            if word is not None:
                self.mav.autopilot_attitude_ok = word
            return self._ignore(acc, IGNORED_WHY["MSG"])
        raise AssertionError(f"record {mtype} listed as used without a handler")

    def _gps(self, msg: Any, t_s: float, acc: TypeAccount) -> list:
        inst = int(getattr(msg, "I", 0))
        if inst != 0:
            return self._ignore(acc, "other instance (GPS 0 is used)")
        if msg.Status < self.config.gnss_min_fix_type:
            raise ConversionError("gnss_no_fix", f"Status={msg.Status}")
        week, ms = getattr(msg, "GWk", 0), getattr(msg, "GMS", 0)
        if week > 0:
            # GPS time of the fix, logged on arrival: the UNIX time of the log (its rows'
            # t_unix_s), the best clock a BIN carries — late by the least latency of the window
            unix_s = GPS_EPOCH_UNIX_S + week * GPS_WEEK_S + ms / 1000.0 - GPS_UTC_LEAP_S
            offset_s = -self._gps_delay.push(t_s, t_s - unix_s)
            self.mav.time.pair_unix(t_s + offset_s, t_s, "GPS")
        # the GPA written with the previous fix: accuracy changes slowly, and GPA follows GPS
        h_acc = self._gps_h_acc_m.get(inst)
        if h_acc is not None:
            sigma = h_acc
        elif 0 < msg.HDop < 99:  # an underwater GPS's HDOP as in its GPS_INPUT
            sigma = msg.HDop * (self.config.usbl_sigma_per_hdop_m if self.mav.gps_fixes_acoustic()
                                else self.config.gnss_sigma_per_hdop_m)
        else:
            raise ConversionError("gnss_no_accuracy", "neither GPA.HAcc nor HDop")
        return [self.mav.gps_fix(GnssSample(t_s, math.radians(msg.Lat), math.radians(msg.Lng), float(sigma)))]

    def _sim(self, msg: Any, t_s: float) -> SimTruth:
        q = (float(msg.Q1), float(msg.Q2), float(msg.Q3), float(msg.Q4))
        vel = self._sim_vel_n_m_s if self._sim_vel_n_m_s is not None else (math.nan, math.nan, math.nan)
        return SimTruth(t_s, float(msg.Lat), float(msg.Lng), float(msg.Alt), vel, q)
