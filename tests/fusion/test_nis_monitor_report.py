"""The integrity monitor's window per aid, as the daemon's health carries it: NIS per degree of
freedom near 1 for a covariance that is right, failing when it is too small."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from adaptnav.fusion.integrity import NisMonitor


def test_the_report_is_the_windows_mean_nis_per_dof_and_its_verdict():
    rng = np.random.default_rng(3)
    mon = NisMonitor(window=20, quantile=0.999)
    depth = rng.chisquare(1, 200)  # a consistent scalar aid
    dvl = 9.0 * rng.chisquare(3, 200)  # a 3-d aid whose covariance is 3x too small in σ
    for a, b in zip(depth, dvl):
        mon.add("depth", float(a), 1)
        mon.add("dvl", float(b), 3)
    rep = mon.report()
    cap1, cap3 = stats.chi2.ppf(0.999, 1), stats.chi2.ppf(0.999, 3)
    assert rep["depth"]["attempts"] == rep["dvl"]["attempts"] == 20
    assert rep["depth"]["nis_per_dof"] == pytest.approx(np.minimum(depth[-20:], cap1).mean(), rel=1e-9)
    assert rep["dvl"]["nis_per_dof"] == pytest.approx(np.minimum(dvl[-20:], cap3).mean() / 3, rel=1e-9)
    assert rep["depth"]["bound_per_dof"] == pytest.approx(stats.chi2.ppf(0.999, 20) / 20, rel=1e-9)
    assert rep["dvl"]["bound_per_dof"] == pytest.approx(stats.chi2.ppf(0.999, 60) / 60, rel=1e-9)
    assert rep["depth"]["failing"] is False and rep["dvl"]["failing"] is True
    assert mon.failing() == ["dvl"]
    mon.clear("dvl")
    assert set(mon.report()) == {"depth"}
