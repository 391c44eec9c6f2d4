"""The codec of a calibrator release (``calibration_release``): the message the EM
calibrator returns — from its child process, from a remote calibrator node over
``adaptnav/<v>/calibration/params``, and into MCAP logs — registered with
:mod:`adaptnav.service.transport.codec` like every other message kind.

Schema version 1. Fields are added, never removed or renamed, without a version bump and a
reader for the old version (``tests/service/test_payload_schemas.py`` pins them).
"""
from __future__ import annotations

import math
from typing import Any

from adaptnav.calibration.online import Release
from adaptnav.fusion.motion_model import MotionParams

KIND = Release.KIND
SCHEMA_VERSION = 1


def release_to_dict(release: Release) -> dict[str, Any]:
    """A :class:`~adaptnav.calibration.online.Release` → JSON-ready dict."""
    params = release.params
    ll = float(release.log_likelihood)
    return {
        "type": KIND,
        "schema_version": SCHEMA_VERSION,
        "t_s": float(release.t_s),
        "params": params.to_dict() if params is not None else None,
        "log_likelihood": ll if math.isfinite(ll) else None,
        "accepted": bool(release.accepted),
        "reason": str(release.reason or ""),
        "iterations": int(release.iterations or 0),
        "current_n_m_s": [float(x) for x in release.current_n_m_s],
        "teachers": [str(x) for x in release.teachers],
        "k_v_teacher": str(release.k_v_teacher),
    }


def _current_from(value: Any) -> tuple[float, float]:
    """Optional ``current_n_m_s`` (north, east, m/s) of a release; absent → (0, 0)."""
    if value is None:
        return (0.0, 0.0)
    n, e = (float(x) for x in value)
    return (n, e)


def release_from_dict(data: Any) -> Release:
    """Dict → :class:`~adaptnav.calibration.online.Release`; ``ValueError`` when malformed."""
    if not isinstance(data, dict) or data.get("type") != KIND:
        raise ValueError(f"not a {KIND}")
    if data.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(f"{KIND} schema_version {data.get('schema_version')!r}")
    try:
        t_s = float(data["t_s"])
        params = MotionParams.from_dict(data["params"]) if data.get("params") is not None else None
        ll = data.get("log_likelihood")
        return Release(t_s=t_s, params=params,
                       log_likelihood=math.nan if ll is None else float(ll),
                       accepted=bool(data["accepted"]), reason=str(data.get("reason", "")),
                       iterations=int(data.get("iterations", 0)),
                       current_n_m_s=_current_from(data.get("current_n_m_s")),
                       teachers=tuple(str(x) for x in data.get("teachers", ())),
                       k_v_teacher=str(data.get("k_v_teacher", "")))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{KIND}: {e}") from e


def release_schema() -> dict:
    """JSON Schema of the dict form (for MCAP channels and third-party readers)."""
    num = {"type": ["number", "null"]}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"adaptnav.{KIND}",
        "type": "object",
        "properties": {
            "type": {"const": KIND}, "schema_version": {"const": SCHEMA_VERSION}, "t_s": {"type": "number"},
            "params": {"type": ["object", "null"]}, "log_likelihood": num, "accepted": {"type": "boolean"},
            "reason": {"type": "string"}, "iterations": {"type": "integer"},
            "current_n_m_s": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
            "teachers": {"type": "array", "items": {"type": "string"}},
            "k_v_teacher": {"type": "string"},
        },
        "required": ["type", "schema_version", "t_s", "params", "accepted"],
    }
