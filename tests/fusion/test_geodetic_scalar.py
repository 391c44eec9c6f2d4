"""``GeoOrigin.to_geodetic_ne`` (one position, Python floats: every output row's latitude and
longitude) gives :meth:`GeoOrigin.to_geodetic`'s numbers bit for bit."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.fusion.frames import GeoOrigin


def test_one_position_in_floats_is_the_array_conversion_bit_for_bit():
    rng = np.random.default_rng(7)
    for lat_deg, lon_deg, alt_m in ((43.1, 5.9, 0.0), (-71.3, 179.9, 12.5), (0.001, -0.002, -3.0)):
        origin = GeoOrigin(math.radians(lat_deg), math.radians(lon_deg), alt_m)
        for pos in rng.normal(0.0, 3000.0, (500, 3)):
            lat, lon, _ = origin.to_geodetic(pos)
            assert origin.to_geodetic_ne(float(pos[0]), float(pos[1])) == (float(lat), float(lon))
