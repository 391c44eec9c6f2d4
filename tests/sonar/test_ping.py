import json
import math

import numpy as np
import pytest

from adaptnav.sonar.ping import PingError, SonarPing


def _ping():
    return SonarPing(t_s=12.5, port=np.arange(8), starboard=np.linspace(0, 1, 8),
                     slant_range_m=30.0, altitude_m=math.nan, heading_rad=0.3,
                     lat_rad=0.8, lon_rad=math.nan, speed_m_s=1.5)


def test_json_round_trip_keeps_arrays_and_nan():
    p = _ping()
    text = json.dumps(p.to_dict(), allow_nan=False)  # strict JSON: NaN must be null
    q = SonarPing.from_dict(json.loads(text))
    assert np.array_equal(q.port, np.arange(8, dtype=np.float32))
    assert np.allclose(q.starboard, np.linspace(0, 1, 8))
    assert math.isnan(q.altitude_m) and math.isnan(q.lon_rad)
    assert q.t_s == 12.5 and q.heading_rad == 0.3 and q.speed_m_s == 1.5


def test_arrays_are_read_only_float32():
    p = _ping()
    assert p.port.dtype == np.float32
    with pytest.raises(ValueError):
        p.port[0] = 5.0


@pytest.mark.parametrize("mutate, words", [
    (lambda d: d.update(extra=1), "unknown field"),
    (lambda d: d.pop("port"), "missing field"),
    (lambda d: d.update(t_s="x"), "expected a number"),
    (lambda d: d.update(port=[1.0, 2.0]), "samples"),
    (lambda d: d.update(schema_version=99), "schema_version"),
    (lambda d: d.update(starboard=[True] * 8), "boolean"),
])
def test_from_dict_is_strict(mutate, words):
    d = _ping().to_dict()
    mutate(d)
    with pytest.raises(PingError, match=words):
        SonarPing.from_dict(d)


def test_json_schema_lists_every_field_of_to_dict():
    schema = SonarPing.json_schema()
    assert set(_ping().to_dict()) == set(schema["properties"])
    assert schema["additionalProperties"] is False
    assert {"t_s", "port", "starboard", "slant_range_m"} <= set(schema["required"])
