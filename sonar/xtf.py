"""XTF side-scan files → :class:`~sonar.ping.SonarPing` per ping (through ``pyxtf``).

XTF (Triton eXtended Triton Format) stores one packet per ping with the samples of every
channel and the navigation/attitude valid at the ping: ``SensorYcoordinate`` /
``SensorXcoordinate`` (latitude/longitude in degrees when ``NavUnits == 3``),
``SensorHeading``/``SensorPitch``/``SensorRoll`` (deg), ``SensorDepth``,
``SensorPrimaryAltitude`` (m) and ``SensorSpeed`` (knots, as the XTF spec says: on the
Scotsman Iver2 file speed × time integrates to the 55 m the lat/lon track covers, not to
twice that as m/s would).  The port channel is stored far-to-near
(so that a plain row of port+starboard is the picture); we reverse it so sample 0 is
nearest the vehicle on both sides.

Robustness: packets pyxtf cannot decode (``XTFUnknownPacket``) are counted and skipped,
pyxtf's warnings are captured; a truncated file keeps every complete ping before the
break and reports it. The packets are framed here (``0xFACE`` and each packet's size) and
each is parsed by pyxtf's class for its type: a packet whose framing or content is damaged
is counted and skipped, and reading goes on at the next packet start after it (pyxtf's own
reader ended the file at the first such packet). A file with no side-scan channel raises
:class:`SonarFileError` with the packet counts, so a CLI can print a clear message.
"""
from __future__ import annotations

import calendar
import dataclasses
import math
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adaptnav.sonar.ping import SonarPing, resample_slant

KNOT_M_S = 1852.0 / 3600.0


class SonarFileError(ValueError):
    """A sonar file that gives no pings (the message says why and what it holds)."""


@dataclass
class XtfReadReport:
    """What :func:`read_xtf` found besides the pings.

    Attributes
    ----------
    packet_counts : dict[str, int]
        Packets by XTF header type name (as decoded by pyxtf, ``unknown`` otherwise).
    n_undecoded : int
        Packets pyxtf has no decoder for (skipped).
    n_truncated : int
        Pings dropped because their samples were cut short (truncated file).
    n_no_nav : int
        Pings whose navigation was all zero (kept, nav set to NaN).
    n_sides_resampled : int
        Pings whose port channel had another sample count than starboard (kept, port
        resampled onto starboard's samples).
    n_times_spread : int
        Pings re-timed because the file stamps them to the whole second (kept, spread evenly
        over their second).
    n_other_channels : int
        Sonar packets without the port and starboard channels read (a dual-frequency sonar
        that writes each frequency's channels in packets of their own: the other frequency's).
    n_speed_from_grid : int
        Pings given the speed of their projected-coordinate track (``NavUnits`` 0, no speed).
    n_sample_format_mended : int
        Channels whose samples' format contradicted their size (read by their size).
    n_damaged : int
        Stretches of damaged bytes skipped: a packet whose start, size or content did not
        read (its pings lost), the reading going on at the next packet start found.
    first_damage : str or None
        Where the first was and why.
    error : str or None
        Why reading stopped early (e.g. truncated file), None when it read to the end.
    warnings : list[str]
        Messages pyxtf emitted (deduplicated).
    """

    packet_counts: dict[str, int] = field(default_factory=dict)
    n_undecoded: int = 0
    n_truncated: int = 0
    n_no_nav: int = 0
    n_sides_resampled: int = 0
    n_times_spread: int = 0
    n_other_channels: int = 0
    n_speed_from_grid: int = 0
    n_sample_format_mended: int = 0
    n_damaged: int = 0
    first_damage: str | None = None
    error: str | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def mended(self) -> bool:
        """The file was read whole, but something was done to it that its user should know
        (sides resampled, times spread, speeds from a projected track, sample format mended,
        another frequency's packets skipped)."""
        return bool(self.n_sides_resampled or self.n_times_spread or self.n_speed_from_grid
                    or self.n_sample_format_mended or self.n_other_channels)

    def summary(self) -> str:
        """One-line human summary."""
        counts = ", ".join(f"{k}: {v}" for k, v in sorted(self.packet_counts.items()))
        text = f"packets {{{counts}}}; undecoded {self.n_undecoded}; truncated pings {self.n_truncated}"
        if self.n_sides_resampled:
            text += f"; port resampled onto starboard's samples in {self.n_sides_resampled} pings"
        if self.n_times_spread:
            text += f"; {self.n_times_spread} pings stamped to the whole second spread over it"
        if self.n_speed_from_grid:
            text += f"; no speed: {self.n_speed_from_grid} pings given their projected track's"
        if self.n_sample_format_mended:
            text += (f"; {self.n_sample_format_mended} channel records whose sample format contradicted "
                     "their size read by their size")
        if self.n_other_channels:
            text += f"; {self.n_other_channels} sonar packets of other channels (another frequency) skipped"
        if self.n_damaged:
            text += f"; {self.n_damaged} damaged stretches skipped (the first: {self.first_damage})"
        if self.error:
            text += f"; stopped early: {self.error}"
        return text


def _ping_time_s(pkt) -> float:
    """POSIX seconds (UTC) of an XTF ping header (date + time + hundredths)."""
    try:
        base = calendar.timegm((int(pkt.Year), int(pkt.Month), int(pkt.Day),
                                int(pkt.Hour), int(pkt.Minute), int(pkt.Second)))
    except (ValueError, OverflowError):
        return math.nan
    return base + 0.01 * float(pkt.HSeconds)


def _channel_sides(file_header) -> tuple[int, int] | None:
    """Indices (into ``ping.data``) of the port and starboard channels, None if absent."""
    info = list(getattr(file_header, "sonar_info", []) or [])
    n = int(getattr(file_header, "NumberOfSonarChannels", len(info)) or 0)
    if n < 2:
        return None
    types = [int(getattr(ci, "TypeOfChannel", -1)) for ci in info[:n]]
    # TypeOfChannel: 1 = port, 2 = starboard (XTF spec); fall back to channel order
    port = types.index(1) if 1 in types else 0
    stbd = types.index(2) if 2 in types else 1
    return port, stbd


def _spread_repeated_times(pings: list[SonarPing]) -> int:
    """Pings stamped to the whole second (a recorder that leaves ``HSeconds`` 0): every ping
    of a second had one time, and all but the first were dropped as duplicates. When most
    pings repeat the time before them, the pings of each run of equal times are spread
    evenly (in file order) up to the next run's time — the last run at the median spacing.
    Returns the number of pings re-timed (0: the file's own times kept)."""
    t = np.array([p.t_s for p in pings], dtype=float)
    if t.size < 3 or not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        return 0
    repeated = np.diff(t) == 0.0
    if repeated.mean() <= 0.5:
        return 0
    starts = np.flatnonzero(np.concatenate([[True], ~repeated]))   # first ping of each run
    ends = np.concatenate([starts[1:], [t.size]])
    spacing = np.median(np.diff(t[starts]) / np.diff(starts)) if starts.size > 1 else 0.0
    out = t.copy()
    for a, b in zip(starts, ends):
        t_next = t[b] if b < t.size else t[a] + (b - a) * spacing
        out[a:b] = t[a] + (t_next - t[a]) * np.arange(b - a) / (b - a)
    moved = np.flatnonzero(out != t)
    for k in moved:
        pings[k] = dataclasses.replace(pings[k], t_s=float(out[k]))
    return int(moved.size)


def _speed_from_grid(pings: list[SonarPing], grid_m: np.ndarray) -> int:
    """A file in projected coordinates (``NavUnits`` 0: easting, northing in metres) gives
    no geodetic position; when it gives no speed either (``SensorSpeed`` 0 on most pings), each
    ping's speed is taken from its grid track (the distance along the fixes,
    :func:`adaptnav.sonar.waterfall.planar_track_distance_m`, over time), so the pings can
    still be spaced along track. Returns the number of pings given a speed."""
    from adaptnav.sonar.waterfall import planar_track_distance_m

    if len(pings) < 3 or np.isfinite([p.speed_m_s for p in pings]).mean() >= 0.5:
        return 0
    t = np.array([p.t_s for p in pings], dtype=float)
    if not np.all(np.diff(t) > 0):
        return 0
    s = planar_track_distance_m(t, grid_m[:, 0], grid_m[:, 1])
    if not np.all(np.isfinite(s)):
        return 0
    speed = np.gradient(s, t)
    for k, v in enumerate(speed.tolist()):
        pings[k] = dataclasses.replace(pings[k], speed_m_s=float(v))
    return len(pings)


_UNSIGNED = {1: np.uint8, 2: np.uint16, 4: np.uint32}
_IBM_FLOAT = 1  # XTF SampleFormat: 4-byte IBM System/360 float


def ibm32_to_float(words: np.ndarray) -> np.ndarray:
    """IBM System/360 single-precision floats (their 32-bit words) as float64: sign bit,
    7-bit base-16 exponent biased by 64, 24-bit fraction in [1/16, 1)."""
    u = np.asarray(words).view(np.uint32)  # the words as read, of any 4-byte type
    fraction = (u & 0x00FFFFFF).astype(np.float64) * 2.0 ** -24
    exponent16 = ((u >> 24) & 0x7F).astype(np.int64) - 64
    value = np.ldexp(fraction, 4 * exponent16)
    return np.where(u >> 31, -value, value)


def _samples(values, n_samples: int, report: XtfReadReport, ibm_float: bool = False) -> np.ndarray:
    """A channel's samples. pyxtf reads ``NumSamples × BytesPerSample`` bytes but types them
    by ``SampleFormat`` when the file sets it: a file whose two disagree (a converter that
    changed the sample size and left the format, e.g. 1 byte per sample typed as 16-bit) gave
    half as many values as samples, every ping "truncated". The bytes are the samples: read
    as unsigned integers of their size (counted in ``n_sample_format_mended``). IBM floats
    (``SampleFormat`` 1), which pyxtf leaves as their 32-bit words, are decoded."""
    a = np.asarray(values)
    if ibm_float and a.nbytes == 4 * n_samples:
        return ibm32_to_float(a)
    if n_samples > 0 and a.size != n_samples and a.nbytes % n_samples == 0 and a.nbytes // n_samples in _UNSIGNED:
        report.n_sample_format_mended += 1
        return a.view(_UNSIGNED[a.nbytes // n_samples])
    return a


def _slant_range_m(chan, pkt) -> float:
    """A channel's slant range (m); some recorders leave it 0: time span × one-way sound speed."""
    slant = float(chan.SlantRange)
    if not slant > 0:
        slant = float(chan.TimeDuration) * float(pkt.SoundVelocity)
    return slant


def read_xtf(path: str | Path, *, speed_in_knots: bool = True) -> tuple[list[SonarPing], XtfReadReport]:
    """Read every side-scan ping of an XTF file.

    Parameters
    ----------
    path : str or Path
        The XTF file.
    speed_in_knots : bool
        ``SensorSpeed`` is in knots (the XTF spec; default) and converted to m/s; False
        for recorders known to write m/s.

    Returns
    -------
    pings : list[SonarPing]
        In file order, port reversed so sample 0 is nearest the vehicle.
    report : XtfReadReport
        Packet counts, undecoded/truncated packets, early stop reason.

    Raises
    ------
    SonarFileError
        The file is missing, not XTF, or holds no side-scan ping.
    """
    import pyxtf  # heavy import kept local

    path = Path(path)
    if path.is_dir():
        raise SonarFileError(f"{path}: a folder, not an XTF file")
    if not path.is_file():
        raise SonarFileError(f"{path}: no such file")
    report = XtfReadReport()
    counts: Counter[str] = Counter()
    pings: list[SonarPing] = []
    grid: list[tuple[float, float]] = []  # a projected file's positions, one per ping
    sides = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f = open(path, "rb")
        try:
            file_header = pyxtf.XTFFileHeader.create_from_buffer(buffer=f)
        except Exception as exc:  # pyxtf raises RuntimeError/ValueError/struct errors
            f.close()
            raise SonarFileError(f"{path}: not a readable XTF file ({exc})") from None
        if file_header.channel_count() > 6:  # (pyxtf's reader refuses them too)
            f.close()
            raise SonarFileError(f"{path}: {file_header.channel_count()} channels: pyxtf reads at most 6")
        gen = _packets(f, file_header, path.stat().st_size, report)
        sides = _channel_sides(file_header)
        n_channels = int(getattr(file_header, "NumberOfSonarChannels", 0) or 0)
        nav_units = int(getattr(file_header, "NavUnits", 3))
        nav_deg = nav_units == 3
        nav_grid = nav_units == 0  # projected: easting, northing in metres (other values: neither)
        info = list(getattr(file_header, "sonar_info", []) or [])
        ibm_float = tuple(k < len(info) and int(getattr(info[k], "SampleFormat", 0)) == _IBM_FLOAT
                          for k in (sides or ()))
        for pkt in gen:
            kind = type(pkt).__name__
            try:
                name = pyxtf.XTFHeaderType(pkt.HeaderType).name
            except ValueError:
                name = "unknown"
            counts[name] += 1
            if kind == "XTFUnknownPacket":
                report.n_undecoded += 1
                continue
            if name != "sonar" or sides is None:
                continue
            ping = _to_ping(pkt, sides, n_channels, nav_deg, speed_in_knots, report, ibm_float)
            if ping is not None:
                pings.append(ping)
                if nav_grid:  # projected (easting, northing) in metres: kept for the speed
                    x, y = float(pkt.SensorXcoordinate), float(pkt.SensorYcoordinate)
                    grid.append((x, y) if (x, y) != (0.0, 0.0) else (math.nan, math.nan))
    report.packet_counts = dict(counts)
    report.warnings = sorted({str(w.message) for w in caught})
    report.n_times_spread = _spread_repeated_times(pings)
    if grid:
        report.n_speed_from_grid = _speed_from_grid(pings, np.array(grid, dtype=float))
    if sides is None:
        raise SonarFileError(
            f"{path}: no side-scan channels (file header declares "
            f"{int(getattr(file_header, 'NumberOfSonarChannels', 0))} sonar channel(s)); "
            + report.summary())
    if not pings:
        raise SonarFileError(f"{path}: no readable side-scan ping; " + report.summary())
    return pings, report


_MAGIC = b"\xce\xfa"  # 0xFACE, little-endian: the first two bytes of every packet


def _packets(f, file_header, size: int, report: XtfReadReport):
    """The packets of an XTF file after its header (``f`` positioned there; closed at the end),
    each parsed by pyxtf's class for its header type. A packet whose start is not ``0xFACE``,
    whose size does not fit, or that pyxtf cannot parse is counted in ``report`` (``n_damaged``,
    ``first_damage``) and the reading goes on at the next packet start after it — one whose
    size leads to another packet's start, or to the file's end. A packet the file ends inside
    is parsed as far as it goes (pyxtf keeps a ping's complete channels) and the reading ends
    there (``report.error``)."""
    import ctypes
    import mmap

    import pyxtf

    head_size = ctypes.sizeof(pyxtf.XTFPacketStart)
    data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # (looked ahead in, not read whole)
    loc = f.tell()

    def framed(at: int) -> int:
        """The packet size at ``at`` when a packet plausibly starts there, else 0."""
        if data[at:at + 2] != _MAGIC or at + head_size > size:
            return 0
        n = int.from_bytes(data[at + 10:at + 14], "little")
        return n if n >= head_size else 0

    def resync(after: int) -> int:
        at = data.find(_MAGIC, after)
        while at >= 0:
            n = framed(at)
            if n and (at + n >= size or framed(at + n)):
                return at
            at = data.find(_MAGIC, at + 1)
        return size

    def damaged(at: int, why: str) -> None:
        report.n_damaged += 1
        if report.first_damage is None:
            report.first_damage = f"byte {at}: {why}"

    try:
        while loc < size:
            n = framed(loc)
            if not n:
                if loc + head_size > size:  # the file ends inside a packet's first bytes
                    report.error = f"the file ends {size - loc} bytes into a packet"
                    return
                damaged(loc, "no packet start (0xFACE and a size) where one was due")
                loc = resync(loc + 1)
                continue
            p_start = pyxtf.XTFPacketStart.from_buffer_copy(data, loc)
            try:
                header_type = pyxtf.XTFHeaderType(p_start.HeaderType)
            except ValueError:
                header_type = pyxtf.XTFHeaderType.unknown
            p_class = pyxtf.XTFPacketClasses.get(header_type, pyxtf.XTFUnknownPacket)
            if header_type == pyxtf.XTFHeaderType.unknown:  # (pyxtf's reader says so too)
                warnings.warn(f"XTFHeaderType ({p_start.HeaderType}) is not known. Returned as XTFUnknownPacket")
            elif p_class is pyxtf.XTFUnknownPacket:
                warnings.warn(f"XTFHeaderType ({header_type.name}) has no implementation. Returned as "
                              "XTFUnknownPacket.")
            f.seek(loc)
            try:
                pkt = p_class.create_from_buffer(buffer=f, file_header=file_header)
            except Exception as exc:  # pyxtf raises RuntimeError/ValueError/IndexError/struct errors
                after = resync(loc + 1)
                if loc + n > size and after >= size:  # the last packet, cut: nothing after it
                    report.error = f"{type(exc).__name__}: {exc}"
                    return
                damaged(loc, f"{type(exc).__name__}: {exc}")
                loc = after
                continue
            yield pkt
            nxt = loc + n
            if nxt == size or (nxt < size and framed(nxt)):
                loc = nxt
                continue
            after = resync(loc + 1)
            if after < size:  # its size leads to no packet, though one follows
                damaged(loc, "a packet size that leads to no packet start")
            loc = after  # (else the last packet, cut: read as far as it goes)
    finally:
        data.close()
        f.close()


def _to_ping(pkt, sides: tuple[int, int], n_channels: int, nav_deg: bool, speed_in_knots: bool,
             report: XtfReadReport, ibm_float: tuple[bool, ...] = (False, False)) -> SonarPing | None:
    """One decoded XTF sonar packet → SonarPing, or None (counted) when truncated;
    ``ibm_float``: the port and starboard channels' samples are IBM floats."""
    data = list(getattr(pkt, "data", []) or [])
    chans = list(getattr(pkt, "ping_chan_headers", []) or [])
    i_port, i_stbd = sides
    # a packet's channels are the file's channels its headers number (ChannelNumber): a
    # dual-frequency sonar may write each frequency's pair in packets of its own. Numbers
    # that do not tell — repeated (recorders that leave them 0), or not all among the file's
    # channels (numbered from 1) — leave the file's order
    numbers = [int(getattr(c, "ChannelNumber", k)) for k, c in enumerate(chans)]
    if (len(set(numbers)) == len(numbers) and numbers != list(range(len(numbers)))
            and all(0 <= k < n_channels for k in numbers)):
        if i_port not in numbers or i_stbd not in numbers:
            if len(numbers) < n_channels:  # a packet of another pair: counted, not a ping
                report.n_other_channels += 1
                return None
        else:
            i_port, i_stbd = numbers.index(i_port), numbers.index(i_stbd)
    if len(data) <= max(i_port, i_stbd) or len(chans) <= max(i_port, i_stbd):
        report.n_truncated += 1
        return None
    n_port, n_stbd = int(chans[i_port].NumSamples), int(chans[i_stbd].NumSamples)
    port = _samples(data[i_port], n_port, report, ibm_float[0])
    stbd = _samples(data[i_stbd], n_stbd, report, ibm_float[1])
    if port.size != n_port or stbd.size != n_stbd or n_port == 0 or n_stbd == 0:
        report.n_truncated += 1
        return None
    slant = _slant_range_m(chans[i_stbd], pkt)
    if n_port != n_stbd:
        # the sides sampled differently (a recorder's choice, not damage): port on starboard's
        # samples — over its own range (port is stored far-to-near)
        port = resample_slant(port[::-1], _slant_range_m(chans[i_port], pkt), n_stbd, slant)[::-1]
        report.n_sides_resampled += 1
    lat, lon = float(pkt.SensorYcoordinate), float(pkt.SensorXcoordinate)
    no_nav = lat == 0.0 and lon == 0.0
    if no_nav:
        report.n_no_nav += 1
    nan = math.nan
    alt = float(pkt.SensorPrimaryAltitude)
    speed = float(pkt.SensorSpeed) * (KNOT_M_S if speed_in_knots else 1.0)
    return SonarPing(
        t_s=_ping_time_s(pkt),
        port=port[::-1].astype(np.float32),
        starboard=stbd.astype(np.float32),
        slant_range_m=slant,
        altitude_m=alt if (alt > 0 and not no_nav) else nan,
        heading_rad=math.radians(float(pkt.SensorHeading)) if not no_nav else nan,
        pitch_rad=math.radians(float(pkt.SensorPitch)),
        roll_rad=math.radians(float(pkt.SensorRoll)),
        lat_rad=math.radians(lat) if (nav_deg and not no_nav) else nan,
        lon_rad=math.radians(lon) if (nav_deg and not no_nav) else nan,
        sensor_depth_m=float(pkt.SensorDepth) if not no_nav else nan,
        speed_m_s=speed if (speed > 0 and not no_nav) else nan,
    )
