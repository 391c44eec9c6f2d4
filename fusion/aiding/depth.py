r"""Depth from absolute pressure (hydrostatic): ``d = (p − p_atm) / (ρ g)``; ``h(x) = p_d``.

Water density ρ (kg/m³) and atmospheric pressure (Pa) come from the config (sea water
≈ 1025, fresh ≈ 1000; UNESCO 1983 gives the full equation of state, unnecessary at
AUV depths for a 0.05 m sensor).

The noise σ the depth is fused with is the sensor's own (:class:`DepthNoise`): measured from
the depth signal's high-frequency residual, bounded below by ``depth.sigma_m`` and above by
``depth.adaptive_max_sigma_m``.
"""
from __future__ import annotations

import math

import numpy as np
from adaptnav.kernels import unguarded

from ..frames import GRAVITY_M_S2
from ..kalman import median_window_push
from ..state import N_ERR, X_POS
from ..config import DepthConfig
from .common import NOT_ANGULAR, AidContext, AidSource, Measurement

# DepthNoise's window kernel without its argument guard (adaptnav.kernels.unguarded): its only
# array is DepthNoise's own window (np.zeros, C-contiguous float64), its value a number
_median_window_push = unguarded(median_window_push)


def pressure_to_depth(pressure_pa, water_density_kg_m3: float, atmospheric_pressure_pa: float):
    """Depth (m, positive down) of an absolute pressure (Pa)."""
    return (np.asarray(pressure_pa, dtype=float) - atmospheric_pressure_pa) / (
        water_density_kg_m3 * GRAVITY_M_S2)


# A vertical run: the depth changing between two level spells. Level: the depth within
# LEVEL_BAND_M for LEVEL_TIME_S (slower than ~0.03 m/s: depth hold, waves at a steady depth).
LEVEL_BAND_M = 0.1
LEVEL_TIME_S = 3.0


def vertical_run_step(run: tuple | None, t_s: float, depth_m: float) -> tuple[tuple, float]:
    """The vertical run after one depth sample, and how much its excursion² grew (m²).

    ``run`` (immutable, ``None`` before the first depth): ``(t_start_s, depth_ref_m,
    excursion_m, level_t0_s, level_lo_m, level_hi_m)`` — when the run began, the level depth it
    left, its largest depth change from there so far, and the candidate level spell (its start
    and the depth band it has spanned). While level the run is empty and follows the depth;
    a depth leaving the band starts one. The excursion is a run's, not a path's: depth noise
    and waves add to it only while they exceed its largest change, and nothing once level."""
    if run is None:  # taken as level (the filter aligned at a steady depth)
        return (t_s, depth_m, 0.0, t_s - LEVEL_TIME_S, depth_m, depth_m), 0.0
    t_start, ref, excursion, level_t0, lo, hi = run
    lo, hi = min(lo, depth_m), max(hi, depth_m)
    if hi - lo > LEVEL_BAND_M:  # left the band: a new candidate level spell starts here
        level_t0, lo, hi = t_s, depth_m, depth_m
    elif t_s - level_t0 >= LEVEL_TIME_S:  # level: no run, the reference is the band's middle
        return (t_s, 0.5 * (lo + hi), 0.0, level_t0, lo, hi), 0.0
    grown = max(excursion, abs(depth_m - ref))
    return (t_start, ref, grown, level_t0, lo, hi), grown * grown - excursion * excursion


def predict(x) -> np.ndarray:
    return np.array([x[X_POS][2]])


def jacobian(x) -> np.ndarray:
    H = np.zeros((1, N_ERR))
    H[0, 2] = 1.0
    return H


def depth_m(pressure_pa: float, water_density_kg_m3: float, atmospheric_pressure_pa: float) -> float:
    """:func:`pressure_to_depth` of one pressure (Pa) as a float (m): the same operations on
    the same floats without the array conversions (a depth every 0.1 s; also the estimator's
    compiled depth path, :meth:`adaptnav.fusion.eskf.Estimator._fast_depth`)."""
    return (float(pressure_pa) - atmospheric_pressure_pa) / (water_density_kg_m3 * GRAVITY_M_S2)


def measure(sample, x, sigma_m, water_density_kg_m3, atmospheric_pressure_pa) -> Measurement:
    # jacobian() and predict() written out: the same operations on the same floats without
    # make()'s conversions (a depth every 0.1 s)
    depth = depth_m(sample.pressure_pa, water_density_kg_m3, atmospheric_pressure_pa)
    H = np.zeros((1, N_ERR))
    H[0, 2] = 1.0
    return Measurement(np.array([depth]), H, np.array([[sigma_m**2]], dtype=float), np.array([float(x[X_POS.start + 2])]),
                       NOT_ANGULAR[1])


def _measure(sample, ctx: AidContext) -> Measurement:
    c = ctx.config
    return measure(sample, ctx.x, c.sigma_m, c.water_density_kg_m3, c.atmospheric_pressure_pa)


AID = AidSource("depth", DepthConfig, _measure, without_imu=True)


# σ̂ = med|Δ²z| / (0.6745 √6) (DepthNoise): the divisor, computed once (the same double)
_MAD_TO_SIGMA = 0.6745 * math.sqrt(6.0)


class DepthNoise:
    r"""The depth sensor's white noise, measured from its own signal, and the σ fused with.

    The default ``sigma_m`` (5 cm) is a Bar30's class with margin (a real one in
    ``ardusub-4.1.0-small.BIN`` shows 3 mm per sample); other pressure sensors are noisier
    (ArduSub's simulated one: 0.115 m per sample, white), and against a σ too small the
    integrity test fails ``nis:depth`` all along: a solution never valid, though sound. So the
    noise is measured as the IMU grade ``auto`` measures the IMU's: from second differences of
    consecutive depths (``Δ²z = z_k − 2 z_{k−1} + z_{k−2}``, evenly spaced samples), in which
    the vehicle's own depth changes drop out (a heave acceleration of 0.5 m/s² moves Δ²z by
    5 mm at 10 Hz) and white noise of σ leaves ``Var Δ²z = 6 σ²``. The scale is robust — the
    median of ``|Δ²z|`` over the last :data:`WINDOW` differences, ``σ̂ = med|Δ²z| / (0.6745 √6)``
    — and the σ fused is ``min(σ̂, adaptive_max_sigma_m)`` once σ̂ exceeds ``sigma_m`` by more
    than :data:`DEADBAND` (the estimate's own sampling spread: over the simulator's hour-long
    survey, depth noise 0.05 m, σ̂ stayed within 0.82–1.18 × 0.05; a sensor as good as
    configured keeps its configured σ), else ``sigma_m``.

    Why this and not the innovations (Mehra 1972, as the learned velocity's surge variance):
    innovations take whatever the sensor does wrong into its variance — a step or a drift
    would be absorbed as "noise" and never fail the integrity test. The high-frequency
    residual sees only noise: a **step** is one or two outlying differences in the median's
    window (σ̂ unchanged: the step's innovations are gated and fail ``nis:depth`` as before);
    a **drift** or any slow error has no second difference at all (σ̂ unchanged); a **stuck**
    sensor has none either (σ̂ → 0: the configured ``sigma_m`` again, the strictest σ).

    The bound, ``adaptive_max_sigma_m`` (0.5 m by default): the noisiest sensor the defaults
    accept as a depth sensor. It is 4× the simulated sensor's 0.115 m and 10× the default
    σ; wave pressure a few metres down stays below it (second differences at 10 Hz see
    ``A ω² Δt²``, a few cm for a metre of swell). A sensor noisier than that — failing,
    in the surf, a baro in a flooded housing — is not made consistent by a larger σ: its σ
    stays at the bound, its innovations exceed it and ``nis:depth`` makes the solution
    invalid, as it would the sensor's owner. The σ used, the measured σ̂ and the bound are
    reported (:meth:`report`; the replay's ``summary.json`` ``filter.depth_noise``).

    Deterministic under late-measurement re-fusion: a depth seen before answers the σ it
    had (by its time stamp).
    """

    WINDOW = 600       # second differences in the median (60 s at 10 Hz)
    MIN_COUNT = 50     # before: the configured sigma_m (5 s at 10 Hz)
    # σ̂ within this factor of sigma_m: sigma_m (sampling spread, above); 1.25 in σ is 1.56 in
    # variance, which the integrity test's window tolerates (its 20-attempt χ² bound at 0.9999
    # is 2.6 × the expected sum): below it the test does not fail, there is nothing to adapt
    DEADBAND = 1.25
    MAX_GAP_S = 1.0    # a triple spanning a longer gap says nothing about the white noise
    MAX_UNEVEN = 0.25  # nor one whose two intervals differ by more than this fraction
    _MEMO = 512        # depths remembered for re-fusion

    def __init__(self, config: DepthConfig):
        self.floor_m = float(config.sigma_m)
        self.bound_m = float(config.adaptive_max_sigma_m)
        self.enabled = self.bound_m > self.floor_m  # the σ adapts (fixed bounds; asked twice per depth)
        # σ̂ above this is noisier than configured (DEADBAND × sigma_m: the same double, once)
        self._noisier_m = self.DEADBAND * self.floor_m
        # the two latest depths (s, m): -inf before there are any (every interval test fails)
        self._t0 = self._z0 = self._t1 = self._z1 = -math.inf
        # the window of |Δ²z|, also kept sorted, so that the median of every depth is two
        # look-ups (numpy.median of the window per depth was a tenth of the replaying
        # process's CPU; bisect on a Python list ~6 µs per depth in a replay): the count, the
        # oldest's index, the values in arrival order, sorted (kalman.median_window_push)
        self._window = np.zeros(2 + 2 * self.WINDOW)
        self._n = 0             # |Δ²z| in the window
        self._median = math.nan  # their median
        # σ by time stamp of the latest _MEMO to 2 × _MEMO depths (trimmed in bulk: dicts keep
        # their insertion order, the oldest go first)
        self._memo: dict[float, float] = {}
        self.measured_sigma_m = math.nan  # σ̂ (m), nan before MIN_COUNT differences
        self.sigma_m = self.floor_m       # the σ fused with now (m)
        self.max_used_sigma_m = self.floor_m
        self.samples = 0
        self.samples_at_bound = 0

    def sigma_at(self, t_s: float, depth_m: float) -> float:
        """The σ (m) to fuse the depth ``depth_m`` measured at ``t_s`` with."""
        t1 = self._t1
        if not t_s > t1:  # seen before (a re-fusion answers its σ), out of order or no time
            memo = self._memo.get(t_s)
            return self.sigma_m if memo is None else memo
        if not math.isfinite(depth_m):
            return self.sigma_m  # the current σ, the estimate untouched
        z1 = self._z1
        dt1, dt2 = t1 - self._t0, t_s - t1
        gap = self.MAX_GAP_S
        # (max and min as comparisons: the builtins' calls were a tenth of this; both finite here)
        if 0.0 < dt1 <= gap and 0.0 < dt2 <= gap and abs(dt2 - dt1) <= self.MAX_UNEVEN * (dt2 if dt2 > dt1 else dt1):
            self._n, self._median = _median_window_push(self._window, abs(depth_m - 2.0 * z1 + self._z0))
        self._t0, self._z0, self._t1, self._z1 = t1, z1, t_s, depth_m
        enabled = self.enabled
        if self._n >= self.MIN_COUNT:
            measured = self.measured_sigma_m = self._median / _MAD_TO_SIGMA
            if enabled:  # off: measured (reported), not used
                bound = self.bound_m
                self.sigma_m = (bound if bound < measured else measured) if measured > self._noisier_m else self.floor_m
        sigma = self.sigma_m
        self.samples += 1
        if enabled and sigma >= self.bound_m:
            self.samples_at_bound += 1
        if sigma > self.max_used_sigma_m:
            self.max_used_sigma_m = sigma
        memo = self._memo
        memo[t_s] = sigma
        if len(memo) > 2 * self._MEMO:
            self._memo = dict(list(memo.items())[-self._MEMO:])
        return sigma

    def variance_m2(self, t_s: float, depth_m: float) -> float:
        """The variance (m²) to fuse the depth ``depth_m`` measured at ``t_s`` with: σ² of
        :meth:`sigma_at`, the configured ``sigma_m²`` (as :func:`measure` makes it) while that is
        the σ or the estimate is off."""
        s = self.sigma_at(t_s, depth_m) if self.enabled else self.floor_m
        return self.floor_m**2 if s == self.floor_m else s * s

    def adapt(self, meas: Measurement, t_s: float) -> Measurement:
        """``meas`` (from :func:`measure`) with the variance of :meth:`variance_m2`."""
        if not self.enabled:
            return meas
        var = self.variance_m2(t_s, float(meas.z[0]))
        return meas if var == float(meas.R[0, 0]) else meas._replace(R=np.array([[var]]))

    def report(self) -> dict:
        """What was used: the configured σ, the bound, the latest measured σ̂, the σ in use and
        the largest used (m), and the share of depths fused at the bound."""
        return {"configured_sigma_m": self.floor_m, "max_sigma_m": self.bound_m if self.enabled else None,
                "measured_sigma_m": None if math.isnan(self.measured_sigma_m) else self.measured_sigma_m,
                "sigma_m": self.sigma_m, "max_used_sigma_m": self.max_used_sigma_m,
                "fraction_at_bound": self.samples_at_bound / self.samples if self.samples and self.enabled else 0.0}
