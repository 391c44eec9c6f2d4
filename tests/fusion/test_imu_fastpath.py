"""The compiled path of an IMU run (Estimator._fast_imu, kalman.ins_run: the check, the
propagation to the learned velocity's epochs, the free-inertial bookkeeping, the stationary
window and the state guard in one call) against the general one (Estimator._imu) on a seeded
simulated mission: the same numbers bit for bit — the whole core array, every status, the
free-inertial integral the calibrator reads — also where it hands a run back (a gap, a sample
not finite) and over a rest on deck (zero-velocity updates), in whole and in small batches."""
import numpy as np
import pytest

from adaptnav.fusion import eskf
from adaptnav.fusion.config import FilterConfig
from adaptnav.fusion.eskf import Estimator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import ImuBatch, ImuSample

from .mission import ORIGIN, make_mission, run
from .test_aid_fastpath import assert_same_filter


def _mission():
    # on deck (depth 0) and at rest for 20 s — the stationary windows' updates — then under way,
    # the learned velocity at 2 Hz (its epochs inside the IMU runs)
    m = make_mission(np.random.default_rng(23), 90.0, depth_m=0.0, static_s=20.0, usbl_period_s=None,
                     heading_period_s=0.2, depth_period_s=0.2)
    keep = ~((m.t_imu > 50.0) & (m.t_imu < 50.6))  # an IMU gap (imu_gap_s): coasted through
    m.t_imu, m.f_b, m.w_b = m.t_imu[keep], m.f_b[keep].copy(), m.w_b[keep].copy()
    m.w_b[np.searchsorted(m.t_imu, 70.0), 1] = np.nan  # a sample not finite: refused
    return m


class _Singles:
    """Feeds the estimator each IMU sample of a batch as an ImuSample (live, the daemon's
    epoch sample)."""

    def __init__(self, est):
        self.est = est

    def process(self, sample):
        if sample.KIND != "imu_batch":
            return self.est.process(sample)
        out = []
        for t, f, w in zip(sample.t_s.tolist(), sample.specific_force_b_m_s2.tolist(), sample.omega_b_rad_s.tolist()):
            out += self.est.process(ImuSample(t, tuple(f), tuple(w)))
        return out


def _run(m, fast: bool, max_batch, keep_history: bool):
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    est.keep_history = keep_history  # False (a replay): the kernel checks the run itself
    if not fast:
        del est._fast[ImuBatch], est._fast[ImuSample]
    _, statuses = run(_Singles(est) if max_batch == 1 else est, m, max_batch=max_batch)
    return est, statuses


@pytest.mark.parametrize("keep_history", [True, False])
@pytest.mark.parametrize("max_batch", [None, 7, 1])  # 1: single ImuSamples
def test_the_compiled_imu_path_gives_the_general_paths_numbers(monkeypatch, max_batch, keep_history):
    m = _mission()
    slow, slow_statuses = _run(m, False, max_batch, keep_history)
    firsts = []
    kernel = eskf.kalman.ins_run
    # (the compiled path's first call of a run: with the stationary window, which the general path keeps itself)
    monkeypatch.setattr(eskf.kalman, "ins_run", lambda *a: (firsts.append(a[3] == 0 and a[11] >= 0) or kernel(*a)))
    fast, fast_statuses = _run(m, True, max_batch, keep_history)
    assert sum(firsts) > 400  # the runs checked and propagated by the compiled path
    # what it hands back happened, and what it does itself: rest updates, learned velocity
    assert fast.rejected["imu_gap"] == 1 and fast.rejected["non_finite"] == 1
    assert fast.zero_velocity_updates >= 4
    assert sum(s.source == "learned_velocity" for s in fast_statuses) > 60
    assert_same_filter(fast, fast_statuses, slow, slow_statuses)
    assert fast._inertial_n.tobytes() == slow._inertial_n.tobytes()
    assert fast._st.tobytes() == slow._st.tobytes()
    assert fast.inertial_velocity() == slow.inertial_velocity()


def test_a_piece_is_propagate_core_and_the_free_inertial_arithmetic():
    """kalman.ins_run's piece against what it replaced: kalman.propagate_core over the same
    samples, then the free-inertial integral's Python arithmetic — bit for bit, through and
    not through a learned-velocity epoch."""
    m = make_mission(np.random.default_rng(5), 20.0, usbl_period_s=None)
    est = Estimator(FilterConfig(), MotionParams(), RpmSpeedTable(), ORIGIN)
    run(est, m)  # a filter under way: a state, a covariance, accumulators
    rng = np.random.default_rng(6)
    t0 = float(est._clock[0])
    t = t0 + np.cumsum(rng.uniform(0.008, 0.012, size=12))
    f = rng.normal(size=(12, 3)) + [0.0, 0.0, -9.8]
    w = rng.normal(size=(12, 3)) * 0.05
    for next_lv_t in (t[-1] + 1.0, float(t[4]), 0.5 * float(t[6] + t[7])):
        inertial = rng.normal(size=6)
        core, ref = est._core.copy(), est._core.copy()
        got_inertial = inertial.copy()
        stop, lv_due, _, _ = eskf.kalman.ins_run(t, f, w, 0, core, est._qdiag, 0.1, next_lv_t, got_inertial, 0.0,
                                                 np.zeros(9), -1.0, 100.0)
        expected_stop = min(int(np.searchsorted(t, next_lv_t, side="right")), t.size) or 1
        assert stop == (t.size if next_lv_t > t[-1] else expected_stop)
        x = ref[eskf.kalman.CORE_X]
        q = x[:6].tolist()
        clock0 = float(ref[eskf.kalman.CORE_CLOCK][0])
        eskf.kalman.propagate_core(t[:stop], f[:stop], w[:stop], ref, est._qdiag, 0.1)
        dt = float(ref[eskf.kalman.CORE_CLOCK][0]) - clock0
        p, v = inertial[:3].tolist(), inertial[3:].tolist()
        for i in range(3):
            p[i] += (x[i] - q[i]) + (v[i] - q[3 + i]) * dt
        for i in range(3):
            v[i] += x[3 + i] - q[3 + i]
        assert core.tobytes() == ref.tobytes()
        assert got_inertial.tobytes() == np.array(p + v).tobytes()
        assert lv_due == (next_lv_t <= t[-1] and float(t[stop - 1]) >= next_lv_t)
