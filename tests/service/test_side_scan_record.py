"""The side-scan estimator's navigation record (:mod:`adaptnav.service.loop_closures`): the ping a
batch's placement starts from is the one the walk back from the newest ping found."""
from __future__ import annotations

from collections import deque

import numpy as np

from adaptnav.service.loop_closures import _ping_at_or_before


def _walked_back(nav: deque, t_s: float) -> int:
    """The previous formulation: from the newest ping back while later than ``t_s``."""
    first = len(nav) - 1
    while first > 0 and nav[first][0] > t_s:
        first -= 1
    return first


def test_the_ping_at_or_before_a_sighting_is_the_one_walked_back_to():
    """Bisection over the record's increasing times against the walk: times before the first
    ping, on a ping's time exactly, between two, after the last, a record of one ping, times a
    hair apart."""
    rng = np.random.default_rng(6)
    for n in (1, 2, 3, 10, 3000):
        t = np.cumsum(rng.uniform(1e-9, 0.2, n)) + 1000.0
        if n > 2:
            t[1] = np.nextafter(t[0], np.inf)
        nav = deque((float(v), 0.0, 1.0) for v in t)
        probes = [t[0] - 1.0, t[0], t[-1], t[-1] + 5.0, np.nextafter(t[0], 0.0), np.nextafter(t[-1], np.inf)]
        probes += list(t[rng.integers(0, n, 20)]) + list(rng.uniform(t[0] - 0.5, t[-1] + 0.5, 50))
        for p in probes:
            assert _ping_at_or_before(nav, float(p)) == _walked_back(nav, float(p)), (n, p)


def _over_the_whole_record(pings: list, t_s: np.ndarray) -> np.ndarray:
    """The previous formulation: every ping read, np.interp per column over all of them."""
    rec = np.array(pings, float).T
    return np.array([np.interp(t_s, rec[0], rec[k]) for k in range(1, rec.shape[0])]).T


def test_the_sightings_interpolated_between_their_pings_are_the_whole_records_numbers():
    """:func:`_interpolated` reads only the pings around each sighting: bit for bit the numbers
    np.interp gives over the whole record — sightings on a ping's time, on the first and the
    last ping, several between two pings, in any order, a record of one ping, values of every
    scale, non-finite values in a column (a velocity covariance not given)."""
    from adaptnav.service.loop_closures import _interpolated

    rng = np.random.default_rng(8)
    for n in (1, 2, 5, 230):
        t = np.cumsum(rng.uniform(0.05, 0.15, n)) + 3000.0
        cols = rng.normal(size=(n, 13)) * 10.0 ** rng.integers(-6, 6, 13)
        cols[rng.random(n) < 0.2, 9:13] = np.nan
        cols[:, 3] = np.cumsum(rng.normal(0.0, 0.1, n))  # an unwrapped heading
        pings = [(float(tk), *row) for tk, row in zip(t, cols.tolist())]
        for probes in (t[[0]], t[[-1]], t, rng.uniform(t[0], t[-1], 13), np.full(4, 0.5 * (t[0] + t[-1])),
                       rng.permutation(np.concatenate([t[rng.integers(0, n, 5)], rng.uniform(t[0], t[-1], 8)]))):
            got, want = _interpolated(pings, probes), _over_the_whole_record(pings, probes)
            assert got.shape == want.shape == (len(probes), 13)
            assert got.tobytes() == want.tobytes(), (n, probes)
