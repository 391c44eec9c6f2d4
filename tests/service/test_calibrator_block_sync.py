"""``ProcessBackend.sync`` waits for the child's side products only up to the ping that
completes its next block (the only sample a product can come from) and for its releases only
up to ``t − L``: whatever the child's speed, every poll returns what the in-process
calibrator's returns (the release rule does not depend on timing). The child here is the
real child loop (``_lagged_child_main``) in a thread over real pipes, with a scripted
calibrator whose blocks, releases and bursts of work are random."""
from __future__ import annotations

import math
import multiprocessing
import os
import random
import threading
from multiprocessing.connection import Connection

import pytest

from adaptnav.calibration.online import Release
from adaptnav.calibration.sidescan import ObjectBatch
from adaptnav.fusion.motion_model import MotionParams
from adaptnav.service.calibrator import lagged
from adaptnav.service.calibrator.lagged import InlineBackend, LaggedCalibrator, ProcessBackend


class Sample:
    """A sample of the runner's stream (pickled whole across the pipe)."""

    def __init__(self, t_s, kind):
        self.t_s, self.KIND = t_s, kind


class ScriptedCalibrator:
    """Side products only at the ping that completes a block (as the object front end: a
    rejected ping does not count), releases at random samples, random bursts of work."""

    def __init__(self, seed):
        self.rng = random.Random(seed)
        self.out, self.taken, self.next_block = [], 0, None
        self.seen, self.blocks_at = 0, []  # samples observed; the index of each block's ping

    def observe(self, sample):
        rng = self.rng
        self.seen += 1
        if rng.random() < 0.02:  # a burst (an EM window, a detector block): the child falls behind
            sum(range(rng.randrange(20000, 200000)))
        if sample.KIND == "sonar":
            if self.next_block is None:
                self.next_block = rng.randrange(3, 30)
            if rng.random() < 0.1:  # rejected: does not count toward the block
                return
            self.taken += 1
            if self.taken == self.next_block:
                self.blocks_at.append(self.seen - 1)
                self.next_block += rng.randrange(3, 30)
                if rng.random() < 0.8:  # (a block without objects has no batch)
                    self.out.append(ObjectBatch(sample.t_s, ()))
        elif rng.random() < 0.01:
            self.out.append(Release(sample.t_s, MotionParams(), 0.0, True, "ok", 1))

    def pings_to_block(self):
        return None if self.next_block is None else self.next_block - self.taken

    def poll(self):
        out, self.out = self.out, []
        return out

    def finish(self):
        pass


class _ThreadProcess(threading.Thread):
    exitcode = None
    pid = os.getpid()

    def __init__(self, target, name, daemon, args):
        # the child's ends of the pipes duplicated: the parent closes its copies once started
        *head, conn_in, conn_out = args
        args = (*head, Connection(os.dup(conn_in.fileno()), writable=False),
                Connection(os.dup(conn_out.fileno()), readable=False))
        super().__init__(target=target, name=name, daemon=daemon, args=args)


class _ThreadContext:
    """multiprocessing's context as ProcessBackend uses it, the child a thread of this process."""

    Pipe = staticmethod(multiprocessing.Pipe)
    Process = _ThreadProcess


@pytest.fixture
def child_in_a_thread(monkeypatch):
    monkeypatch.setattr(lagged.mp, "get_context", lambda method: _ThreadContext())
    monkeypatch.setattr(lagged, "ignore_sigint", lambda: None)  # (a thread cannot set handlers)
    monkeypatch.setattr(lagged, "keep_freed_heap", lambda: None)
    monkeypatch.setattr(lagged.gc, "freeze", lambda: None)
    monkeypatch.setattr(lagged, "make_calibrator", lambda cfg, params0, seed: ScriptedCalibrator(seed))


def _stream(seed, jumps, n=3000):
    """Samples at irregular times (repeats, late and NaN times); side-scan pings from the
    300th on; ``jumps``: {sample index: clock jump before it (s)}."""
    rng = random.Random(seed)
    t = 1000.0
    for i in range(n):
        t += rng.choice([0.0, 0.05, 0.1, 0.1, 0.37, 2.0])
        r = rng.random()
        ts = math.nan if r < 0.005 else t - 3.0 if r < 0.02 else t
        kind = "sonar" if i >= 300 and rng.random() < 0.3 else "rpm"
        yield i, Sample(ts, kind), jumps.get(i, 0.0)


def _replay(backend, seed, runner_burst, jumps):
    """A runner's loop: poll after every sample unless below ``quiet_until_s``; what each poll
    returned, by sample."""
    cal = LaggedCalibrator(backend, 60.0, 5.0)
    rng = random.Random(seed + 7)
    got, data_t = [], -math.inf
    try:
        for i, sample, jump in _stream(seed, jumps):
            if jump:
                cal.shift_time(jump)
                data_t += jump
            cal.observe(sample)
            if sample.t_s > data_t:
                data_t = sample.t_s
            if runner_burst and rng.random() < 0.02:
                sum(range(rng.randrange(20000, 200000)))
            if not data_t < cal.quiet_until_s:
                got += [(i, o.KIND, o.t_s) for o in cal.poll(data_t)]
        got += [(-1, o.KIND, o.t_s) for o in cal.poll(math.inf)]
    finally:
        cal.close()
    return got


@pytest.mark.parametrize("seed", range(4))
def test_each_poll_returns_what_the_in_process_calibrator_returns(child_in_a_thread, seed):
    # clock jumps right after a block's ping (sent, perhaps not yet processed by the child)
    # and elsewhere: where blocks complete does not depend on the times
    scripted = ScriptedCalibrator(seed)
    _replay(InlineBackend(scripted), seed, False, {})
    blocks = scripted.blocks_at
    jumps = {blocks[5] + 1: -200.0, blocks[20] + 1: 150.0, blocks[35] + 1: -30.0, 2000: -200.0}
    expected = _replay(InlineBackend(ScriptedCalibrator(seed)), seed, False, jumps)
    assert sum(k == "sonar_objects" for _, k, _ in expected) > 20
    assert sum(k == "calibration_release" for _, k, _ in expected) > 5
    for runner_burst in (False, True):
        backend = ProcessBackend(None, MotionParams(), seed, batch_size=64, start_method="thread")
        assert _replay(backend, seed, runner_burst, jumps) == expected

