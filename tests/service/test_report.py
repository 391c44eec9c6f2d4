"""``adaptnav replay --report``: the page renders in a real headless Chromium with no console
errors, self-contained (no request leaves the file), with the track, error/3σ, aid table,
innovations, releases, summary and what the input lacked — for a simulated survey and a
real ArduSub ``.tlog``."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from adaptnav.service.cli import main

from .headless import Page, chromium_path

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parents[2]
TLOG = REPO.parent / "shared" / "data" / "mavlink" / "ardusub-4.1.1-bluerov2-ugps.tlog"


@pytest.fixture(scope="module")
def browser():
    binary = chromium_path()
    if binary is None:
        pytest.skip("no Chromium on this machine: `make browser` installs Debian's chromium "
                    "(apt-get install chromium); the report is checked in a real browser only")
    return binary


def _check_page(binary: str, page_path: Path, tmp_path: Path) -> dict:
    with Page(binary) as page:
        page.load(page_path.resolve().as_uri())
        facts = page.evaluate("""(() => ({
            svgs: document.querySelectorAll('figure svg').length,
            figures: [...document.querySelectorAll('figure')].map(f => f.id),
            headings: [...document.querySelectorAll('h2')].map(h => h.textContent),
            tables: document.querySelectorAll('table').length,
            text: document.body.innerText,
            widest: Math.max(...[...document.querySelectorAll('figure svg')].map(s => s.getBoundingClientRect().width)),
            resources: performance.getEntriesByType('resource').map(r => r.name),
        }))()""")
        shot = page.screenshot(tmp_path / (page_path.stem + ".png"))
        facts["errors"] = list(page.errors)
    import matplotlib.image as mpimg

    img = mpimg.imread(shot)
    facts["shot_shape"] = img.shape
    facts["shot_std"] = float(img[..., :3].std())
    return facts


def test_report_checker_sees_console_errors(browser, tmp_path):
    """The check can fail: a page with a script error and a console.error is caught."""
    bad = tmp_path / "bad.html"
    bad.write_text("<!DOCTYPE html><html><body><p>x</p><script>console.error('boom'); undefinedFn();"
                   "</script></body></html>")
    with Page(browser) as page:
        page.load(bad.as_uri())
        errors = list(page.errors)
    assert any("boom" in e for e in errors) and any("undefinedFn" in e for e in errors), errors


def test_survey_report_renders_without_console_errors(browser, tmp_path):
    report = tmp_path / "survey.html"
    assert main(["replay", "--scenario", "survey", "--set", "duration_s=900", "--out", str(tmp_path / "r"),
                 "--report", str(report), "--no-plots", "--no-progress"]) == 0
    facts = _check_page(browser, report, tmp_path)
    assert facts["errors"] == []
    assert facts["resources"] == []  # self-contained: nothing fetched
    assert set(facts["figures"]) >= {"track", "error", "innovations", "params"}
    assert facts["svgs"] >= 4 and facts["widest"] > 300
    text = facts["text"]
    for heading in ("Summary", "What was missing in the input", "Aids: fused and rejected",
                    "Normalised innovations", "Calibrator releases", "Metrics against truth"):
        assert heading in facts["headings"]
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert f"{summary['metrics']['rms_horizontal_error_m']:.4g}" in text  # the metrics are the run's
    assert "usbl" in text and "learned_velocity" in text
    assert facts["shot_shape"][0] > 1600 and facts["shot_std"] > 0.05  # a long page, not blank


@pytest.mark.realdata
def test_real_tlog_report_renders_and_says_what_was_missing(browser, tmp_path):
    if not TLOG.is_file():
        pytest.skip(f"{TLOG} absent (shared/data)")
    report = tmp_path / "tlog.html"
    assert main(["replay", str(TLOG), "--out", str(tmp_path / "r"), "--report", str(report), "--no-plots",
                 "--no-progress"]) == 0
    facts = _check_page(browser, report, tmp_path)
    assert facts["errors"] == []
    assert facts["resources"] == []
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    # what the real log lacks is said on the page (this log: a 2 Hz RAW_IMU, too slow for strapdown)
    assert summary["missing_streams"]
    for item in summary["missing_streams"]:
        assert str(item) in facts["text"]
    for reason in summary["rejected_samples"]:
        assert reason in facts["text"]
    assert "No truth in the input" in facts["text"]
    assert {"track", "error"} <= set(facts["figures"])
