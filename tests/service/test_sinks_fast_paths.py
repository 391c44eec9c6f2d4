"""The replay sinks' fast paths (issue 17) write what the plain formulation writes, byte for byte:
trajectory.csv's rows (cov.item and tolist instead of arrays, one format per row, the truth's
current and k_v text kept from one sample to the next, rows written in blocks), aid_status.csv's
rows in blocks with a csv-quoted row among them, the recorder's current rows, the health fast
path and the aid-consistency tallies. References: plain per-field formatting and the slow paths,
on seeded random and edge inputs (NaN, ±inf, -0.0, negative variances, non-float64 vectors)."""
from __future__ import annotations

import csv
import math
import random

import numpy as np
import pytest

from adaptnav.fusion.frames import GeoOrigin, quat_to_euler
from adaptnav.fusion.state import NavState
from adaptnav.fusion.status import AidStatus
from adaptnav.service.runtime import sinks as sk
from adaptnav.service.runtime.health import Health
from adaptnav.service.runtime.replay import AidConsistency


def _g(v) -> str:
    return "%.10g" % float(v)


def _state(rng, t_s, *, dtype=float, current=None, var=None, valid=True, pos=None):
    cov = np.diag(rng.uniform(0.01, 4.0, 18))
    if var is not None:
        cov[0, 0], cov[1, 1], cov[2, 2] = var
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return NavState(t_s=t_s, pos_n_m=np.asarray(rng.normal(0, 300, 3) if pos is None else pos, dtype=dtype),
                    vel_n_m_s=np.asarray(rng.normal(0, 2, 3), dtype=dtype), q_nb=q,
                    bias_acc_b_m_s2=np.zeros(3), bias_gyro_b_rad_s=np.zeros(3),
                    current_n_m_s=rng.normal(0, 0.2, 2) if current is None else current,
                    k_speed=float(rng.uniform(0.9, 1.1)), cov=cov, valid=valid, reset_counter=0)


class _Truth:
    KIND = "truth"

    def __init__(self, t_s, pos, current, k_v):
        self.t_s, self.pos_n_m, self.current_n_m_s, self.k_v = t_s, pos, current, k_v


def _row_ref(state, origin) -> str:
    """trajectory.csv's row of a state up to its truth columns, field by field."""
    p = np.asarray(state.pos_n_m, dtype=float)
    v = np.asarray(state.vel_n_m_s, dtype=float)
    var = np.asarray(state.cov, dtype=float).diagonal()[:3]
    cur = np.asarray(state.current_n_m_s, dtype=float).ravel()[:2]
    fields = [_g(state.t_s), *map(_g, p), *map(_g, v), *map(_g, quat_to_euler(state.q_nb)),
              *(_g(math.sqrt(max(float(x), 0.0))) for x in var), *map(_g, cur), _g(state.k_speed),
              "1" if state.valid else "0"]
    geo = sk.geo_time_fields(state, None, origin)
    fields += ["", "%.9f" % geo["lat_deg"] if "lat_deg" in geo else "", "%.9f" % geo["lon_deg"] if "lon_deg" in geo else ""]
    return ",".join(fields)


def _truth_ref(truth) -> str:
    if truth is None:
        return "," * 6
    return "," + ",".join(_g(x) for x in (*truth.pos_n_m, truth.current_n_m_s[0], truth.current_n_m_s[1], truth.k_v))


def _calls(seed):
    """States at 10 Hz, each followed by its truth sample (some missing, some late), with edge values."""
    rng = np.random.default_rng(seed)
    calls, k_v = [], 1.0
    cur = (0.07, -0.03, 0.0)
    edges = {3: dict(var=(-0.0, 0.0, 1.0)), 4: dict(var=(math.nan, -1e-9, math.inf)),
             5: dict(dtype=np.float32), 6: dict(dtype=int), 7: dict(current=np.array([[0.1, -0.2, 0.0]])),
             8: dict(current=(-0.0, 0.0)), 9: dict(current=np.array([1, 2])), 10: dict(valid=False),
             11: dict(current=np.array([0.5, 0.25, 0.0])), 12: dict(pos=[math.inf, 0.0, 0.0]),
             13: dict(pos=[math.nan, 1.0, 2.0]), 14: dict(current=np.array([0.1, 0.2], dtype=np.float32))}
    for k in range(700):
        t = round(0.1 * k, 10)
        calls.append(("nav", _state(rng, t, **edges.get(k % 40, {}))))
        if k % 17 == 5:
            continue  # no truth for this state
        if k % 50 == 20:
            k_v = float(rng.uniform(0.8, 1.2))  # a step of k_v
        if k % 90 == 30:
            cur = (-0.0, 0.0, 0.0) if k % 180 == 30 else (float(rng.normal()), float(rng.normal()), 0.0)
        kv = 0.0 if k % 130 == 7 else (-0.0 if k % 130 == 8 else k_v)
        t_truth = t + (0.2 if k % 23 == 4 else 0.0)  # too late to match
        calls.append(("sample", _Truth(t_truth, tuple(rng.normal(0, 300, 3)), cur, kv)))
    return calls


def _expected(calls, origin, max_age_s):
    out, pending, last = [], None, None
    for kind, x in calls:
        if kind == "nav":
            if pending is not None:
                out.append(pending[1] + _truth_ref(None))
                pending = None
            row = _row_ref(x, origin)
            if last is not None and abs(x.t_s - last.t_s) <= max_age_s:
                out.append(row + _truth_ref(last))
            else:
                pending = (x.t_s, row)
        else:
            last = x
            if pending is not None and abs(pending[0] - x.t_s) <= max_age_s:
                out.append(pending[1] + _truth_ref(x))
                pending = None
    if pending is not None:
        out.append(pending[1] + _truth_ref(None))
    return out


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_origin", [True, False])
def test_trajectory_rows_are_the_plain_fields(tmp_path, seed, with_origin):
    origin = GeoOrigin(math.radians(43.0), math.radians(5.9)) if with_origin else None
    calls = _calls(seed)
    sink = sk.TrajectoryCsvSink(tmp_path / "t.csv", truth=True, truth_max_age_s=0.05, origin=origin)
    for kind, x in calls:
        (sink.on_nav if kind == "nav" else sink.on_sample)(x)
    sink.close()
    lines = (tmp_path / "t.csv").read_text().split("\n")
    assert lines[0] == ",".join(sk.TrajectoryCsvSink.COLUMNS + sk.TrajectoryCsvSink.TRUTH_COLUMNS)
    assert lines[-1] == ""
    want = _expected(calls, origin, 0.05)
    assert len(lines[1:-1]) == len(want) > 2 * sk._ROWS_PER_WRITE
    for got, exp in zip(lines[1:-1], want):
        assert got == exp


def test_trajectory_rows_without_truth_and_with_a_unix_clock(tmp_path):
    origin = GeoOrigin(math.radians(-12.5), math.radians(130.8))
    rng = np.random.default_rng(5)
    states = [_state(rng, 0.1 * k, var=(-0.0, math.nan, -2.0) if k == 3 else None) for k in range(300)]
    sink = sk.TrajectoryCsvSink(tmp_path / "t.csv", truth=False, origin=origin, unix_of=lambda t: 1.7e9 + t)
    for s in states:
        sink.on_nav(s)
    sink.close()
    lines = (tmp_path / "t.csv").read_text().split("\n")[1:-1]
    for got, s in zip(lines, states, strict=True):
        want = _row_ref(s, origin).split(",")
        want[17] = "%.6f" % (1.7e9 + s.t_s)
        assert got == ",".join(want)


def test_aid_status_rows_in_blocks_keep_their_order_around_a_quoted_row(tmp_path):
    rng = random.Random(3)
    statuses = []
    for k in range(3 * sk._ROWS_PER_WRITE + 17):
        n = rng.choice([0, 1, 3])
        reason = "" if k % 7 else rng.choice(["gate", "invalid", "odd, quoted", None])
        fused = rng.choice([True, False, 1, 0, np.bool_(True), np.bool_(False)]) if reason == "" else False
        vec = tuple(rng.choice([rng.gauss(0, 1), -0.0, math.nan, math.inf]) for _ in range(n))
        statuses.append(AidStatus(0.1 * k, rng.choice(["dvl", "depth", "heading"]), vec, vec, vec,
                                  rng.choice([rng.random(), math.nan]), fused, reason))
    sink = sk.AidStatusCsvSink(tmp_path / "a.csv")
    for k in range(0, len(statuses), 3):
        sink.on_aid(statuses[k:k + 3])
    sink.close()
    with open(tmp_path / "a.csv", newline="") as f:
        rows = list(csv.reader(f))[1:]
    assert len(rows) == len(statuses)
    for s, row in zip(statuses, rows):
        vec = ";".join(_g(v) for v in s.observation)
        assert row == [_g(s.t_s), s.source, "1" if s.fused else "0", s.reason or "", _g(s.test_ratio), vec, vec, vec]


@pytest.mark.parametrize("current", [np.array([0.25, -0.5]), np.array([0.1, 0.2], dtype=np.float32),
                                     np.array([3, -4]), np.array([0.5, 0.25, 1.0]), np.array([[0.5, -0.25]]),
                                     (0.75, -0.125, 0.0), np.array([-0.0, math.nan])])
def test_recorder_current_rows_are_the_first_two_components(current):
    rec = sk.SeriesRecorder(aid_rows=False)
    rng = np.random.default_rng(1)
    rec.on_nav(_state(rng, 0.0, current=current))
    got = rec.track().current_n_m_s[0]
    want = np.asarray(current, dtype=float).ravel()[:2]
    assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))


class _SlowHealth(Health):
    """Health without its fast path: every finite sample through _SensorStats.add."""

    def on_sample(self, kind, t_s, n=1):
        stats = self._sensors.get(kind)
        if stats is not None:
            stats.last_bucket_end_s = -math.inf  # no bucket to add to in place
        super().on_sample(kind, t_s, n)


def test_health_fast_path_counts_as_the_slow_path():
    rng = random.Random(7)
    fast, slow = Health(), _SlowHealth()
    t = 100.0
    for k in range(5000):
        r = rng.random()
        if r < 0.02:
            s = rng.choice([math.nan, math.inf, -math.inf])
        elif r < 0.06:
            s = t - rng.uniform(0, 3)  # late
        elif r < 0.08:
            s = float(math.floor(t) + 1)  # exactly on the next second
        else:
            t += rng.choice([0.0, 0.01, 0.1, 0.7, 2.5])
            s = t
        kind = rng.choice(["imu", "dvl", "depth"])
        n = rng.choice([1, 1, 1, 40])
        for h in (fast, slow):
            h.on_sample(kind, s, n)
        if k % 1000 == 999:
            for h in (fast, slow):
                h.shift_time(-37.5)
            t -= 37.5
        if k % 5 == 0:  # (often: right after a shift too)
            assert fast.report() == slow.report()
    assert fast.report() == slow.report()
    for kind, s in slow._sensors.items():
        assert list(fast._sensors[kind].buckets) == list(s.buckets)


def test_aid_consistency_tallies_as_per_status_dicts():
    rng = random.Random(11)
    gate = {1: 10.83, 2: 13.82, 3: 16.27}
    statuses = []
    for k in range(3000):
        m = rng.choice([0, 1, 2, 3])
        fused = rng.random() < 0.7
        reason = "" if fused else rng.choice(["gate", "invalid", None, ""])
        ratio = rng.choice([rng.uniform(0, 2), math.nan, math.inf, 0.0])
        statuses.append(AidStatus(0.1 * k, rng.choice(["dvl", "usbl", "heading"]), (0.0,) * m, (0.1,) * m,
                                  (1.0,) * m, ratio, fused, reason))
    c = AidConsistency(lambda m: gate[m])
    for k in range(0, len(statuses), 4):
        c.on_aid(statuses[k:k + 4])
    want: dict = {}
    for s in statuses:
        a = want.setdefault(s.source, {"attempts": 0, "fused": 0, "refused": {}, "tested": 0, "sum": 0.0, "in": 0})
        a["attempts"] += 1
        if s.fused:
            a["fused"] += 1
        else:
            a["refused"][s.reason or "unspecified"] = a["refused"].get(s.reason or "unspecified", 0) + 1
        m = len(s.innovation)
        if (s.fused or s.reason == "gate") and m and math.isfinite(s.test_ratio):
            nis = s.test_ratio * gate[m]
            a["tested"] += 1
            a["sum"] += nis / m
            a["in"] += nis <= c._chi2(0.95, m)
    got = c.report()
    assert sorted(got) == sorted(want)
    for source, a in want.items():
        n = a["tested"]
        assert got[source] == {"attempts": a["attempts"], "fused": a["fused"], "refused": dict(sorted(a["refused"].items())),
                               "tested": n, "nis_per_dof_mean": a["sum"] / n if n else None,
                               "within_95": a["in"] / n if n else None}
