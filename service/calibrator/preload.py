"""Preload of the calibrator's forkserver (:class:`adaptnav.service.calibrator.lagged.ProcessBackend`).

Imported once by the ``multiprocessing`` forkserver: it imports the calibrator's modules
and runs one tiny EM window so that numba loads its cached kernels there; every child
forked from the server then starts with all of it in memory (milliseconds instead of
~1.5 s of imports and kernel loading per replay). Only the server runs this.
"""
from __future__ import annotations

import numpy as np

import adaptnav.calibration.online  # noqa: F401 (the import is the point)
import adaptnav.service.config  # noqa: F401 (the child unpickles a ServiceConfig; its MAVLink settings need no pymavlink)
import adaptnav.calibration.sidescan  # noqa: F401 (its object front end, on the first ping)
import adaptnav.sonar.objects  # noqa: F401
from adaptnav.calibration.em import EMOptions, run_em
from adaptnav.calibration.sensors import HeadingObservation, PositionFix
from adaptnav.fusion.motion_model import MotionParams


def warm_kernels() -> None:
    """One tiny EM window: every calibrator kernel compiled or loaded from its cache."""
    rng = np.random.default_rng(0)
    T, n = 4, 20
    obs = [[PositionFix((0.0, 0.0), 2.0)], [HeadingObservation(0.0, 0.05)], [], [],
           [PositionFix((6.0, 0.0), 2.0), HeadingObservation(0.0, 0.05)]]
    init = np.column_stack([rng.normal(0.0, 1.0, (n, 2)), rng.normal(0.0, 0.05, n)])
    try:
        run_em(MotionParams(), np.full(T, 1.5), np.zeros(T), 1.0, obs, init, rng,
               EMOptions(n_particles=n, n_smoothed=5, max_iterations=1))
    except Exception:  # noqa: BLE001 - a warm-up only: the child reports real failures
        pass


warm_kernels()
