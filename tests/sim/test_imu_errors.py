"""IMU error processes against their defining formulas (Gauss–Markov, random walk, white)."""
import math

import numpy as np

from adaptnav.sim.imu import IMU_GRADES, SensorErrorModel, triad_errors


def test_gauss_markov_bias_instability_statistics():
    model = SensorErrorModel(turn_on_sigma=0.0, instability_sigma=2.0, correlation_time_s=1.0,
                             white_density=0.0, random_walk_density=0.0)
    dt, n = 0.01, 400_000
    bias, white = triad_errors(model, n, dt, np.random.default_rng(3))
    assert np.all(white == 0.0)
    # stationary σ (≈ 2000 correlation times per axis → a few % scatter)
    assert np.all(np.abs(bias.std(axis=0) / 2.0 - 1.0) < 0.08)
    # autocorrelation at lag τ is e^{-1}
    lag = int(round(1.0 / dt))
    rho = [np.corrcoef(bias[:-lag, i], bias[lag:, i])[0, 1] for i in range(3)]
    assert np.all(np.abs(np.array(rho) - math.exp(-1.0)) < 0.06)


def test_random_walk_and_white_noise_densities():
    model = SensorErrorModel(turn_on_sigma=0.0, instability_sigma=0.0, correlation_time_s=1.0,
                             white_density=0.3, random_walk_density=0.05)
    dt, n = 0.01, 100_000
    bias, white = triad_errors(model, n, dt, np.random.default_rng(4))
    steps = np.diff(bias, axis=0)
    assert np.all(np.abs(steps.std(axis=0) / (0.05 * math.sqrt(dt)) - 1.0) < 0.02)
    assert np.all(np.abs(white.std(axis=0) / (0.3 / math.sqrt(dt)) - 1.0) < 0.02)


def test_turn_on_bias_spread_over_runs():
    model = IMU_GRADES["tactical"].gyro
    b0 = np.array([triad_errors(model, 2, 0.01, np.random.default_rng(s))[0][0] for s in range(400)])
    # turn-on and instability add in quadrature at t = 0 (RW ≈ 0 yet)
    expected = math.hypot(model.turn_on_sigma, model.instability_sigma)
    assert abs(b0.std() / expected - 1.0) < 0.08
    assert math.isclose(model.turn_on_sigma, math.radians(1.0) / 3600.0)  # 1 °/h, HG1700 class
