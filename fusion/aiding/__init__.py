"""Aid sources: one module per measurement (DESIGN.md "Fusion").

A module that fuses a sample kind declares ``AID = AidSource(...)``
(:class:`~adaptnav.fusion.aiding.common.AidSource`): its kind, its config section and its
``measure(sample, ctx)``. :data:`AIDS` collects them by kind — every module of this
package is looked at, so a new aid is one new file (plus its config section in
:class:`adaptnav.fusion.config.FilterConfig`); ``tests/test_sensor_table.py`` checks the
aids against the sensor table (:data:`adaptnav.fusion.samples.SENSORS`).
``learned_velocity`` is no sample kind (the estimator fuses it on a clock from the RPM)
and declares none.
"""
from __future__ import annotations

import importlib
import pkgutil

from .common import AidContext, AidSource


def _discover() -> dict[str, AidSource]:
    found: dict[str, AidSource] = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        aid = getattr(importlib.import_module(f"{__name__}.{info.name}"), "AID", None)
        if isinstance(aid, AidSource):
            if aid.kind in found:
                raise ImportError(f"two aid sources for kind {aid.kind!r}")
            found[aid.kind] = aid
    return found


AIDS: dict[str, AidSource] = _discover()
# the kinds that are absolute position fixes (geodetic: lat/lon through the mission origin)
FIX_KINDS: tuple[str, ...] = tuple(k for k, a in AIDS.items() if a.absolute_position)

__all__ = ["AIDS", "FIX_KINDS", "AidContext", "AidSource"]
