"""`adaptnav experiment thesis`: the seed's §3.6 table (static vs learned motion model);
`adaptnav experiment landmarks`: side-scan object landmarks re-found on reciprocal legs.

See :mod:`adaptnav.calibration.thesis` for the simulation, the controls chosen and the learner,
and :mod:`adaptnav.service.tools.landmarks_experiment` for the landmark survey. Its
``drift_percent_with_landmarks`` is issue 14's: the landmarks in the filter and the calibrator
(:mod:`adaptnav.service.tools.landmark_learning`, through the runner), against
``drift_percent_without_landmarks`` (neither); ``drift_percent_with_landmarks_filter_only`` is the
filter fusing the closures without the calibrator.
"""
from __future__ import annotations

import math
import sys

HELP = "reproduce the thesis experiments (static vs learned motion model); side-scan landmark survey"


def _usage(message: str) -> None:
    """An argument the experiment cannot run with: one line, exit 2 (as argparse's own)."""
    print(f"adaptnav experiment: {message}", file=sys.stderr)
    raise SystemExit(2)


def _pair(text: str) -> tuple[float, float]:
    parts = text.split(",")
    if len(parts) != 2:
        raise ValueError(f"expected SDD,STR, got {text!r}")
    return float(parts[0]), float(parts[1])


def add_arguments(parser):
    import argparse

    parser.add_argument("name", choices=("thesis", "landmarks"), help="which experiment")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="landmarks: scenario key override (e.g. seed=7, duration_s=1800); repeatable")
    parser.add_argument("--seeds", type=int, default=20, help="seeds per row (default 20)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (default 0)")
    parser.add_argument("--jobs", type=int, default=0,
                        help="worker processes (default: the CPUs this process may use); same output for any number")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    parser.add_argument("--no-calibrator", action="store_true",
                        help="landmarks: skip the run through the runner with the online calibrator (about half "
                             "the time); drift_percent_with_landmarks and the calibrator's k_V keys are then absent")
    # the calibrator run used to be opt-in; the flag is still accepted and changes nothing
    parser.add_argument("--calibrator", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--plots", metavar="DIR", help="write error-vs-time plots (one per row) into DIR")
    parser.add_argument("--initial", metavar="SDD,STR", help="custom row: initial σ_Dd,σ_Tr")
    parser.add_argument("--changed", metavar="SDD,STR", help="custom row: changed σ*_Dd,σ*_Tr")
    parser.add_argument("--sensor-noise", type=float, help="custom row: range noise (m)")
    parser.add_argument("--change-step", type=int, help="custom row: step of the change (default 5)")
    parser.add_argument("--steps", type=int, help="custom row: number of steps (default 100)")
    parser.add_argument("--landmarks", type=int, help="custom row: number of landmarks (default 4)")


def _rows(args):
    from adaptnav.calibration.thesis import THESIS_ROWS, ThesisRow

    custom = any(x is not None for x in (args.initial, args.changed, args.sensor_noise, args.change_step,
                                          args.steps, args.landmarks))
    if not custom:
        return list(THESIS_ROWS)
    base = ThesisRow()
    ini = _pair(args.initial) if args.initial else (base.sigma_dd_initial, base.sigma_tr_initial)
    chg = _pair(args.changed) if args.changed else (base.sigma_dd_changed, base.sigma_tr_changed)
    row = ThesisRow(ini[0], ini[1], chg[0], chg[1],
                    args.sensor_noise if args.sensor_noise is not None else base.sensor_noise,
                    args.change_step if args.change_step is not None else base.change_step,
                    args.steps if args.steps is not None else base.steps,
                    args.landmarks if args.landmarks is not None else base.landmarks)
    if row.steps < 2 or row.landmarks < 1 or not 0 <= row.change_step <= row.steps:
        _usage("need steps ≥ 2, landmarks ≥ 1, 0 ≤ change-step ≤ steps")
    if not all(0.0 < v < math.inf for v in (*ini, *chg, row.sensor_noise)):  # (NaN too)
        _usage("σ values and sensor noise must be positive numbers")
    return [row]


def _plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    r = result.row
    t = np.arange(result.static_errors.shape[1])
    fig, ax = plt.subplots(figsize=(7, 4))
    for errs, label, colour in ((result.static_errors, "static", "tab:red"),
                                (result.learned_errors, "learned", "tab:blue")):
        m = errs.mean(axis=0)
        lo, hi = np.percentile(errs, [10, 90], axis=0)
        ax.plot(t, m, color=colour, label=f"{label} (mean {errs.mean():.2f} m)")
        ax.fill_between(t, lo, hi, color=colour, alpha=0.15)
    ax.axvline(r.change_step, color="k", ls=":", lw=1)
    ax.set_xlabel("time step")
    ax.set_ylabel("localisation error (m)")
    ax.set_title(f"σDd {r.sigma_dd_initial}→{r.sigma_dd_changed}, σTr {r.sigma_tr_initial}→{r.sigma_tr_changed}, "
                 f"sensor noise {r.sensor_noise} ({result.static_errors.shape[0]} seeds)", fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _nothing():
    import contextlib

    return contextlib.nullcontext()


def _run_landmarks(args) -> int:
    import json

    from adaptnav.fusion.typed_config import ConfigError
    from adaptnav.service.tools.landmarks_experiment import load, run

    try:
        scenario = load(args.overrides)
    except (ConfigError, ValueError) as e:
        raise SystemExit(f"adaptnav experiment landmarks: {e}")
    result = run(scenario).to_dict()
    # the drift_percent_with_landmarks has the landmarks in the filter *and* the calibrator
    # (vs neither); the filter-only figure keeps its own name
    result["drift_percent_with_landmarks_filter_only"] = result.pop("drift_percent_with_landmarks")
    if not args.no_calibrator:
        from adaptnav.service.tools.landmark_learning import run as run_learning

        learned = run_learning(scenario)
        result["drift_percent_with_landmarks"] = learned.pop("drift_percent_with_landmarks_and_calibrator")
        result.update(learned)
    if args.json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k:34s} {v}")
    return 0


def run(args):
    import json
    if args.name == "landmarks":
        return _run_landmarks(args)
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from pathlib import Path

    from adaptnav.service.console import progress

    from adaptnav.calibration.thesis import row_result, run_seed

    if args.seeds < 1:
        _usage("--seeds must be ≥ 1")
    if args.jobs < 0:
        _usage("--jobs must be ≥ 0 (0: one per CPU)")
    try:
        rows = _rows(args)
    except ValueError as e:
        _usage(str(e))
    if args.plots:  # the plots' folder before the seeds run: a traceback came after all of them
        from adaptnav.service.commands.paths import output_folder_problem

        problem = output_folder_problem(args.plots)
        if problem:
            _usage(f"--plots {args.plots}: cannot make the folder {problem}")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    tasks = [(row, seed) for row in rows for seed in seeds]
    jobs = min(args.jobs if args.jobs > 0 else len(os.sched_getaffinity(0)), len(tasks))
    bar = progress(len(tasks), "thesis", "seed")  # a bar on a terminal, else a line every 10 s
    with bar if bar is not None else _nothing():
        if jobs == 1:
            per_task = []
            for row, seed in tasks:
                per_task.append(run_seed(row, seed))
                if bar is not None:
                    bar.update(1)
        else:
            # every (row, seed) owns its generators (calibration.thesis.run_seed): the
            # result does not depend on which worker ran it or when
            with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(run_seed, row, seed) for row, seed in tasks]
                for f in as_completed(futures):
                    if bar is not None:
                        bar.update(1)
                per_task = [f.result() for f in futures]
    n = len(seeds)
    results = [row_result(row, per_task[i * n:(i + 1) * n]) for i, row in enumerate(rows)]
    summaries = [r.summary() for r in results]
    if args.plots:
        out = Path(args.plots)
        out.mkdir(parents=True, exist_ok=True)
        for i, res in enumerate(results, 1):
            r = res.row
            _plot(res, out / f"row{i}_dd{r.sigma_dd_changed}_tr{r.sigma_tr_changed}_noise{r.sensor_noise}.png")
    if args.json:
        print(json.dumps(summaries, indent=2))
    else:
        print(f"{'σDd':>5} {'σTr':>5} {'σ*Dd':>5} {'σ*Tr':>5} {'noise':>5} | {'static m':>18} | "
              f"{'learned m':>18} | {'σDd learned':>11} {'σTr learned':>11}")
        for s in summaries:
            def fmt(key):
                return f"{s[key]:6.2f} [{s[key + '_ci95'][0]:5.2f},{s[key + '_ci95'][1]:5.2f}]"
            print(f"{s['sigma_dd_initial']:5.2f} {s['sigma_tr_initial']:5.2f} {s['sigma_dd_changed']:5.2f} "
                  f"{s['sigma_tr_changed']:5.2f} {s['sensor_noise']:5.1f} | {fmt('static_error_m')} | "
                  f"{fmt('learned_error_m')} | {s['learned_sigma_dd']:11.3f} "
                  f"{s['learned_sigma_tr']:11.3f}")
    return 0
