"""A replay says, per aid, what its innovations say of the filter's covariance — the check a
real log without truth allows (summary.json ``aid_consistency``, and `adaptnav replay`'s
table). On a seeded simulation the filter is consistent: NIS per degree of freedom near 1,
about 95 % of the attempts within the χ² 95 % bound. A heading σ ten times too small is seen
at once. The figures are checked against aid_status.csv, recomputed here with scipy.stats."""
from __future__ import annotations

import csv
import json

import pytest
from scipy import stats

from adaptnav.service.cli import main as cli_main
from adaptnav.service.runtime import replay as rp


def _replay(out, *config_set):
    inp = rp.open_scenario("short", ["duration_s=300"])
    cfg = rp.build_config(inp.scenario, None, list(config_set))
    return rp.replay(inp, cfg, out, progress=False, plots=False), cfg


def _from_csv(path, source, gate_sigma):
    """(attempts, fused, tested, mean NIS per dof, within 95 %) of ``source`` from aid_status.csv."""
    attempts = fused = 0
    per_dof, within = [], 0
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if row["source"] != source:
                continue
            attempts += 1
            fused += row["fused"] == "1"
            if not (row["fused"] == "1" or row["reason"] == "gate"):
                continue
            m = len(row["innovation"].split(";"))
            gate = stats.chi2.ppf(1.0 - 2.0 * stats.norm.sf(gate_sigma), m)
            nis = float(row["test_ratio"]) * gate
            per_dof.append(nis / m)
            within += nis <= stats.chi2.ppf(0.95, m)
    return attempts, fused, len(per_dof), sum(per_dof) / len(per_dof), within / len(per_dof)


def test_a_consistent_filter_and_a_heading_sigma_ten_times_too_small(tmp_path):
    res, cfg = _replay(tmp_path / "right")
    report = res.summary["aid_consistency"]
    for source in ("depth", "heading"):
        a = report[source]
        assert a["tested"] > 2500
        assert 0.85 <= a["nis_per_dof_mean"] <= 1.15, (source, a)
        assert 0.92 <= a["within_95"] <= 0.98, (source, a)
        attempts, fused, tested, mean, within = _from_csv(tmp_path / "right" / "aid_status.csv", source,
                                                          cfg.filter.gate_sigma)
        assert (a["attempts"], a["fused"], a["tested"]) == (attempts, fused, tested)
        assert a["nis_per_dof_mean"] == pytest.approx(mean, rel=1e-9)
        assert a["within_95"] == pytest.approx(within, abs=1e-12)

    sigma = cfg.filter.heading.sigma_rad / 10.0
    res, cfg = _replay(tmp_path / "small", f"filter.heading.sigma_rad={sigma}")
    a = res.summary["aid_consistency"]["heading"]
    assert a["nis_per_dof_mean"] > 5.0 and a["within_95"] < 0.6, a
    assert a["refused"].get("gate", 0) > 100
    _, fused, tested, mean, within = _from_csv(tmp_path / "small" / "aid_status.csv", "heading", cfg.filter.gate_sigma)
    assert (a["fused"], a["tested"]) == (fused, tested)
    assert a["nis_per_dof_mean"] == pytest.approx(mean, rel=1e-9)
    # the depth, untouched, stays consistent
    assert 0.85 <= res.summary["aid_consistency"]["depth"]["nis_per_dof_mean"] <= 1.15


def test_the_replay_command_prints_the_table(tmp_path, capsys):
    assert cli_main(["replay", "--scenario", "short", "--set", "duration_s=60", "--out", str(tmp_path),
                     "--no-plots", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "NIS per dof" in out
    report = json.loads((tmp_path / "summary.json").read_text())["aid_consistency"]
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("    ")}
    for source in ("depth", "heading"):
        fused, slash, attempts, nis, within = rows[source][1:6]
        assert (int(fused), slash, int(attempts)) == (report[source]["fused"], "/", report[source]["attempts"])
        assert float(nis) == pytest.approx(report[source]["nis_per_dof_mean"], rel=5e-3)
        assert float(within) == pytest.approx(100 * report[source]["within_95"], abs=0.051)


def test_the_report_page_carries_the_figures(tmp_path):
    """``--report``: the aid table has the NIS columns with the summary's figures."""
    page = tmp_path / "report.html"
    assert cli_main(["replay", "--scenario", "short", "--set", "duration_s=60", "--out", str(tmp_path / "r"),
                     "--no-plots", "--no-progress", "--report", str(page)]) == 0
    html = page.read_text()
    report = json.loads((tmp_path / "r" / "summary.json").read_text())["aid_consistency"]
    assert "NIS per dof" in html
    for source in ("depth", "heading"):
        assert format(report[source]["nis_per_dof_mean"], ".3g") in html
        assert f"{100.0 * report[source]['within_95']:.1f} %" in html
