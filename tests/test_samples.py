"""Sample codec: round trips, strictness, schemas."""
import json
import math

import pytest

from adaptnav.fusion.samples import (SAMPLE_TYPES, DvlSample, ImuSample, SampleError, from_dict,
                            is_finite, json_schema, to_dict)


def test_round_trip_through_json():
    s = ImuSample(1.25, (0.1, 0.2, -9.8), (0.0, 0.01, 0.02))
    assert from_dict(json.loads(json.dumps(to_dict(s)))) == s


def test_imu_source_round_trips_and_is_optional():
    s = ImuSample(1.25, (0.1, 0.2, -9.8), (0.0, 0.01, 0.02), "autopilot")
    assert from_dict(json.loads(json.dumps(to_dict(s)))) == s
    older = {k: v for k, v in to_dict(s).items() if k != "source"}  # a recording from before the field
    assert from_dict(older).source == ""
    with pytest.raises(SampleError, match="imu.source: expected a string"):
        from_dict({**to_dict(s), "source": 3})


def test_nan_survives_as_null_and_is_flagged():
    s = ImuSample(1.0, (math.nan, 0.0, 0.0), (0.0, 0.0, math.inf))
    d = json.loads(json.dumps(to_dict(s), allow_nan=False))
    back = from_dict(d)
    assert math.isnan(back.specific_force_b_m_s2[0]) and not is_finite(back)
    assert is_finite(DvlSample(0.0, (1.0, 0.0, 0.0)))  # optional altitude NaN is fine


@pytest.mark.parametrize("payload, msg", [
    ([], "expected an object"),
    ({"type": "nope", "schema_version": 1}, "unknown sample type"),
    ({"type": "rpm", "schema_version": 2, "t_s": 0, "rpm": 1}, "schema_version"),
    ({"type": "rpm", "schema_version": 1, "t_s": 0}, "missing field"),
    ({"type": "rpm", "schema_version": 1, "t_s": 0, "rpm": "fast"}, "expected a number"),
    ({"type": "rpm", "schema_version": 1, "t_s": 0, "rpm": 1, "x": 2}, "unknown field"),
    ({"type": "imu", "schema_version": 1, "t_s": 0, "specific_force_b_m_s2": [1, 2],
      "omega_b_rad_s": [0, 0, 0]}, "expected 3 numbers"),
])
def test_malformed_payloads_say_why(payload, msg):
    with pytest.raises(SampleError, match=msg):
        from_dict(payload)


def test_every_type_has_a_schema_that_requires_its_fields():
    for kind, cls in SAMPLE_TYPES.items():
        schema = json_schema(cls)
        assert schema["properties"]["type"]["const"] == kind
        assert "t_s" in schema["required"]


def test_an_imu_batch_with_mismatched_arrays_is_refused_with_a_clear_error():
    import numpy as np

    from adaptnav.fusion.samples import ImuBatch, SampleError

    ImuBatch(np.arange(3.0), np.zeros((3, 3)), np.zeros((3, 3)))  # consistent: fine
    with pytest.raises(SampleError, match="specific_force_b_m_s2 has shape"):
        ImuBatch(np.arange(3.0), np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(SampleError, match="omega_b_rad_s has shape"):
        ImuBatch(np.arange(3.0), np.zeros((3, 3)), np.zeros((3, 2)))
