"""`adaptnav sonar`: side-scan files → waterfall picture, visual motion records.

    adaptnav sonar waterfall FILE.xtf --out FILE.png [--res-m 0.05]   (a long file: FILE-001.png, …)
    adaptnav sonar motion FILE.xtf [--window PINGS --step PINGS] [--detector sift|orb] --json

Files without side-scan channels, unreadable or truncated files give a one-line
message (exit code 2), never a traceback.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

HELP = "side-scan sonar: waterfall images and visual motion from XTF files"


def add_arguments(parser):
    sub = parser.add_subparsers(dest="sonar_cmd", metavar="CMD", required=True)
    w = sub.add_parser("waterfall", help="ground-range waterfall PNG (port left, starboard right, time down)")
    w.add_argument("file", help="XTF file")
    w.add_argument("--out", required=True, help="output PNG")
    w.add_argument("--res-m", type=float, default=None,
                   help="pixel size in metres (default: the slant sample spacing)")
    w.add_argument("--bottom", choices=("auto", "altitude", "detect"), default="auto",
                   help="altitude source for the slant-range correction")
    m = sub.add_parser("motion", help="visual motion between consecutive windows of pings")
    m.add_argument("file", help="XTF file")
    m.add_argument("--window", type=int, default=200, help="pings per window")
    m.add_argument("--step", type=int, default=20, help="pings between window starts")
    m.add_argument("--detector", choices=("sift", "orb"), default="sift")
    m.add_argument("--max-keypoints", type=int, default=400)
    m.add_argument("--json", action="store_true", help="one JSON record per line")


def _fail(msg: str) -> int:
    print(f"adaptnav sonar: {msg}", file=sys.stderr)
    return 2


def run(args) -> int:
    from adaptnav.sonar.xtf import SonarFileError, read_xtf

    if args.sonar_cmd == "waterfall":
        import cv2

        # before the file is read and the picture made: OpenCV picks its writer by the name's
        # extension, and without one it raised (a traceback) after all the work
        if not cv2.haveImageWriter(str(args.out)):
            return _fail(f"--out {args.out}: not a picture file name OpenCV can write (e.g. waterfall.png, .jpg, .tif)")
        # (NaN and negative sizes raised deep in the waterfall; 0 was taken for the default)
        if args.res_m is not None and not 0.0 < args.res_m < math.inf:
            return _fail(f"--res-m must be a positive number of metres, got {args.res_m:g}")
    elif args.window < 8 or args.step < 1:  # (checked before the file is read, as the others)
        return _fail("--window must be ≥ 8 and --step ≥ 1")
    elif args.max_keypoints < 1:  # (the detector's ValueError, a traceback)
        return _fail(f"--max-keypoints must be ≥ 1, got {args.max_keypoints}")
    try:
        pings, report = read_xtf(args.file)
    except SonarFileError as exc:
        return _fail(str(exc))
    if report.error or report.n_truncated or report.n_damaged:
        print(f"adaptnav sonar: warning: {report.summary()}", file=sys.stderr)
    elif report.mended:
        print(f"adaptnav sonar: note: {report.summary()}", file=sys.stderr)
    from adaptnav.sonar.waterfall import clean_pings

    pings, dropped = clean_pings(pings)
    if dropped:
        print(f"adaptnav sonar: warning: pings set aside, reordered or resampled: {dropped}", file=sys.stderr)
    if len(pings) < 2:
        return _fail(f"{args.file}: fewer than 2 usable pings")
    if args.sonar_cmd == "waterfall":
        return _waterfall(args, pings)
    return _motion(args, pings)


def scale_bar_m(width_m: float) -> float:
    """A round length (1, 2 or 5 × 10^k m) of about a fifth of ``width_m``."""
    target = max(width_m / 5.0, 1e-3)
    exp = math.floor(math.log10(target))
    for step in (5.0, 2.0, 1.0):
        if step * 10 ** exp <= target:
            return step * 10 ** exp
    return 10 ** exp


def with_scale_bar(img, res_m_per_px: float):
    """The waterfall (uint8, rows = pings) with a labelled across-track scale bar in its
    lower left corner: white on a black band, readable on any backscatter."""
    import cv2
    import numpy as np

    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    h, w = out.shape[:2]
    if not (res_m_per_px > 0 and math.isfinite(res_m_per_px)) or h < 20 or w < 40:
        return out
    length_m = scale_bar_m(w * res_m_per_px)
    px = max(1, int(round(length_m / res_m_per_px)))
    thick = max(2, h // 150)
    font = max(0.4, min(w, h) / 900.0)
    label = f"{length_m:g} m across track"
    (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, font, 1)
    x0, y0 = max(5, w // 40), h - max(8, h // 40)
    band = (x0 - 4, y0 - th - 2 * thick - 10, x0 + max(px, tw) + 4, y0 + 4)
    cv2.rectangle(out, band[:2], band[2:], (0, 0, 0), -1)
    cv2.rectangle(out, (x0, y0 - thick), (x0 + px - 1, y0), (255, 255, 255), -1)  # inclusive corners
    cv2.putText(out, label, (x0, y0 - thick - 6), cv2.FONT_HERSHEY_SIMPLEX, font, (255, 255, 255), 1, cv2.LINE_AA)
    return np.ascontiguousarray(out)


# pings per picture of `sonar waterfall`: a longer file is written as numbered tiles (a 206 MB
# XTF at the sample spacing was one 212,258 × 2048 picture and took 8.9 GB to make)
WATERFALL_TILE_PINGS = 3000


def _waterfall(args, pings) -> int:
    import cv2

    from adaptnav.sonar.waterfall import WaterfallConfig, build_waterfall, to_uint8

    res = args.res_m or pings[0].sample_spacing_m
    tiles = [pings[k:k + WATERFALL_TILE_PINGS] for k in range(0, len(pings), WATERFALL_TILE_PINGS)]
    if len(tiles) > 1 and len(tiles[-1]) < 2:  # a last ping alone makes no picture: to the one before
        tiles[-2] += tiles.pop()
    out = Path(args.out)
    try:  # (as replay's --out: its directory made when missing; OpenCV only says it could not write)
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return _fail(f"--out {out}: {e.strerror or e}")
    for k, tile in enumerate(tiles):
        path = out if len(tiles) == 1 else out.with_name(f"{out.stem}-{k + 1:03d}{out.suffix}")
        wf = build_waterfall(tile, WaterfallConfig(ground_res_m=res, along_res_m=res, bottom=args.bottom))
        if not cv2.imwrite(str(path), with_scale_bar(to_uint8(wf.image), wf.ground_res_m)):
            return _fail(f"could not write {path}")
        print(f"{path}: {wf.image.shape[0]} rows x {wf.image.shape[1]} columns, "
              f"{wf.ground_res_m:.3f} m/px across, "
              f"{wf.along_res_m:.3f} m/{'px' if math.isfinite(wf.along_res_m) else 'ping'} along"
              + (f" (pings {k * WATERFALL_TILE_PINGS}–{k * WATERFALL_TILE_PINGS + len(tile) - 1})"
                 if len(tiles) > 1 else ""))
    return 0


# pings per waterfall of `sonar motion`: the file's windows are registered chunk by chunk, so
# memory is bounded by the chunk, not by the file (a 206 MB XTF took 2.4 GB as one waterfall)
MOTION_CHUNK_PINGS = 4000


def _motion(args, pings) -> int:
    import numpy as np

    from adaptnav.sonar.features import make_detector
    from adaptnav.sonar.motion import WindowRegistrar
    from adaptnav.sonar.waterfall import WaterfallConfig, along_track_distance_m, build_waterfall

    if len(pings) < args.window + args.step:
        return _fail(f"{len(pings)} pings: too few for --window {args.window} --step {args.step}")
    if not np.all(np.isfinite(along_track_distance_m(pings))):
        return _fail("the file has no speed: along-track distances are unknown")
    reg = WindowRegistrar(make_detector(args.detector, max_keypoints=args.max_keypoints))
    n_ok = 0
    start = 0  # first ping of the chunk: the window of the next pair to register
    while start + args.window + args.step <= len(pings):
        chunk = pings[start:start + max(MOTION_CHUNK_PINGS, args.window + args.step)]
        # one row per ping so that --window/--step are in pings
        wf = build_waterfall(chunk, WaterfallConfig(resample_along=False))
        last = None
        for a, b, mot in reg.register_stream(wf, args.window, args.step):
            last = a
            if mot is None:
                rec = {"t_s": float(wf.t_s[min(b + args.window // 2, len(wf.t_s) - 1)]), "along_m": None,
                       "across_m": None, "dheading_rad": None, "inliers": 0, "matches": 0}
            else:
                n_ok += 1
                r = mot.to_record()
                rec = {k: r[k] for k in ("t_s", "along_m", "across_m", "dheading_rad", "inliers", "matches")}
            rec["ping_a"], rec["ping_b"] = start + a, start + b
            if args.json:
                print(json.dumps(rec))
            else:
                vals = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in rec.items())
                print(vals)
        if last is None:
            break
        start += last + args.step
    return 0 if n_ok else _fail("no window pair could be registered")
