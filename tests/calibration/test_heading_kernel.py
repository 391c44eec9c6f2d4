"""The numba heading log-likelihood of the particle filter's fast path gives the same
floats as :meth:`adaptnav.calibration.sensors.HeadingObservation.log_likelihood` (the reference)."""
import math

import numpy as np

from adaptnav.calibration._kernels import heading_loglik
from adaptnav.calibration.particle_filter import _observation_log_lik
from adaptnav.calibration.sensors import HeadingObservation, PositionFix


def test_heading_kernel_equals_the_observation_model_bit_for_bit():
    rng = np.random.default_rng(0)
    for _ in range(100):
        poses = rng.normal(0.0, 5.0, (int(rng.integers(1, 600)), 3))
        poses[rng.random(len(poses)) < 0.02, 2] = np.nan
        ob = HeadingObservation(float(rng.uniform(-7.0, 7.0)), float(rng.uniform(1e-3, 0.5)))
        ref = ob.log_likelihood(poses)
        got = heading_loglik(poses, ob.yaw_rad, ob.sigma_rad, math.log(ob.sigma_rad), 0.5 * math.log(2.0 * math.pi))
        np.testing.assert_array_equal(got, ref)
        # the filter's dispatch takes the kernel for a lone heading, the models otherwise
        np.testing.assert_array_equal(_observation_log_lik([ob], poses, None), ref)
        fix = PositionFix((1.0, -2.0), 2.0)
        np.testing.assert_array_equal(_observation_log_lik([ob, fix], poses, None),
                                      np.zeros(len(poses)) + ref + fix.log_likelihood(poses))
