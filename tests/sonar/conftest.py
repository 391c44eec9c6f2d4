"""Shared fixtures of the sonar tests: real files (skipped when absent) and a synthetic survey."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "sidescan"
SCOTSMAN = DATA / "scotsman-iver2.xtf"
MBES = DATA / "mbes-lib-150708-R2Testing-0001.xtf"


def need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    return path


@pytest.fixture(scope="session")
def scotsman_pings():
    from adaptnav.sonar.xtf import read_xtf

    pings, report = read_xtf(need(SCOTSMAN))
    return pings, report


def straight_pass(renderer, rng, start_n_m, yaw_rad, n_pings, ds_m=0.2, speed_m_s=1.5,
                  altitude_m=7.0):
    """Pings along a straight line; returns (pings, positions (P, 2))."""
    f = np.array([math.cos(yaw_rad), math.sin(yaw_rad)])
    pos = np.asarray(start_n_m, float) + np.outer(np.arange(n_pings) * ds_m, f)
    pings = renderer.render_track(np.arange(n_pings) * ds_m / speed_m_s, pos, yaw_rad,
                                  altitude_m, rng, speed_m_s)
    return pings, pos
