"""Sinks of the runner loop: where nav states, aid statuses and calibrator releases go.

Live, the sinks are the Zenoh publishers and the MAVLink bridge; in replay they are the
files written here (DESIGN.md "Service": the runner is the same, only sources, clock and
sinks change). A sink implements any of

- ``on_nav(state)`` — a :class:`adaptnav.fusion.state.NavState` at the output rate,
- ``on_aid(statuses)`` — the :class:`adaptnav.fusion.status.AidStatus` records of one sample,
- ``on_release(release)`` — a :class:`adaptnav.calibration.online.Release` (accepted or not),
- ``on_sample(sample)`` — every non-IMU input sample (truth included, for metrics),
- ``on_first_sample(sample)`` — the first of them only (a time stamp: ``params.csv``'s
  initial row; ``on_sample`` for that would take every sample of the run),
- ``close()`` — flush and write what is written at the end;

:class:`Sink` gives no-op defaults. Files written here (all deterministic: same input,
same bytes):

- ``trajectory.csv`` (:class:`TrajectoryCsvSink`), ``aid_status.csv``
  (:class:`AidStatusCsvSink`), ``params.csv`` (:class:`ParamsCsvSink`);
- ``metrics.json`` (:class:`MetricsSink`, only when truth is present) and the plots
  ``track.png``, ``params.png``, ``innovations.png`` (:class:`PlotSink`), both from the
  series kept by :class:`SeriesRecorder`.
"""
from __future__ import annotations

import csv
import itertools
import json
import logging
import math
from collections import Counter, deque
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from adaptnav.fusion.aiding import FIX_KINDS
from adaptnav.fusion.frames import quat_to_euler
from adaptnav.service.runtime.protocols import RunAborted
from adaptnav.service.tools.metrics import TrackArrays, TruthArrays, compute_metrics, dvl_outage_metrics

log = logging.getLogger(__name__)


def fmt(value: Any) -> str:
    """Deterministic compact text of a number, bool, string or vector (``;``-joined)."""
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return "nan" if math.isnan(v) else format(v, ".10g")
    if isinstance(value, str):
        return value
    arr = np.asarray(value, dtype=float).ravel()
    return ";".join(format(float(v), ".10g") if math.isfinite(v) else str(float(v)) for v in arr)


def _vec(values: Any) -> str:
    return ";".join(format(float(v), ".10g") for v in values)


# trajectory.csv's numeric columns t_s … k_speed, and its truth columns (comma-separated)
_NAV_FORMAT = ",".join(["%.10g"] * 16)
# (the truth's position, then its current and k_v: the same from one sample to the next in a simulation)
_TRUTH_POS_FORMAT = ",%.10g,%.10g,%.10g"
_TRUTH_TAIL_FORMAT = ",%.10g,%.10g,%.10g\n"
_NO_TRUTH = "," * 6 + "\n"
# rows a CSV sink joins into one write
_ROWS_PER_WRITE = 256
_F64 = np.dtype(np.float64)
# the estimator's sea current: north, east
_NE_SHAPE = (2,)
# characters that make csv.writer quote a field
_CSV_SPECIAL = frozenset(',"\r\n')


def _state_slices():
    # imported lazily: fusion.state is the estimator's contract (DESIGN.md named slices)
    from adaptnav.fusion import state as st
    return st


class OutputNotWritten(RunAborted):
    """A replay's output file could not be written (disk full, an I/O error): the run stops
    there instead of going on item after item without its product."""


class _OutputFile:
    """A replay output's text file (what ``csv.writer`` and the sinks call: ``write``,
    ``close``); a failure to open, write or close it raises :class:`OutputNotWritten`
    naming the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._file = open(path, "w", newline="")
        except OSError as e:
            raise self._not_written(e) from None

    def write(self, text: str) -> int:
        try:
            return self._file.write(text)
        except OSError as e:
            raise self._not_written(e) from None

    def close(self) -> None:
        try:
            self._file.close()
        except OSError as e:
            raise self._not_written(e) from None

    def _not_written(self, error: OSError) -> OutputNotWritten:
        return OutputNotWritten(f"cannot write {self.path}: {error.strerror or error}")


class Sink:
    """No-op base: override what you need. ``sample_kinds``: the sample kinds ``on_sample``
    wants (``None``: all); the runner hands it no others."""

    sample_kinds: frozenset | None = None
    # its output depends on nothing but its calls, in their order: it may take them later
    # (DeferredSinks); not a live sink, nor one that reads anything that changes meanwhile
    deferrable = False

    def on_nav(self, state: Any) -> None:
        pass

    def on_aid(self, statuses: list) -> None:
        pass

    def on_release(self, release: Any) -> None:
        pass

    def on_sample(self, sample: Any) -> None:
        pass

    def on_inertial(self, sample: Any) -> None:
        """The estimator's free-inertial velocity at a nav epoch (InertialVelocitySample)."""
        pass

    def on_first_sample(self, sample: Any) -> None:
        """The first sample ``on_sample`` would get (any kind), before it goes there."""
        pass

    def close(self) -> None:
        pass


def sink_methods(sinks: list, name: str) -> list:
    """The sinks' ``name`` methods, leaving out the no-op defaults of :class:`Sink`."""
    base = getattr(Sink, name)
    out = []
    for s in sinks:
        m = getattr(s, name, None)
        if m is not None and getattr(m, "__func__", None) is not base:
            out.append(m)
    return out


def sample_methods(methods: list, kind: str) -> list:
    """Of ``on_sample`` methods, those whose sink wants samples of ``kind`` (:attr:`Sink.sample_kinds`)."""
    out = []
    for f in methods:
        kinds = getattr(getattr(f, "__self__", None), "sample_kinds", None)
        if kinds is None or kind in kinds:
            out.append(f)
    return out


def close_sinks(sinks: list) -> None:
    """Every sink's ``close()``; one that fails is logged and the others are still closed. A
    :class:`RunAborted` (a replay's output not written) is raised once all are closed."""
    aborted = None
    for s in sinks:
        try:
            close = getattr(s, "close", None)
            if close is not None:
                close()
        except RunAborted as e:  # (said by whoever catches it: no traceback per sink)
            aborted = aborted or e
        except Exception:
            log.exception("runner: closing sink %r failed", s)
    if aborted is not None:
        raise aborted


class DeferredSinks:
    """Replay: the calls to ``sinks`` queued in their order and made later — a slice at a time
    while the runner waits for its calibrator child (:meth:`work` is the backend's idle hook,
    :attr:`adaptnav.service.calibrator.lagged.ProcessBackend.idle`), whenever ``max_pending``
    are queued, and at :meth:`close`. The same calls in the same order: the same files. The
    sinks' work (~9 % of the replaying process) then fills the waits for the calibrator's
    side-scan blocks instead of adding to them. Not for a live sink (it would lag).

    The objects handed over must not change afterwards: the runner's nav states, aid
    statuses, samples and releases are fresh or immutable."""

    def __init__(self, sinks: list, max_pending: int = 1024) -> None:
        self.sinks = list(sinks)
        self.max_pending = int(max_pending)
        self._queue: deque = deque()
        for name in ("on_nav", "on_aid", "on_release", "on_inertial", "on_first_sample"):
            methods = sink_methods(self.sinks, name)
            if methods:  # the runner calls what is there only
                setattr(self, name, partial(self._defer, methods))
        self._on_sample = sink_methods(self.sinks, "on_sample")
        self._by_kind: dict[str, list] = {}
        if self._on_sample:
            self.on_sample = self._sample
            # what its sinks want, for the runner: no call at all for the other kinds
            kinds = [getattr(f.__self__, "sample_kinds", None) for f in self._on_sample]
            self.sample_kinds = None if None in kinds else frozenset().union(*kinds)

    def _defer(self, methods: list, arg: Any) -> None:
        q = self._queue
        q.append((methods, arg))
        if len(q) >= self.max_pending:
            self.work(len(q))

    def _sample(self, sample: Any) -> None:
        kind = sample.KIND
        methods = self._by_kind.get(kind)
        if methods is None:
            methods = self._by_kind[kind] = sample_methods(self._on_sample, kind)
        if methods:
            self._defer(methods, sample)

    def work(self, n: int = 32) -> bool:
        """Make up to ``n`` of the queued calls, oldest first; False when none was queued."""
        q = self._queue
        if not q:
            return False
        for _ in range(min(n, len(q))):
            methods, arg = q.popleft()
            for f in methods:
                f(arg)
        return True

    def close(self) -> None:
        """The calls still queued, then every sink's ``close()`` (also when a call failed)."""
        try:
            self.work(len(self._queue))
        finally:
            close_sinks(self.sinks)


def geo_time_fields(state: Any, unix_of: Any = None, origin: Any = None) -> dict[str, float]:
    """``t_unix_s`` (when ``unix_of(t_s)`` knows it) and ``lat_deg``, ``lon_deg`` (when the
    NED ``origin``, a :class:`adaptnav.fusion.frames.GeoOrigin`, is known) of a nav state."""
    out: dict[str, float] = {}
    t_unix = unix_of(float(state.t_s)) if unix_of is not None else None
    if t_unix is not None:
        out["t_unix_s"] = float(t_unix)
    if origin is not None:
        lat, lon = origin.to_geodetic_ne(*np.asarray(state.pos_n_m, dtype=float)[:2].tolist())
        if math.isfinite(lat) and math.isfinite(lon):
            out["lat_deg"], out["lon_deg"] = math.degrees(lat), math.degrees(lon)
    return out


def geo_time_text(t_s: float, north_m: float, east_m: float, unix_of: Any = None, origin: Any = None) -> str:
    """trajectory.csv's ``t_unix_s,lat_deg,lon_deg`` of a state: :func:`geo_time_fields`'
    numbers, each empty when unknown (from the Python floats of the row: no dict, no arrays)."""
    t_unix = unix_of(t_s) if unix_of is not None else None
    text = "" if t_unix is None else "%.6f" % t_unix
    if origin is not None:
        lat, lon = origin.to_geodetic_ne(north_m, east_m)
        if math.isfinite(lat) and math.isfinite(lon):
            return text + ",%.9f,%.9f" % (math.degrees(lat), math.degrees(lon))
    return text + ",,"


def _current_xy(state: Any) -> tuple[float, float]:
    """The state's sea current north, east as Python floats (every nav state, two sinks: one
    tolist and two float() cost 0.17 µs, np.asarray(..., float).ravel()[:2].tolist() 0.44)."""
    c = state.current_n_m_s
    xy = c.ravel().tolist() if isinstance(c, np.ndarray) else c
    return float(xy[0]), float(xy[1])


class TrajectoryCsvSink(Sink):
    """``trajectory.csv``: one row per nav state.

    Columns: ``t_s, north_m, east_m, down_m, vel_n_m_s, vel_e_m_s, vel_d_m_s, roll_rad,
    pitch_rad, yaw_rad, sigma_north_m, sigma_east_m, sigma_down_m, current_n_m_s,
    current_e_m_s, k_speed, valid, t_unix_s, lat_deg, lon_deg`` (``t_unix_s`` when
    ``unix_of`` maps mission time to UNIX time — a wall-clock reference exists —,
    ``lat_deg``/``lon_deg`` when the ``origin`` is known; empty otherwise) and, with ``truth=True``, ``truth_north_m,
    truth_east_m, truth_down_m, truth_current_n_m_s, truth_current_e_m_s, truth_k_v`` from
    the truth sample within ``truth_max_age_s`` of the state: the latest one, or the one
    that arrives before the next state (the runner emits an epoch's state when the IMU
    reaches it, before that epoch's truth sample); empty when there is none.
    """

    COLUMNS = ("t_s", "north_m", "east_m", "down_m", "vel_n_m_s", "vel_e_m_s", "vel_d_m_s",
               "roll_rad", "pitch_rad", "yaw_rad", "sigma_north_m", "sigma_east_m",
               "sigma_down_m", "current_n_m_s", "current_e_m_s", "k_speed", "valid", "t_unix_s", "lat_deg",
               "lon_deg")
    TRUTH_COLUMNS = ("truth_north_m", "truth_east_m", "truth_down_m", "truth_current_n_m_s",
                     "truth_current_e_m_s", "truth_k_v")
    sample_kinds = frozenset({"truth"})

    def __init__(self, path: str | Path, truth: bool = False, truth_max_age_s: float = 0.05,
                 unix_of: Any = None, origin: Any = None) -> None:
        self.path = Path(path)
        self.unix_of = unix_of
        self.origin = origin
        self.truth = truth
        self.truth_max_age_s = truth_max_age_s
        self._file = _OutputFile(self.path)
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(self.COLUMNS + (self.TRUTH_COLUMNS if truth else ()))
        self._last_truth = None
        self._pending: tuple[float, str] | None = None  # (t_s, row) waiting for its truth sample
        self._pos = _state_slices().POS
        # the position's variances by index into the covariance (cov.item: Python floats, no arrays)
        self._pos_ix = tuple(range(_state_slices().N_ERR))[self._pos]
        # rows joined and written in blocks (a file write per row cost more than the join)
        self._rows: list[str] = []
        # a truth sample's current and k_v are the same from one to the next (a simulation's
        # run): their text is kept (key, text)
        self._truth_tail: tuple[tuple, str] = ((), "")
        # a log's UNIX time of a state is what the source has learnt of its clock by then
        self.deferrable = unix_of is None

    def on_sample(self, sample: Any) -> None:
        if sample.KIND == "truth":
            self._last_truth = sample
            pending = self._pending
            # a truth sample matches a state within truth_max_age_s of it
            if pending is not None and abs(pending[0] - sample.t_s) <= self.truth_max_age_s:
                self._pending = None
                self._write(pending[1], sample)

    def _write(self, row: str, truth: Any) -> None:
        # the fields are numbers, never quoted: what csv.writer would write, joined directly
        rows = self._rows
        if not self.truth:
            rows.append(row + "\n")
        elif truth is not None:
            cur, k_v = truth.current_n_m_s, truth.k_v
            key, tail = self._truth_tail
            c_n, c_e = cur[0], cur[1]
            # equal numbers have equal text, but for the sign of zero: zeros are formatted
            if not (key and c_n == key[0] and c_e == key[1] and k_v == key[2] and c_n and c_e and k_v):
                tail = _TRUTH_TAIL_FORMAT % (c_n, c_e, k_v)
                self._truth_tail = ((c_n, c_e, k_v), tail)
            rows.append(row + _TRUTH_POS_FORMAT % tuple(truth.pos_n_m) + tail)
        else:
            rows.append(row + _NO_TRUTH)
        if len(rows) >= _ROWS_PER_WRITE:
            self._file.write("".join(rows))
            rows.clear()

    def _row(self, state: Any) -> tuple[float, str]:
        """The state's time and row up to its truth columns."""
        # Python floats (tolist) format as their numpy scalars do, several times faster
        pos, vel, cov = state.pos_n_m, state.vel_n_m_s, state.cov
        p = pos.tolist() if type(pos) is np.ndarray and pos.dtype is _F64 else np.asarray(pos, dtype=float).tolist()
        v = vel.tolist() if type(vel) is np.ndarray and vel.dtype is _F64 else np.asarray(vel, dtype=float).tolist()
        roll, pitch, yaw = quat_to_euler(state.q_nb)
        i, j, k = self._pos_ix
        if type(cov) is np.ndarray and cov.dtype is _F64:
            var_n, var_e, var_d = cov.item(i, i), cov.item(j, j), cov.item(k, k)
        else:
            var_n, var_e, var_d = np.asarray(cov, dtype=float).diagonal()[self._pos].tolist()
        c = state.current_n_m_s
        cn, ce = c.tolist() if type(c) is np.ndarray and c.dtype is _F64 and c.shape == _NE_SHAPE else _current_xy(state)
        t_s = state.t_s
        if type(t_s) is not float:
            t_s = float(t_s)
        # sqrt(max(var, 0.0)) as it was: -0.0 and NaN kept, a negative variance 0
        nums = (t_s, p[0], p[1], p[2], v[0], v[1], v[2], roll, pitch, yaw,
                math.sqrt(var_n) if not var_n < 0.0 else 0.0, math.sqrt(var_e) if not var_e < 0.0 else 0.0,
                math.sqrt(var_d) if not var_d < 0.0 else 0.0, cn, ce, state.k_speed)
        return t_s, (_NAV_FORMAT % nums + (",1," if state.valid else ",0,")
                     + geo_time_text(t_s, p[0], p[1], self.unix_of, self.origin))

    def on_nav(self, state: Any) -> None:
        if self._pending is not None:  # its truth did not come before the next state: none
            self._write(self._pending[1], None)
            self._pending = None
        t_s, row = self._row(state)
        truth = self._last_truth
        if not self.truth or (truth is not None and abs(t_s - truth.t_s) <= self.truth_max_age_s):
            self._write(row, truth)
        else:
            # the runner emits the state of epoch t_k as soon as the IMU reaches t_k, before
            # the truth sample of t_k arrives: hold the row for it
            self._pending = (t_s, row)

    def close(self) -> None:
        if self._pending is not None:
            self._write(self._pending[1], None)
            self._pending = None
        self._file.write("".join(self._rows))
        self._rows.clear()
        self._file.close()


class AidStatusCsvSink(Sink):
    """``aid_status.csv``: one row per :class:`AidStatus` (vectors ``;``-joined)."""

    deferrable = True

    COLUMNS = ("t_s", "source", "fused", "reason", "test_ratio", "observation", "innovation",
               "innovation_variance")

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file = _OutputFile(self.path)
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(self.COLUMNS)
        # (source, fused, reason, vector lengths) → the row's format: a handful of them per run
        self._line_formats: dict[tuple, str] = {}
        # rows joined and written in blocks (see TrajectoryCsvSink)
        self._rows: list[str] = []

    def on_aid(self, statuses: list) -> None:
        formats, rows = self._line_formats, self._rows
        for s in statuses:
            obs, nu, var = s.observation, s.innovation, s.innovation_variance
            key = (s.source, bool(s.fused), s.reason, len(obs), len(nu), len(var))
            try:  # (a subscript, not a get call: ~130k statuses per data hour)
                line = formats[key]
            except KeyError:
                line = formats[key] = self._line_format(*key)
            if line:
                rows.append(line % (s.t_s, s.test_ratio, *obs, *nu, *var))
            else:
                self._file.write("".join(rows))
                rows.clear()
                self._writer.writerow(["%.10g" % s.t_s, s.source, "1" if s.fused else "0", s.reason or "",
                                       "%.10g" % s.test_ratio, _vec(obs), _vec(nu), _vec(var)])
        if len(rows) >= _ROWS_PER_WRITE:
            self._file.write("".join(rows))
            rows.clear()

    @staticmethod
    def _line_format(source: str, fused: bool, reason: str | None, n_obs: int, n_nu: int, n_var: int) -> str:
        """The ``%`` format of a whole row with these fixed fields (what csv.writer writes of it,
        ``%.10g`` being ``format(float(v), ".10g")``); "" when a field needs csv's quoting."""
        reason = reason or ""
        if not (_CSV_SPECIAL.isdisjoint(source) and _CSV_SPECIAL.isdisjoint(reason)):
            return ""
        vec = [";".join(["%.10g"] * n) for n in (n_obs, n_nu, n_var)]
        return ",".join(["%.10g", source.replace("%", "%%"), "1" if fused else "0", reason.replace("%", "%%"),
                         "%.10g", *vec]) + "\n"

    def close(self) -> None:
        self._file.write("".join(self._rows))
        self._rows.clear()
        self._file.close()


class ParamsCsvSink(Sink):
    """``params.csv``: motion parameters over time.

    A first row ``initial`` with the parameters the filter started with, then one row per
    release: ``t_s``, every :class:`~fusion.motion_model.MotionParams` field,
    ``log_likelihood``, ``accepted`` and ``reason`` (why not, when rejected), ``iterations``,
    and the calibrator's sea current ``current_n_m_s``, ``current_e_m_s`` (empty if unknown).
    """

    deferrable = True

    def __init__(self, path: str | Path, initial_params: Any = None) -> None:
        from adaptnav.fusion.motion_model import MotionParams

        self.path = Path(path)
        self.names = tuple(MotionParams().to_dict())
        self._file = _OutputFile(self.path)
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(("t_s",) + self.names + ("log_likelihood", "accepted", "reason", "iterations",
                                                             "current_n_m_s", "current_e_m_s"))
        self._initial = initial_params  # written with the data time of the first input

    def _write_initial(self, t_s: float) -> None:
        d = self._initial.to_dict()
        self._initial = None
        self._writer.writerow([fmt(t_s)] + [fmt(d[n]) for n in self.names] + ["", "1", "initial", "", "", ""])

    def on_first_sample(self, sample: Any) -> None:
        if self._initial is not None:
            self._write_initial(sample.t_s)

    def on_nav(self, state: Any) -> None:
        if self._initial is not None:
            self._write_initial(state.t_s)

    def on_release(self, release: Any) -> None:
        if self._initial is not None:
            self._write_initial(release.t_s)
        d = release.params.to_dict() if release.params is not None else {}
        self._writer.writerow([fmt(release.t_s)] + [fmt(d.get(n)) for n in self.names]
                              + [fmt(release.log_likelihood), fmt(bool(release.accepted)),
                                 str(release.reason or ""), fmt(getattr(release, "iterations", None))]
                              + [fmt(x) for x in (getattr(release, "current_n_m_s", None) or (None, None))])

    def close(self) -> None:
        self._file.close()


# rows a SeriesRecorder's arrays start with (a minute at 10 Hz), doubled when full
_FIRST_ROWS = 600
# a truth row: t, pos (3), vel (3), current n, e, k_v, q_nb (4)
_TRUTH_ROW = 14


class SeriesRecorder(Sink):
    """Keeps the series that metrics and plots need, as growing arrays and compact lists.

    Nav: t, pos, vel, q_nb, (pos, vel, att) covariance 9×9, current, k_speed. Truth: t,
    pos, vel, current, k_v, q_nb. Aid: t, source, fused, test ratio, normalised innovation
    ``ν/√S`` per component. Releases and the initial params. Fused absolute fixes (USBL,
    GNSS) set ``last_fix_t_s``.
    """

    FIX_SOURCES = FIX_KINDS
    sample_kinds = frozenset({"truth"})
    deferrable = True

    def __init__(self, initial_params: Any = None, aid_rows: bool = True) -> None:
        st = _state_slices()
        idx = np.arange(st.N_ERR)
        self._pva = np.r_[idx[st.POS], idx[st.VEL], idx[st.ATT]]
        self._pva_ix = np.ix_(self._pva, self._pva)  # built once: np.ix_ per state cost more than the copy
        a = int(self._pva[0])
        # one block of the covariance (it is: POS, VEL, ATT follow each other): a sliced copy, cheaper
        self._pva_block = (slice(a, a + self._pva.size) if np.array_equal(self._pva, np.arange(a, a + self._pva.size))
                           else None)
        self.nav_t: list[float] = []
        self.nav_k_speed: list[float] = []
        # the nav states' vectors row by row in growing arrays (the first len(nav_t) rows
        # hold data): no array per epoch, and track() is a view
        self._nav_pos = np.empty((_FIRST_ROWS, 3))
        self._nav_vel = np.empty((_FIRST_ROWS, 3))
        self._nav_q = np.empty((_FIRST_ROWS, 4))
        self._nav_cov_pva = np.empty((_FIRST_ROWS, 9, 9))
        self._nav_current = np.empty((_FIRST_ROWS, 2))
        self.truth_rows: list[tuple] = []
        self.aid_rows: list[tuple[float, str, bool, float, tuple]] = []
        self.releases: list[Any] = []
        self.initial_params = initial_params
        self.last_fix_t_s: float | None = None
        self.fused_counts: Counter[str] = Counter()
        self.dvl_lock: list[tuple[float, bool]] = []  # (t, bottom lock) per DVL status
        self.rejected_reasons: Counter[tuple[str, str]] = Counter()  # (source, reason) → count
        # the normalised innovations are for the plots and the report only (``aid_rows=False``:
        # none kept, a replay without either)
        self._keep_aid_rows = bool(aid_rows)

    def _grow(self) -> None:
        for name in ("_nav_pos", "_nav_vel", "_nav_q", "_nav_cov_pva", "_nav_current"):
            old = getattr(self, name)
            new = np.empty((2 * len(old), *old.shape[1:]))
            new[:len(old)] = old
            setattr(self, name, new)

    def on_nav(self, state: Any) -> None:
        nav_t = self.nav_t
        i = len(nav_t)
        if i == len(self._nav_pos):
            self._grow()
        self._nav_pos[i] = state.pos_n_m
        self._nav_vel[i] = state.vel_n_m_s
        self._nav_q[i] = state.q_nb
        cov = np.asarray(state.cov)
        b = self._pva_block
        self._nav_cov_pva[i] = cov[b, b] if b is not None else cov[self._pva_ix]
        c = state.current_n_m_s
        # the estimator's current is a float vector of two: its row as it is (no Python floats between)
        self._nav_current[i] = c if type(c) is np.ndarray and c.shape == _NE_SHAPE else _current_xy(state)
        nav_t.append(float(state.t_s))
        self.nav_k_speed.append(float(state.k_speed))

    def on_sample(self, sample: Any) -> None:
        if sample.KIND == "truth":
            self.truth_rows.append((sample.t_s, *sample.pos_n_m, *sample.vel_n_m_s,
                                    sample.current_n_m_s[0], sample.current_n_m_s[1], sample.k_v,
                                    *sample.q_nb))

    def on_aid(self, statuses: list) -> None:
        keep_rows = self._keep_aid_rows
        for s in statuses:
            source, fused = s.source, s.fused
            if fused:
                self.fused_counts[source] += 1
                if source in self.FIX_SOURCES and (self.last_fix_t_s is None or s.t_s > self.last_fix_t_s):
                    self.last_fix_t_s = float(s.t_s)
            else:
                self.rejected_reasons[(source, s.reason or "unspecified")] += 1
            if source == "dvl":
                self.dvl_lock.append((float(s.t_s), bool(fused or s.reason == "gate")))
            if not keep_rows:
                continue
            # AidStatus carries the diagonal of S (fusion/status.py): ν_i/√S_ii per component
            nu, var = s.innovation, s.innovation_variance
            if len(nu) == len(var):
                normed = tuple(n / math.sqrt(v) if v > 0 else math.nan for n, v in zip(nu, var))
            else:
                normed = (math.nan,) * len(nu)
            self.aid_rows.append((float(s.t_s), s.source, bool(s.fused), float(s.test_ratio), normed))

    def on_release(self, release: Any) -> None:
        self.releases.append(release)

    # -- arrays ------------------------------------------------------------------------
    def track(self) -> TrackArrays:
        """The nav series; its vectors are views of the recorder's arrays (read, do not write)."""
        n = len(self.nav_t)
        return TrackArrays(t_s=np.asarray(self.nav_t, dtype=float), pos_n_m=self._nav_pos[:n],
                           vel_n_m_s=self._nav_vel[:n], q_nb=self._nav_q[:n], cov_pva=self._nav_cov_pva[:n],
                           current_n_m_s=self._nav_current[:n])

    def truth(self) -> TruthArrays | None:
        if len(self.truth_rows) < 2:
            return None
        a = self._truth_table()
        if not np.all(np.diff(a[:, 0]) > 0):  # (a simulation's are: no copies then)
            # sort by time and drop duplicate stamps so interpolation is well defined
            a = a[np.argsort(a[:, 0], kind="stable")]
            keep = np.concatenate([[True], np.diff(a[:, 0]) > 0])
            a = a[keep]
        return TruthArrays(t_s=a[:, 0], pos_n_m=a[:, 1:4], vel_n_m_s=a[:, 4:7], q_nb=a[:, 10:14],
                           current_n_m_s=a[:, 7:9])

    def truth_k_v(self) -> tuple[np.ndarray, np.ndarray]:
        a = self._truth_table()
        return a[:, 0], a[:, 9]

    def _truth_table(self) -> np.ndarray:
        # the rows' floats in one pass (np.asarray of the tuples takes twice as long)
        n = len(self.truth_rows)
        return np.fromiter(itertools.chain.from_iterable(self.truth_rows), float, n * _TRUTH_ROW).reshape(n, _TRUTH_ROW)

    def metrics(self) -> dict:
        truth = self.truth()
        if truth is None:
            return {}
        track = self.track()
        out = compute_metrics(track, truth, self.last_fix_t_s)
        if self.dvl_lock and out:
            a = np.asarray(self.dvl_lock, dtype=float)
            out.update(dvl_outage_metrics(track, truth, a[:, 0], a[:, 1] > 0.5))
        return out


class MetricsSink(Sink):
    """Writes ``metrics.json`` at close when truth was seen (keeps the dict in ``.metrics``)."""

    deferrable = True

    def __init__(self, recorder: SeriesRecorder, path: str | Path) -> None:
        self.recorder = recorder
        self.path = Path(path)
        self.metrics: dict = {}

    def close(self) -> None:
        self.metrics = self.recorder.metrics()
        if self.metrics:
            self.path.write_text(json.dumps(self.metrics, indent=2, sort_keys=True) + "\n")


class PlotSink(Sink):
    """Writes ``track.png``, ``params.png``, ``innovations.png`` into ``out_dir`` at close;
    ``gaps`` — the door's data gaps ``(kind, from_s, to_s)``, filled while the run goes on — are
    shaded on the error plot."""

    def __init__(self, recorder: SeriesRecorder, out_dir: str | Path, title: str = "",
                 gaps: Sequence[tuple[str, float, float]] = ()) -> None:
        self.recorder = recorder
        self.out_dir = Path(out_dir)
        self.title = title
        self.gaps = gaps
        self.written: list[Path] = []

    def close(self) -> None:
        from adaptnav.service.tools import plots

        self.written = plots.write_all(self.recorder, self.out_dir, self.title,
                                       gaps_s=[(a, b) for _, a, b in self.gaps])
