"""`adaptnav bench sonar`: side-scan window registrations per second vs plain SIFT; the
calibrator's side-scan front end, objects vs SIFT windows (:func:`calibrator_front_ends`).

Two inputs, each turned into a ping-indexed waterfall whose consecutive 200-ping windows
(step 20 pings) are registered: the real Scotsman survey (1024 samples per side; the
headline figures, when ``../shared/data`` is present) and a synthetic survey line
(1024 samples per side, 30 m range, strongly textured seabed).

* ours: :class:`adaptnav.sonar.motion.WindowRegistrar` — SIFT on a 2× downsampled image, K = 400
  strongest, features of the previous window cached (one detection per window);
* peer: plain full-resolution SIFT on both windows of every pair (no cap, no cache),
  the same ratio test and RANSAC.

OpenCV runs on one thread (``cv2.setNumThreads(1)``) so the figures are per core.
"""
from __future__ import annotations

import math
import time

import numpy as np


def _survey(n_pings: int, samples: int, seed: int = 0):
    from adaptnav.sim.seabed import Seabed
    from adaptnav.sim.sidescan import SidescanRenderer

    rng = np.random.default_rng(seed)
    ds, v = 0.2, 1.5
    seabed = Seabed.random((n_pings * ds + 20.0, 70.0), rng, n_objects=int(n_pings * ds / 2))
    ren = SidescanRenderer(seabed, 30.0, samples)
    pos = np.column_stack([10.0 + np.arange(n_pings) * ds, np.full(n_pings, 35.0)])
    t0 = time.perf_counter()
    pings = ren.render_track(np.arange(n_pings) * ds / v, pos, 0.0, 8.0, rng, v)
    return pings, (time.perf_counter() - t0) / n_pings


def _plain_sift_pair(img_a, img_b, mask_a, mask_b, res_along, wa, wb):
    import cv2

    from adaptnav.sonar.matching import fit_similarity, match_descriptors
    from adaptnav.sonar.motion import window_metric_xy

    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(img_a, mask_a)
    kb, db = sift.detectAndCompute(img_b, mask_b)
    if da is None or db is None:
        return None
    pairs = match_descriptors(da, db, ratio=0.8)
    if len(pairs) < 6:
        return None
    pa = window_metric_xy(wa, np.array([ka[i].pt for i in pairs[:, 0]]), res_along)
    pb = window_metric_xy(wb, np.array([kb[i].pt for i in pairs[:, 1]]), res_along)
    return fit_similarity(pa, pb, ransac_threshold=0.3)


def _measure(wf, window: int, step: int, n_plain_max: int) -> dict:
    """Ours (streamed, cached) vs plain full-image SIFT on the same window pairs."""
    from adaptnav.sonar.motion import WindowRegistrar
    from adaptnav.sonar.waterfall import to_uint8

    reg = WindowRegistrar()
    t0 = time.perf_counter()
    ours = list(reg.register_stream(wf, window, step))
    ours_s = time.perf_counter() - t0
    ok = [m for _, _, m in ours if m is not None]
    err_pings = [abs(m.along_m / wf.along_res_m - step) for m in ok]

    img = to_uint8(wf.image)
    mask = (wf.image > 0).astype(np.uint8) * 255
    n_plain = min(len(ours), n_plain_max)
    t0 = time.perf_counter()
    plain_ok = 0
    plain_err = []
    for a, b, _ in ours[:n_plain]:
        sim = _plain_sift_pair(img[a:a + window], img[b:b + window], mask[a:a + window],
                               mask[b:b + window], wf.along_res_m,
                               wf.rows(a, a + window), wf.rows(b, b + window))
        plain_ok += sim is not None
    plain_s = time.perf_counter() - t0
    ours_rate = len(ours) / ours_s
    plain_rate = n_plain / plain_s
    return {
        "registrations": len(ours),
        "registrations_ok": len(ok),
        "ours_registrations_per_s": ours_rate,
        "ours_max_along_error_pings": float(max(err_pings)) if err_pings else math.nan,
        "plain_sift_pairs": n_plain,
        "plain_sift_ok": plain_ok,
        "plain_sift_registrations_per_s": plain_rate,
        "speedup_vs_plain_sift": ours_rate / plain_rate,
    }


def calibrator_front_ends(duration_s: float = 300.0) -> dict:
    """CPU (``time.process_time``, one thread) of the calibrator's side-scan front end per ping
    and per data second on the landmark survey (seed 1, 10 Hz pings): the object detector it
    runs (:class:`adaptnav.calibration.sidescan.CalibratorSonar`) against the SIFT landmark
    windows it ran before (:class:`adaptnav.sonar.stream.SonarFrontEnd`, no registration), both
    fed the same pings with positions from the same ping dead reckoning."""
    from adaptnav.calibration.sidescan import CalibratorSonar
    from adaptnav.sim.scenario import load_scenario
    from adaptnav.sim.simulator import simulate
    from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
    from adaptnav.sonar.stream import FrontEndConfig, SonarFrontEnd

    sc = load_scenario("survey", [f"duration_s={duration_s}", "seed=1", "dvl.enabled=false", "sonar.enabled=true"])
    pings = [it for it in simulate(sc).iter_blocks() if it.KIND == "sonar"]
    objects = CalibratorSonar()
    t0 = time.process_time()
    batches = sum(objects.push(p) is not None for p in pings)
    t_obj = time.process_time() - t0
    sift, dr = SonarFrontEnd(FrontEndConfig(register=False, detect_margin_pings=8)), AnchoredDeadReckoning()
    t0 = time.process_time()
    for p in pings:
        pos, sigma = dr.push(p)
        sift.push(p, pos, None)
    t_sift = time.process_time() - t0
    n, secs = len(pings), float(pings[-1].t_s - pings[0].t_s)
    return {"calibrator_pings": n, "calibrator_objects_ms_per_ping": 1e3 * t_obj / n,
            "calibrator_objects_ms_per_data_s": 1e3 * t_obj / secs,
            "calibrator_objects_blocks": objects.front_end.blocks, "calibrator_object_batches": batches,
            "calibrator_sift_ms_per_ping": 1e3 * t_sift / n, "calibrator_sift_ms_per_data_s": 1e3 * t_sift / secs,
            "calibrator_sift_windows": sift.windows,
            "calibrator_sift_ms_per_window": 1e3 * t_sift / max(sift.windows, 1),
            "calibrator_objects_ms_per_block": 1e3 * t_obj / max(objects.front_end.blocks, 1)}


def run(args) -> dict:
    """Figures on the synthetic survey and, when present, the real Scotsman file."""
    from pathlib import Path

    import cv2

    from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall
    from adaptnav.sonar.xtf import SonarFileError, read_xtf

    cv2.setNumThreads(1)
    quick = bool(getattr(args, "quick", False))
    window, step, samples = 200, 20, 1024
    n_pairs = 5 if quick else 20
    pings, render_s = _survey(window + step * n_pairs, samples)
    wf = build_waterfall(pings, WaterfallConfig(resample_along=False))
    out: dict = {"samples_per_side": samples, "window_pings": window, "step_pings": step,
                 "synthetic_render_ms_per_ping": render_s * 1e3}
    for k, v in _measure(wf, window, step, 3 if quick else 8).items():
        out[f"synthetic_{k}"] = v

    real = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "sidescan" / "scotsman-iver2.xtf"
    if real.is_file():
        try:
            rp, _ = read_xtf(real)
            rwf = build_waterfall(rp, WaterfallConfig(resample_along=False))
            for k, v in _measure(rwf, window, step, 3 if quick else 13).items():
                out[f"scotsman_{k}"] = v
        except SonarFileError as exc:
            out["scotsman_error"] = str(exc)
    out.update(calibrator_front_ends(120.0 if quick else 300.0))
    src = "scotsman" if "scotsman_registrations" in out else "synthetic"
    out["ours_registrations_per_s"] = out[f"{src}_ours_registrations_per_s"]
    out["plain_sift_registrations_per_s"] = out[f"{src}_plain_sift_registrations_per_s"]
    out["speedup_vs_plain_sift"] = out[f"{src}_speedup_vs_plain_sift"]
    out["headline_source"] = src
    return out
