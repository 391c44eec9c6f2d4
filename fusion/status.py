"""Per-fusion diagnostic record, like PX4's ``estimator_aid_src_*`` topics."""
from __future__ import annotations

import math
from dataclasses import dataclass

AID_STATUS_SCHEMA_VERSION = 1

REASONS = ("", "gate", "not_initialized", "surface_only", "non_finite", "stale", "invalid",
           "too_late", "disabled", "no_rpm", "no_imu")


@dataclass(frozen=True, init=False)
class AidStatus:
    """One attempt to fuse one measurement.

    ``observation`` is z, ``innovation`` z ⊖ h(x) (angles wrapped),
    ``innovation_variance`` the diagonal of S = H P Hᵀ + R, ``test_ratio`` the
    normalised innovation squared divided by the chi-square gate (> 1 ⇒ rejected),
    ``reason`` is "" when fused, else why not.
    """

    t_s: float
    source: str
    observation: tuple
    innovation: tuple
    innovation_variance: tuple
    test_ratio: float
    fused: bool
    reason: str

    def __init__(self, t_s: float, source: str, observation: tuple, innovation: tuple,
                 innovation_variance: tuple, test_ratio: float, fused: bool, reason: str) -> None:
        # the fields in one call (a frozen dataclass's own __init__ sets them one by one
        # through object.__setattr__: 0.87 against 0.49 µs, ~130k statuses per data hour)
        object.__setattr__(self, "__dict__", {
            "t_s": t_s, "source": source, "observation": observation, "innovation": innovation,
            "innovation_variance": innovation_variance, "test_ratio": test_ratio, "fused": fused,
            "reason": reason})

    def to_dict(self) -> dict:
        def arr(a):
            return [float(v) if math.isfinite(v) else None for v in a]
        return {
            "type": "aid_status",
            "schema_version": AID_STATUS_SCHEMA_VERSION,
            "t_s": float(self.t_s),
            "source": self.source,
            "observation": arr(self.observation),
            "innovation": arr(self.innovation),
            "innovation_variance": arr(self.innovation_variance),
            "test_ratio": float(self.test_ratio) if math.isfinite(self.test_ratio) else None,
            "fused": bool(self.fused),
            "reason": self.reason,
        }


def rejected(t_s: float, source: str, reason: str, observation: tuple = ()) -> AidStatus:
    """Status of a measurement that never reached the update."""
    return AidStatus(float(t_s), source, tuple(float(v) for v in observation), (), (), math.nan,
                     False, reason)
