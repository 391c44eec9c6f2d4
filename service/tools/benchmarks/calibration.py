"""`adaptnav bench calibration`: seconds per EM iteration (PF + FFBSi + M-step).

Problem: T = 100 steps of the thesis simulation (4 landmarks, ranges σ 2 m), N = 1000
particles, M = 100 smoothed trajectories. Measured in one process on one core
(process time): the production iteration (PF + MCMC backward kernel + M-step) and the
same iteration with the exact O(N·M·T) FFBSi, plus the smoothers alone, with ratios.
Reference from the issue: the `particles` library's exact backward sampling takes
~0.77 s for N = 1000, M = 100, T = 100 on this machine class.
"""
from __future__ import annotations

import time


def add_arguments(parser):  # pragma: no cover - bench verb owns the parser
    pass


def _best(fn, repeats):
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def run(args) -> dict:
    import json
    import os
    import subprocess
    import sys

    from adaptnav.service.calibrator.lagged import CHILD_THREAD_ENV

    if any(os.environ.get(k) != v for k, v in CHILD_THREAD_ENV.items()):
        # measured as the calibrator child runs it: BLAS on one thread (its numpy is
        # loaded already here, so in a fresh process)
        cmd = [sys.executable, "-m", "adaptnav", "bench", "calibration", "--json"]
        cmd += ["--quick"] if getattr(args, "quick", False) else []
        out = subprocess.run(cmd, env={**os.environ, **CHILD_THREAD_ENV}, check=True,
                             capture_output=True, text=True).stdout
        return json.loads(out)
    import numpy as np

    from adaptnav.service.calibrator.heap import keep_freed_heap

    heap_kept = keep_freed_heap()  # as the calibrator's processes run EM (service/calibrator/heap.py)

    from adaptnav.calibration.mstep import m_step
    from adaptnav.calibration.particle_filter import run_particle_filter
    from adaptnav.calibration.smoother import ffbsi_exact, ffbsi_mcmc
    from adaptnav.calibration.thesis import ThesisRow, simulate, _init_cloud

    quick = bool(getattr(args, "quick", False))
    T, N, M = (30, 300, 30) if quick else (100, 1000, 100)
    repeats = 2 if quick else 5
    data = simulate(ThesisRow(0.05, 0.05, 0.2, 0.05, 2.0, steps=T), np.random.default_rng(1))
    params = data.params_initial
    rng = np.random.default_rng(2)
    init = _init_cloud(N, rng)
    v, w, dt, obs = data.v, data.w, data.dt, data.observations

    state = {}

    def pf():
        state["fr"] = run_particle_filter(params, v, w, dt, obs, init, rng, N)

    def iteration(smoother):
        def go():
            pf()
            traj = smoother(state["fr"], params, v, w, dt, M, rng)
            m_step(traj, v, w, dt, params)
        return go

    pf()
    fr = state["fr"]
    t_pf = _best(pf, repeats)
    t_mcmc = _best(lambda: ffbsi_mcmc(fr, params, v, w, dt, M, rng), repeats)
    t_exact = _best(lambda: ffbsi_exact(fr, params, v, w, dt, M, rng), max(1, repeats // 2))
    traj = ffbsi_mcmc(fr, params, v, w, dt, M, rng)
    t_m = _best(lambda: m_step(traj, v, w, dt, params), repeats)
    t_iter = _best(iteration(ffbsi_mcmc), repeats)
    t_iter_exact = _best(iteration(ffbsi_exact), max(1, repeats // 2))
    return {
        "T": T, "N": N, "M": M,
        "em_iteration_s": t_iter,
        "em_iteration_exact_smoother_s": t_iter_exact,
        "em_iteration_speedup": t_iter_exact / t_iter,
        "particle_filter_s": t_pf,
        "smoother_mcmc_s": t_mcmc,
        "smoother_exact_s": t_exact,
        "smoother_speedup": t_exact / t_mcmc,
        "m_step_s": t_m,
        "goal_em_iteration_s": 0.01,
        "reference_particles_exact_backward_s": 0.77,
        "timing": "best of repeats, process time, one core (BLAS on one thread, as the calibrator child)",
        "heap_kept": heap_kept,
    }
