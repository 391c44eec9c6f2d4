"""Python's garbage collector kept off the live daemon's latency path.

CPython collects a generation when its count of new container objects passes a threshold,
in whichever thread allocates that object. Live, that was sometimes the output epoch's own
sample: traced across the outside client's and the daemon's processes at 200 Hz
(``adaptnav bench service``'s client), a young collection costs 0.2–0.7 ms with the caches
cold, a middle one up to 2.5 ms, and a full one — every ~2 minutes, over every object the
imports made — 33 ms, during which the epoch's sample waited (its nav state 21–26 ms late).

:class:`CollectorPacing` does two things:

- :meth:`~CollectorPacing.freeze`, once the daemon is up: one full collection, then
  :func:`gc.freeze` — what the imports, the configuration and the filter allocated moves to
  the permanent generation, which no collection traverses again (the calibrator child and
  replay do the same). A full collection then only walks what came after.
- :meth:`~CollectorPacing.after_output`, right after a nav state was published: collects
  the generation CPython would collect next as soon as the young count is past
  ``young_fraction`` of its threshold. The next latency-critical sample is an output period
  away, and the thresholds are rarely reached between two outputs, so the automatic
  collections (still on: the safety net when no output comes) seldom run elsewhere.

``counts``: ``paced_<gen>`` collections run here, ``automatic_<gen>`` those CPython ran on its
own (a :data:`gc.callbacks` entry); in the daemon's health report as ``gc``.
"""
from __future__ import annotations

import gc
import threading
from collections import Counter
from typing import Any


class CollectorPacing:
    """Freeze at start, collections at the safe point (module docstring).

    ``young_fraction``: the share of the youngest generation's threshold past which
    :meth:`after_output` collects (0 < f ≤ 1)."""

    def __init__(self, young_fraction: float = 0.5) -> None:
        if not 0.0 < young_fraction <= 1.0:
            raise ValueError(f"young_fraction must be within (0, 1], got {young_fraction!r}")
        self.young_fraction = float(young_fraction)
        # every key there from the start: the health report reads them from another thread, and a
        # key added while it copies (a collection its own allocation triggered) would break it
        self.counts: Counter[str] = Counter({f"{how}_{g}": 0 for how in ("paced", "automatic") for g in range(3)})
        self.frozen_objects = 0
        # the thread running a paced collection: the callback counts everything else as
        # automatic (another thread may trigger one meanwhile, waiting for the GIL after it)
        self._pacing_thread: int | None = None
        self._installed = False

    def start(self) -> None:
        """Count CPython's own collections from now on (idempotent)."""
        if not self._installed:
            gc.callbacks.append(self._on_collect)
            self._installed = True

    def stop(self) -> None:
        """Stop counting and give the frozen objects back to the collector."""
        if self._installed:
            gc.callbacks.remove(self._on_collect)
            self._installed = False
        if self.frozen_objects:
            gc.unfreeze()
            self.frozen_objects = 0

    def freeze(self) -> int:
        """A full collection, then everything alive moved to the permanent generation; the
        number of objects frozen."""
        self._collect(2)
        gc.freeze()
        self.frozen_objects = gc.get_freeze_count()
        return self.frozen_objects

    def due_generation(self) -> int | None:
        """The generation :meth:`after_output` would collect now, None when none is due."""
        count0, count1, count2 = gc.get_count()
        threshold0, threshold1, threshold2 = gc.get_threshold()
        if threshold0 <= 0 or count0 < self.young_fraction * threshold0:
            return None  # threshold 0: the collector is off; so are we
        # CPython's own choice when the young count passes its threshold: the oldest
        # generation whose count (of collections of the one below) is past its threshold
        # (the full one also waits for a quarter more long-lived objects, which Python does
        # not expose: after the freeze there are few, and a full pass is short)
        return 2 if count2 > threshold2 else 1 if count1 > threshold1 else 0

    def after_output(self) -> int | None:
        """At the safe point: the due generation collected (its number), or None."""
        generation = self.due_generation()
        if generation is not None:
            self._collect(generation)
        return generation

    def _collect(self, generation: int) -> None:
        self._pacing_thread = threading.get_ident()
        try:
            gc.collect(generation)
        finally:
            self._pacing_thread = None
        self.counts[f"paced_{generation}"] += 1

    def _on_collect(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start" and self._pacing_thread != threading.get_ident():
            self.counts[f"automatic_{info['generation']}"] += 1

    def report(self) -> dict[str, int]:
        return {"frozen_objects": self.frozen_objects, **self.counts}
