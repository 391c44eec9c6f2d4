"""One side-scan ping: the sonar sample of the bus, the simulator and the XTF reader.

A ping holds the echo intensity of the port and starboard channels as functions of
slant range, ``r_k = (k + 0.5) * slant_range_m / N`` for sample ``k`` (sample 0 nearest
the vehicle on both sides), and the navigation/attitude valid at the ping time.

JSON form (for the Zenoh bus and logs), like :mod:`adaptnav.fusion.samples` but with arrays::

    {"type": "sonar", "schema_version": 1, "t_s": ..., "port": [...], "starboard": [...], ...}

Non-finite numbers become ``null``.  :meth:`SonarPing.from_dict` is strict (unknown or
missing fields, wrong types, unequal channel lengths raise :class:`PingError`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

SCHEMA_VERSION = 1


class PingError(ValueError):
    """A payload that cannot be turned into a :class:`SonarPing` (the message says why)."""


_SCALARS = ("t_s", "slant_range_m", "altitude_m", "heading_rad", "pitch_rad", "roll_rad",
            "lat_rad", "lon_rad", "sensor_depth_m", "speed_m_s")
_OPTIONAL_NAN = ("altitude_m", "lat_rad", "lon_rad", "speed_m_s", "pitch_rad", "roll_rad",
                 "sensor_depth_m")


@dataclass(frozen=True, eq=False)
class SonarPing:
    """Side-scan ping with per-ping navigation.

    Attributes
    ----------
    t_s : float
        Time of the ping (s, mission time).
    port, starboard : numpy.ndarray, shape (N,), float32
        Echo intensity by slant-range sample, sample 0 nearest the vehicle (read-only).
    slant_range_m : float
        Slant range of the last sample (m).
    altitude_m : float
        Height above the seabed (m); NaN when unknown (0 in some files also means unknown).
    heading_rad, pitch_rad, roll_rad : float
        Attitude (rad); heading from north towards east.
    lat_rad, lon_rad : float
        Geodetic position (rad), NaN when unknown.
    sensor_depth_m : float
        Depth of the sonar below the surface (m).
    speed_m_s : float
        Speed over ground (m/s), NaN when unknown.
    """

    KIND: ClassVar[str] = "sonar"
    t_s: float
    port: np.ndarray
    starboard: np.ndarray
    slant_range_m: float
    altitude_m: float = math.nan
    heading_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0
    lat_rad: float = math.nan
    lon_rad: float = math.nan
    sensor_depth_m: float = math.nan
    speed_m_s: float = math.nan

    def __post_init__(self) -> None:
        for name in ("port", "starboard"):
            arr = np.array(getattr(self, name), dtype=np.float32).reshape(-1)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if self.port.shape != self.starboard.shape:
            raise PingError(f"sonar: port has {self.port.size} samples, starboard "
                            f"{self.starboard.size}; they must be equal")
        for name in _SCALARS:
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def n_samples(self) -> int:
        """Samples per side."""
        return int(self.port.size)

    @property
    def sample_spacing_m(self) -> float:
        """Slant-range spacing of the samples (m)."""
        return self.slant_range_m / max(self.n_samples, 1)

    @property
    def has_geometry(self) -> bool:
        """A slant range (finite, > 0) and at least 8 samples a side: a ping an image can be made of."""
        return bool(self.slant_range_m > 0 and math.isfinite(self.slant_range_m) and self.n_samples >= 8)

    def resampled(self, n_samples: int, slant_range_m: float) -> "SonarPing":
        """This ping on another geometry — ``n_samples`` per side over ``slant_range_m`` —
        (:func:`resample_slant`); itself when it already has it."""
        if n_samples == self.n_samples and slant_range_m == self.slant_range_m:
            return self
        return dataclasses.replace(
            self, port=resample_slant(self.port, self.slant_range_m, n_samples, slant_range_m),
            starboard=resample_slant(self.starboard, self.slant_range_m, n_samples, slant_range_m),
            slant_range_m=slant_range_m)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (``type``, ``schema_version``, arrays as lists, NaN → None)."""
        out: dict[str, Any] = {"type": self.KIND, "schema_version": SCHEMA_VERSION}
        for name in _SCALARS:
            v = getattr(self, name)
            out[name] = v if math.isfinite(v) else None
        for name in ("port", "starboard"):
            arr = getattr(self, name)
            values = arr.tolist()
            if not np.all(np.isfinite(arr)):
                values = [x if math.isfinite(x) else None for x in values]
            out[name] = values
        return out

    @classmethod
    def from_dict(cls, data: Any) -> "SonarPing":
        """Strict inverse of :meth:`to_dict`; raises :class:`PingError` on bad payloads."""
        if not isinstance(data, dict):
            raise PingError(f"payload is {type(data).__name__}, expected an object")
        if data.get("type") != cls.KIND:
            raise PingError(f"expected type {cls.KIND!r}, got {data.get('type')!r}")
        if data.get("schema_version") != SCHEMA_VERSION:
            raise PingError(f"sonar: schema_version {data.get('schema_version')!r} not "
                            f"supported (want {SCHEMA_VERSION})")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names - {"type", "schema_version"}
        if unknown:
            raise PingError(f"sonar: unknown field(s) {sorted(unknown)}")
        kwargs: dict[str, Any] = {}
        for name in _SCALARS:
            if name not in data:
                if name in _OPTIONAL_NAN or name == "heading_rad":
                    continue
                raise PingError(f"sonar: missing field {name!r}")
            v = data[name]
            if v is None:
                kwargs[name] = math.nan
            elif isinstance(v, bool) or not isinstance(v, (int, float)):
                raise PingError(f"sonar.{name}: expected a number, got {type(v).__name__}")
            else:
                kwargs[name] = float(v)
        for name in ("port", "starboard"):
            if name not in data:
                raise PingError(f"sonar: missing field {name!r}")
            v = data[name]
            if not isinstance(v, list):
                raise PingError(f"sonar.{name}: expected an array")
            try:
                kwargs[name] = np.array([math.nan if x is None else x for x in v], dtype=np.float32)
            except (TypeError, ValueError) as exc:
                raise PingError(f"sonar.{name}: expected numbers ({exc})") from None
            if any(isinstance(x, bool) for x in v):
                raise PingError(f"sonar.{name}: expected numbers, got a boolean")
        return cls(**kwargs)

    @classmethod
    def json_schema(cls) -> dict[str, Any]:
        """JSON Schema (draft 2020-12) of the JSON form."""
        num = {"type": ["number", "null"]}
        props: dict[str, Any] = {"type": {"const": cls.KIND},
                                 "schema_version": {"const": SCHEMA_VERSION}}
        for name in _SCALARS:
            props[name] = dict(num)
        for name in ("port", "starboard"):
            props[name] = {"type": "array", "items": dict(num)}
        required = ["type", "schema_version", "t_s", "port", "starboard", "slant_range_m"]
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"adaptnav.{cls.KIND}",
            "type": "object",
            "properties": props,
            "required": required,
            "additionalProperties": False,
        }


def resample_slant(values: np.ndarray, slant_range_m: float, n_samples: int,
                   to_slant_range_m: float) -> np.ndarray:
    """One channel's samples over ``slant_range_m`` → ``n_samples`` over ``to_slant_range_m``.

    Each sample is the mean echo over its range bin (sample ``k`` covers ``[k, k + 1)`` times
    the spacing): a coarser grid averages the samples it covers, a finer one repeats them —
    no aliasing of speckle either way. Bins beyond the ping's range have no data (NaN, as
    non-finite samples are taken downstream); non-finite input samples count as no echo.
    A sonar's range or sample count changes within a survey (the operator, auto-range)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    n_in = v.size
    out = np.full(int(n_samples), np.nan, dtype=np.float32)
    if n_in == 0 or not (slant_range_m > 0 and to_slant_range_m > 0) or n_samples <= 0:
        return out
    v = np.where(np.isfinite(v), v, 0.0)
    step_in = slant_range_m / n_in
    edges_in = np.arange(n_in + 1) * step_in
    integral_in = np.concatenate(([0.0], np.cumsum(v))) * step_in   # ∫ echo dr at each input edge
    edges = np.minimum(np.arange(int(n_samples) + 1) * (to_slant_range_m / n_samples), slant_range_m)
    covered = np.diff(edges)
    integral = np.diff(np.interp(edges, edges_in, integral_in))
    has_data = covered > 1e-9 * step_in
    out[has_data] = integral[has_data] / covered[has_data]
    return out
