"""``DeferredSinks`` (replay: the sinks' work done while the runner waits for its calibrator
child): every sink gets the same calls in the same order as called directly, only the kinds
of samples it wants, everything before it is closed; the runner sees only the methods some
sink has."""
from __future__ import annotations

from types import SimpleNamespace

from adaptnav.service.runtime.sinks import DeferredSinks, Sink, sink_methods


class _Recording(Sink):
    deferrable = True

    def __init__(self, log, name, kinds=None):
        self.log, self.name = log, name
        self.sample_kinds = kinds

    def on_nav(self, state):
        self.log.append((self.name, "nav", state))

    def on_aid(self, statuses):
        self.log.append((self.name, "aid", statuses))

    def on_sample(self, sample):
        self.log.append((self.name, "sample", sample.t_s))

    def close(self):
        self.log.append((self.name, "close", None))


def _feed(target, work=None):
    for i in range(300):
        target.on_nav(i)
        target.on_aid((i, "depth"))
        target.on_sample(SimpleNamespace(KIND="truth" if i % 3 == 0 else "depth", t_s=float(i)))
        if work is not None and i % 7 == 0:
            work(5)  # the runner waited: a slice of the queued calls
    target.close()


def test_the_same_calls_in_the_same_order_and_all_before_close():
    direct, deferred = [], []

    class _Direct:
        def __init__(self, sinks):
            self.sinks = sinks

        def __getattr__(self, name):  # what the runner does: each sink's method in turn
            def call(arg):
                for s in self.sinks:
                    if name != "on_sample" or s.sample_kinds is None or arg.KIND in s.sample_kinds:
                        getattr(s, name)(arg)
            return call

        def close(self):
            for s in self.sinks:
                s.close()

    _feed(_Direct([_Recording(direct, "a"), _Recording(direct, "b", frozenset({"truth"}))]))
    d = DeferredSinks([_Recording(deferred, "a"), _Recording(deferred, "b", frozenset({"truth"}))], max_pending=50)
    _feed(d, d.work)
    assert deferred == direct
    assert ("b", "sample", 1.0) not in deferred  # only the kinds it wants


def test_calls_wait_until_there_is_time_for_them():
    log = []
    d = DeferredSinks([_Recording(log, "a")])
    d.on_nav(1)
    assert log == []
    assert d.work() is True and log == [("a", "nav", 1)]
    assert d.work() is False


def test_the_runner_sees_only_what_some_sink_has():
    class _NavOnly(Sink):
        def on_nav(self, state):
            pass

    d = DeferredSinks([_NavOnly()])
    assert len(sink_methods([d], "on_nav")) == 1
    # no sink takes the free-inertial velocity: the runner must not compute it for nothing
    assert sink_methods([d], "on_inertial") == []
    assert sink_methods([d], "on_sample") == []


def test_the_first_sample_goes_once_and_other_kinds_are_not_offered():
    """``on_first_sample`` (params.csv's initial row): the first sample only, deferred like the
    rest; a DeferredSinks whose sinks want truth only is not handed other kinds at all."""
    log = []

    class _First(Sink):
        deferrable = True

        def on_first_sample(self, sample):
            log.append(("first", sample.t_s))

    d = DeferredSinks([_First(), _Recording(log, "b", frozenset({"truth"}))])
    assert d.sample_kinds == frozenset({"truth"})
    assert len(sink_methods([d], "on_first_sample")) == 1
    d.on_first_sample(SimpleNamespace(KIND="depth", t_s=1.0))
    assert log == []
    d.close()
    assert log == [("first", 1.0), ("b", "close", None)]
    assert DeferredSinks([_Recording(log, "a"), _Recording(log, "b", frozenset({"truth"}))]).sample_kinds is None


def test_the_runner_hands_the_first_sample_once(tmp_path):
    from adaptnav.fusion.samples import DepthSample, HeadingSample
    from adaptnav.service.runtime.clock import LogClock
    from adaptnav.service.runtime.runner import run

    firsts = []

    class _First(Sink):
        def on_first_sample(self, sample):
            firsts.append(sample.t_s)

    class _Quiet:  # an estimator that takes everything and says nothing
        initialized = False
        rejected = {}

        def process(self, sample):
            return []

    run([DepthSample(1.0, 101325.0), HeadingSample(1.5, 0.0), DepthSample(2.0, 101325.0)], _Quiet(), [_First()],
        LogClock())
    assert firsts == [1.0]
