"""What goes to the calibrator, and its data time: IMU runs compacted into batches, batches
packed for the process boundary, the data time τ of a sample (the release rule's clock).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from adaptnav.fusion.samples import ImuBatch, ImuSample


def compact_imu(batch: list[Any]) -> list[Any]:
    """Runs of consecutive ``ImuSample`` → one ``ImuBatch`` each (order kept, nothing lost).

    The calibrator only bins the yaw rate, and does so vectorised for an ``ImuBatch``;
    one array object instead of hundreds of small ones is also ~50× cheaper to pickle
    across the process boundary (the demo's 100 Hz IMU at 20× real time is 2000 /s).
    """
    out: list[Any] = []
    run: list[Any] = []

    def close() -> None:
        if len(run) == 1:
            out.append(run[0])
        elif run:
            out.append(ImuBatch(np.array([s.t_s for s in run], dtype=float),
                                np.array([s.specific_force_b_m_s2 for s in run], dtype=float),
                                np.array([s.omega_b_rad_s for s in run], dtype=float)))
        run.clear()

    for s in batch:
        if type(s) is ImuSample:
            run.append(s)
        else:
            close()
            out.append(s)
    close()
    return out



def data_time(sample: Any) -> float:
    """Latest finite time of a sample or :class:`~fusion.samples.ImuBatch` (s); NaN if none."""
    t = getattr(sample, "t_s", None)
    if t is None:
        return math.nan
    if isinstance(t, (int, float)):
        return float(t)
    try:
        n = len(t)
    except TypeError:
        return math.nan
    for i in range(n - 1, -1, -1):  # the last finite entry (a bad batch may end in NaN)
        v = float(t[i])
        if math.isfinite(v):
            return v
    return math.nan


class DataClock:
    """Running maximum of the sample times observed (the calibrator's data time τ)."""

    def __init__(self) -> None:
        self.tau = -math.inf

    def advance(self, sample: Any) -> float:
        t = data_time(sample)
        if t > self.tau:  # False for NaN
            self.tau = t
        return self.tau



def pack_batch(batch: list[Any]) -> tuple:
    """Samples → a compact picklable form for the child: the arrays of every
    :class:`~fusion.samples.ImuBatch` concatenated (three arrays per message instead of three
    per batch: pickling many small arrays was most of the transport's cost), each batch
    replaced by its row span; other samples as they are. Inverse: :func:`unpack_batch`."""
    items: list[Any] = []
    ts, fs, ws = [], [], []
    row = 0
    for s in batch:  # not compact_imu: the child must see what an in-process calibrator sees
        if type(s) is ImuBatch:
            n = len(s)
            ts.append(np.asarray(s.t_s, dtype=float))
            fs.append(np.asarray(s.specific_force_b_m_s2, dtype=float))
            ws.append(np.asarray(s.omega_b_rad_s, dtype=float))
            items.append((row, row + n))
            row += n
        else:
            items.append(s)
    if not ts:
        return items, None
    return items, (np.concatenate(ts), np.concatenate(fs), np.concatenate(ws))


def unpack_batch(packed: tuple) -> list[Any]:
    """Inverse of :func:`pack_batch` (batches become views of the shared arrays)."""
    items, arrays = packed
    if arrays is None:
        return items
    t, f, w = arrays
    return [ImuBatch(t[s[0]:s[1]], f[s[0]:s[1]], w[s[0]:s[1]]) if type(s) is tuple else s for s in items]


