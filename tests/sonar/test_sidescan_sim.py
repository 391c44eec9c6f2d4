import math

import numpy as np

from adaptnav.sim.seabed import Seabed
from adaptnav.sim.sidescan import SidescanRenderer, SidescanSettings


def test_same_seed_same_ping():
    sb = Seabed.random((40.0, 40.0), np.random.default_rng(1), n_objects=5)
    ren = SidescanRenderer(sb, 20.0, 256)
    a = ren.render(1.0, (20.0, 20.0), 0.3, 5.0, np.random.default_rng(9))
    b = ren.render(1.0, (20.0, 20.0), 0.3, 5.0, np.random.default_rng(9))
    assert np.array_equal(a.port, b.port) and np.array_equal(a.starboard, b.starboard)
    assert a.KIND == "sonar" and a.n_samples == 256 and a.altitude_m == 5.0


def test_object_casts_a_shadow_behind_its_highlight():
    rng = np.random.default_rng(0)
    sb = Seabed.random((60.0, 60.0), rng, n_objects=0)
    # one tall object 10 m to starboard of a vehicle at (30, 20) heading north
    sb2 = Seabed.random((60.0, 60.0), np.random.default_rng(0), n_objects=0)
    height = sb2.height_m.copy()
    refl = sb2.reflectivity.copy()
    ii, jj = np.meshgrid(np.arange(height.shape[0]) * sb.res_m, np.arange(height.shape[1]) * sb.res_m,
                         indexing="ij")
    d2 = ((ii - 30.0) ** 2 + (jj - 30.0) ** 2) / 0.5 ** 2
    height[d2 < 1] = 1.0 * np.sqrt(1 - d2[d2 < 1])
    obj = Seabed(refl, height, sb.res_m, np.array([[30.0, 30.0]]), np.array([0.5]), np.array([1.0]))
    settings = SidescanSettings(line_probability=0.0, line_gain_sigma=0.0)
    ren = SidescanRenderer(obj, 25.0, 1000, settings)
    p = ren.render(0.0, (30.0, 20.0), 0.0, 5.0, np.random.default_rng(1))
    r = (np.arange(1000) + 0.5) * 0.025
    g = np.sqrt(np.maximum(r ** 2 - 25.0, 0.0))
    behind = (g > 10.8) & (g < 12.2)  # shadow ends at 10 m × H / (H − h) = 12.5 m
    ahead = (g > 7.0) & (g < 9.0)
    assert p.starboard[behind].mean() < 0.2 * p.starboard[ahead].mean()
    # the port side (no object) has no such hole
    assert p.port[behind].mean() > 0.5 * p.port[ahead].mean()
    # water column: only noise before the first bottom return
    assert p.starboard[r < 4.9].mean() < 0.1 * p.starboard[ahead].mean()


def test_renders_fast_enough_to_be_vectorised():
    # not a timing test: the renderer must not loop in Python over samples
    import inspect

    from adaptnav.sim import sidescan
    src = inspect.getsource(sidescan.SidescanRenderer._sides)
    assert "for " not in src
