import math

import numpy as np
import pytest

from adaptnav.sim.seabed import Seabed
from adaptnav.sim.sidescan import SidescanRenderer
from adaptnav.sonar.features import OrbDetector, SiftDetector
from adaptnav.sonar.motion import WindowRegistrar
from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall
from tests.sonar.conftest import straight_pass

CFG = WaterfallConfig(ground_res_m=0.1, along_res_m=0.1)


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(7)
    seabed = Seabed.random((120.0, 70.0), rng, n_objects=40)
    return seabed, SidescanRenderer(seabed, 25.0, 512)


def _window_centre(pos, wf, yaw):
    """True (n, e) of a waterfall's centre row: start + centre distance along the track."""
    s = 0.5 * (wf.along_m[0] + wf.along_m[-1])
    return pos[0] + s * np.array([math.cos(yaw), math.sin(yaw)])


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_two_passes_register_to_true_relative_pose(world, seed):
    seabed, ren = world
    rng = np.random.default_rng(seed)
    yaw_a = rng.uniform(-0.2, 0.2)
    yaw_b = yaw_a + math.radians(rng.uniform(-3.0, 3.0))
    start_a = np.array([10.0, 35.0])
    start_b = start_a + rng.uniform(-4, 4, 2)
    pa, pos_a = straight_pass(ren, rng, start_a, yaw_a, 260)
    pb, pos_b = straight_pass(ren, rng, start_b, yaw_b, 260)
    wa, wb = build_waterfall(pa, CFG), build_waterfall(pb, CFG)
    m = WindowRegistrar().register(wa, wb)
    assert m is not None and m.inliers >= 15
    d_n = _window_centre(pos_b, wb, yaw_b) - _window_centre(pos_a, wa, yaw_a)
    c, s = math.cos(yaw_a), math.sin(yaw_a)
    along, across = c * d_n[0] + s * d_n[1], -s * d_n[0] + c * d_n[1]
    tol = max(0.05 * abs(along), 0.3)
    assert abs(m.along_m - along) < tol
    assert abs(m.across_m - across) < 0.3
    assert abs(math.degrees(m.dheading_rad - (yaw_b - yaw_a))) < 1.0
    # the covariance is a real covariance, consistent with the actual error (|z| < 6)
    assert np.all(np.linalg.eigvalsh(m.cov) > 0)
    err = np.array([m.along_m - along, m.across_m - across, m.dheading_rad - (yaw_b - yaw_a)])
    assert np.all(np.abs(err) < 6.0 * np.sqrt(np.diag(m.cov)))


def test_orb_option_registers_too(world):
    seabed, ren = world
    rng = np.random.default_rng(11)
    pa, pos_a = straight_pass(ren, rng, [10.0, 35.0], 0.0, 260)
    pb, pos_b = straight_pass(ren, rng, [13.0, 36.0], 0.0, 260)
    wa, wb = build_waterfall(pa, CFG), build_waterfall(pb, CFG)
    m = WindowRegistrar(OrbDetector(max_keypoints=1500)).register(wa, wb)
    assert m is not None
    d = _window_centre(pos_b, wb, 0.0) - _window_centre(pos_a, wa, 0.0)
    assert abs(m.along_m - d[0]) < 0.3 and abs(m.across_m - d[1]) < 0.3


def test_keeps_only_the_k_strongest():
    rng = np.random.default_rng(0)
    img = (rng.random((200, 300)) * 255).astype(np.uint8)
    all_f = SiftDetector(max_keypoints=10_000).detect(img)
    top = SiftDetector(max_keypoints=25).detect(img)
    assert len(top) == 25 and len(all_f) > 100
    assert top.response.min() >= np.sort(all_f.response)[-25] - 1e-6


def test_scotsman_windows_offset_by_known_pings(scotsman_pings):
    pings, _ = scotsman_pings
    wf = build_waterfall(pings, WaterfallConfig(resample_along=False))
    reg = WindowRegistrar()
    for a, k in [(100, 37), (200, 64), (150, 15)]:
        m = reg.register(wf.rows(a, a + 200), wf.rows(a + k, a + k + 200))
        assert m is not None
        assert abs(m.along_m / wf.along_res_m - k) <= 2.0
        assert abs(m.across_m) < 0.3
