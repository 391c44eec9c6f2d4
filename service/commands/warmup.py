"""`adaptnav warmup [--config FILE] [--jit-only]`: compile the kernels before the service needs them.

Run at install (``make``) and before every start of the systemd unit (``ExecStartPre``).
It runs the filter and one EM window just in time (filling numba's on-disk cache:
``NUMBA_CACHE_DIR`` when set, else ``__pycache__`` next to the sources) and compiles
every kernel ahead of time into one extension module (:mod:`adaptnav.kernels`): the
daemon and its calibrator child then import compiled code and never numba (no JIT
memory, no compile before the first solution). A no-op when the module for the current
sources exists and this CPU can run it (:mod:`adaptnav.kernels`: one built on a CPU with
instructions this one lacks is built again); ``--portable`` builds anew for any CPU of the
architecture (a container image, a copy for other computers). Without a C and a C++
compiler (numba.pycc needs both) the ahead-of-time step fails with a warning, before the
warm-up, and the just-in-time cache is what the service uses.
"""
from __future__ import annotations

from adaptnav.service.commands.config_args import add_config_arguments, load_config_or_report

HELP = "compile the kernels ahead of time (install step; the unit's ExecStartPre)"


def add_arguments(parser):
    add_config_arguments(parser)
    parser.add_argument("--jit-only", action="store_true",
                        help="only fill numba's just-in-time cache (no ahead-of-time module)")
    parser.add_argument("--portable", action="store_true",
                        help="build for any CPU of this architecture, not only this one (an image "
                             "or a copy that runs elsewhere; always builds anew)")


def _exercise_calibration_kernels() -> None:
    """The calibrator kernels one EM window may leave uncalled (range likelihood,
    resampling, the step-by-step filter, the exact smoother): a small thesis problem runs them all."""
    import numpy as np

    from adaptnav.calibration.particle_filter import filter_step, run_particle_filter
    from adaptnav.calibration.sensors import HeadingObservation, PositionFix
    from adaptnav.calibration.smoother import ffbsi_exact, ffbsi_mcmc
    from adaptnav.calibration.thesis import ThesisRow, _init_cloud, simulate

    rng = np.random.default_rng(0)
    data = simulate(ThesisRow(steps=12), rng)
    p = data.params_initial
    fr = run_particle_filter(p, data.v, data.w, data.dt, data.observations, _init_cloud(64, rng), rng, 64)
    # the step-by-step path of a window with a landmark map
    run_particle_filter(p, data.v, data.w, data.dt, data.observations, _init_cloud(64, rng), rng, 64,
                        map_landmarks=True)
    # the online calibrator's per-step filter (a heading alone, then a fix)
    poses, log_w = fr.poses[-1].copy(), fr.log_w[-1].copy()
    for obs in ([HeadingObservation(0.0, 0.1)], [PositionFix((0.0, 0.0), 50.0)]):
        poses, log_w, _ = filter_step(p, poses, log_w, 1.0, 0.1, 1.0, obs, rng)
    ffbsi_exact(fr, p, data.v, data.w, data.dt, 8, rng)
    ffbsi_mcmc(fr, p, data.v, data.w, data.dt, 8, rng)


def _exercise_sonar_kernels() -> None:
    """The side-scan object detector's kernels (the calibrator's child runs them on every
    block of pings): a small image with object-like highlights and shadows through
    :func:`adaptnav.sonar.objects.local_level` and both sides' shadow and near-nadir detection
    (labels, runs, deep shadow and the candidates' measurements, with thresholds low enough
    that candidates reach them)."""
    from dataclasses import replace

    import numpy as np

    from adaptnav.sonar.objects import (ObjectDetectorConfig, _deep_shadow_rows, _detect_near, _detect_shadowed,
                                        _Runs, local_level)
    from adaptnav.sonar.ping import SonarPing
    from adaptnav.sonar.waterfall import Waterfall, WaterfallConfig, build_waterfall, row_medians

    rng = np.random.default_rng(0)
    rows, w = 64, 128
    image = rng.gamma(4.0, 0.25, (rows, 2 * w)).astype(np.float32)
    for r in range(4, rows - 8, 9):  # a lit face then its shadow, on both sides
        for c in (w + 30 + r, w - 31 - r):
            image[r:r + 4, c:c + 3] *= 6.0
            image[r:r + 4, c + 3:c + 15] *= 0.05
    config = replace(ObjectDetectorConfig(), min_contrast=1.0, compact_min_contrast=1.0, short_min_contrast=1.0,
                     min_height_m=0.0)
    lev = local_level(image, 0.1, 0.15, config, {})
    wf = Waterfall(image, 0.1, 0.15, np.arange(rows) * 0.1, np.arange(rows) * 0.15, np.zeros(rows),
                   np.arange(rows, dtype=float), np.full((rows, 2), 8.0))
    args = (0.1, wf.along_m, 0.15, np.arange(rows, dtype=float), wf, wf.altitude_m[:, 0], config)
    # a side of the image as the detector takes it (columns outward from the nadir: strided)
    runs = _Runs(np.array([1, 2]), np.array([3, 5]), np.array([4, 10]), np.array([30, 40]))
    for side, sub in (("starboard", lev[:, w:]), ("port", lev[:, w - 1::-1])):
        _deep_shadow_rows(sub, runs, 0.3)
        _detect_shadowed(sub, side, *args)
        _detect_near(sub, side, *args)
    # the waterfall of a block of pings as the object front end builds it
    pings = [SonarPing(t_s=0.1 * i, port=row[:w], starboard=row[w:], slant_range_m=12.8, altitude_m=3.0 + 0.01 * i)
             for i, row in enumerate(image)]
    build_waterfall(pings, WaterfallConfig(ground_res_m=0.1, resample_along=False, line_removal=True))
    # a real block's rows are ~1000 columns: their medians by selection (longer rows than here)
    row_medians(rng.gamma(2.0, 0.5, (8, 600)).astype(np.float32))


def run(args):
    import os
    import shutil
    import sys
    import tempfile
    import time

    from adaptnav import kernels

    path = kernels.aot_path()
    if args.portable and not args.jit_only:
        # built anew whatever lies there: a build for this CPU has the same name
        os.environ["ADAPTNAV_KERNELS"] = "jit"
    elif not args.jit_only and kernels.using_aot():
        # a build passed over (damaged, or for another CPU) for a good one elsewhere: removed,
        # so that it is not looked at (and warned of) at every start
        for unusable in kernels.passed_over:
            try:
                unusable.with_name(unusable.name.split(".")[0] + ".json").unlink(missing_ok=True)
                unusable.unlink(missing_ok=True)
                print(f"adaptnav warmup: removed the unusable build {unusable}")
            except OSError as e:
                print(f"adaptnav warmup: could not remove the unusable build {unusable}: {e}", file=sys.stderr)
        print(f"adaptnav warmup: kernels compiled ahead of time ({kernels.loaded_build()}): "
              f"{kernels.loaded_aot_path()}")
        return 0
    tmp = None
    saved_cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if not args.jit_only:
        # compiled afresh (not loaded from numba's cache), a kernel records the signatures
        # of the kernels it calls too: all of them are then built ahead of time
        tmp = tempfile.mkdtemp(prefix="adaptnav-jit-")
        os.environ["NUMBA_CACHE_DIR"] = tmp
    try:
        cfg = load_config_or_report(args, "warmup")
        if cfg is None:
            return 2

        def warm_up() -> None:
            from adaptnav.service.calibrator.preload import warm_kernels
            from adaptnav.service.daemon import warm_up_filter

            t0 = time.monotonic()
            warm_up_filter(cfg)
            warm_kernels()
            _exercise_calibration_kernels()
            _exercise_sonar_kernels()
            print(f"adaptnav warmup: kernels just in time {time.monotonic() - t0:.1f} s")

        if args.jit_only:
            warm_up()
            return 0
        t0 = time.monotonic()
        try:
            kernels.build(warm_up, portable=args.portable)
        except Exception as e:  # noqa: BLE001 - no compiler, read-only directory: JIT still works
            print(f"adaptnav warmup: ahead-of-time build failed ({type(e).__name__}: {e}); "
                  "the service uses its kernels just in time, cached now", file=sys.stderr)
            import subprocess

            env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
            if saved_cache_dir is not None:
                env["NUMBA_CACHE_DIR"] = saved_cache_dir
            cmd = [sys.executable, "-m", "adaptnav", "warmup", "--jit-only"]
            if args.config:
                cmd += ["--config", args.config]
            for o in args.overrides:
                cmd += ["--set", o]
            return subprocess.run(cmd, env=env).returncode
        print(f"adaptnav warmup: kernels compiled ahead of time ({'portable' if args.portable else 'host'}) "
              f"in {time.monotonic() - t0:.1f} s: {path}")
        return 0
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
