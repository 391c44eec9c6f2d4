"""`adaptnav bench fusion`: the ESKF over a 1 h, 100 Hz IMU log with aiding, vs pyins.

Data: a deterministic snaking survey leg (heading ψ = 0.3 + 0.6 sin(2π t / 120 s),
water speed 1.5 m/s, current (0.1, −0.05) m/s, depth 10 m), IMU at 100 Hz with
tactical-grade noise and biases (seeded), RPM/heading/depth at 1 Hz, USBL every 60 s.
The estimator gets the IMU as :class:`~fusion.samples.ImuBatch` runs between the other
samples, as the replay harness feeds it. pyins (``python-ins``,
``pyins.filters.run_feedback_filter`` with 0.1 s covariance steps) runs on the first
5 minutes of the same IMU with the same surge velocity as a ``BodyVelocity``
measurement at the same 2 Hz, in the same process; its rate is IMU samples per second
of wall time.
"""
from __future__ import annotations

import time

import numpy as np

from adaptnav.fusion.frames import GRAVITY_M_S2, GeoOrigin
from adaptnav.fusion.imu_grades import PROFILES
from adaptnav.fusion.samples import DepthSample, HeadingSample, ImuBatch, RpmSample, UsblSample, replay_order_key
from adaptnav.service.compose import make_estimator
from adaptnav.service.config import ServiceConfig

ORIGIN = GeoOrigin(np.radians(43.0), np.radians(5.0), 0.0)
# the service's defaults: the log's sensor noise and RPM table are the filter's
CONFIG = ServiceConfig()
SPEED_M_S = 1.5
CURRENT_N = np.array([0.1, -0.05])
DEPTH_M = 10.0
LV_RATE_HZ = 2.0


def add_arguments(parser):  # pragma: no cover - argparse wiring
    parser.add_argument("--duration-s", type=float, default=3600.0, help="log length (s)")
    parser.add_argument("--pyins-slice-s", type=float, default=300.0, help="pyins slice length (s)")


def make_log(duration_s: float, rate_hz: float = 100.0, seed: int = 0):
    """IMU arrays, truth positions and the aiding samples of the benchmark mission."""
    rng = np.random.default_rng(seed)
    cfg = CONFIG.filter
    n = int(round(duration_s * rate_hz))
    t = np.arange(1, n + 1) / rate_hz
    w0 = 2 * np.pi / 120.0
    psi = 0.3 + 0.6 * np.sin(w0 * t)
    psid = 0.6 * w0 * np.cos(w0 * t)
    c, s = np.cos(psi), np.sin(psi)
    vel = np.stack([SPEED_M_S * c + CURRENT_N[0], SPEED_M_S * s + CURRENT_N[1], np.zeros(n)], axis=1)
    acc = np.stack([-SPEED_M_S * psid * s, SPEED_M_S * psid * c, np.zeros(n)], axis=1)
    pos = np.cumsum(vel, axis=0) / rate_hz
    pos[:, 2] = DEPTH_M
    f_n = acc - np.array([0.0, 0.0, GRAVITY_M_S2])
    f_b = np.stack([c * f_n[:, 0] + s * f_n[:, 1], -s * f_n[:, 0] + c * f_n[:, 1], f_n[:, 2]], axis=1)
    w_b = np.zeros((n, 3))
    w_b[:, 2] = psid
    imu = PROFILES["tactical"]  # the simulated IMU: tactical-grade datasheet figures
    f_b += rng.normal(0, imu.acc_bias_sigma_m_s2, 3) + imu.acc_noise_m_s2_rthz * np.sqrt(rate_hz) * rng.standard_normal((n, 3))
    w_b += rng.normal(0, imu.gyro_bias_sigma_rad_s, 3) + imu.gyro_noise_rad_s_rthz * np.sqrt(rate_hz) * rng.standard_normal((n, 3))
    rpm = float(CONFIG.motion.rpm_table.rpm_for_speed(SPEED_M_S))
    aids = []
    for k in range(1, int(duration_s)):
        i = k * int(rate_hz) - 1
        aids.append(RpmSample(float(k) - 0.5, rpm))
        aids.append(HeadingSample(float(k), float(psi[i] + cfg.heading.sigma_rad * rng.standard_normal())))
        aids.append(DepthSample(float(k), 101325.0 + 1025.0 * GRAVITY_M_S2 * (DEPTH_M + 0.05 * rng.standard_normal())))
        if k % 60 == 0:
            lat, lon, _ = ORIGIN.to_geodetic(pos[i] + np.r_[2.0 * rng.standard_normal(2), 0.0])
            aids.append(UsblSample(float(k), float(lat), float(lon), DEPTH_M, 2.0))
    aids.sort(key=lambda a: replay_order_key(a, 0))
    return t, f_b, w_b, pos, vel, psi, aids


def _events(t, f_b, w_b, aids):
    out = []
    k0 = 0
    for a in aids:
        k1 = int(np.searchsorted(t, a.t_s, side="right"))
        if k1 > k0:
            out.append(ImuBatch(t[k0:k1], f_b[k0:k1], w_b[k0:k1]))
            k0 = k1
        out.append(a)
    if k0 < t.size:
        out.append(ImuBatch(t[k0:], f_b[k0:], w_b[k0:]))
    return out


def run_adaptnav(t, f_b, w_b, aids):
    est = make_estimator(CONFIG, origin=ORIGIN)  # as the daemon and replay build it
    events = _events(t, f_b, w_b, aids)
    t0 = time.perf_counter()
    for e in events:
        est.process(e)
    return time.perf_counter() - t0, est


def run_pyins(t, f_b, w_b, vel, psi, slice_s: float) -> float:
    """Wall time of pyins' feedback filter over the first ``slice_s`` seconds."""
    import pandas as pd
    from pyins import filters, measurements, strapdown

    rate = 1.0 / (t[1] - t[0])
    n = int(slice_s * rate)
    imu = pd.DataFrame(np.hstack([w_b[:n], f_b[:n]]), index=t[:n],
                       columns=["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"])
    increments = strapdown.compute_increments_from_imu(imu, "rate")
    lat, lon, _ = ORIGIN.to_geodetic(np.zeros(3))
    pva = pd.Series({"lat": np.degrees(lat), "lon": np.degrees(lon), "alt": -DEPTH_M,
                     "VN": vel[0, 0], "VE": vel[0, 1], "VD": 0.0, "roll": 0.0, "pitch": 0.0,
                     "heading": np.degrees(psi[0])}, name=t[0])
    step = int(rate / LV_RATE_HZ)
    idx = np.arange(step, n - 1, step)
    body = pd.DataFrame({"VX": np.full(idx.size, SPEED_M_S), "VY": 0.0, "VZ": 0.0}, index=t[idx])
    t0 = time.perf_counter()
    filters.run_feedback_filter(pva, 10.0, 1.0, 1.0, 3.0, increments,
                                measurements=[measurements.BodyVelocity(body, 0.05)], time_step=0.1)
    return n / (time.perf_counter() - t0)


def run(args) -> dict:
    duration = 120.0 if getattr(args, "quick", False) else getattr(args, "duration_s", 3600.0)
    slice_s = 30.0 if getattr(args, "quick", False) else getattr(args, "pyins_slice_s", 300.0)
    t, f_b, w_b, pos, vel, psi, aids = make_log(duration)
    run_adaptnav(t[:2000], f_b[:2000], w_b[:2000], [a for a in aids if a.t_s < 20])  # JIT warm-up
    elapsed, est = run_adaptnav(t, f_b, w_b, aids)
    state = est.nav_state()
    rate = t.size / elapsed
    pyins_rate = run_pyins(t, f_b, w_b, vel, psi, slice_s)
    return {
        "duration_s": float(duration),
        "imu_samples": int(t.size),
        "wall_s": elapsed,
        "imu_samples_per_s": rate,
        "realtime_factor": duration / elapsed,
        "pyins_imu_samples_per_s": pyins_rate,
        "pyins_slice_s": float(slice_s),
        "pyins_realtime_factor": pyins_rate / (t.size / duration),
        "speedup_vs_pyins": rate / pyins_rate,
        "final_horizontal_error_m": float(np.linalg.norm(state.pos_n_m[:2] - pos[-1, :2])),
        "rejected": int(sum(est.rejected.values())),
    }
