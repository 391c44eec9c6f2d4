"""The simulator's replay stream (SimResult.iter_blocks) and SimSource's counters, against the
plain formulation: every sample merged by ``replay_order_key``, IMU runs built by ImuBatch's own
constructor, and the counters kept per item handed out — after a whole iteration, after
every stop part way, and summed over repeated iterations."""
from __future__ import annotations

import pickle
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.samples import ImuBatch, replay_order_key
from adaptnav.service.runtime.sources import NAV_STREAMS, SimSource, simulate
from adaptnav.sim.scenario import load_scenario


@pytest.fixture(scope="module")
def sim30():
    scenario = load_scenario("short", ["duration_s=30"])
    return scenario, simulate(scenario)


def _reference_blocks(result) -> list:
    """IMU runs between the other samples, from one merge of every sample in replay order."""
    keyed = [(replay_order_key(s, i), s) for i, s in
             enumerate(s for kind in sorted(result.samples) for s in result.samples[kind])]
    t_imu = result.imu.t_s
    out, start = [], 0
    for _, s in sorted(keyed, key=lambda ks: ks[0][:2] + (ks[0][2],)):
        stop = int(np.searchsorted(t_imu, s.t_s, side="right"))
        if stop > start:
            out.append(ImuBatch(t_imu[start:stop], result.imu.specific_force_b_m_s2[start:stop],
                                result.imu.omega_b_rad_s[start:stop]))
            start = stop
        out.append(s)
    if start < len(t_imu):
        out.append(ImuBatch(t_imu[start:], result.imu.specific_force_b_m_s2[start:],
                            result.imu.omega_b_rad_s[start:]))
    return out


def _same_stream(items, reference) -> None:
    assert len(items) == len(reference)
    for a, b in zip(items, reference):
        if isinstance(b, ImuBatch):
            assert type(a) is ImuBatch and vars(a).keys() == vars(b).keys()
            assert pickle.dumps(a) == pickle.dumps(b)  # what the calibrator child is sent
            assert a.t_s.base is b.t_s.base  # views of the simulated arrays, no copies
        else:
            assert a is b


def _counted(items) -> tuple[int, Counter]:
    """The counters the source kept per item before: (messages read, by kind in first-seen order)."""
    by_kind: Counter = Counter()
    for item in items:
        if isinstance(item, ImuBatch):
            by_kind["imu"] += len(item)
        else:
            by_kind[item.KIND] += 1
    return sum(by_kind.values()), by_kind


def test_blocks_are_the_merged_stream(sim30):
    _, result = sim30
    _same_stream(list(result.iter_blocks()), _reference_blocks(result))


def test_a_kind_list_of_mixed_kinds_and_unknown_priority(sim30):
    # the order keys on each sample's own KIND, not the list it is in
    _, result = sim30
    mixed = dict(result.samples)
    mixed["depth"] = sorted(mixed["depth"] + mixed.pop("heading"), key=lambda s: s.t_s)
    changed = replace(result, samples=mixed)
    _same_stream(list(changed.iter_blocks()), _reference_blocks(changed))


@pytest.mark.parametrize("stop_after", [0, 1, 2, 3, 7, 50, 333, -2, -1, None])
def test_counters_of_a_stopped_iteration(sim30, stop_after):
    scenario, result = sim30
    src = SimSource(scenario, result)
    items = []
    it = iter(src)
    total = len(_reference_blocks(result))
    n = total if stop_after is None else stop_after % total if stop_after < 0 else stop_after
    for _ in range(n):
        items.append(next(it))
        messages, by_kind = _counted(items)
        if len(items) in (1, 2, 3, n) or len(items) % 97 == 0:
            c = src.counters
            assert c.messages_read == c.samples == messages
            assert list(c.by_kind.items()) == list(by_kind.items())  # counts and first-seen order
    messages, by_kind = _counted(items)
    assert src.report_counters()["messages_read"] == messages
    assert src.missing == [k for k in NAV_STREAMS if k not in by_kind]


def test_counters_add_up_over_iterations(sim30):
    scenario, result = sim30
    src = SimSource(scenario, result)
    whole = list(src)
    part = []
    for item in src:
        part.append(item)
        if len(part) == 123:
            break
    messages, by_kind = _counted(whole + part)
    assert src.counters.messages_read == messages and src.counters.by_kind == by_kind


def test_stream_without_imu_before_the_others(sim30):
    # the IMU's first run after every other sample (its by-kind place last)
    scenario, result = sim30
    late = replace(result, imu=ImuBatch(result.imu.t_s + 1e3, result.imu.specific_force_b_m_s2,
                                        result.imu.omega_b_rad_s))
    src = SimSource(scenario, late)
    items = list(src)
    _same_stream(items, _reference_blocks(late))
    assert list(src.counters.by_kind.items()) == list(_counted(items)[1].items())
    empty = replace(result, imu=ImuBatch(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))), samples={})
    src = SimSource(scenario, empty)
    assert list(src) == [] and src.counters.messages_read == 0 and not src.counters.by_kind


def test_first_seen_order_when_a_kind_starts_after_the_first_imu_run(sim30):
    # depth at t=0, then the IMU's first run, then the first heading: imu before heading
    scenario, result = sim30
    later = replace(result, samples={"depth": result.samples["depth"][:1], "heading": result.samples["heading"][1:]})
    src = SimSource(scenario, later)
    items = list(src)
    _same_stream(items, _reference_blocks(later))
    assert list(src.counters.by_kind) == ["depth", "imu", "heading"] == list(_counted(items)[1])


class _StandIn:
    """A result that is not a SimResult: its own iter_blocks, without a progress record."""

    def __init__(self, result) -> None:
        self._result = result

    def iter_blocks(self):
        yield from self._result.iter_blocks()


def test_a_stand_in_result_counted_item_by_item(sim30):
    scenario, result = sim30
    src = SimSource(scenario, _StandIn(result))
    items = []
    for item in src:
        items.append(item)
        if len(items) == 77:
            break
    messages, by_kind = _counted(items)
    assert src.counters.messages_read == messages and list(src.counters.by_kind.items()) == list(by_kind.items())
    src.result = result  # then a SimResult's iteration adds to it
    items += list(src)
    messages, by_kind = _counted(items)
    assert src.counters.messages_read == messages and src.counters.by_kind == by_kind
