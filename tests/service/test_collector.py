"""The live daemon's garbage-collector pacing (service/runtime/collector.py), against CPython's
own collector observed through ``gc.callbacks``."""
import gc
import weakref

import pytest

from adaptnav.service.runtime.collector import CollectorPacing


@pytest.fixture
def collector_settings():
    """The process's thresholds and a record of every collection (generation), restored after."""
    thresholds = gc.get_threshold()
    seen: list[int] = []

    def record(phase, info):
        if phase == "start":
            seen.append(info["generation"])

    gc.collect()
    gc.callbacks.append(record)
    try:
        yield seen
    finally:
        gc.callbacks.remove(record)
        gc.set_threshold(*thresholds)


class _Node:
    pass


def test_freeze_collects_garbage_first_then_freezes_the_living(collector_settings):
    pacing = CollectorPacing()
    cycle = _Node()
    cycle.self = cycle  # garbage only a collection frees
    gone = weakref.ref(cycle)
    del cycle
    try:
        frozen = pacing.freeze()
        assert gone() is None, "garbage frozen: it would never be freed"
        assert frozen == gc.get_freeze_count() > 0
        assert pacing.report()["frozen_objects"] == frozen
    finally:
        pacing.stop()
    assert gc.get_freeze_count() == 0, "stop() gives the frozen objects back"


def test_after_output_collects_only_past_the_young_fraction(collector_settings):
    seen = collector_settings
    gc.set_threshold(700, 10, 10)
    pacing = CollectorPacing(young_fraction=0.5)
    gc.collect(0)
    keep = [[] for _ in range(100)]  # well under half the threshold
    seen.clear()
    assert pacing.after_output() is None
    assert seen == []
    keep += [[] for _ in range(400)]  # past half, not yet the threshold itself
    assert not seen, "CPython collected on its own before the test could"
    assert pacing.after_output() == 0
    assert seen == [0]
    assert gc.get_count()[0] < 50
    assert pacing.counts["paced_0"] == 1 and pacing.counts["automatic_0"] == 0


def test_due_generation_is_the_one_cpython_collects(collector_settings):
    """At each of CPython's own collections (its callback's start, the counts as CPython
    read them), due_generation() names the generation CPython collects (full collections
    kept out: CPython also waits for long-lived objects there, which Python does not expose)."""
    gc.set_threshold(40, 3, 10**6)
    pacing = CollectorPacing(young_fraction=1.0)
    pairs = []

    def at_start(phase, info):
        if phase == "start":
            pairs.append((info["generation"], pacing.due_generation()))

    gc.collect()
    gc.callbacks.append(at_start)
    try:
        keep = [[] for _ in range(40 * 60)]
    finally:
        gc.callbacks.remove(at_start)
    del keep
    assert len(pairs) > 40
    assert all(cpython == ours for cpython, ours in pairs), pairs
    assert {cpython for cpython, _ in pairs} == {0, 1}


def test_paced_and_automatic_collections_are_told_apart(collector_settings):
    gc.set_threshold(50, 1000, 1000)
    pacing = CollectorPacing(young_fraction=0.2)
    pacing.start()
    try:
        keep = [[] for _ in range(500)]  # CPython collects by itself about ten times
        assert pacing.counts["automatic_0"] >= 5
        automatic = pacing.counts["automatic_0"]
        gc.collect(0)
        keep += [[] for _ in range(15)]
        assert pacing.after_output() == 0
        assert pacing.counts["paced_0"] == 1
        assert pacing.counts["automatic_0"] == automatic + 1  # the explicit gc.collect(0) above
    finally:
        pacing.stop()
    keep += [[] for _ in range(200)]
    assert pacing.counts["automatic_0"] == automatic + 1, "stop() ends the counting"
    del keep


def test_pacing_at_ten_hertz_leaves_cpython_nothing_to_collect(collector_settings):
    """The daemon's case: ~60 containers between two outputs that only a collection frees
    (reference cycles), the pacing after each: CPython never reaches its own threshold."""
    gc.set_threshold(700, 10, 10)
    pacing = CollectorPacing()
    pacing.start()
    try:
        for _ in range(400):
            for _ in range(60):
                cycle = []
                cycle.append(cycle)
            del cycle
            pacing.after_output()
        report = pacing.report()
    finally:
        pacing.stop()
    assert [report[f"automatic_{g}"] for g in range(3)] == [0, 0, 0], report
    assert report["paced_0"] > 40 and report["paced_1"] > 3


def test_young_fraction_is_checked():
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError):
            CollectorPacing(young_fraction=bad)
