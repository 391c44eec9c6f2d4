"""eskf._rpm_finite (the RPM sample's finiteness test of three floats, process()'s with every
RPM sample) answers as eskf._finite (samples.is_finite's field loop) on seeded samples: Python
floats finite, NaN, ±inf, and fields of other types (int, numpy float64/float32 NaN, None), a
subclass with a field more."""
from __future__ import annotations

import dataclasses
import math
import random

import numpy as np

from adaptnav.fusion import eskf
from adaptnav.fusion.samples import RpmSample


@dataclasses.dataclass(frozen=True, slots=True)
class _RpmWithMore(RpmSample):
    extra: float = 0.0


def test_rpm_finite_is_finite():
    rng = random.Random(3)
    values = [0.0, -0.0, 1500.0, -1200.5, 1e308, math.nan, math.inf, -math.inf, 7, 10**400, np.float64(math.nan),
              np.float64(3.0), np.float32(math.nan), None]
    answers = set()
    for _ in range(5000):
        t, r, y = (rng.choice(values) if rng.random() < 0.3 else rng.uniform(-3000.0, 3000.0) for _ in range(3))
        sample = RpmSample(t, r, y) if rng.random() < 0.9 else _RpmWithMore(t, r, y, rng.choice([0.0, math.nan]))
        try:
            want = eskf._finite(sample)
        except (TypeError, OverflowError) as exc:
            want = type(exc)
        try:
            got = eskf._rpm_finite(sample)
        except (TypeError, OverflowError) as exc:
            got = type(exc)
        assert got == want, sample
        answers.add((type(sample), want))
    assert {(RpmSample, True), (RpmSample, False), (_RpmWithMore, False)} <= answers
