"""``adaptnav replay --report OUT.html``: one self-contained page to share after a replay.

Like PX4 Flight Review's page, but a single file: figures are matplotlib SVG written into
the page, tables are HTML, there is no script, no font or style sheet from outside — it
opens offline in any browser, from a mail attachment or a ticket. Sections:

1. the summary (input, duration, speed, samples, origin) and *what was missing in the
   input* (streams a navigation run wants, corrupt frames, truncation, rejected samples);
2. the track in local metres (north/east at the NED origin, truth when present) and the
   horizontal error with the filter's ±3σ bound;
3. aids: one row per source, fused and rejected counts, rejections by reason;
4. normalised innovations ν/√S per source, components named (north, east, surge, ...);
5. calibrator releases, accepted or rejected, with their reasons, and the motion
   parameters over time;
6. the metrics against truth (when present).
"""
from __future__ import annotations

import html
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from adaptnav.service.tools.plots import error_sigma_series, headless_pyplot, plot_params
from adaptnav.service.tools.plots import innovations_figure as innovations_plot

def _svg(fig: Any) -> str:
    plt = headless_pyplot()
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    plt.close(fig)
    text = buf.getvalue()
    return text[text.index("<svg"):]  # drop the XML prolog and DOCTYPE: inline SVG in HTML


def _esc(x: Any) -> str:
    return html.escape(str(x))


def _num(x: Any, fmt: str = ".4g") -> str:
    if isinstance(x, bool) or x is None:
        return _esc(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "–" if not math.isfinite(float(x)) else format(float(x), fmt)
    return _esc(x)


def _table(header: list[str], rows: list[list[Any]], cls: str = "") -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


# -- figures ---------------------------------------------------------------------------------
def track_figure(rec: Any) -> str | None:
    track = rec.track()
    if len(track.t_s) == 0:
        return None
    plt = headless_pyplot()
    truth = rec.truth()
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    ax.plot(track.pos_n_m[:, 1], track.pos_n_m[:, 0], lw=1.0, label="estimate")
    if truth is not None:
        ax.plot(truth.pos_n_m[:, 1], truth.pos_n_m[:, 0], lw=1.0, ls="--", label="truth")
    ax.plot(track.pos_n_m[:1, 1], track.pos_n_m[:1, 0], "go", ms=5, label="start")
    ax.set_xlabel("east of the origin (m)")
    ax.set_ylabel("north of the origin (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    return _svg(fig)


def error_figure(rec: Any) -> str | None:
    track = rec.track()
    if len(track.t_s) == 0:
        return None
    plt = headless_pyplot()
    truth = rec.truth()
    t_min, sigma_h, err, fix_t_min = error_sigma_series(rec, track, truth)
    fig, ax = plt.subplots(figsize=(9, 3.6))
    ax.fill_between(t_min, 0.0, 3.0 * sigma_h, alpha=0.25, color="tab:orange", label="3σ horizontal (m)")
    if err is not None:
        ax.plot(t_min, err, lw=1.0, label="horizontal error vs truth (m)")
    if len(fix_t_min):
        ax.plot(fix_t_min, np.zeros(len(fix_t_min)), "k|", ms=10, label="fused position fix")
    ax.set_xlabel("time since the first state (min)")
    ax.set_ylabel("m")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return _svg(fig)


def innovations_figure(rec: Any) -> str | None:
    # an SVG in a page: a few thousand points per panel
    fig = innovations_plot(rec, max_points=4000, width_in=9.0)
    return None if fig is None else _svg(fig)


def params_figure(rec: Any) -> str | None:
    buf = io.StringIO()
    ok = plot_params(rec, buf, "", fmt="svg")
    if not ok:
        return None
    text = buf.getvalue()
    return text[text.index("<svg"):]


# -- tables ----------------------------------------------------------------------------------
def aid_table(consistency: dict) -> str:
    """Per aid, from the replay's ``aid_consistency`` (summary.json): fused and rejected, by
    reason, its mean NIS per degree of freedom and the share within the χ² 95 % bound."""
    rows = []
    for src, a in sorted(consistency.items()):
        n_rej = a["attempts"] - a["fused"]
        reasons = ", ".join(f"{_esc(k)} {v}" for k, v in sorted(a["refused"].items(), key=lambda kv: -kv[1])) or "–"
        nis, within = a["nis_per_dof_mean"], a["within_95"]
        share = f"{100.0 * a['fused'] / a['attempts']:.1f} %" if a["attempts"] else "–"
        rows.append([_esc(src), a["fused"], n_rej, share,
                     _num(nis, ".3g") if nis is not None else "–",
                     f"{100.0 * within:.1f} %" if within is not None else "–", reasons])
    return _table(["source", "fused", "rejected", "fused share", "NIS per dof (≈ 1)", "within χ² 95 % (≈ 95 %)",
                   "rejected by reason"], rows)


def releases_table(rec: Any) -> str:
    if not rec.releases:
        return "<p>No calibrator releases (the calibrator was off, or no window completed).</p>"
    rows = []
    for r in rec.releases:
        p = r.params
        rows.append([_num(float(r.t_s), ".1f"), "accepted" if r.accepted else "<b>rejected</b>",
                     _num(p.k_v) if p is not None else "–",
                     _num(math.sqrt(p.var_vv)) if p is not None else "–",
                     _num(float(r.log_likelihood)), _esc(r.reason or "–")])
    return _table(["data time (s)", "verdict", "k_V (–)", "σ_Vv (–)", "log-likelihood", "reason / what was held"],
                  rows)


def _flat(prefix: str, obj: Any, out: list) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _flat(f"{prefix}.{k}" if prefix else str(k), v, out)
    else:
        out.append((prefix, obj))


def summary_table(summary: dict) -> str:
    keys = ("input", "duration_s", "wall_s", "realtime_factor", "messages_read", "samples_used", "nav_states",
            "imu_samples", "corrupt_frames", "rejected_total", "late_samples", "releases", "releases_accepted",
            "calibrate")
    rows = [[_esc(k), _num(summary.get(k))] for k in keys if k in summary]
    origin = summary.get("origin") or {}
    if origin:
        rows.append(["NED origin", f"{_num(origin.get('lat_deg'), '.7f')}°, {_num(origin.get('lon_deg'), '.7f')}°"
                                   f" (from {_esc(origin.get('from'))})"])
    return _table(["", "value"], rows, "kv")


def missing_section(summary: dict) -> str:
    items = [_esc(m) for m in summary.get("missing_streams") or []]
    if summary.get("corrupt_frames"):
        items.append(f"{summary['corrupt_frames']} corrupt frames skipped")
    if summary.get("truncated"):
        items.append(f"the log is truncated: {_esc(summary['truncated'])}")
    for reason, n in (summary.get("rejected_samples") or {}).items():
        items.append(f"{n} samples rejected: {_esc(reason)}")
    if summary.get("errors"):
        items.append("processing errors: " + ", ".join(f"{_esc(k)} {v}" for k, v in summary["errors"].items()))
    if not items:
        return "<p>Nothing: every stream a navigation run uses was present and readable.</p>"
    return "<ul>" + "".join(f"<li>{i}</li>" for i in items) + "</ul>"


def metrics_table(metrics: dict) -> str:
    if not metrics:
        return "<p>No truth in the input: no error metrics.</p>"
    out: list = []
    _flat("", metrics, out)
    return _table(["metric", "value"], [[_esc(k), _num(v)] for k, v in out], "kv")


_STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;margin:2em auto;max-width:1100px;color:#222;
padding:0 1em}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}th,td{border:1px solid #ddd;padding:.25em .6em;
text-align:left;vertical-align:top}th{background:#f3f3f3}table.kv td:first-child{font-family:monospace}
figure{margin:.5em 0}svg{max-width:100%;height:auto}.note{color:#555;font-size:.9em}
"""


def render(rec: Any, summary: dict, title: str = "") -> str:
    """The report page (a string of HTML, self-contained)."""
    title = title or f"adaptnav replay: {summary.get('input', '')}"
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{_esc(title)}</title>",
             f"<style>{_STYLE}</style></head><body>", f"<h1>{_esc(title)}</h1>",
             "<p class='note'>Written by <code>adaptnav replay --report</code>; one file, no network "
             "needed.</p>",
             "<h2>Summary</h2>", summary_table(summary),
             "<h2>What was missing in the input</h2>", missing_section(summary)]
    fig = track_figure(rec)
    if fig:
        parts += ["<h2>Track (local metres at the NED origin)</h2>", f"<figure id='track'>{fig}</figure>"]
    fig = error_figure(rec)
    if fig:
        parts += ["<h2>Horizontal error and ±3σ</h2>", f"<figure id='error'>{fig}</figure>"]
    parts += ["<h2>Aids: fused and rejected</h2>",
              "<p class='note'>The NIS columns test the filter's covariance against each aid's innovations, "
              "no truth needed: about 1 and 95 % when it is right; far above, over-confident.</p>",
              aid_table(summary.get("aid_consistency") or {})]
    fig = innovations_figure(rec)
    if fig:
        parts += ["<h2>Normalised innovations</h2>",
                  "<p class='note'>ν/√S per component: about ±1 when the filter's uncertainty is right, "
                  "dotted lines at ±3.</p>", f"<figure id='innovations'>{fig}</figure>"]
    parts += ["<h2>Calibrator releases</h2>", releases_table(rec)]
    fig = params_figure(rec)
    if fig:
        parts += ["<h2>Motion parameters</h2>", f"<figure id='params'>{fig}</figure>"]
    parts += ["<h2>Metrics against truth</h2>", metrics_table(summary.get("metrics") or {}), "</body></html>"]
    return "\n".join(parts)


def write_report(rec: Any, summary: dict, path: str | Path, title: str = "") -> Path:
    """Write :func:`render` to ``path``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render(rec, summary, title), encoding="utf-8")
    return path
