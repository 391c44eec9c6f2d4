"""The one wire format of every message kind (Zenoh payloads and MCAP messages).

A message is UTF-8 JSON: an object with ``type`` (the kind) and ``schema_version``
plus the kind's fields — self-describing, so ``zenoh-cli`` or the ``mcap`` CLI can
print it. Non-finite numbers travel as ``null`` (strict JSON has no NaN).

- :func:`encode` ``(sample) -> bytes``
- :func:`decode` ``(bytes) -> sample``; anything malformed (not UTF-8, not JSON, not an
  object, unknown type, wrong field types) raises :class:`adaptnav.fusion.samples.SampleError`
  and never any other exception.
- :func:`schema_for` ``(kind) -> dict``: the JSON Schema of a kind (MCAP channels).
- :func:`register` ``(kind, encode_fn, decode_fn, schema, topic=None)``: how other
  packages add kinds (navigation state, aid status, parameters ...).

Built in: every type of :data:`adaptnav.fusion.samples.SAMPLE_TYPES`, and ``sonar``
(:class:`adaptnav.sonar.ping.SonarPing`, imported on first use; intensity arrays as JSON lists).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Callable

import orjson

from adaptnav.fusion import samples as fs
from adaptnav.fusion.samples import SampleError

__all__ = ["SampleError", "encode", "decode", "decode_dict", "schema_for", "register", "kinds",
           "topic_for", "kind_of", "time_of"]


@dataclass(frozen=True)
class Codec:
    """How one kind goes to and from its JSON dict."""

    kind: str
    to_dict: Callable[[Any], dict]
    from_dict: Callable[[dict], Any]
    schema: dict | Callable[[], dict]
    topic: str


_REGISTRY: dict[str, Codec] = {}


def _default_topic(kind: str) -> str:
    return "/adaptnav/truth" if kind == "truth" else f"/adaptnav/sensor/{kind}"


def register(kind: str, encode_fn: Callable[[Any], dict], decode_fn: Callable[[dict], Any],
             schema: dict | Callable[[], dict], topic: str | None = None) -> None:
    """Register (or replace) a message kind.

    Parameters
    ----------
    kind : the ``type`` string of the JSON form (and the object's ``KIND``)
    encode_fn : object → JSON-ready dict, including ``type`` and ``schema_version``
    decode_fn : dict → object; may raise ``ValueError``/``TypeError``/``KeyError`` on bad
        payloads (they are turned into :class:`SampleError`)
    schema : JSON Schema dict, or a zero-argument function returning it (lazy)
    topic : MCAP topic for logs (default ``/adaptnav/<kind>``)
    """
    _REGISTRY[kind] = Codec(kind, encode_fn, decode_fn, schema, topic or f"/adaptnav/{kind}")


for _kind, _cls in fs.SAMPLE_TYPES.items():
    register(_kind, fs.to_dict, fs.from_dict, (lambda c=_cls: fs.json_schema(c)), _default_topic(_kind))


def _sonar_codec() -> Codec:
    from adaptnav.sonar.ping import SonarPing  # lazy: keeps numpy-only consumers light

    return Codec("sonar", SonarPing.to_dict, SonarPing.from_dict, SonarPing.json_schema,
                 _default_topic("sonar"))


def _release_codec() -> Codec:
    from adaptnav.service.transport.release import KIND, release_from_dict, release_schema, release_to_dict

    return Codec(KIND, release_to_dict, release_from_dict, release_schema, "/adaptnav/calibration/params")


# kinds whose types live in packages this module does not load up front
_LAZY = {"sonar": _sonar_codec, "calibration_release": _release_codec}


def _lookup(kind: Any) -> Codec:
    codec = _REGISTRY.get(kind) if isinstance(kind, str) else None
    if codec is None and isinstance(kind, str) and kind in _LAZY:
        codec = _REGISTRY[kind] = _LAZY[kind]()
    if codec is None:
        raise SampleError(f"unknown message type {kind!r} (known: {', '.join(kinds())})")
    return codec


def kinds() -> list[str]:
    """Every registered kind (the lazily loaded ``sonar`` and ``calibration_release`` included)."""
    return sorted(set(_REGISTRY) | set(_LAZY))


def kind_of(obj: Any) -> str:
    """A message's kind: ``obj.KIND``, or ``obj["type"]`` for kinds carried as dicts."""
    kind = obj.get("type") if isinstance(obj, dict) else getattr(obj, "KIND", None)
    if not isinstance(kind, str):
        raise TypeError(f"{type(obj).__name__} has no KIND (or 'type'): not a message")
    return kind


def time_of(obj: Any) -> float:
    """A message's ``t_s`` (NaN when it has none)."""
    t = obj.get("t_s") if isinstance(obj, dict) else getattr(obj, "t_s", None)
    return float(t) if isinstance(t, (int, float)) and not isinstance(t, bool) else float("nan")


def encode(obj: Any) -> bytes:
    """Message → UTF-8 JSON bytes (``allow_nan=False``: NaN must already be null)."""
    d = _lookup(kind_of(obj)).to_dict(obj)
    return json.dumps(d, separators=(",", ":"), allow_nan=False).encode("utf-8")


def _fast_decoder(cls: type) -> Callable[[dict], Any]:
    """A decoder for the common, well-formed payload of a sample type (the hot path of
    log replay and of every sample off the bus). It returns ``None`` for anything unusual
    (ints for floats, nulls, missing/unknown fields ...), which then goes to the strict
    generic decoder :func:`adaptnav.fusion.samples.from_dict` for the verdict and its error
    message. A loop over the field specs: a decoder generated per type with ``exec`` saved
    ~0.5 µs of an IMU sample's ~100 µs, not worth code nobody can read or step through."""
    import dataclasses

    spec = []
    for f in dataclasses.fields(cls):
        jtype, length = fs._field_spec(f)
        spec.append((f.name, {"number": float, "integer": int, "boolean": bool, "string": str}[jtype], length))
    all_keys = frozenset([f.name for f in dataclasses.fields(cls)] + ["type", "schema_version"])

    def decode(data: dict) -> Any:
        if data.keys() != all_keys or data["schema_version"] != fs.SCHEMA_VERSION:
            return None
        kwargs = {}
        for name, typ, length in spec:
            v = data[name]
            if length is None:
                if type(v) is not typ:
                    return None
            else:
                if type(v) is not list or (length > 0 and len(v) != length):
                    return None
                for x in v:
                    if type(x) is not typ:
                        return None
                v = tuple(v)
            kwargs[name] = v
        return cls(**kwargs)

    return decode


_FAST = {kind: _fast_decoder(cls) for kind, cls in fs.SAMPLE_TYPES.items()}


def _fast_encoder(cls: type) -> Callable[[Any], dict]:
    """:func:`adaptnav.fusion.samples.to_dict` with the field list computed once (log writing)."""
    import dataclasses
    import math

    names = [f.name for f in dataclasses.fields(cls)]
    isfinite = math.isfinite

    def encode(sample: Any) -> dict:
        out: dict[str, Any] = {"type": cls.KIND, "schema_version": fs.SCHEMA_VERSION}
        for name in names:
            v = getattr(sample, name)
            if type(v) is tuple:
                out[name] = [float(x) if isfinite(x) else None for x in v]
            elif type(v) is float and not isfinite(v):
                out[name] = None
            else:
                out[name] = v
        return out

    return encode


for _kind, _cls in fs.SAMPLE_TYPES.items():
    _REGISTRY[_kind] = Codec(_kind, _fast_encoder(_cls), fs.from_dict, _REGISTRY[_kind].schema,
                             _REGISTRY[_kind].topic)


def decode_dict(data: Any) -> Any:
    """JSON value → message; raises :class:`SampleError` only."""
    if not isinstance(data, dict):
        raise SampleError(f"payload is {type(data).__name__}, expected an object")
    kind = data.get("type")
    fast = _FAST.get(kind) if isinstance(kind, str) else None
    if fast is not None and _REGISTRY.get(kind) is not None and _REGISTRY[kind].from_dict is fs.from_dict:
        sample = fast(data)
        if sample is not None:
            return sample
    codec = _lookup(kind)
    try:
        return codec.from_dict(data)
    except SampleError:
        raise
    except Exception as e:  # noqa: BLE001 — the contract: a bad payload is a SampleError, whoever decodes it
        raise SampleError(f"{codec.kind}: {type(e).__name__}: {e}") from None


def decode(payload: bytes | bytearray | memoryview | str) -> Any:
    """UTF-8 JSON bytes → message; raises :class:`SampleError` on anything malformed."""
    if isinstance(payload, bytes):
        # the live hot path (every sample off the bus): orjson parses a sample in ~1 µs
        # against ~8 for json; anything it refuses (NaN literals, bad UTF-8, deep nesting)
        # or reads otherwise (an integer beyond 64 bits becomes a float) so that the
        # message is refused takes the general way below, which decides as it always did
        try:
            return decode_dict(orjson.loads(payload))
        except (orjson.JSONDecodeError, SampleError):
            pass
    try:
        if isinstance(payload, str):
            text = payload
        elif isinstance(payload, (bytes, bytearray, memoryview)):
            text = bytes(payload).decode("utf-8")
        else:
            raise SampleError(f"payload is {type(payload).__name__}, expected bytes")
        data = json.loads(text)
    except SampleError:
        raise
    except UnicodeDecodeError as e:
        raise SampleError(f"payload is not UTF-8: {e}") from None
    except (json.JSONDecodeError, RecursionError) as e:
        raise SampleError(f"payload is not JSON: {e}") from None
    return decode_dict(data)


def schema_for(kind: str) -> dict:
    """JSON Schema (draft 2020-12) of a kind."""
    codec = _lookup(kind)
    return codec.schema() if callable(codec.schema) else codec.schema


def topic_for(kind: str) -> str:
    """MCAP topic of a kind: ``/adaptnav/sensor/<kind>``, ``/adaptnav/truth``, ..."""
    return _lookup(kind).topic
