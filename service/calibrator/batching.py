"""What goes to the calibrator, and its data time: IMU runs compacted into batches, batches
packed for the process boundary, the data time τ of a sample (the release rule's clock), and
what of the calibrator's outputs is due by that rule.
"""
from __future__ import annotations

import dataclasses
import math
import operator
from collections import deque
from itertools import accumulate, repeat
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



# the kinds of group in a packed batch (:func:`pack_batch`)
_IMU, _FIELDS, _WHOLE = 0, 1, 2
_T_S = operator.attrgetter("t_s")
_F = operator.attrgetter("specific_force_b_m_s2")
_W = operator.attrgetter("omega_b_rad_s")
_SIZE = operator.attrgetter("size")
_DTYPE = operator.attrgetter("dtype")
_NDIM = operator.attrgetter("ndim")
_C_CONTIGUOUS = operator.attrgetter("flags.c_contiguous")
_NDARRAY, _FLOAT32 = np.ndarray, np.dtype(np.float32)


def _is_echo(v: Any) -> bool:
    """A 1-D C-contiguous float32 array (an echo: written as raw bytes beside the message)."""
    return type(v) is _NDARRAY and v.dtype == _FLOAT32 and v.ndim == 1 and v.flags.c_contiguous


def pack_batch(batch: list[Any]) -> tuple:
    """Samples → a compact picklable form for the child, and the echo arrays that go beside
    it (inverse: :func:`unpack_batch`).

    Pickling each sample object was most of the transport's cost (a side-scan ping 44 µs,
    a DVL sample 14 µs: the dataclasses' ``__reduce__`` and one array object per echo
    side), so the message carries plain values, in columns: the samples grouped by type,
    ``items`` is ``(codes, groups)`` — ``codes`` (bytes) each sample's group, in batch order,
    ``groups`` per group one of

    * ``(_IMU, sizes)``: :class:`~fusion.samples.ImuBatch` runs, their arrays concatenated in
      ``imu`` (three arrays per message instead of three per batch), each batch its row count;
    * ``(_FIELDS, class, columns, echo_fields)``: a sample dataclass, one tuple of values per
      field in definition order, a field declared as an array (the sonar's echoes: 1-D
      C-contiguous float32, ``echo_fields`` their indices) as the tuple of their sizes, the
      arrays laid end to end in ``echoes``, field after field;
    * ``(_WHOLE, samples)``: anything else — not a sample dataclass, a sample carrying more than
      its fields, an array field holding no such echo (never made by the samples'
      constructors) —, pickled as it is.

    A tuple per field instead of one per sample, taken from the samples and given back to
    them by C loops (``map``) instead of a Python loop per sample: packing and pickling a
    survey's batches cost 1.8 µs a sample, unpacking in the child 2.2 µs. Returns ``(items,
    imu, echoes)``: ``echoes`` the list of those arrays, in order, for the caller to write as
    raw bytes (pickled inside the message, every echo was copied into the pickle and out of
    it again).
    """
    keys: list[Any] = list(map(type, batch))
    packed = _pack_groups(batch, keys)
    if packed is None:  # (rare) samples that go whole among others of their type
        keys = [_WHOLE if _goes_whole(s, cls) else cls for s, cls in zip(batch, keys)]
        packed = _pack_groups(batch, keys)
    return packed


def _goes_whole(s: Any, cls: type) -> bool:
    """A sample dataclass's sample that :func:`pack_batch` pickles whole: more than its fields,
    or an array field holding no echo."""
    getter = _getter(cls)
    if getter is None:
        return False
    n_fields, get, array_fields = getter
    if cls.__dictoffset__ and len(vars(s)) != n_fields:
        return True
    values = get(s)
    return not all(_is_echo(values[i]) for i in array_fields)


def _pack_groups(batch: list, keys: list) -> tuple | None:
    """:func:`pack_batch` with the samples grouped by ``keys`` (their types, or ``_WHOLE``); None
    when a group of a sample dataclass has a sample :func:`_goes_whole` would send whole."""
    kinds = list(dict.fromkeys(keys))
    if len(kinds) > 256:  # pragma: no cover - (codes are bytes) 256 sample types in one batch
        keys, kinds = [_WHOLE] * len(batch), [_WHOLE]
    if len(kinds) == 1:
        members_of = [list(batch)]
    else:
        by_kind: dict[Any, list] = {cls: [] for cls in kinds}
        for s, cls in zip(batch, keys):  # (the one Python loop per sample)
            by_kind[cls].append(s)
        members_of = list(by_kind.values())
    groups: list[tuple] = []
    ts: list[np.ndarray] = []
    fs: list[np.ndarray] = []
    ws: list[np.ndarray] = []
    echoes: list[np.ndarray] = []
    for cls, members in zip(kinds, members_of):
        getter = None if cls is _WHOLE else _getter(cls)
        if cls is ImuBatch:
            n0 = len(ts)
            ts += map(_T_S, members)
            fs += map(_F, members)
            ws += map(_W, members)
            groups.append((_IMU, tuple(map(len, ts[n0:]))))
        elif getter is None:  # not a sample dataclass, or it goes whole
            groups.append((_WHOLE, members))
        else:
            group = _pack_fields(cls, getter, members, echoes)
            if group is None:
                return None
            groups.append(group)
    imu = (np.concatenate(ts, dtype=float), np.concatenate(fs, dtype=float),
           np.concatenate(ws, dtype=float)) if ts else None
    code_of = {cls: k for k, cls in enumerate(kinds)}
    return (bytes(map(code_of.__getitem__, keys)), groups), imu, echoes


def _all_echoes(col: tuple) -> bool:
    """Every value of ``col`` a 1-D C-contiguous float32 array (an echo: written as raw bytes
    beside the message), by C loops over the column."""
    return (set(map(type, col)) == {_NDARRAY} and set(map(_DTYPE, col)) == {_FLOAT32}
            and set(map(_NDIM, col)) == {1} and all(map(_C_CONTIGUOUS, col)))


def _pack_fields(cls: type, getter: tuple, members: list, echoes: list) -> tuple | None:
    """:func:`pack_batch`'s group of the sample dataclass ``cls`` (its echoes appended to
    ``echoes``); None if a sample in it goes whole (:func:`_goes_whole`)."""
    n_fields, get, array_fields = getter
    if cls.__dictoffset__ and set(map(len, map(vars, members))) != {n_fields}:
        return None
    columns = list(zip(*map(get, members)))
    for i in array_fields:
        if not _all_echoes(columns[i]):
            return None
    for i in array_fields:
        echoes += columns[i]
        columns[i] = tuple(map(_SIZE, columns[i]))
    return _FIELDS, cls, tuple(columns), array_fields


def unpack_batch(packed: tuple) -> list[Any]:
    """Inverse of :func:`pack_batch`, given ``(items, imu, echoes)`` with ``echoes`` the echo
    arrays laid end to end in one float32 array (None: none): IMU batches and echo arrays
    become (read-only) views of the shared arrays; dataclass samples are rebuilt field by
    field, as unpickling does (without ``__post_init__``: they were valid when they were
    packed), a column at a time."""
    (codes, groups), imu, echoes = packed
    if echoes is None:  # none, or echoes of no samples
        echoes = np.zeros(0, dtype=np.float32)
    echoes.setflags(write=False)  # as SonarPing keeps its echoes
    rows = at = 0
    out_of: list[Any] = []
    for group in groups:
        kind = group[0]
        if kind == _IMU:
            # rebuilt field by field too (ImuBatch's __post_init__, its shape test, was most of
            # a batch's unpacking: the rows of all three are the same slices, as packed)
            ends = list(accumulate(group[1], initial=rows))
            rows_of = list(map(slice, ends[:-1], ends[1:]))
            rows = ends[-1]
            batches = list(map(object.__new__, repeat(ImuBatch, len(rows_of))))
            for name, col in zip(_IMU_FIELDS, imu):
                deque(map(_SETATTR, batches, repeat(name, len(rows_of)), map(col.__getitem__, rows_of)), maxlen=0)
            deque(map(_SETATTR, batches, repeat("source", len(rows_of)), repeat("")), maxlen=0)
            out_of.append(iter(batches))
        elif kind == _WHOLE:
            out_of.append(iter(group[1]))
        else:
            _, cls, columns, echo_fields = group
            n = len(columns[0])
            objs = list(map(object.__new__, repeat(cls, n)))
            columns = list(columns)
            for i in echo_fields:
                ends = list(accumulate(columns[i], initial=at))
                columns[i] = list(map(echoes.__getitem__, map(slice, ends[:-1], ends[1:])))
                at = ends[-1]
            for name, col in zip(_field_names(cls), columns):
                deque(map(_SETATTR, objs, repeat(name, n), col), maxlen=0)
            out_of.append(iter(objs))
    return list(map(next, map(out_of.__getitem__, codes)))


_SETATTR = object.__setattr__
_IMU_FIELDS = ("t_s", "specific_force_b_m_s2", "omega_b_rad_s")  # ImuBatch's arrays, as packed


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


# per sample type: (number of fields, a getter of their values in definition order (a tuple),
# indices of the fields declared as arrays), or None for the types pickled whole
_GETTERS: dict[type, tuple[int, Any, tuple[int, ...]] | None] = {}


def _getter(cls: type) -> tuple[int, Any, tuple[int, ...]] | None:
    try:
        return _GETTERS[cls]
    except KeyError:
        pass
    names = _field_names(cls)
    if not names:
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
