"""Replay plots (matplotlib, Agg backend — no display needed).

- ``track.png``: estimated vs true track (north/east), and horizontal error vs time with
  the filter's ±3σ horizontal bound ``3·sqrt(P_NN + P_EE)`` and fused fixes marked;
- ``params.png``: motion parameters over time (k_V, then σ of each variance term),
  with the filter's ``k_speed`` state and the truth ``k_v`` when present;
- ``innovations.png``: normalised innovations ``ν/√S`` per aiding source over time,
  fused and rejected apart, with ±3.
"""
from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any, Sequence

import numpy as np


# what each aid's measurement vector holds (fusion/aiding/<source>.py), for labels
AID_COMPONENTS: dict[str, tuple[str, ...]] = {
    "gnss": ("north", "east"),
    "usbl": ("north", "east", "down"),
    "depth": ("down",),
    "heading": ("yaw",),
    "attitude": ("roll", "pitch", "yaw"),
    "dvl": ("forward", "right", "down"),
    "learned_velocity": ("surge", "sway", "heave"),
    "visual_motion": ("along-track", "across-track"),
}


def component_names(source: str, width: int) -> list[str]:
    """Names of the ``width`` components of ``source``'s measurement (index when unknown)."""
    names = AID_COMPONENTS.get(source, ())
    return [names[j] if width <= len(names) else f"component {j + 1}" for j in range(width)]


def headless_pyplot():
    """matplotlib on its file backend (no display on a vehicle or in CI)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Any, dpi: int = 90, fmt: str | None = None) -> None:
    """Lay out, write and close ``fig`` (closing frees the figure's memory in a long run)."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi, format=fmt)
    headless_pyplot().close(fig)


def error_sigma_series(rec: Any, track: Any, truth: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """What the error plots show, shared by the PNGs and the HTML report.

    Returns
    -------
    t_min : (N,) minutes since the first state
    sigma_h_m : (N,) horizontal 1σ from the covariance (m)
    err_h_m : (N,) horizontal error against truth (m, NaN outside the truth's span), or None
    fix_t_min : (K,) times of fused position fixes (min)
    """
    t_min = (track.t_s - track.t_s[0]) / 60.0
    sigma_h_m = np.sqrt(np.clip(track.cov_pva[:, 0, 0] + track.cov_pva[:, 1, 1], 0.0, None))
    err_h_m = None
    if truth is not None:
        inside = (track.t_s >= truth.t_s[0]) & (track.t_s <= truth.t_s[-1])
        n = np.interp(track.t_s, truth.t_s, truth.pos_n_m[:, 0])
        e = np.interp(track.t_s, truth.t_s, truth.pos_n_m[:, 1])
        err_h_m = np.where(inside, np.hypot(track.pos_n_m[:, 0] - n, track.pos_n_m[:, 1] - e), np.nan)
    fixes = [r[0] for r in rec.aid_rows if r[2] and r[1] in rec.FIX_SOURCES]
    fix_t_min = (np.asarray(fixes, float) - track.t_s[0]) / 60.0
    return t_min, sigma_h_m, err_h_m, fix_t_min


def plot_track(rec: Any, path: Path, title: str = "", gaps_s: Sequence[tuple[float, float]] = ()) -> bool:
    """The track (and the truth's) and the horizontal error with its 3σ over time; the spans
    of ``gaps_s`` (data missing, coasted through: ``(from_s, to_s)``) shaded."""
    track = rec.track()
    if len(track.t_s) == 0:
        return False
    plt = headless_pyplot()
    truth = rec.truth()
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 5.5))
    ax0.plot(track.pos_n_m[:, 1], track.pos_n_m[:, 0], lw=1.0, label="estimate")
    if truth is not None:
        ax0.plot(truth.pos_n_m[:, 1], truth.pos_n_m[:, 0], lw=1.0, ls="--", label="truth")
    ax0.set_xlabel("east (m)")
    ax0.set_ylabel("north (m)")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.legend(loc="best")
    ax0.set_title("track")
    t_min, sigma_h, err, fix_t_min = error_sigma_series(rec, track, truth)
    if err is not None:
        ax1.plot(t_min, err, lw=1.0, label="horizontal error")
    ax1.fill_between(t_min, 0.0, 3.0 * sigma_h, alpha=0.25, color="tab:orange", label="3σ (horizontal)")
    if len(fix_t_min):
        ax1.plot(fix_t_min, np.zeros(len(fix_t_min)), "k|", ms=10, label="fused position fixes")
    for k, (a, b) in enumerate(gaps_s):
        ax1.axvspan((a - track.t_s[0]) / 60.0, (b - track.t_s[0]) / 60.0, color="0.6", alpha=0.4,
                    label="no input (coasted)" if k == 0 else None)
    ax1.set_xlabel("time (min)")
    ax1.set_ylabel("m")
    ax1.set_title("horizontal error and ±3σ")
    ax1.legend(loc="upper left")
    if title:
        fig.suptitle(title)
    save_figure(fig, path)
    return True


# units of σ of each variance term (DESIGN.md "Motion model": V ~ N(k_V v, v²σ_Vv² + w²σ_Vw² + σ_V1²), ...)
SIGMA_UNITS = {"var_vv": "–", "var_vw": "m", "var_v1": "m/s", "var_wv": "rad/m", "var_ww": "–",
               "var_w1": "rad/s", "var_s": "m/s"}


def plot_params(rec: Any, path: Any, title: str = "", fmt: str | None = None) -> bool:
    plt = headless_pyplot()
    from adaptnav.fusion.motion_model import MotionParams

    rows = []
    if rec.initial_params is not None and rec.nav_t:
        rows.append((rec.nav_t[0], rec.initial_params, True))
    rows += [(r.t_s, r.params, bool(r.accepted)) for r in rec.releases if r.params is not None]
    if not rows and not rec.nav_t:
        return False
    names = MotionParams.VARIANCE_NAMES
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    t0 = rec.nav_t[0] if rec.nav_t else rows[0][0]
    t_end = rec.nav_t[-1] if rec.nav_t else rows[-1][0]
    if rows:
        t = (np.asarray([r[0] for r in rows]) - t0) / 60.0
        acc = np.asarray([r[2] for r in rows])
        k_v = np.asarray([r[1].k_v for r in rows])
        # accepted values hold until the next accepted release: extend the steps to the end
        t_acc = np.append(t[acc], (t_end - t0) / 60.0)
        axes[0].step(t_acc, np.append(k_v[acc], k_v[acc][-1]), where="post", label="model k_V (accepted)")
        if np.any(~acc):
            axes[0].plot(t[~acc], k_v[~acc], "rx", label="rejected release")
        for name in names:
            sig = np.sqrt([getattr(r[1], name) for r in rows])
            axes[1].step(t_acc, np.append(sig[acc], sig[acc][-1]), where="post",
                         label=f"σ_{name[4:].upper()} ({SIGMA_UNITS.get(name, '?')})")
            if np.any(~acc):
                axes[1].plot(t[~acc], sig[~acc], "x", color=axes[1].lines[-1].get_color(), ms=4)
    if rec.nav_t:
        t_nav = np.asarray(rec.nav_t)
        scale = np.asarray(rec.nav_k_speed)
        if rows and np.any(acc):
            # the filter's surge scale is k_speed · k_V of the model in use at that time
            t_rel = np.asarray([r[0] for r in rows])[acc]
            idx = np.clip(np.searchsorted(t_rel, t_nav, side="right") - 1, 0, None)
            scale = scale * k_v[acc][idx]
        axes[0].plot((t_nav - t0) / 60.0, scale, lw=1.0, label="filter k_speed · model k_V")
    if rec.truth_rows:
        t_truth, k_true = rec.truth_k_v()
        axes[0].plot((t_truth - t0) / 60.0, k_true, "k--", lw=1.0, label="truth k_V")
    if rows:
        axes[1].set_yscale("log")  # the seven σ span decades
        axes[1].legend(loc="best", fontsize=8, ncol=2)
    axes[0].set_ylabel("speed scale")
    axes[0].legend(loc="best")
    axes[1].set_ylabel("σ (unit of each term in the legend)")
    axes[1].set_xlabel("time (min)")
    fig.suptitle(title or "motion parameters")
    save_figure(fig, path, fmt=fmt)
    return True


def innovations_figure(rec: Any, max_points: int = 20000, width_in: float = 10.0) -> Any:
    """One panel per aid source: fused normalised innovations ν/√S per component, the
    rejected ones as their largest |ν/√S|, ±3 marked; None without aid statuses.
    ``max_points`` per panel (dense sources are decimated)."""
    if not rec.aid_rows:
        return None
    plt = headless_pyplot()
    sources = sorted({r[1] for r in rec.aid_rows})
    fig, axes = plt.subplots(len(sources), 1, figsize=(width_in, 1.8 * len(sources) + 0.9), sharex=True,
                             squeeze=False)
    t0 = rec.nav_t[0] if rec.nav_t else rec.aid_rows[0][0]
    for ax, src in zip(axes[:, 0], sources):
        rows = [r for r in rec.aid_rows if r[1] == src]
        width = max(len(r[4]) for r in rows)
        t = (np.asarray([r[0] for r in rows]) - t0) / 60.0
        fused = np.asarray([r[2] for r in rows])
        nu = np.full((len(rows), width), np.nan)
        for i, r in enumerate(rows):
            nu[i, :len(r[4])] = r[4]
        step = max(1, len(rows) // max_points)
        for j, name in enumerate(component_names(src, width)):
            ax.plot(t[fused][::step], nu[fused, j][::step], ".", ms=1.5, label=f"{name} fused")
        if np.any(~fused):
            ax.plot(t[~fused], np.nanmax(np.abs(nu[~fused]), axis=1, initial=0.0), "rx", ms=3, label="rejected")
        ax.axhline(3.0, color="k", lw=0.5, ls=":")
        ax.axhline(-3.0, color="k", lw=0.5, ls=":")
        ax.set_ylabel(f"{src}\nν/√S (–)", fontsize=8)
        ax.legend(loc="upper right", fontsize=7, ncol=4, markerscale=4)
    axes[-1, 0].set_xlabel("time since the first state (min)")
    return fig


def plot_innovations(rec: Any, path: Path, title: str = "") -> bool:
    fig = innovations_figure(rec)
    if fig is None:
        return False
    fig.suptitle(title or "normalised innovations")
    save_figure(fig, path)
    return True


def write_all(rec: Any, out_dir: Path, title: str = "", gaps_s: Sequence[tuple[float, float]] = ()) -> list[Path]:
    """Write the three plots that have data (``gaps_s`` as :func:`plot_track`'s); return the
    paths written."""
    out_dir = Path(out_dir)
    written = []
    for name, fn in (("track.png", partial(plot_track, gaps_s=gaps_s)), ("params.png", plot_params),
                     ("innovations.png", plot_innovations)):
        if fn(rec, out_dir / name, title):
            written.append(out_dir / name)
    return written
