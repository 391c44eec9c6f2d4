"""The bus payloads are user-facing (Foxglove, zenoh-cli, logs, other programs): fields are
added, never removed or renamed, without a ``schema_version`` bump and a reader for the
old version. The fields of each (type, schema_version) as first published are pinned here;
a payload must still carry them, and a payload of that version with only them must still
be read (added fields have defaults)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from adaptnav.calibration.online import Release
from adaptnav.fusion import samples as fs
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.fusion.state import NavState
from adaptnav.fusion.status import AidStatus
from adaptnav.service.transport import codec

# (type, schema_version) → the fields of that version as first published. Never edit a
# row: a new version gets a new row (and its reader).
PINNED: dict[tuple[str, int], set[str]] = {
    ("nav_state", 1): {"type", "schema_version", "t_s", "pos_n_m", "vel_n_m_s", "q_nb", "euler_rad",
                       "bias_acc_b_m_s2", "bias_gyro_b_rad_s", "current_n_m_s", "k_speed", "cov", "valid",
                       "reset_counter"},
    ("aid_status", 1): {"type", "schema_version", "t_s", "source", "observation", "innovation",
                        "innovation_variance", "test_ratio", "fused", "reason"},
    ("calibration_release", 1): {"type", "schema_version", "t_s", "params", "log_likelihood", "accepted",
                                 "reason", "iterations", "current_n_m_s"},
    ("imu", 1): {"t_s", "specific_force_b_m_s2", "omega_b_rad_s"},
    ("rpm", 1): {"t_s", "rpm"},
    ("dvl", 1): {"t_s", "vel_d_m_s", "valid", "altitude_m"},
    ("depth", 1): {"t_s", "pressure_pa"},
    ("heading", 1): {"t_s", "yaw_rad"},
    ("attitude", 1): {"t_s", "roll_rad", "pitch_rad", "yaw_rad"},
    ("gnss", 1): {"t_s", "lat_rad", "lon_rad", "sigma_h_m"},
    ("usbl", 1): {"t_s", "lat_rad", "lon_rad", "depth_m", "sigma_h_m", "sigma_v_m"},
    ("range", 1): {"t_s", "beacon_id", "beacon_pos_n_m", "range_m", "sigma_m"},
    ("altitude", 1): {"t_s", "altitude_m"},
    ("visual_motion", 1): {"t_s", "t0_s", "along_m", "across_m", "dheading_rad", "cov"},
    ("inertial_velocity", 1): {"t_s", "vel_n_m_s", "pos_n_m", "yaw_rad", "reset_counter"},
    ("truth", 1): {"t_s", "pos_n_m", "vel_n_m_s", "q_nb", "current_n_m_s", "k_v", "bias_acc_b_m_s2",
                   "bias_gyro_b_rad_s"},
}
SAMPLE_ENVELOPE = {"type", "schema_version"}


def _example(cls):
    """A sample of ``cls`` with every field at a plain value of its type."""
    import dataclasses

    values = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            continue
        spec, n = fs._field_spec(f)
        one = {"number": 1.5, "integer": 2, "boolean": True}[spec]
        values[f.name] = one if n is None else tuple([one] * (n if n > 0 else 9))
    return cls(**values)


def _payloads() -> dict[str, dict]:
    out = {kind: fs.to_dict(_example(cls)) for kind, cls in fs.SAMPLE_TYPES.items()}
    out["nav_state"] = NavState(1.0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3),
                                np.zeros(2), 1.0, np.eye(18), True, 0).to_dict()
    out["aid_status"] = AidStatus(1.0, "depth", (1.0,), (0.1,), (0.01,), 0.5, True, "").to_dict()
    out["calibration_release"] = json.loads(codec.encode(Release(1.0, MotionParams(), -2.0, True, "", 3)))
    return out


@pytest.mark.parametrize("kind", sorted({k for k, _ in PINNED}))
def test_a_payload_keeps_every_field_of_its_version(kind):
    doc = _payloads()[kind]
    version = doc["schema_version"]
    pinned = PINNED.get((kind, version))
    assert pinned is not None, (f"{kind} schema_version {version} has no pinned row: add one (and keep a "
                                f"reader for the older versions)")
    fields = set(doc) if kind in ("nav_state", "aid_status", "calibration_release") else set(doc) - SAMPLE_ENVELOPE
    missing = pinned - fields
    assert not missing, (f"{kind} v{version} lost {sorted(missing)}: fields are added, never removed or renamed, "
                         f"without a schema_version bump and a reader for the old version")


def test_every_payload_kind_is_pinned():
    assert set(_payloads()) == {k for k, _ in PINNED}


@pytest.mark.parametrize("kind", sorted(fs.SAMPLE_TYPES) + ["calibration_release"])
def test_a_payload_with_only_the_fields_of_its_first_version_is_still_read(kind):
    doc = _payloads()[kind]
    pinned = PINNED[(kind, 1)] | SAMPLE_ENVELOPE
    old = {k: v for k, v in doc.items() if k in pinned}
    back = codec.decode_dict(old)  # added fields must have defaults
    assert codec.kind_of(back) == kind and math.isclose(back.t_s, doc["t_s"])
