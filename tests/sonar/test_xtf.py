import shutil

import numpy as np
import pytest

from adaptnav.sonar.xtf import SonarFileError, read_xtf
from tests.sonar.conftest import MBES, SCOTSMAN, need


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
