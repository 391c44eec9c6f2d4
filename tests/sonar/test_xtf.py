import shutil
import struct

import numpy as np
import pytest

from adaptnav.sonar.xtf import SonarFileError, read_xtf
from tests.sonar.conftest import MBES, SCOTSMAN, need, rewrite_xtf


def test_scotsman_pings_nav_and_orientation(scotsman_pings):
    pings, report = scotsman_pings
    assert len(pings) == 461 and report.error is None and report.n_truncated == 0
    assert all(p.n_samples == 1024 for p in pings)
    assert abs(pings[10].slant_range_m - 30.0) < 0.1
    t = np.array([p.t_s for p in pings])
    assert np.all(np.diff(t) > 0) and 45 < t[-1] - t[0] < 60
    # ping 0 has zero lat/lon in the file: unknown, not (0, 0)
    assert np.isnan(pings[0].lat_rad) and report.n_no_nav == 1
    lat = np.degrees([p.lat_rad for p in pings[1:]])
    assert np.all(np.abs(lat - 48.445) < 0.01)
    # sample 0 nearest the vehicle on both sides: the water column (dark) comes first
    for side in ("port", "starboard"):
        x = np.stack([getattr(p, side) for p in pings])
        assert np.median(x[:, 5:60]) < 0.2 * np.median(x[:, 400:700]), side


def test_truncated_file_keeps_complete_pings(tmp_path):
    src = need(SCOTSMAN)
    cut = tmp_path / "cut.xtf"
    data = src.read_bytes()
    cut.write_bytes(data[:1_000_000])
    pings, report = read_xtf(cut)
    full, _ = read_xtf(src)
    assert len(pings) == 222 and report.n_truncated == 1
    assert np.array_equal(pings[-1].starboard, full[221].starboard)


def test_file_cut_inside_the_header_is_a_clear_error(tmp_path):
    cut = tmp_path / "tiny.xtf"
    cut.write_bytes(need(SCOTSMAN).read_bytes()[:300])
    with pytest.raises(SonarFileError, match="not a readable XTF"):
        read_xtf(cut)


def test_mbes_file_without_sonar_channels_is_a_clear_error(tmp_path):
    f = tmp_path / "mbes.xtf"
    shutil.copy(need(MBES), f)  # pyxtf may look for an index next to the file
    with pytest.raises(SonarFileError) as err:
        read_xtf(f)
    msg = str(err.value)
    assert "no side-scan channels" in msg and "undecoded 923" in msg


def test_cli_mbes_exit_code_2_without_traceback(capsys):
    from adaptnav.service.cli import main

    rc = main(["sonar", "motion", str(need(MBES)), "--json"])
    err = capsys.readouterr().err
    assert rc == 2 and "no side-scan channels" in err and "Traceback" not in err


def _port_halved(src, dst):
    """``src`` with each sonar packet's port channel at half its samples (the mean of each
    pair), as a recorder that samples the two sides differently writes it."""
    def halve(packet):  # ping header, then per channel its header and uint16 samples
        n = struct.unpack_from("<I", packet, 256 + 42)[0]
        port = np.frombuffer(packet, "<u2", n, 256 + 64).astype(float)
        halved = (0.5 * (port[0::2] + port[1::2])).round().astype("<u2")
        head = bytearray(packet[256:256 + 64])
        struct.pack_into("<I", head, 42, n // 2)
        return packet[:256] + head + halved.tobytes() + packet[256 + 64 + 2 * n:]

    rewrite_xtf(src, dst, packet=halve)


def test_sides_sampled_differently_are_read_not_dropped(tmp_path):
    """A recorder that samples port and starboard differently: every ping was dropped as
    "truncated" and the file read as holding no side-scan ping. Port is now resampled onto
    starboard's samples."""
    src = need(SCOTSMAN)
    odd = tmp_path / "halved-port.xtf"
    _port_halved(src, odd)
    full, _ = read_xtf(src)
    pings, report = read_xtf(odd)
    assert len(pings) == len(full) and report.n_truncated == 0 and report.n_sides_resampled == len(full)
    assert "port resampled" in report.summary()
    for a, b in zip(pings[::50], full[::50]):
        assert a.n_samples == b.n_samples and np.array_equal(a.starboard, b.starboard)
        # the echo at each range is kept: the recorder averaged pairs, the reader repeats each
        pairs = np.round(0.5 * (b.port[0::2].astype(float) + b.port[1::2]))
        assert np.allclose(a.port, np.repeat(pairs, 2), atol=0.51)


def _whole_seconds(src, dst):
    """``src`` with every ping's hundredths of a second 0, as some recorders write the time."""
    def whole(packet):
        packet = bytearray(packet)
        packet[21] = 0  # XTFPingHeader.HSeconds
        return packet

    rewrite_xtf(src, dst, packet=whole)


def test_pings_stamped_to_the_whole_second_are_spread_over_it(tmp_path):
    """A recorder that stamps pings to the whole second: the ~9 pings of each second had one
    time, and all but one were dropped as duplicates before any waterfall. They are spread
    evenly over their second now."""
    from adaptnav.sonar.waterfall import clean_pings

    src = need(SCOTSMAN)
    coarse = tmp_path / "whole-seconds.xtf"
    _whole_seconds(src, coarse)
    full, _ = read_xtf(src)
    pings, report = read_xtf(coarse)
    assert report.n_times_spread > 0.8 * len(full) and "whole second" in report.summary()
    kept, dropped = clean_pings(pings)
    assert len(kept) == len(full) and "duplicate time" not in dropped
    t, t_true = np.array([p.t_s for p in pings]), np.array([p.t_s for p in full])
    assert np.all(np.diff(t) > 0)
    assert np.max(np.abs(t - t_true)[:-20]) < 0.15  # within a ping spacing of the file's own times
    # a file with its own hundredths is left alone
    assert read_xtf(src)[1].n_times_spread == 0


def _dual_frequency(src, dst):
    """``src`` as a dual-frequency sonar writes it with each frequency's pair in packets of
    its own: the file header declares four channels (low-frequency port, starboard, then the
    high-frequency pair), each ping is followed by a high-frequency packet 0.05 s later whose
    channels are numbered 2 and 3 and whose samples are all 7."""
    def four_channels(head):
        struct.pack_into("<H", head, 166, 4)  # NumberOfSonarChannels
        head[256 + 2 * 128:256 + 4 * 128] = head[256:256 + 2 * 128]  # the pair's ChanInfo again

    def with_high(packet):
        high, h = bytearray(packet), 256
        for number in (2, 3):  # ping channel headers: ChannelNumber, then the samples
            struct.pack_into("<H", high, h, number)
            n = struct.unpack_from("<I", high, h + 42)[0]
            high[h + 64:h + 64 + 2 * n] = np.full(n, 7, "<u2").tobytes()
            h += 64 + 2 * n
        if high[21] < 95:
            high[21] += 5  # XTFPingHeader.HSeconds
        return [packet, high]

    rewrite_xtf(src, dst, packet=with_high, header=four_channels)


def test_a_dual_frequency_file_with_a_packet_per_frequency_reads_one_frequency(tmp_path):
    """A packet's channels are the ones its channel headers number: the high-frequency packets
    of a sonar that writes each frequency apart were read as port and starboard, pings of the
    two frequencies interleaved. Now the packets of the pair read are taken, the others counted."""
    src = need(SCOTSMAN)
    dual = tmp_path / "dual-frequency.xtf"
    _dual_frequency(src, dual)
    full, _ = read_xtf(src)
    pings, report = read_xtf(dual)
    assert len(pings) == len(full) and report.n_other_channels == len(full)
    assert "other channels" in report.summary()
    for a, b in zip(pings[::40], full[::40]):
        assert a.t_s == b.t_s and np.array_equal(a.port, b.port) and np.array_equal(a.starboard, b.starboard)


def test_channels_numbered_from_one_are_read_in_the_files_order(tmp_path):
    """Numbers that do not fit the file's channels (counted from 1 by some recorders) say
    nothing about which channel is which: the file's order is kept, every ping read."""
    src = need(SCOTSMAN)

    def from_one(packet):
        packet, h = bytearray(packet), 256
        for number in (1, 2):
            struct.pack_into("<H", packet, h, number)
            h += 64 + 2 * struct.unpack_from("<I", packet, h + 42)[0]
        return packet

    odd = tmp_path / "from-one.xtf"
    rewrite_xtf(src, odd, packet=from_one)
    full, _ = read_xtf(src)
    pings, report = read_xtf(odd)
    assert len(pings) == len(full) and report.n_other_channels == 0
    assert all(np.array_equal(a.port, b.port) and np.array_equal(a.starboard, b.starboard)
               for a, b in zip(pings, full))


def _rewrite_samples(src, dst, bytes_per_sample: int, sample_format: int, encode):
    """``src`` with every 16-bit sample written as ``encode(samples) -> bytes`` of
    ``bytes_per_sample`` each, and the channels' ``BytesPerSample`` and ``SampleFormat`` as given."""
    def header(head):
        for i in range(2):  # ChanInfo: BytesPerSample at 6, SampleFormat at 74
            struct.pack_into("<H", head, 256 + 128 * i + 6, bytes_per_sample)
            head[256 + 128 * i + 74] = sample_format

    def samples(packet):
        new, h = bytearray(packet[:256]), 256
        for _ in range(2):
            n = struct.unpack_from("<I", packet, h + 42)[0]
            new += packet[h:h + 64] + encode(np.frombuffer(packet, "<u2", n, h + 64))
            h += 64 + 2 * n
        return new + packet[h:]

    rewrite_xtf(src, dst, packet=samples, header=header)


def _eight_bit(src, dst, sample_format: int):
    """``src`` with 1-byte samples (each the 16-bit one over 128), ``BytesPerSample`` 1 and
    ``SampleFormat`` as given (8: 1-byte integer; 3: 2-byte, a converter that left it)."""
    _rewrite_samples(src, dst, 1, sample_format,
                     lambda samples: (samples >> 7).clip(0, 255).astype(np.uint8).tobytes())


def _ibm32_words(values: np.ndarray) -> np.ndarray:
    """Non-negative integers below 16⁶ as IBM single-precision words (exact): the fraction
    v / 16^e in [1/16, 1) with e the number of hex digits of v."""
    v = np.asarray(values, dtype=np.int64)
    e = np.zeros_like(v)
    while np.any(v >= 16 ** e):
        e += v >= 16 ** e
    mantissa = v << (24 - 4 * e)  # v / 16^e × 2^24
    return np.where(v == 0, 0, ((e + 64) << 24) | mantissa).astype("<u4")


def test_one_byte_samples_are_read_even_when_the_format_says_two(tmp_path):
    """8-bit samples read as they are; a file whose SampleFormat still says 16-bit while
    BytesPerSample says 1 had every ping dropped as "truncated" (pyxtf types the bytes by the
    format): its bytes are read as the samples they are now, the same pings."""
    src = need(SCOTSMAN)
    good, odd = tmp_path / "8bit.xtf", tmp_path / "8bit-format-16.xtf"
    _eight_bit(src, good, 8)
    _eight_bit(src, odd, 3)
    ref, ref_report = read_xtf(good)
    pings, report = read_xtf(odd)
    full, _ = read_xtf(src)
    assert len(ref) == len(pings) == len(full) and ref_report.n_sample_format_mended == 0
    assert report.n_truncated == 0 and report.n_sample_format_mended == 2 * len(full)
    assert "sample format contradicted" in report.summary()
    for a, b, c in zip(pings[::30], ref[::30], full[::30]):
        assert np.array_equal(a.port, b.port) and np.array_equal(a.starboard, b.starboard)
        assert np.array_equal(b.starboard, np.clip(c.starboard.astype(np.uint16) >> 7, 0, 255))


def test_ibm_float_samples_are_decoded(tmp_path):
    """SampleFormat 1 (4-byte IBM float, old recorders and converters): pyxtf has no type for
    it and returned the raw 32-bit words, so every echo was a number near 10⁹ with no
    relation to its strength. Decoded, the pings are the 16-bit file's, sample for sample."""
    src = need(SCOTSMAN)
    ibm = tmp_path / "ibm-float.xtf"
    _rewrite_samples(src, ibm, 4, 1, lambda samples: _ibm32_words(samples).tobytes())
    pings, report = read_xtf(ibm)
    full, _ = read_xtf(src)
    assert len(pings) == len(full) and report.n_truncated == 0 and report.n_sample_format_mended == 0
    for a, b in zip(pings, full):
        assert np.array_equal(a.port, b.port) and np.array_equal(a.starboard, b.starboard)
    # the words themselves, against published IBM encodings (one sign, fractions, zero)
    from adaptnav.sonar.xtf import ibm32_to_float
    words = np.array([0x41100000, 0xC276A000, 0x40280000, 0x00000000, 0x42640000], dtype=np.uint32)
    assert ibm32_to_float(words).tolist() == [1.0, -118.625, 0.15625, 0.0, 100.0]
    assert _ibm32_words(np.array([1, 100, 0])).tolist() == [0x41100000, 0x42640000, 0]


def _packet_offsets(data: bytes) -> list[int]:
    """Where each packet of an (undamaged) XTF file starts: after the 1024-byte file header,
    each packet's size (bytes 10–13) leads to the next."""
    out, o = [], 1024
    while o + 14 <= len(data):
        out.append(o)
        o += struct.unpack_from("<I", data, o + 10)[0]
    return out


@pytest.mark.parametrize("damage", ["content", "start", "size"])
def test_a_damaged_packet_loses_at_most_its_own_ping(tmp_path, damage):
    """One sonar packet damaged mid-file: its channel count (pyxtf raised IndexError), its
    0xFACE start, or its size (pointing past the file's end). pyxtf's reader ended the file
    there — the half after it lost. The packet is skipped, counted, and every other ping is the
    whole file's."""
    src = need(SCOTSMAN)
    full, _ = read_xtf(src)
    data = bytearray(src.read_bytes())
    at = _packet_offsets(bytes(data))[230]
    if damage == "content":
        data[at + 4] = 200  # NumChansToFollow: 200 channels in a two-channel file
    elif damage == "start":
        data[at] ^= 0x01
    else:
        struct.pack_into("<I", data, at + 10, len(data))
    odd = tmp_path / "damaged.xtf"
    odd.write_bytes(bytes(data))
    pings, report = read_xtf(odd)
    assert report.n_damaged == 1 and report.error is None and "damaged" in report.summary()
    lost = [k for k, p in enumerate(full) if not any(p.t_s == q.t_s for q in pings)]
    assert lost in ([230], []) and len(pings) == len(full) - len(lost)
    kept = [p for k, p in enumerate(full) if k not in lost]
    assert all(np.array_equal(p.starboard, q.starboard) and p.t_s == q.t_s for p, q in zip(kept, pings))
