"""What the runner needs of its collaborators, as typed protocols (structural: any object
with these members fits; nothing inherits from them).

- :class:`Estimator` — :class:`adaptnav.fusion.eskf.Estimator`;
- :class:`Calibrator` — :class:`~adaptnav.service.calibrator.lagged.LaggedCalibrator`,
  :class:`~adaptnav.service.calibrator.live.CalibratorProcess`,
  :class:`~adaptnav.service.calibrator.node.RemoteCalibrator`;
- :class:`Sink` — the output side (:class:`adaptnav.service.runtime.sinks.Sink` is the base
  class with no-op methods that concrete sinks extend);
- :class:`Clock` — :mod:`adaptnav.service.runtime.clock`.
"""
from __future__ import annotations

from collections import Counter
from typing import Any, Protocol, runtime_checkable

from adaptnav.service.runtime.clock import Clock


class RunAborted(RuntimeError):
    """A collaborator can no longer give the run the output it is defined to have: replay's
    calibrator child died (what follows would not be the deterministic solution), or a
    replay's output file cannot be written. The runner does not count it as one bad item and
    go on, as it does other errors: it raises it. The live daemon's collaborators never raise it."""


@runtime_checkable
class Estimator(Protocol):
    """The navigation filter as the runner drives it."""

    rejected: Counter

    @property
    def initialized(self) -> bool: ...

    def process(self, sample: Any) -> list: ...

    def nav_state(self) -> Any: ...

    def set_motion_params(self, params: Any, adopt_k_v: bool = False) -> None: ...

    def inertial_velocity(self) -> Any: ...

    # optional: ``settle()``, the work of the last ``process`` that none of its outputs
    # depends on, called by the runner once the item's outputs are out


@runtime_checkable
class Calibrator(Protocol):
    """Takes samples, returns releases (``calibration_release``) when they are due: the one
    route of a release back to the runner, live and in replay."""

    def observe(self, sample: Any) -> None: ...

    def poll(self, data_time_s: float) -> list:
        """Releases due by the runner's data time ``data_time_s`` (s; ∞ when the data ended)."""
        ...


@runtime_checkable
class Sink(Protocol):
    """Receives what the runner produces; any method may be absent (then not called)."""

    def on_nav(self, state: Any) -> None: ...


__all__ = ["Calibrator", "Clock", "Estimator", "RunAborted", "Sink"]
