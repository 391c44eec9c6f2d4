"""A calibrator for the runner without EM: each release comes back from ``poll`` once the
runner's data time reaches the time it is scripted for (the runner's one route of a
release, :mod:`adaptnav.service.runtime.runner`); what is under test is the runner's
handling of releases (gate, application, sinks, health), not the learning."""
from __future__ import annotations

from typing import Any


class ReleasesAt:
    """``ReleasesAt((t_s, release), ...)``: ``release`` due once the data time is ≥ ``t_s``."""

    def __init__(self, *script: tuple[float, Any]) -> None:
        self.pending = sorted(script, key=lambda entry: entry[0])

    def observe(self, sample: Any) -> None:
        """Nothing learned here."""

    def poll(self, data_time_s: float) -> list:
        due = [rel for t, rel in self.pending if t <= data_time_s]
        self.pending = [(t, rel) for t, rel in self.pending if t > data_time_s]
        return due
