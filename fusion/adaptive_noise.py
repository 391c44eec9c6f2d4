r"""Adaptive surge variance of the learned velocity (innovation-based, Mehra 1972).

When the water changes (density, temperature), the motion model's released surge variance
σ_V² is too tight until the calibrator catches up, and the learned velocity would be gated
or pull the state too hard. The surge variance is then scaled up to the innovation-based
estimate (Mehra 1972, IEEE TAC 17(5))::

    r̂ ← (1 − α) r̂ + α min(y² − h P hᵀ, 100 σ_V² s_max),   α = min(1, T / window)
    R₀₀ ← σ_V² clip(r̂ / σ_V², 1, s_max)

with ``y`` the surge innovation, ``h`` its Jacobian row, ``P`` the prior covariance, ``T``
the fusion period, ``window = learned_velocity.adaptive_window_s`` and
``s_max = adaptive_max_scale``: never down, and not for ``adaptive_suspend_after_release_s``
after a calibrator release (its variance is used as it is: the calibrator has caught up).
Gated innovations count too: after a change of water every surge innovation may exceed
the gate, and those are exactly the ones that say the model is too tight.

The estimator's compiled epoch (:func:`adaptnav.fusion.kalman.lv_epoch`, INS mode) does
:meth:`SurgeVariance.adapt`'s arithmetic in the same order on the estimate held here; this
class stays the reference its tests compare it with (tests/fusion/test_lv_kernels.py).
"""
from __future__ import annotations

import math

import numpy as np

from .aiding.common import Measurement
from .config import LearnedVelocityConfig


class SurgeVariance:
    """The innovation-based surge variance estimate ``r̂`` (m²/s²) and its use.

    Parameters
    ----------
    config : LearnedVelocityConfig
        ``adaptive_window_s`` (≤ 0: off), ``adaptive_max_scale``,
        ``adaptive_suspend_after_release_s``, and ``rate_hz`` (the fusion period).
    """

    def __init__(self, config: LearnedVelocityConfig):
        self.config = config
        self.period_s = 1.0 / config.rate_hz
        self.r_hat_m2_s2: float | None = None  # None: no innovation seen yet

    @property
    def enabled(self) -> bool:
        return self.config.adaptive_window_s > 0

    def adapt(self, meas: Measurement, P_prior: np.ndarray | None, since_release_s: float,
              extra_var: float = 0.0) -> Measurement:
        """``meas`` with its surge variance scaled to the estimate.

        ``P_prior`` (18, 18) the covariance before this epoch's update: its innovation joins
        the estimate first (None: the estimate is used as it is, e.g. for the re-measurement
        after a reset). ``since_release_s`` the state time since the latest calibrator
        release (s): within ``adaptive_suspend_after_release_s`` the estimate is kept
        current but ``meas`` is returned unchanged. ``extra_var`` (m²/s²): surge variance
        the caller adds to ``meas`` for a known cause (a thrust transient): taken out of this
        epoch's innovation sample, so the steady-state estimate does not take it.
        """
        if not self.enabled:
            return meas
        adapted = self._scaled(meas, P_prior, extra_var)
        return adapted if since_release_s >= self.config.adaptive_suspend_after_release_s else meas

    def _scaled(self, meas: Measurement, P_prior: np.ndarray | None, extra_var: float = 0.0) -> Measurement:
        cfg = self.config
        r_model = float(meas.R[0, 0])
        if P_prior is not None:
            h = meas.H[0]
            hph = float(h @ P_prior @ h)
            y0 = float(meas.z[0] - meas.h[0])
            if not (math.isfinite(y0) and math.isfinite(hph)):
                return meas
            alpha = min(1.0, self.period_s / cfg.adaptive_window_s)
            sample = min(y0 * y0 - hph - extra_var, 100.0 * r_model * cfg.adaptive_max_scale)
            self.r_hat_m2_s2 = sample if self.r_hat_m2_s2 is None else (1 - alpha) * self.r_hat_m2_s2 + alpha * sample
        if self.r_hat_m2_s2 is None:
            return meas
        scale = min(max(self.r_hat_m2_s2 / r_model, 1.0), cfg.adaptive_max_scale)
        if scale == 1.0:
            return meas
        R = meas.R.copy()
        R[0, 0] *= scale
        return meas._replace(R=R)

    def doubt(self, meas: Measurement) -> None:
        """The learned velocity was rejected for ``reset.velocity_after_s``: before the
        velocity is reset onto it, the estimate takes the rejected innovation, so the model
        is re-admitted with a variance that explains it instead of being gated again."""
        y0 = float(meas.innovation()[0])
        if self.enabled and math.isfinite(y0):
            cap = 100.0 * float(meas.R[0, 0]) * self.config.adaptive_max_scale
            self.r_hat_m2_s2 = max(self.r_hat_m2_s2 or 0.0, min(y0 * y0, cap))
