"""The report pages: facts and plots poured into a jinja2 template whose styles and script are inlined,
written atomically (store.batch.atomic_write), thumbnails beside it."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from pathlib import Path

import jinja2

from scenegen import __version__
from scenegen.report.facts import NOT_AUDITED, ReportError, batch_facts
from scenegen.store.batch import REPORT, REPORT_FILES, atomic_write

TEMPLATES = Path(__file__).parent / "templates"


def _environment() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )


def _now() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")


def batch_report(batch: Path, audit: bool = True, workers: int = 1, progress=None) -> Path:
    """Write ``batch/report.html`` (and its thumbnails in ``batch/report_files``); its path.
    ``audit``: recompute the audit of the batch's manifest (its verdict is on the page);
    ``progress``: a callable wrapping an iterable (tqdm) for the thumbnails."""
    from scenegen.report.plots import funnel_svg, stage_svg, tag_rates_svg
    from scenegen.report.thumbs import write_thumbnails

    batch = Path(batch)
    for leftover in batch.glob(f".{REPORT}.tmp*"):  # a killed report's (the audit counts it otherwise)
        leftover.unlink()
    report, reason = None, NOT_AUDITED
    if audit and (batch / "manifest.yaml").is_file():
        from scenegen.audit.manifest import audit as run_audit

        report = run_audit(batch / "manifest.yaml", workers=workers)
    elif audit:
        reason = "not audited: no manifest.yaml (an unfinished batch: rerun its generate command)"
    facts = batch_facts(batch, report, audit_reason=reason)
    files = batch / REPORT_FILES
    files.mkdir(exist_ok=True)
    scenes = facts["scenes"]
    for scene in progress(scenes) if progress else scenes:
        made = write_thumbnails(batch, scene, files)
        scene["thumbs"] = {
            camera: {kind: f"{REPORT_FILES}/{name}" for kind, name in kinds.items()}
            for camera, kinds in made.items()
        }
    plots = {
        "funnel": funnel_svg(facts["funnel"]),
        "stages": stage_svg(facts["timings"]) if facts["timings"]["stages"] else "",
        "tags": tag_rates_svg(facts["tag_rates"]),
    }
    tags = Counter(t for s in scenes for t in s["tags_held"])
    categories = Counter(s["category"] for s in scenes)
    html = (
        _environment()
        .get_template("batch.html.j2")
        .render(
            f=facts,
            plots=plots,
            tag_counts=sorted(tags.items()),
            category_counts=sorted(categories.items()),
            css=(TEMPLATES / "report.css").read_text(),
            js=(TEMPLATES / "batch.js").read_text(),
            made=_now(),
            version=__version__,
        )
    )
    atomic_write(batch / REPORT, html)
    return batch / REPORT


def project_report(manifest: Path, out: Path | None = None, audit: bool = True, workers: int = 1) -> Path:
    """Write the project manifest's report (default: ``report.html`` beside it); its path."""
    from scenegen.report.plots import contrasts_svg, shares_svg
    from scenegen.report.project import project_facts, read_project_manifest

    manifest = Path(manifest)
    read_project_manifest(manifest)  # a one-line error before any audit
    report = None
    if audit:
        from scenegen.audit.manifest import audit as run_audit

        report = run_audit(manifest, workers=workers)
    facts = project_facts(manifest, report)
    shares = [
        (r["name"], shares_svg(list(r["effective_shares"]), list(r["effective_shares"].values()), r["name"]))
        for r in facts["recipes"]
        if len(r.get("effective_shares") or {}) > 1
    ]
    contrasts = facts["transfer"]["contrasts"]
    html = (
        _environment()
        .get_template("project.html.j2")
        .render(
            f=facts,
            share_plots=shares,
            contrast_plot=contrasts_svg(contrasts) if contrasts else "",
            css=(TEMPLATES / "report.css").read_text(),
            made=_now(),
            version=__version__,
        )
    )
    out = Path(out) if out else manifest.parent / REPORT
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, html)
    return out


__all__ = ["ReportError", "batch_report", "project_report"]
