"""Typed configuration trees: frozen dataclasses built strictly from TOML-like dicts.

One mechanism for every configuration in the project (filter, scenario, service):

- :func:`build` turns a nested dict into a (nested) frozen dataclass; an unknown key is
  an error naming its dotted path (no silent parameter typos), a wrong type too.
- :func:`apply_overrides` applies ``section.key=value`` strings (values parsed as TOML
  scalars/arrays, so ``true``, ``1.5``, ``[1, 2]`` and ``"text"`` work; bare words are
  strings) to the raw dict before :func:`build`, so overrides get the same validation.
- Every float must be finite (TOML's ``nan``/``inf`` are refused naming the key), except
  NaN for a key whose default is NaN ("not set").
- :func:`as_dict` gives the effective config back (for logs and replay outputs).

Dataclasses may define ``validate(self)`` raising ``ValueError`` for cross-field rules.

Keys are user-facing (config files outlive releases). A renamed key stays accepted for at
least one release: the dataclass declares ``RENAMED_KEYS: ClassVar[dict[str, str]] =
{"old_name": "new_name"}``; :func:`build` takes the old name with a
:class:`ConfigDeprecationWarning` that names both, and refuses a file that sets both.

Vocabulary: a config dataclass is named ``<Thing>Config`` (older ones named ``Options``,
``Settings`` or ``Section`` keep their names: the names are imported across packages, and
the TOML keys, which users see, do not depend on them). This module lives in
:mod:`adaptnav.fusion` because that is the bottom layer every other package may import
(DESIGN.md "Layout"); it uses nothing of the filter.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
import warnings
from typing import Any


class ConfigError(ValueError):
    """A configuration that does not fit its schema; the message names the key."""


class ConfigDeprecationWarning(FutureWarning):
    """A config key under its old name (still accepted; the message names the new one).
    A ``FutureWarning``: shown by default, it is meant for the people who write the files."""


def _renamed(cls: type, raw: dict, path: str) -> dict:
    """``raw`` with the old names of ``cls.RENAMED_KEYS`` replaced by the new ones."""
    renamed = getattr(cls, "RENAMED_KEYS", None)
    if not renamed or not any(old in raw for old in renamed):
        return raw
    raw = dict(raw)
    where = f"{path}." if path else ""
    for old, new in renamed.items():
        if old not in raw:
            continue
        if new in raw:
            raise ConfigError(f"{where}{old} and {where}{new} are both set: {old} is the old name of {new}")
        warnings.warn(f"config key {where}{old} is deprecated: use {where}{new}", ConfigDeprecationWarning,
                      stacklevel=3)
        raw[new] = raw.pop(old)
    return raw


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # a bare word is a string


def apply_overrides(raw: dict, overrides: list[str] | tuple[str, ...]) -> dict:
    """Return a copy of ``raw`` with each ``a.b.c=value`` override applied."""
    import copy

    out = copy.deepcopy(raw)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected key=value")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {key!r}: {p!r} is not a section")
        node[parts[-1]] = _parse_value(text.strip())
    return out


def _coerce(value: Any, hint: Any, path: str) -> Any:
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a section (table)")
        return build(hint, value, path)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, path)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{path}: bad value {value!r}")
    if origin is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(f"{path}: {value!r} is not one of {list(allowed)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list")
        args = typing.get_args(hint)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{path}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, f"{path}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        item = args[0] if args else Any
        seq = [_coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(seq) if origin is tuple else seq
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {value!r}")
        if not math.isfinite(value):  # TOML has nan and inf literals; no setting wants them
            raise ConfigError(f"{path}: expected a finite number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {value!r}")
        return value
    return value


def build(cls: type, raw: dict | None = None, path: str = "") -> Any:
    """Build dataclass ``cls`` from ``raw``; missing keys take the dataclass defaults."""
    raw = _renamed(cls, raw or {}, path)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(raw) - names)
    if unknown:
        where = f" in [{path}]" if path else ""
        raise ConfigError(f"unknown key(s){where}: {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    kwargs = {}
    nan_default = {f.name for f in dataclasses.fields(cls)
                   if isinstance(f.default, float) and math.isnan(f.default)}
    for name, value in raw.items():
        if name in nan_default and isinstance(value, float) and math.isnan(value):
            kwargs[name] = value  # NaN is this key's own "not set"
            continue
        kwargs[name] = _coerce(value, hints[name], f"{path}.{name}" if path else name)
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{path or cls.__name__}: {e}") from e
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except ValueError as e:
            raise ConfigError(f"{path or cls.__name__}: {e}") from e
    return obj


def load_toml(cls: type, text: str, overrides: list[str] | tuple[str, ...] = ()) -> Any:
    """Parse TOML ``text``, apply overrides, build ``cls``."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"TOML syntax: {e}") from e
    return build(cls, apply_overrides(raw, overrides))


def as_dict(obj: Any) -> Any:
    """Dataclass tree → plain dict (tuples become lists), for TOML/JSON output."""
    if dataclasses.is_dataclass(obj):
        return {f.name: as_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [as_dict(v) for v in obj]
    return obj
