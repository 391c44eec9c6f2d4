import json
import struct

import cv2
import numpy as np

from adaptnav.service.cli import main
from tests.sonar.conftest import SCOTSMAN, need, rewrite_xtf


def test_waterfall_png_port_left_starboard_right(tmp_path, capsys):
    out = tmp_path / "not" / "yet" / "wf.png"  # (its directory made, as replay's --out)
    rc = main(["sonar", "waterfall", str(need(SCOTSMAN)), "--out", str(out), "--res-m", "0.1"])
    assert rc == 0 and out.is_file()
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    # ~55 m of track (speed in knots × time) at 0.1 m/px down, 2 × 30 m across
    assert img.shape[1] == 600 and 450 < img.shape[0] < 650
    # the wreck's long acoustic shadow runs across the starboard (right) half only
    dark = 0.4 * np.median(img[img > 0])
    right, left = img[:, 320:].astype(float), img[:, :280].astype(float)
    dark_right = ((right > 0) & (right < dark)).mean(axis=1)  # 0 = no data, not shadow
    dark_left = ((left > 0) & (left < dark)).mean(axis=1)
    assert dark_right.max() > 0.5 and dark_left.max() < 0.25


def test_motion_json_records(capsys):
    rc = main(["sonar", "motion", str(need(SCOTSMAN)), "--window", "150", "--step", "40", "--json"])
    assert rc == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) == (461 - 150) // 40
    # independent truth: the distance the lat/lon fixes cover between the window centres
    from adaptnav.sonar.xtf import read_xtf

    pings, _ = read_xtf(SCOTSMAN)
    lat = np.array([p.lat_rad for p in pings])
    lon = np.array([p.lon_rad for p in pings])
    ok = np.isfinite(lat)
    north = (lat - lat[ok][0]) * 6_371_000.0
    east = (lon - lon[ok][0]) * 6_371_000.0 * np.cos(lat[ok][0])
    for rec in lines:
        assert {"t_s", "along_m", "across_m", "dheading_rad", "inliers", "matches"} <= set(rec)
        a, b = rec["ping_a"] + 75, rec["ping_b"] + 75
        nav_m = np.hypot(north[b] - north[a], east[b] - east[a])
        assert abs(rec["along_m"] - nav_m) < 0.2 * nav_m and abs(rec["across_m"]) < 0.3
        assert rec["inliers"] <= rec["matches"]
    t = np.array([r["t_s"] for r in lines])
    assert np.all(np.diff(t) > 0)


def test_waterfall_png_has_a_labelled_scale_bar():
    """The bar is as long as the length it says: 1000 px at 0.05 m/px → a 10 m bar of 200 px."""
    import numpy as np

    from adaptnav.service.commands.sonar import scale_bar_m, with_scale_bar

    assert [scale_bar_m(w) for w in (50.0, 12.0, 3.0, 480.0)] == [10.0, 2.0, 0.5, 50.0]
    img = with_scale_bar(np.full((400, 1000), 128, np.uint8), 0.05)
    white = (img == 255).all(axis=2)
    longest = max(int(np.diff(np.flatnonzero(np.diff(np.r_[0, row, 0]))).max(initial=0)) for row in white)
    assert longest == 200


def _without_speed(src, dst):
    """``src`` with every ping's SensorSpeed 0, as many recorders write it."""
    def no_speed(packet):
        packet = bytearray(packet)
        struct.pack_into("<f", packet, 152, 0.0)  # XTFPingHeader.SensorSpeed
        return packet

    rewrite_xtf(src, dst, packet=no_speed)


def test_motion_of_a_file_without_speed_follows_its_positions(tmp_path, capsys):
    """A file without speed (0 in every ping) failed: "the file has no speed". The distance
    along its position track now spaces the pings, as the speed did."""
    f = tmp_path / "nospeed.xtf"
    _without_speed(need(SCOTSMAN), f)
    from adaptnav.sonar.xtf import read_xtf

    assert all(not np.isfinite(p.speed_m_s) for p in read_xtf(f)[0])
    runs = {}
    for name, path in (("speed", need(SCOTSMAN)), ("positions", f)):
        rc = main(["sonar", "motion", str(path), "--window", "150", "--step", "40", "--json"])
        assert rc == 0, capsys.readouterr().err
        runs[name] = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(runs["positions"]) == len(runs["speed"]) == (461 - 150) // 40
    for a, b in zip(runs["positions"], runs["speed"]):
        # the fixes cover 55.7 m, the speed 53.9: within 5 %
        assert abs(a["along_m"] - b["along_m"]) < 0.05 * b["along_m"] and abs(a["across_m"]) < 0.3


def _projected_without_speed(src, dst):
    """``src`` in projected coordinates (``NavUnits`` 0: easting, northing in metres, a local
    grid 500 km east of its meridian) and without speed, as a survey package exports it."""
    import math
    lat0 = []

    def projected(packet):
        packet = bytearray(packet)
        lon, = struct.unpack_from("<d", packet, 168)  # SensorXcoordinate
        lat, = struct.unpack_from("<d", packet, 160)  # SensorYcoordinate
        if (lat, lon) != (0.0, 0.0):
            lat0[:] = lat0 or [lat]
            east = 500_000.0 + 6_371_000.0 * math.cos(math.radians(lat0[0])) * math.radians(lon + 70.0)
            struct.pack_into("<d", packet, 168, east)
            struct.pack_into("<d", packet, 160, 6_371_000.0 * math.radians(lat))
        struct.pack_into("<f", packet, 152, 0.0)  # SensorSpeed
        return packet

    rewrite_xtf(src, dst, packet=projected, header=lambda head: struct.pack_into("<H", head, 164, 0))


def test_motion_of_a_projected_file_without_speed_follows_its_grid_track(tmp_path, capsys):
    """A file in projected coordinates gives no latitude and longitude: without speed it had
    no along-track distance at all ("the file has no speed"). Its pings now take the speed of
    their grid track: the same motion as the geodetic file's fixes give."""
    geo, grid = tmp_path / "nospeed.xtf", tmp_path / "projected.xtf"
    _without_speed(need(SCOTSMAN), geo)
    _projected_without_speed(need(SCOTSMAN), grid)
    runs = {}
    for name, path in (("geo", geo), ("grid", grid)):
        rc = main(["sonar", "motion", str(path), "--window", "150", "--step", "40", "--json"])
        out, err = capsys.readouterr()
        assert rc == 0, err
        runs[name] = [json.loads(x) for x in out.splitlines()]
    assert "given their projected track's" in err
    assert len(runs["grid"]) == len(runs["geo"]) == (461 - 150) // 40
    for a, b in zip(runs["grid"], runs["geo"]):
        assert abs(a["along_m"] - b["along_m"]) < 0.02 * b["along_m"]


def test_motion_registers_a_long_file_chunk_by_chunk(capsys, monkeypatch):
    """`sonar motion` built one waterfall of the whole file: a 206 MB XTF took 2.4 GB. It is
    built chunk by chunk now; the chunks cover every window pair once, as the whole file did,
    and each pair registers as in one waterfall (the chunk's own gain normalisation aside)."""
    from adaptnav.service.commands import sonar

    def run():
        assert main(["sonar", "motion", str(need(SCOTSMAN)), "--window", "60", "--step", "20", "--json"]) == 0
        return [json.loads(x) for x in capsys.readouterr().out.splitlines()]

    whole = run()
    monkeypatch.setattr(sonar, "MOTION_CHUNK_PINGS", 100)  # 461 pings in 8 chunks
    chunked = run()
    assert [(r["ping_a"], r["ping_b"]) for r in chunked] == [(r["ping_a"], r["ping_b"]) for r in whole]
    assert len(whole) == (461 - 60) // 20
    pairs = [(c, w) for c, w in zip(chunked, whole) if c["along_m"] is not None and w["along_m"] is not None]
    assert len(pairs) >= 0.9 * len(whole)
    assert all(abs(c["along_m"] - w["along_m"]) < 0.1 * abs(w["along_m"]) + 0.1 for c, w in pairs)


def test_a_long_waterfall_is_written_as_numbered_tiles(tmp_path, capsys, monkeypatch):
    """One picture of a whole survey does not fit in memory (a 206 MB XTF took 8.9 GB for a
    212,258-row picture): a file longer than a tile is written as numbered tiles covering
    every ping once; a short one stays one picture under the name given."""
    from adaptnav.service.commands import sonar

    out = tmp_path / "wf.png"
    assert main(["sonar", "waterfall", str(need(SCOTSMAN)), "--out", str(out), "--res-m", "0.1"]) == 0
    rows_whole = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE).shape[0]
    capsys.readouterr()
    monkeypatch.setattr(sonar, "WATERFALL_TILE_PINGS", 200)  # 461 pings: 200 + 200 + 61
    tiled = tmp_path / "tiles" / "wf.png"
    tiled.parent.mkdir()
    assert main(["sonar", "waterfall", str(need(SCOTSMAN)), "--out", str(tiled), "--res-m", "0.1"]) == 0
    said = capsys.readouterr().out
    names = sorted(p.name for p in tiled.parent.iterdir())
    assert names == ["wf-001.png", "wf-002.png", "wf-003.png"], names
    assert "pings 0–199" in said and "pings 400–460" in said
    imgs = [cv2.imread(str(tiled.parent / n), cv2.IMREAD_GRAYSCALE) for n in names]
    assert all(img is not None and img.shape[1] == 600 for img in imgs)
    # the same track, cut in three (each tile's rows start at its first ping)
    assert abs(sum(img.shape[0] for img in imgs) - rows_whole) <= 0.02 * rows_whole + 3


def test_motion_of_a_dual_frequency_file_says_the_other_frequency_was_skipped(tmp_path, capsys):
    """The other frequency's packets are set aside, said on stderr, and the motion is the
    low-frequency pair's: the same records as the file with that pair only."""
    from tests.sonar.test_xtf import _dual_frequency

    dual = tmp_path / "dual.xtf"
    _dual_frequency(need(SCOTSMAN), dual)
    args = ["--window", "150", "--step", "40", "--json"]
    assert main(["sonar", "motion", str(dual), *args]) == 0
    out, err = capsys.readouterr()
    assert "461 sonar packets of other channels (another frequency) skipped" in err
    assert main(["sonar", "motion", str(need(SCOTSMAN)), *args]) == 0
    assert out == capsys.readouterr().out


def test_a_waterfall_named_without_a_picture_extension_is_one_line_before_any_work(tmp_path, capsys):
    """``--out`` without an extension OpenCV writes (a directory's name, say) raised cv2.error
    — a traceback — after the file was read and the picture made; now one line, exit 2, and
    nothing written."""
    for name in ("waterfall", "waterfall.xyz"):
        out = tmp_path / name
        rc = main(["sonar", "waterfall", str(need(SCOTSMAN)), "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and f"--out {out}" in err and "Traceback" not in err
        assert not list(tmp_path.iterdir())


def test_numbers_that_are_no_sizes_are_one_line_before_any_work(tmp_path, capsys):
    """``--res-m nan`` / ``-1`` raised deep in the waterfall (tracebacks) and ``0`` was taken for
    the default; ``--max-keypoints 0`` was the detector's ValueError. Each is one line, exit 2,
    and nothing written — checked before the file is read (a missing file would say so first)."""
    for res in ("nan", "-1", "0"):
        out = tmp_path / "w.png"
        rc = main(["sonar", "waterfall", str(tmp_path / "absent.xtf"), "--out", str(out), "--res-m", res])
        assert rc == 2 and capsys.readouterr().err.strip().splitlines() == [
            f"adaptnav sonar: --res-m must be a positive number of metres, got {float(res):g}"]
        assert not out.exists()
    rc = main(["sonar", "motion", str(tmp_path / "absent.xtf"), "--max-keypoints", "0"])
    assert rc == 2 and capsys.readouterr().err.strip().splitlines() == [
        "adaptnav sonar: --max-keypoints must be ≥ 1, got 0"]


def test_a_folder_given_for_the_xtf_file_is_said_to_be_a_folder(tmp_path, capsys):
    """It was "no such file" — the folder is there."""
    assert main(["sonar", "waterfall", str(tmp_path), "--out", str(tmp_path / "w.png")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"adaptnav sonar: {tmp_path}: a folder, not an XTF file"]
