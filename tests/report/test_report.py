"""``scenegen report``: a real batch's page opened in a real browser (Debian's chromium through
Playwright): it loads with no console error and no request leaving the file; its counts equal a
recount from the scene folders and the rejection log (not from the manifest it was made from); the tag
filter shows exactly the scenes whose scene.json holds the tag; a click opens a scene's facts; the
checker itself catches a copy of the page that shows a wrong count. A screenshot is kept in
runs/test_artefacts/. The project manifest's page loads too, and the batch still audits clean with
its report beside it."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from scenegen.audit.manifest import audit
from scenegen.cli import main
from scenegen.paths import PROJECT_ROOT

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARTEFACTS = Path(os.environ.get("SCENEGEN_TEST_ARTEFACTS", PROJECT_ROOT / "runs" / "test_artefacts"))


@pytest.fixture(scope="module")
def reported(tmp_path_factory) -> Path:
    """A rendered batch of 10 procedural scenes (seed 0: 3 occluded, 1 under_overhang, 6 nominal) and
    its report, audited as it is made."""
    batch = tmp_path_factory.mktemp("report") / "batch"
    recipe = PROJECT_ROOT / "pipelines" / "procedural.yaml"
    assert main(["generate", str(recipe), "--n", "10", "--seed", "0", "--out", str(batch), "--quiet"]) == 0
    assert main(["report", str(batch), "--quiet"]) == 0
    assert recount(batch)["rejected"] > 0  # the funnel and its counts have something to show
    return batch


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).is_file():
        pytest.fail(
            f"{CHROMIUM}: no chromium; install Debian's (apt-get install chromium, or `make browser`)"
        )
    with sync_playwright() as playwright:
        args = ["--no-sandbox"] if os.geteuid() == 0 else []
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=args)
        yield browser
        browser.close()


def open_page(browser, html: Path):
    """The page at ``html``, with every console error, page error and request that left file://."""
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    seen = {"errors": [], "outside": []}
    page.on("console", lambda m: seen["errors"].append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: seen["errors"].append(str(e)))
    page.on(
        "request", lambda r: None if r.url.startswith(("file://", "data:")) else seen["outside"].append(r.url)
    )
    page.goto(html.as_uri(), wait_until="load")
    return page, seen


def recount(batch: Path) -> dict:
    """The batch's counts from its files: scene folders holding a scene.json, rejection log rows."""
    scenes = sorted(p.parent.name for p in batch.glob("scene_*/scene.json"))
    rejected = [json.loads(line) for line in (batch / "rejections.jsonl").read_text().splitlines() if line]
    return {
        "scenes": len(scenes),
        "rejected": len(rejected),
        "tries": len(scenes) + len(rejected),
        "repaired": sum(bool(r.get("repaired")) for r in rejected),
    }


def holding(batch: Path, tag: str) -> set[str]:
    records = [json.loads(p.read_text()) for p in batch.glob("scene_*/scene.json")]
    return {r["scene_id"] for r in records if r["tags"][tag]["holds"]}


def page_problems(page, batch: Path) -> list[str]:
    """What the page gets wrong about the batch: counts, then the tag filter, scene by scene."""
    problems = []
    for key, n in recount(batch).items():
        shown = page.text_content(f'[data-count="{key}"]').strip()
        if shown != str(n):
            problems.append(f"{key}: the page shows {shown}, the files hold {n}")
    tags = page.eval_on_selector_all("#tag-filter option", "os => os.map(o => o.value).filter(v => v)")
    for tag in tags:
        page.select_option("#tag-filter", tag)
        visible = set(
            page.eval_on_selector_all("figure.scene:not([hidden])", "es => es.map(e => e.dataset.id)")
        )
        if visible != holding(batch, tag):
            problems.append(
                f"tag {tag}: the filter shows {sorted(visible)}, not {sorted(holding(batch, tag))}"
            )
        if page.text_content("#shown-count").strip() != str(len(visible)):
            problems.append(f"tag {tag}: the shown count is not the number of scenes shown")
    page.select_option("#tag-filter", "")
    return problems


def test_the_page_loads_offline_and_its_counts_filter_and_facts_match_the_files(reported, browser):
    page, seen = open_page(browser, reported / "report.html")
    assert page.text_content("#audit-verdict").strip() == "PASSED"
    assert page_problems(page, reported) == []
    assert set(page.eval_on_selector_all("#tag-filter option", "os => os.map(o => o.value)")) >= {
        "occluded",
        "under_overhang",
        "nominal",
    }  # the seed's scenes hold three tags: the filter has something to tell apart
    page.select_option("#view-filter", "depth")
    assert all(
        "_depth.png" in src
        for src in page.eval_on_selector_all("figure.scene img", "es => es.map(e => e.src)")
    )
    page.select_option("#view-filter", "rgb")
    first = page.eval_on_selector("figure.scene", "e => e.dataset.id")
    page.click(f'figure.scene[data-id="{first}"]')
    assert page.is_visible("dialog#facts")
    facts = page.text_content("dialog#facts")
    record = json.loads((reported / first / "scene.json").read_text())
    target = next(o for o in record["objects"] if o["name"] == record["target"])
    assert first in facts and record["target"] in facts and "Settled objects" in facts
    assert f"{target['position'][0]:.4f}" in facts  # the settled pose, as stored
    assert record["provenance"]["pipeline_sha256"] in facts
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTEFACTS / "report_facts.png"))
    page.click("#facts-close")
    page.screenshot(path=str(ARTEFACTS / "report.png"), full_page=True)
    assert seen == {"errors": [], "outside": []}, seen
    page.close()


def test_the_checker_catches_a_page_showing_a_wrong_count(reported, browser):
    html = (reported / "report.html").read_text()
    n = recount(reported)["scenes"]
    wrong = reported / "report_wrong_count.html"  # beside the original, so its thumbnails resolve
    wrong.write_text(html.replace(f'data-count="scenes">{n}<', f'data-count="scenes">{n + 1}<', 1))
    try:
        page, _ = open_page(browser, wrong)
        assert page_problems(page, reported) == [f"scenes: the page shows {n + 1}, the files hold {n}"]
        page.close()
    finally:
        wrong.unlink()


def test_the_batch_audits_clean_with_its_report_and_a_stray_file_still_fails(reported):
    assert (reported / "report_files").is_dir() and any((reported / "report_files").iterdir())
    assert audit(reported / "manifest.yaml").ok
    stray = reported / "report_files" / "link"
    stray.symlink_to(reported / "manifest.yaml")
    try:
        report = audit(reported / "manifest.yaml")
        assert [f.check for f in report.violations] == ["location"], report.violations
    finally:
        stray.unlink()


def test_the_project_page_loads_with_its_sources_mixture_coverage_and_transfer(browser, tmp_path, capsys):
    out = tmp_path / "project.html"
    assert main(["report", str(PROJECT_ROOT / "data_manifest.yaml"), "--out", str(out), "--no-audit"]) == 0
    page, seen = open_page(browser, out)
    for section in ("sources", "recipes", "coverage", "transfer"):
        assert page.is_visible(f"section#{section}"), section
    assert page.text_content('[data-count="sources"]').strip() == "1"
    assert "C - A+" in page.text_content("section#transfer")
    assert seen == {"errors": [], "outside": []}, seen
    page.close()


def test_bad_paths_get_one_line(tmp_path, capsys):
    (tmp_path / "notes.yaml").write_text("just: notes\n")
    for path, words in (
        (tmp_path / "missing", "no such batch folder or manifest file"),
        (tmp_path / "notes.yaml", "not a project manifest"),
        (tmp_path, "no index.jsonl"),
    ):
        assert main(["report", str(path)]) == 2
        error = capsys.readouterr().err.strip()
        assert error.count("\n") == 0 and words in error, error


def test_an_unrendered_batch_reports_its_scenes_without_images(tmp_path):
    batch = tmp_path / "batch"
    recipe = PROJECT_ROOT / "pipelines" / "procedural.yaml"
    assert (
        main(
            [
                "generate",
                str(recipe),
                "--n",
                "2",
                "--seed",
                "1",
                "--out",
                str(batch),
                "--no-render",
                "--quiet",
            ]
        )
        == 0
    )
    assert main(["report", str(batch), "--quiet", "--no-audit"]) == 0
    html = (batch / "report.html").read_text()
    assert html.count('class="noimg">not rendered<') == 2 and "NOT AUDITED" in html
    assert not any((batch / "report_files").iterdir())
    assert f'data-count="scenes">{recount(batch)["scenes"]}<' in html


def test_a_killed_batch_reports_what_it_holds_and_says_why_it_was_not_audited(reported, tmp_path):
    killed = tmp_path / "killed"
    shutil.copytree(reported, killed, ignore=shutil.ignore_patterns("report*", "manifest.yaml"))
    whole = recount(killed)
    with open(killed / "rejections.jsonl", "a") as log:
        log.write('{"check": "collision", "label": "coll')  # a torn last line, as a SIGKILL leaves it
    before = (killed / "rejections.jsonl").read_bytes()
    assert main(["report", str(killed), "--quiet"]) == 0
    html = (killed / "report.html").read_text()
    assert (
        f'data-count="rejected">{whole["rejected"]}<' in html
        and f'data-count="scenes">{whole["scenes"]}<' in html
    )
    assert "not audited: no manifest.yaml" in html
    assert (killed / "rejections.jsonl").read_bytes() == before  # the report writes nothing of the batch's
