"""What the project's report says, from data_manifest.yaml and the files it names: each source with
its counts and realism checks, each training recipe's alpha and effective shares, the models, the
coverage of (task x tag) recounted from the sources' files, the transfer outcome with every contrast
and arm, the datasheet, and the audit's verdict recomputed now."""

from __future__ import annotations

from pathlib import Path

import yaml

from scenegen.data.coverage import CoverageError, coverage_table
from scenegen.report.facts import ReportError, audit_facts


def read_project_manifest(path: Path) -> dict:
    """The manifest's mapping; ReportError (one line) when it is not a project manifest."""
    path = Path(path)
    try:
        manifest = yaml.safe_load(path.read_text())
    except yaml.YAMLError:
        raise ReportError(f"{path}: not YAML; give a batch folder or a project manifest") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ReportError(f"{path}: unreadable ({exc.__class__.__name__})") from None
    if not isinstance(manifest, dict) or manifest.get("kind") != "project":
        raise ReportError(f"{path}: not a project manifest (kind: project); give data_manifest.yaml")
    return manifest


def project_facts(path: Path, audit_report=None) -> dict:
    path = Path(path)
    manifest = read_project_manifest(path)
    try:
        coverage = coverage_table(path)
    except CoverageError as exc:
        raise ReportError(str(exc)) from None
    return {
        "manifest": path.name,
        "datasheet": manifest.get("datasheet") or {},
        "sources": [_source(s) for s in manifest.get("sources") or []],
        "recipes": manifest.get("recipes") or [],
        "models": manifest.get("models") or [],
        "coverage": {
            "tags": list(coverage.tags),
            "rows": [
                {
                    "task": task,
                    "scenes": coverage.scenes.get(task, 0),
                    "cells": [
                        {"n": coverage.count(task, tag), "sparse": coverage.is_sparse(task, tag)}
                        for tag in coverage.tags
                    ],
                }
                for task in coverage.tasks
            ],
            "total": coverage.total,
            "sparse_below": coverage.sparse_below(),
            "skipped": list(coverage.skipped),
        },
        "transfer": _transfer(manifest.get("transfer") or {}),
        "audit": audit_facts(audit_report),
    }


def _source(source: dict) -> dict:
    return {
        "name": source.get("name"),
        "origin": source.get("origin"),
        "location": source.get("location"),
        "counts": source.get("counts") or {},
        "generator": (source.get("generator") or {}).get("kind", ""),
        "realism": [
            {k: check.get(k) for k in ("metric", "value", "threshold", "comparison", "status")}
            for check in source.get("realism") or []
        ],
        "description": source.get("description", ""),
    }


def _interval(entry: dict) -> dict:
    return {k: entry.get(k) for k in ("mean", "low", "high", "seeds", "scenes")}


def _transfer(transfer: dict) -> dict:
    metrics = transfer.get("metrics") or {}
    arms = []
    for arm, entry in (metrics.get("arms") or {}).items():
        arms.append(
            {"arm": arm, **{k: _interval(v) for k, v in entry.items() if isinstance(v, dict) and "mean" in v}}
        )
    return {
        "status": transfer.get("status", "absent"),
        "panel": transfer.get("panel", ""),
        "note": transfer.get("note", ""),
        "artifact": transfer.get("artifact") or "",
        "artifact_sha256": transfer.get("artifact_sha256") or "",
        "version": metrics.get("version"),
        "positive_control": _interval(metrics["positive_control"]) if "positive_control" in metrics else None,
        "primary": {**_interval(metrics["primary"]), "endpoint": metrics["primary"].get("endpoint", "")}
        if "primary" in metrics
        else None,
        "contrasts": [{"contrast": c, **_interval(v)} for c, v in (metrics.get("contrasts") or {}).items()],
        "arms": arms,
        "arm_columns": sorted({k for a in arms for k in a if k != "arm"}),
    }
