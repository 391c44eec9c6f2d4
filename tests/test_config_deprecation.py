"""A renamed config key stays accepted, with a warning that names the new one
(fusion/typed_config.py RENAMED_KEYS)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import pytest

from adaptnav.fusion.typed_config import ConfigDeprecationWarning, ConfigError, apply_overrides, build


@dataclass(frozen=True)
class _Inner:
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"sigma": "sigma_m"}
    sigma_m: float = 1.0


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)


def test_the_old_name_is_taken_with_a_warning_naming_the_new_one():
    with pytest.warns(ConfigDeprecationWarning, match=r"inner\.sigma is deprecated: use inner\.sigma_m"):
        cfg = build(_Outer, {"inner": {"sigma": 2.5}})
    assert cfg.inner.sigma_m == 2.5


def test_an_override_by_the_old_name_works_too():
    with pytest.warns(ConfigDeprecationWarning):
        cfg = build(_Outer, apply_overrides({}, ["inner.sigma=3.0"]))
    assert cfg.inner.sigma_m == 3.0


def test_both_names_set_is_an_error():
    with pytest.raises(ConfigError, match="both set"):
        build(_Outer, {"inner": {"sigma": 2.5, "sigma_m": 1.0}})


def test_the_new_name_gives_no_warning(recwarn):
    assert build(_Outer, {"inner": {"sigma_m": 2.0}}).inner.sigma_m == 2.0
    assert not [w for w in recwarn if issubclass(w.category, ConfigDeprecationWarning)]
