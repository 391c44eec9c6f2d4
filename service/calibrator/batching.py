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
            out.append(ImuBatch.of(run, source=""))  # a run may mix sources: the calibrator reads none
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
    """Samples → a compact picklable form for the child, and the echo arrays that go beside
    it (inverse: :func:`unpack_batch`).

    Pickling each sample object was most of the transport's cost (a side-scan ping 44 µs,
    a DVL sample 14 µs: the dataclasses' ``__reduce__`` and one array object per echo
    side), so the message carries plain values: the arrays of every
    :class:`~fusion.samples.ImuBatch` concatenated (three arrays per message instead of three
    per batch), each batch replaced by its row count; a dataclass sample as ``(class, field
    values)``, or, when a field declared as an array holds a 1-D float32 one (the sonar's
    echoes), as ``[class, field values, indices of those fields]`` with each such array
    replaced by its span ``(start, stop)`` in the echoes laid end to end; anything else as it
    is. Returns ``(items, imu, echoes)``: ``echoes`` the list of those arrays, in span order,
    for the caller to write as raw bytes (pickled inside the message, every echo was copied
    into the pickle and out of it again).
    """
    ndarray, float32 = np.ndarray, np.float32
    items: list[Any] = []
    ts, fs, ws = [], [], []
    echoes: list[np.ndarray] = []
    at = 0
    for s in batch:  # not compact_imu: the child must see what an in-process calibrator sees
        cls = type(s)
        if cls is ImuBatch:
            ts.append(s.t_s)
            fs.append(s.specific_force_b_m_s2)
            ws.append(s.omega_b_rad_s)
            items.append(len(s))
            continue
        getter = _GETTERS.get(cls, _UNSEEN)
        if getter is _UNSEEN:
            getter = _getter(cls)
        if getter is None:
            items.append(s)  # not a dataclass: pickled whole
            continue
        n_fields, get, array_fields = getter
        d = getattr(s, "__dict__", None)
        if d is not None and len(d) != n_fields:
            items.append(s)  # it carries more than its fields: pickled whole
            continue
        if not array_fields:  # DVL, depth, heading, …: most of a batch
            items.append((cls, get(s)))
            continue
        values = list(get(s))
        spans = []
        for i in array_fields:
            v = values[i]
            if type(v) is ndarray and v.dtype == float32 and v.ndim == 1 and v.flags.c_contiguous:
                echoes.append(v)
                values[i] = (at, at + v.size)
                spans.append(i)
                at += v.size
        items.append([cls, values, spans])
    imu = (np.concatenate(ts, dtype=float), np.concatenate(fs, dtype=float),
           np.concatenate(ws, dtype=float)) if ts else None
    return items, imu, echoes


def unpack_batch(packed: tuple) -> list[Any]:
    """Inverse of :func:`pack_batch`, given ``(items, imu, echoes)`` with ``echoes`` the echo
    arrays laid end to end in one float32 array (None: none): IMU batches and echo arrays
    become (read-only) views of the shared arrays; dataclass samples are rebuilt field by
    field, as unpickling does (without ``__post_init__``: they were valid when they were
    packed)."""
    items, imu, echoes = packed
    if echoes is not None:
        echoes.setflags(write=False)  # as SonarPing keeps its echoes
    out: list[Any] = []
    setattr_ = object.__setattr__
    row = 0
    for s in items:
        kind = type(s)
        if kind is int:
            t, f, w = imu
            out.append(ImuBatch(t[row:row + s], f[row:row + s], w[row:row + s]))
            row += s
            continue
        if kind is tuple:
            cls, values = s
        elif kind is list:
            cls, values = s[0], s[1]
            for i in s[2]:
                a, b = values[i]
                values[i] = echoes[a:b]
        else:
            out.append(s)
            continue
        obj = object.__new__(cls)
        for name, v in zip(_field_names(cls), values):
            setattr_(obj, name, v)
        out.append(obj)
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
# per sample type: (number of fields, a getter of their values in definition order (a tuple),
# indices of the fields declared as arrays), or None for the types pickled whole
# (pack_batch's per-sample cost: one C call instead of a getattr each, and the echo test
# only where an echo can be)
_GETTERS: dict[type, tuple[int, Any, tuple[int, ...]] | None] = {}


def _getter(cls: type) -> tuple[int, Any, tuple[int, ...]] | None:
    names = _field_names(cls)
    if names is None:
        getter = None
    else:
        # annotations are strings here (``from __future__ import annotations``) or types
        array_fields = tuple(i for i, f in enumerate(dataclasses.fields(cls)) if "ndarray" in str(f.type))
        if len(names) == 1:
            name = names[0]
            getter = (1, lambda s: (getattr(s, name),), array_fields)
        else:
            getter = (len(names), operator.attrgetter(*names), array_fields)
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
