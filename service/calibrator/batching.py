"""What goes to the calibrator, and its data time: IMU runs compacted into batches, batches
packed for the process boundary, the data time τ of a sample (the release rule's clock), and
what of the calibrator's outputs is due by that rule.
"""
from __future__ import annotations

import dataclasses
import math
import operator
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
    """Samples → a compact picklable form for the child (inverse: :func:`unpack_batch`).

    Pickling each sample object was most of the transport's cost (a side-scan ping 44 µs,
    a DVL sample 14 µs: the dataclasses' ``__reduce__`` and one array object per echo
    side), so the message carries plain values: the arrays of every
    :class:`~fusion.samples.ImuBatch` concatenated (three arrays per message instead of three
    per batch), each batch replaced by its row span ``(start, stop)``; a dataclass sample
    as ``[class, field values]`` with its 1-D float32 arrays (the sonar's echoes)
    concatenated into one buffer, each replaced by its span ``(start, stop)`` (their field
    indices in a third entry); anything else as it is.
    """
    ndarray, float32 = np.ndarray, np.float32
    items: list[Any] = []
    ts, fs, ws = [], [], []
    echoes: list[np.ndarray] = []
    row = 0
    at = 0
    for s in batch:  # not compact_imu: the child must see what an in-process calibrator sees
        cls = type(s)
        if cls is ImuBatch:
            n = len(s)
            ts.append(np.asarray(s.t_s, dtype=float))
            fs.append(np.asarray(s.specific_force_b_m_s2, dtype=float))
            ws.append(np.asarray(s.omega_b_rad_s, dtype=float))
            items.append((row, row + n))
            row += n
            continue
        getter = _GETTERS.get(cls, _UNSEEN)
        if getter is _UNSEEN:
            getter = _getter(cls)
        if getter is None:
            items.append(s)  # not a dataclass: pickled whole
            continue
        n_fields, get = getter
        d = getattr(s, "__dict__", None)
        if d is not None and len(d) != n_fields:
            items.append(s)  # it carries more than its fields: pickled whole
            continue
        values = list(get(s))
        # the per-field test only for the samples that hold an array (a side-scan ping):
        # the others (DVL, depth, heading, …: most of a batch) skip it in one C-level scan
        if ndarray not in map(type, values):
            items.append([cls, values])
            continue
        spans = []
        for i, v in enumerate(values):
            if type(v) is ndarray and v.dtype == float32 and v.ndim == 1:
                echoes.append(v)
                values[i] = (at, at + v.size)
                spans.append(i)
                at += v.size
        items.append([cls, values, spans] if spans else [cls, values])
    imu = (np.concatenate(ts), np.concatenate(fs), np.concatenate(ws)) if ts else None
    return items, imu, (np.concatenate(echoes) if echoes else None)


def unpack_batch(packed: tuple) -> list[Any]:
    """Inverse of :func:`pack_batch`: IMU batches and echo arrays become (read-only) views of
    the shared arrays; dataclass samples are rebuilt field by field, as unpickling does
    (without ``__post_init__``: they were valid when they were packed)."""
    items, imu, echoes = packed
    if echoes is not None:
        echoes.setflags(write=False)  # as SonarPing keeps its echoes
    out: list[Any] = []
    setattr_ = object.__setattr__
    for s in items:
        kind = type(s)
        if kind is tuple:
            t, f, w = imu
            out.append(ImuBatch(t[s[0]:s[1]], f[s[0]:s[1]], w[s[0]:s[1]]))
        elif kind is list:
            cls, values = s[0], s[1]
            if len(s) > 2:
                for i in s[2]:
                    a, b = values[i]
                    values[i] = echoes[a:b]
            obj = object.__new__(cls)
            for name, v in zip(_field_names(cls), values):
                setattr_(obj, name, v)
            out.append(obj)
        else:
            out.append(s)
    return out


_FIELD_NAMES: dict[type, tuple[str, ...] | None] = {}


# the sample types rebuilt field by field (plain frozen dataclasses whose fields are their
# whole state); anything else is pickled as it is
_BY_FIELDS_MODULES = ("adaptnav.fusion.samples", "adaptnav.sonar.ping")


def _field_names(cls: type) -> tuple[str, ...] | None:
    """Field names of a sample dataclass type in definition order (None for other types)."""
    try:
        return _FIELD_NAMES[cls]
    except KeyError:
        names = _FIELD_NAMES[cls] = (tuple(f.name for f in dataclasses.fields(cls))
                                     if dataclasses.is_dataclass(cls) and cls.__module__ in _BY_FIELDS_MODULES
                                     else None)
        return names


_UNSEEN = object()
# per sample type: (number of fields, a getter of their values in definition order), or None
# for the types pickled whole (pack_batch's per-sample cost: one C call instead of a getattr each)
_GETTERS: dict[type, tuple[int, Any] | None] = {}


def _getter(cls: type) -> tuple[int, Any] | None:
    names = _field_names(cls)
    if names is None:
        getter = None
    elif len(names) == 1:
        name = names[0]
        getter = (1, lambda s: (getattr(s, name),))
    else:
        getter = (len(names), operator.attrgetter(*names))
    _GETTERS[cls] = getter
    return getter


def split_due(held: Any, data_time_s: float, latency_s: float, product_latency_s: float) -> tuple[list, list]:
    """The release rule over ``held`` ((τ, output) pairs, oldest first): ``(due, kept)`` —
    a release is due once ``τ + latency_s ≤ data_time_s``, a side product (side-scan objects
    for the filter) once ``τ + product_latency_s ≤ data_time_s``; both lists keep the order."""
    due, kept = [], []
    for tau, out in held:
        if _due_at(tau, out, latency_s, product_latency_s) <= data_time_s:
            due.append(out)
        else:
            kept.append((tau, out))
    return due, kept


def next_due(held: Any, latency_s: float, product_latency_s: float) -> float:
    """The data time at which the first of ``held`` is due by :func:`split_due`'s rule (∞: none)."""
    return min((_due_at(tau, out, latency_s, product_latency_s) for tau, out in held), default=math.inf)


def _due_at(tau: float, out: Any, latency_s: float, product_latency_s: float) -> float:
    return tau + (latency_s if out.KIND == "calibration_release" else product_latency_s)
