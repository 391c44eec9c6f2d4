r"""Resampling for the particle filter (Douc, Cappé & Moulines 2005; Doucet & Johansen 2009).

Systematic resampling: one uniform ``u ~ U[0, 1/N)``, points ``u + i/N``, each mapped
through the inverse CDF of the normalised weights. filterpy's ``systematic_resample``
uses ``np.cumsum(weights)`` as the CDF; with round-off its last element can be slightly
below 1, and a point ``u + (N-1)/N`` above it runs off the end (index N). Here the
cumulative sum's last element is forced to exactly 1.

Effective sample size ``ESS = 1 / Σ W_i²`` of normalised weights ``W``.
"""
from __future__ import annotations

import numpy as np


def logsumexp(a: np.ndarray) -> float:
    """``log Σ exp(a)`` of a 1-D array (numpy only: scipy's version is ~10x slower at N=1000)."""
    m = np.max(a)
    if not np.isfinite(m):
        return float(m)
    return float(m + np.log(np.sum(np.exp(a - m))))


def normalise_log_weights(log_w: np.ndarray) -> np.ndarray:
    """Return ``log_w − logsumexp(log_w)`` (log of weights summing to 1); shape kept."""
    log_w = np.asarray(log_w, dtype=float)
    total = logsumexp(log_w)
    if not np.isfinite(total):
        raise FloatingPointError("all particle weights are zero (or non-finite)")
    return log_w - total


def ess(log_w: np.ndarray) -> float:
    """Effective sample size of (unnormalised) log-weights ``log_w`` (N,)."""
    w = np.exp(normalise_log_weights(log_w))
    return float(1.0 / np.sum(w * w))


def systematic_resample(weights: np.ndarray, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Systematic resampling indices.

    Parameters
    ----------
    weights : (N,) non-negative weights (normalised inside)
    rng : numpy Generator (one uniform drawn)
    n : number of indices to draw (default N)

    Returns
    -------
    (n,) int64 indices into ``weights``, non-decreasing.
    """
    weights = np.asarray(weights, dtype=float)
    n = weights.size if n is None else int(n)
    cdf = np.cumsum(weights)
    if not (cdf[-1] > 0 and np.isfinite(cdf[-1])):
        raise FloatingPointError("systematic_resample: weights sum to zero or are not finite")
    cdf /= cdf[-1]
    cdf[-1] = 1.0  # the round-off guard
    points = (rng.random() + np.arange(n)) / n
    return np.searchsorted(cdf, points, side="right")


def multinomial_indices(log_w: np.ndarray, size, rng: np.random.Generator) -> np.ndarray:
    """``size`` i.i.d. indices drawn ∝ ``exp(log_w)`` (inverse CDF with the same guard)."""
    w = np.exp(normalise_log_weights(log_w))
    cdf = np.cumsum(w)
    cdf[-1] = 1.0
    return np.searchsorted(cdf, rng.random(size), side="right")
