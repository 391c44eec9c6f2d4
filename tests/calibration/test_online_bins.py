"""OnlineCalibrator's control and DVL bins: the IMU batch's yaw-rate sum taken from its finite
test (ndarray.sum's own numbers, the masked batch's recomputed), bins created once per step and
added to after (not rebuilt per sample)."""
from __future__ import annotations

import math

import numpy as np

from adaptnav.calibration.online import CalibratorConfig, OnlineCalibrator
from adaptnav.fusion.motion_model import MotionParams, RpmSpeedTable
from adaptnav.fusion.samples import DvlSample, HeadingSample, ImuBatch, RpmSample, UsblSample

STEP_S = 5.0
CONFIG = CalibratorConfig(window_steps=96, step_s=STEP_S, period_steps=12, min_window_steps=24, em_iterations=1,
                          n_particles=50, n_smoothed=10, origin_lat_deg=43.0, origin_lon_deg=5.0,
                          model_step_s=STEP_S)


def _started(t0_s=100.0):
    cal = OnlineCalibrator(CONFIG, MotionParams(), RpmSpeedTable(), np.random.default_rng(3))
    cal.observe(HeadingSample(t0_s - 0.5, 0.2))
    cal.observe(UsblSample(t0_s, math.radians(43.0), math.radians(5.0), 10.0, 2.0))
    assert cal._t0 == t0_s
    return cal


def _batch(t, wz):
    t = np.asarray(t, float)
    return ImuBatch(t, np.zeros((t.size, 3)), np.column_stack([np.zeros(t.size), np.zeros(t.size), wz]))


def test_imu_batches_add_their_numpy_sums_to_the_step_bins():
    rng = np.random.default_rng(17)
    cal = _started()
    want: dict[int, list] = {}
    t = 100.0
    for j in range(40):
        n = int(rng.integers(1, 30)) if j < 39 else 9
        ts = t + np.cumsum(rng.uniform(0.001, 0.01, n))
        if j == 39:  # the last, masked, inside the step still open
            ts = (math.floor((t - 100.0) / STEP_S) + 1.0) * STEP_S + 100.1 + 0.01 * np.arange(n)
        wz = rng.normal(0.0, 0.3, n) * 10.0 ** rng.uniform(-8, 0, n)  # sums that round
        if j in (7, 39):
            wz[n // 2] = math.nan  # the masked batch: its finite samples only
        if j == 11:
            ts[-1] = math.inf
        cal.observe(_batch(ts, wz))
        ok = np.isfinite(ts) & np.isfinite(wz)
        k = np.floor((ts[ok] - 100.0) / STEP_S).astype(int)
        for kk in np.unique(k).tolist():  # (a batch across a step's end: a sum per bin)
            sel = k == kk
            want.setdefault(kk, []).append((float(wz[ok][sel].sum()), int(sel.sum())))
        t = float(ts[ok][-1]) + float(rng.uniform(0.0, 0.8))
    assert cal.rejected.get("non-finite imu") == 3
    for k, sums in want.items():
        if k <= cal._closed:  # (closed: popped)
            continue
        acc = 0.0
        for s, _ in sums:
            acc += s
        b = cal._bins[k]
        assert b.yaw_rate_sum.hex() == acc.hex(), k
        assert b.yaw_rate_n == sum(n for _, n in sums)
    assert max(want) > cal._closed


def test_rpm_and_dvl_bins_accumulate_every_sample_of_their_step():
    cal = _started()
    rpm_n, dvl = 0, []
    for j in range(12):  # two steps' worth at 1 Hz (t0 + 0…11 s: bins 0, 1, 2)
        t = 100.0 + j + 0.25
        cal.observe(RpmSample(t, 800.0))
        cal.observe(DvlSample(t, (1.0 + 0.01 * j, 0.02 * j, 0.0)))
        rpm_n += 1
        dvl.append(t)
    # the bins still open (step 2 at least) hold every sample of their step
    for k in range(3):
        in_k = [t for t in dvl if math.floor((t - 100.0) / STEP_S) == k]
        if k in cal._bins:
            assert cal._bins[k].speed_n == len(in_k)
        if k in cal._dvl_bins:
            assert cal._dvl_bins[k].n == len(in_k)
    assert 2 in cal._bins and 2 in cal._dvl_bins and cal._dvl_bins[2].n == 2


def test_dvl_samples_are_corrected_by_the_filters_scale_and_misalignment():
    from adaptnav.calibration.dvl_teacher import DvlBin
    from adaptnav.fusion.aiding.dvl import correct_velocity

    cal = _started()
    cal._dvl_correction = (0.013, -0.021)  # as an inertial-velocity sample sets it
    want = DvlBin()
    for j in range(4):  # inside the step still open (bin 0 closes at t0 + 2.5 s)
        vel = (1.0 + 0.1 * j, -0.05 * j, 0.01)
        cal.observe(DvlSample(100.2 + 0.5 * j, vel))
        want.add(*cal.dvl_water.body(correct_velocity(vel, 0.013, -0.021), False, 0.2, cal._last_yaw_rate,
                                     cal._filter_current))
    cal.observe(DvlSample(102.3, (math.inf, 0.0, 0.0)))
    assert cal.rejected.get("non-finite dvl") == 1
    assert cal._dvl_bins[0].n == want.n == 4
    assert cal._dvl_bins[0].sum_m_s.tobytes() == want.sum_m_s.tobytes()
