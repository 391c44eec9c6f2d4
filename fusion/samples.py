"""Timestamped sample types — the messages of the simulator, the logs and the bus.

Every sample is a frozen dataclass whose first field is ``t_s``: sensor time of
validity in seconds (mission time, float). Vectors are tuples of floats in the frame
their name says (``_b`` body FRD, ``_n`` local NED, ``_d`` DVL head); SI units only.

The same types travel over Zenoh and are written to MCAP: :func:`to_dict` /
:func:`from_dict` give the versioned JSON form ``{"type": ..., "schema_version": ...,
<fields>}`` and :func:`json_schema` its JSON Schema, so third-party tools (Foxglove,
the ``mcap`` CLI, ``zenoh-cli``) can read them.  :func:`from_dict` is strict: a
missing or unknown field, a wrong length or a non-number raises
:class:`SampleError` with a message that says which.  Non-finite numbers are
*representable* (a real sensor does send NaN) and are judged by the estimator,
which rejects and counts them; :func:`is_finite` is the check.

Replay order is deterministic: :func:`replay_order_key` sorts by
``(t_s, source priority, seq)``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import numpy as np

SCHEMA_VERSION = 1
# who measured an IMU sample (ImuSample.source): unknown, a flight controller's own, a dedicated IMU
IMU_SOURCES = ("", "autopilot", "dedicated")

Vec3 = tuple[float, float, float]


class SampleError(ValueError):
    """A payload that cannot be turned into a sample (the message says why)."""


@dataclass(frozen=True, slots=True)
class ImuSample:
    """Strapdown IMU: specific force and angular rate in body FRD.

    ``source``: who measured it, when the reader knows (one of :data:`IMU_SOURCES`):
    ``"autopilot"`` — a flight controller's own IMU (its MEMS parts, low-pass filtered by its
    firmware before they are streamed), ``"dedicated"`` — an IMU or INS of its own (e.g. a
    companion computer's driver for a fibre-optic IMU), ``""`` — unknown (a simulator, a
    log without the information).  ``filter.imu.grade = "auto"`` uses it
    (:mod:`adaptnav.fusion.imu_grades`).
    """

    KIND: ClassVar[str] = "imu"
    t_s: float
    specific_force_b_m_s2: Vec3
    omega_b_rad_s: Vec3
    source: str = ""


@dataclass(frozen=True, slots=True)
class RpmSample:
    """Propeller speed (rev/min) — the motion model's control input.

    ``sway_rpm``: lateral thrust as a signed RPM (starboard positive) for vehicles with
    lateral thrusters (a BlueROV2's vectored frame); 0 for those without.
    """

    KIND: ClassVar[str] = "rpm"
    t_s: float
    rpm: float
    sway_rpm: float = 0.0


@dataclass(frozen=True, slots=True)
class DvlSample:
    """DVL velocity in the DVL head frame; ``valid`` false on lost lock.

    Bottom track (``water_track`` false): the head's velocity over the seabed. Water track
    (``water_track`` true, the DVL's fallback without bottom lock): its velocity relative
    to a water layer a few metres away, i.e. over ground minus the current.

    ``sigma_m_s``: the sensor's own 1-σ per axis when it reports one (a DVL's figure of
    merit); NaN: the configured sigma. The filter uses the larger.
    """

    KIND: ClassVar[str] = "dvl"
    t_s: float
    vel_d_m_s: Vec3
    valid: bool = True
    altitude_m: float = math.nan
    water_track: bool = False
    sigma_m_s: float = math.nan


@dataclass(frozen=True, slots=True)
class DepthSample:
    """Absolute pressure at the depth sensor (Pa); the depth aid turns it into depth."""

    KIND: ClassVar[str] = "depth"
    t_s: float
    pressure_pa: float


@dataclass(frozen=True, slots=True)
class HeadingSample:
    """Heading (yaw of ``q_nb``, from north towards east) from a compass/AHRS, rad."""

    KIND: ClassVar[str] = "heading"
    t_s: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """Roll, pitch, yaw from an external AHRS (e.g. ArduSub ATTITUDE), rad."""

    KIND: ClassVar[str] = "attitude"
    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class GnssSample:
    """Surface GNSS fix (geodetic, WGS-84) with its horizontal 1-σ."""

    KIND: ClassVar[str] = "gnss"
    t_s: float
    lat_rad: float
    lon_rad: float
    sigma_h_m: float


@dataclass(frozen=True, slots=True)
class UsblSample:
    """Acoustic (USBL/ultra-short baseline) position fix, geodetic, with 1-σ."""

    KIND: ClassVar[str] = "usbl"
    t_s: float
    lat_rad: float
    lon_rad: float
    depth_m: float
    sigma_h_m: float
    sigma_v_m: float = math.nan


@dataclass(frozen=True, slots=True)
class RangeSample:
    """Acoustic range to a beacon/landmark at a known local NED position."""

    KIND: ClassVar[str] = "range"
    t_s: float
    beacon_id: int
    beacon_pos_n_m: Vec3
    range_m: float
    sigma_m: float


@dataclass(frozen=True, slots=True)
class AltitudeSample:
    """Height above the seabed (echosounder / DVL / DISTANCE_SENSOR), m."""

    KIND: ClassVar[str] = "altitude"
    t_s: float
    altitude_m: float


@dataclass(frozen=True, slots=True)
class VisualMotionSample:
    """Side-scan visual motion between two sonar windows centred at ``t0_s`` and ``t_s``.

    ``along_m``/``across_m`` are the displacement in the sonar frame (along-track
    forward, across-track starboard), ``dheading_rad`` the yaw change; ``cov`` the
    3×3 covariance of (along, across, dheading), row-major.
    """

    KIND: ClassVar[str] = "visual_motion"
    t_s: float
    t0_s: float
    along_m: float
    across_m: float
    dheading_rad: float
    cov: tuple[float, ...] = field(default=(0.0,) * 9)


@dataclass(frozen=True, slots=True)
class InertialVelocitySample:
    """The estimator's free-inertial velocity (NED, m/s), its time integral ``pos_n_m`` (m)
    and the yaw at ``t_s`` (a filter output).

    The strapdown's velocity increments summed without aiding corrections: the value
    drifts, its changes over seconds are the IMU's. ``reset_counter`` changes across an
    IMU gap (no increments while coasting). The calibrator's surge-noise evidence
    (:mod:`adaptnav.calibration.inertial`): mean velocities over steps are differences of ``pos_n_m``.
    ``current_n_m_s`` is the filter's sea-current estimate (north, east, 0): the DVL teacher
    turns DVL ground velocities into water-relative ones with it (:mod:`adaptnav.calibration.dvl_teacher`),
    after removing the filter's DVL scale factor error (–) and yaw misalignment (rad),
    ``dvl_scale_misalignment`` (:class:`adaptnav.fusion.aiding.dvl.DvlCalibration`), so that the
    model learns the vehicle, not the head's mounting.
    """

    KIND: ClassVar[str] = "inertial_velocity"
    t_s: float
    vel_n_m_s: Vec3
    pos_n_m: Vec3
    yaw_rad: float
    reset_counter: int = 0
    current_n_m_s: Vec3 = (0.0, 0.0, 0.0)
    dvl_scale_misalignment: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True, slots=True)
class TruthSample:
    """Simulator ground truth (never used by the estimator, only by metrics)."""

    KIND: ClassVar[str] = "truth"
    t_s: float
    pos_n_m: Vec3
    vel_n_m_s: Vec3
    q_nb: tuple[float, float, float, float]
    current_n_m_s: Vec3
    k_v: float
    bias_acc_b_m_s2: Vec3 = (0.0, 0.0, 0.0)
    bias_gyro_b_rad_s: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SensorKind:
    """One row of :data:`SENSORS`, the table every list of sample kinds derives from.

    Attributes
    ----------
    kind : str
        The ``KIND`` of its sample type, the ``type`` of its JSON form, its bus topic name.
    sample_type : type or None
        Its sample class; ``None`` for a kind declared outside :mod:`adaptnav.fusion`
        (``sonar``: :class:`adaptnav.sonar.ping.SonarPing`, sonar being a leaf package).
    priority : int
        Replay order among samples with equal ``t_s`` (lower first).
    role : str
        ``"propagate"`` (moves the state: the IMU), ``"control"`` (an input of the motion
        model: RPM), ``"aid"`` (corrects the state through an aid source of
        :mod:`adaptnav.fusion.aiding`), ``"calibration"`` (only the calibrator learns from
        it), ``"context"`` (used by other consumers, e.g. sonar's slant-range correction),
        ``"truth"`` (simulator ground truth: metrics only).
    calibrator_uses : bool
        :class:`adaptnav.calibration.online.OnlineCalibrator` learns from it (the others
        are not sent to it).
    nav_stream : bool
        A navigation log is expected to carry it (a replay reports it missing otherwise).
    aid_source : str or None
        The aid source whose status says why nothing is fused when this sensor is silent.
    """

    kind: str
    sample_type: type | None
    priority: int
    role: str
    calibrator_uses: bool
    nav_stream: bool = False
    aid_source: str | None = None


ROLES = ("propagate", "control", "aid", "calibration", "context", "truth")

# The sensor table. A new kind is one row here (and its sample class above); every other
# list of kinds derives from it, and tests/test_sensor_table.py checks each consumer
# covers every kind it must. Priorities: the IMU propagates to t before aiding at t is
# fused; truth last, so metrics see the state after every update at t.
SENSORS: tuple[SensorKind, ...] = (
    SensorKind("imu", ImuSample, 0, "propagate", calibrator_uses=True, nav_stream=True),
    SensorKind("rpm", RpmSample, 1, "control", calibrator_uses=True, nav_stream=True,
               aid_source="learned_velocity"),
    SensorKind("attitude", AttitudeSample, 2, "aid", calibrator_uses=True, aid_source="attitude"),
    SensorKind("heading", HeadingSample, 3, "aid", calibrator_uses=True, nav_stream=True, aid_source="heading"),
    SensorKind("depth", DepthSample, 4, "aid", calibrator_uses=False, nav_stream=True, aid_source="depth"),
    SensorKind("dvl", DvlSample, 5, "aid", calibrator_uses=True, nav_stream=True, aid_source="dvl"),
    SensorKind("altitude", AltitudeSample, 6, "context", calibrator_uses=False),
    SensorKind("gnss", GnssSample, 7, "aid", calibrator_uses=True, nav_stream=True, aid_source="gnss"),
    SensorKind("usbl", UsblSample, 8, "aid", calibrator_uses=True, nav_stream=True, aid_source="usbl"),
    SensorKind("range", RangeSample, 9, "aid", calibrator_uses=True, aid_source="range"),
    SensorKind("visual_motion", VisualMotionSample, 10, "aid", calibrator_uses=False,
               aid_source="visual_motion"),
    SensorKind("inertial_velocity", InertialVelocitySample, 11, "calibration", calibrator_uses=True),
    SensorKind("sonar", None, 50, "calibration", calibrator_uses=True),
    SensorKind("truth", TruthSample, 99, "truth", calibrator_uses=False),
)

SENSOR_BY_KIND: dict[str, SensorKind] = {s.kind: s for s in SENSORS}

# derived lists (never written out by hand elsewhere)
SAMPLE_TYPES: dict[str, type] = {s.kind: s.sample_type for s in SENSORS if s.sample_type is not None}
SOURCE_PRIORITY: dict[str, int] = {s.kind: s.priority for s in SENSORS}
DEFAULT_PRIORITY = 50  # a kind the table does not know (a newer sender's)


def kinds(*, role: str | None = None, calibrator_uses: bool | None = None,
          nav_stream: bool | None = None) -> tuple[str, ...]:
    """The kinds of :data:`SENSORS` with the given attributes, in table order."""
    return tuple(s.kind for s in SENSORS
                 if (role is None or s.role == role)
                 and (calibrator_uses is None or s.calibrator_uses == calibrator_uses)
                 and (nav_stream is None or s.nav_stream == nav_stream))


def replay_order_key(sample: Any, seq: int) -> tuple[float, int, int]:
    """Sort key of the deterministic replay order ``(t_s, source priority, seq)``."""
    return (sample.t_s, SOURCE_PRIORITY.get(sample.KIND, DEFAULT_PRIORITY), seq)


def _field_spec(f: dataclasses.Field) -> tuple[str, int | None]:
    """('number'|'integer'|'boolean'|'string', fixed length or None for scalars)."""
    ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    ann = ann.replace(" ", "")
    if ann in ("float",):
        return "number", None
    if ann == "int":
        return "integer", None
    if ann == "bool":
        return "boolean", None
    if ann == "str":
        return "string", None
    if ann == "Vec3":
        return "number", 3
    if ann == "tuple[float,float,float,float]":
        return "number", 4
    if ann == "tuple[float,float]":
        return "number", 2
    if ann == "tuple[float,...]":
        return "number", -1
    raise TypeError(f"unsupported field annotation {ann!r}")


def _number(value: Any, where: str) -> float:
    # bool is an int subclass; a boolean where a number belongs is a malformed payload
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        if value is None:
            return math.nan  # JSON has no NaN; null stands for it
        raise SampleError(f"{where}: expected a number, got {type(value).__name__}")
    return float(value)


def to_dict(sample: Any) -> dict[str, Any]:
    """Sample → JSON-ready dict with ``type`` and ``schema_version``.

    Non-finite floats become ``None`` (JSON null) so the output is strict JSON.
    """
    out: dict[str, Any] = {"type": sample.KIND, "schema_version": SCHEMA_VERSION}
    for f in dataclasses.fields(sample):
        v = getattr(sample, f.name)
        if isinstance(v, tuple):
            out[f.name] = [None if not math.isfinite(x) else float(x) for x in v]
        elif isinstance(v, float) and not math.isfinite(v):
            out[f.name] = None
        else:
            out[f.name] = v
    return out


def from_dict(data: Any) -> Any:
    """JSON dict → sample; raises :class:`SampleError` on anything malformed."""
    if not isinstance(data, dict):
        raise SampleError(f"payload is {type(data).__name__}, expected an object")
    kind = data.get("type")
    cls = SAMPLE_TYPES.get(kind)  # type: ignore[arg-type]
    if cls is None:
        raise SampleError(f"unknown sample type {kind!r}")
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise SampleError(f"{kind}: schema_version {version!r} not supported (want {SCHEMA_VERSION})")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields) - {"type", "schema_version"}
    if unknown:
        raise SampleError(f"{kind}: unknown field(s) {sorted(unknown)}")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is not dataclasses.MISSING:
                continue
            raise SampleError(f"{kind}: missing field {name!r}")
        value = data[name]
        jtype, length = _field_spec(f)
        where = f"{kind}.{name}"
        if length is None:
            if jtype == "boolean":
                if not isinstance(value, bool):
                    raise SampleError(f"{where}: expected true/false")
                kwargs[name] = value
            elif jtype == "string":
                if not isinstance(value, str):
                    raise SampleError(f"{where}: expected a string")
                kwargs[name] = value
            elif jtype == "integer":
                if isinstance(value, bool) or not isinstance(value, int):
                    raise SampleError(f"{where}: expected an integer")
                kwargs[name] = value
            else:
                kwargs[name] = _number(value, where)
        else:
            if not isinstance(value, (list, tuple)):
                raise SampleError(f"{where}: expected an array")
            if length > 0 and len(value) != length:
                raise SampleError(f"{where}: expected {length} numbers, got {len(value)}")
            kwargs[name] = tuple(_number(x, f"{where}[{i}]") for i, x in enumerate(value))
    return cls(**kwargs)


def json_schema(cls: type) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a sample type, for MCAP channels and the bus."""
    props: dict[str, Any] = {
        "type": {"const": cls.KIND},
        "schema_version": {"const": SCHEMA_VERSION},
    }
    required = ["type", "schema_version"]
    for f in dataclasses.fields(cls):
        jtype, length = _field_spec(f)
        scalar = {"type": [jtype, "null"]} if jtype == "number" else {"type": jtype}
        if length is None:
            props[f.name] = scalar
        else:
            arr: dict[str, Any] = {"type": "array", "items": scalar}
            if length > 0:
                arr.update(minItems=length, maxItems=length)
            props[f.name] = arr
        if f.default is dataclasses.MISSING:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"adaptnav.{cls.KIND}",
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def is_finite(sample: Any) -> bool:
    """True when every number the sample carries is finite (optional NaN fields excepted).

    Fields whose default is NaN (e.g. ``DvlSample.altitude_m``) mean "not reported".
    """
    spec = _FINITE_SPEC.get(type(sample))
    if spec is None:  # (name, optional NaN) per field, once per class (every sample is checked)
        spec = _FINITE_SPEC[type(sample)] = tuple(
            (f.name, isinstance(f.default, float) and math.isnan(f.default)) for f in dataclasses.fields(sample))
    isfinite = math.isfinite
    for name, optional_nan in spec:
        v = getattr(sample, name)
        if isinstance(v, tuple):
            for x in v:
                if not isfinite(x):
                    return False
        elif isinstance(v, float) and not optional_nan and not isfinite(v):
            return False
    return True


_FINITE_SPEC: dict[type, tuple[tuple[str, bool], ...]] = {}


@dataclass(frozen=True)
class ImuBatch:
    """A run of consecutive IMU samples as arrays — the replay fast path.

    Not a bus message (the bus carries :class:`ImuSample`); sources that read logs group
    IMU runs between other samples so the estimator can propagate them in one call.
    ``t_s`` (N,), ``specific_force_b_m_s2`` (N, 3), ``omega_b_rad_s`` (N, 3); ``source``
    as :attr:`ImuSample.source`, the same for the whole run.
    """

    KIND: ClassVar[str] = "imu_batch"
    t_s: Any
    specific_force_b_m_s2: Any
    omega_b_rad_s: Any
    source: str = ""

    def __post_init__(self) -> None:
        # the propagation kernels index the three arrays together: mismatched shapes would
        # read past an array's end, so they are refused at construction
        n = len(self.t_s)
        for name in ("specific_force_b_m_s2", "omega_b_rad_s"):
            shape = getattr(getattr(self, name), "shape", None) or (len(getattr(self, name)),)
            if shape[0] != n or (len(shape) > 1 and shape[1:] != (3,)):
                raise SampleError(f"imu_batch: {name} has shape {tuple(shape)}, expected ({n}, 3)")

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def of(cls, run: Sequence[ImuSample], source: str | None = None) -> "ImuBatch":
        """A non-empty run of :class:`ImuSample` as one batch; ``source`` the run's first
        sample's unless given."""
        return cls(np.fromiter((s.t_s for s in run), dtype=float, count=len(run)),
                   np.array([s.specific_force_b_m_s2 for s in run], dtype=float).reshape(-1, 3),
                   np.array([s.omega_b_rad_s for s in run], dtype=float).reshape(-1, 3),
                   run[0].source if source is None else source)

    def samples(self):
        """The batch as individual :class:`ImuSample` (for code paths without batching)."""
        for t, f, w in zip(self.t_s, self.specific_force_b_m_s2, self.omega_b_rad_s):
            yield ImuSample(float(t), tuple(map(float, f)), tuple(map(float, w)), self.source)
