"""What a batch's report says, read from the batch's own files, never copied from its manifest alone:
the counts are recounted from the scene folders and the rejection log, the funnel from the log's
rows, the stage times from timings.json, each scene's facts from its scene.json, the realism checks
from the manifest (with the rule each was judged by), each tag's rate against the reference table's
with Wilson intervals, and the audit's verdict recomputed now."""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import pyarrow.parquet as pq
import yaml

from scenegen.analysis.realism import wilson_interval
from scenegen.core.files import sha256_file
from scenegen.paths import ASSETS_DIR
from scenegen.schema.condition import TAGS
from scenegen.store.batch import REJECTIONS, TIMINGS, StoreError, scene_dirs

REFERENCE = ASSETS_DIR / "reference" / "reference.parquet"
STAGE_ORDER = ("propose", "check", "build", "settle", "tag", "render", "store")  # runner/pipeline.py STAGES
CAMERA = re.compile(r"^[A-Za-z0-9_]+$")  # a camera name that can be part of a thumbnail's file name
OBJECT_FACTS = ("name", "asset", "category", "support", "position", "quat")  # of each settled object
RULES = {  # how each realism metric is judged, in words beside its threshold
    "layout_c2st": "a classifier tells the batch's layouts from the reference's no better than this AUC",
    "layout_mmd": "maximum mean discrepancy of the layout features at most this",
    "image_stats": "exposure and colour statistics within this distance of the reference renders",
}


class ReportError(ValueError):
    """The path cannot be reported; the message names it and what to do."""


NOT_AUDITED = "audit left out (--no-audit)"


def batch_facts(
    batch: Path, audit_report=None, reference: Path = REFERENCE, audit_reason: str = NOT_AUDITED
) -> dict:
    """Everything the batch page shows (JSON-serializable). ``audit_report``: an AuditReport made
    now (None: not audited, for ``audit_reason``)."""
    batch = Path(batch)
    try:
        rows_dirs = scene_dirs(batch)
    except StoreError as exc:
        raise ReportError(str(exc)) from None
    recipe = _read_yaml(batch / "pipeline.yaml")
    manifest = _read_yaml(batch / "manifest.yaml") if (batch / "manifest.yaml").is_file() else {}
    source = (manifest.get("sources") or [{}])[0]
    rejections = _rows(batch / REJECTIONS)
    scenes = [_scene(row, folder, batch) for row, folder in rows_dirs]
    timings = json.loads((batch / TIMINGS).read_text()) if (batch / TIMINGS).is_file() else {}
    return {
        "batch": batch.name,
        "request": _request(recipe, source),
        "counts": _counts(scenes, rejections),
        "funnel": _funnel(len(scenes), rejections),
        "timings": _timings(timings),
        "realism": [_check(c) for c in source.get("realism") or []],
        "tag_rates": tag_rates(scenes, recipe, reference),
        "scenes": scenes,
        "audit": audit_facts(audit_report, audit_reason),
    }


def _rows(path: Path) -> list[dict]:
    """An append-only log's rows, leaving out a torn last line (a killed run's; the next run of the
    batch cuts it), without writing to the batch."""
    if not path.is_file():
        return []
    data = path.read_bytes()
    return [json.loads(line) for line in data[: data.rfind(b"\n") + 1].decode().splitlines() if line.strip()]


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ReportError(f"{path}: missing; give a batch folder written by `scenegen generate`") from None
    except (OSError, yaml.YAMLError) as exc:
        raise ReportError(f"{path}: unreadable ({exc.__class__.__name__})") from None
    if not isinstance(data, dict):
        raise ReportError(f"{path}: not a mapping")
    return data


def _request(recipe: dict, source: dict) -> dict:
    condition = recipe.get("condition") or {}
    proposer = recipe.get("proposer") or {}
    checkpoint = ((source.get("generator") or {}).get("checkpoint")) or {}
    tags = {t: v for t, v in (condition.get("tags") or {}).items() if v != "unspecified"}
    return {
        "recipe": recipe.get("name", ""),
        "text": condition.get("text") or "",
        "task": condition.get("task", ""),
        "target": condition.get("target", ""),
        "tags": tags,
        "seed": recipe.get("seed"),
        "n": recipe.get("n"),
        "generator": proposer.get("kind", ""),
        "checkpoint": checkpoint.get("path") or proposer.get("checkpoint") or "",
        "checkpoint_sha256": checkpoint.get("sha256") or proposer.get("checkpoint_sha256") or "",
        "guidance": (source.get("generator") or {}).get("guidance") or {},
        "render": bool(recipe.get("render", True)),
    }


def _counts(scenes: list[dict], rejections: list[dict]) -> dict:
    repaired = sum(bool(r.get("repaired")) for r in rejections)
    return {
        "scenes": len(scenes),
        "rejected": len(rejections),
        "tries": len(scenes) + len(rejections),
        "repaired": repaired,
        "first_tries": len({r["proposal_index"] for r in rejections} | {s["proposal_index"] for s in scenes}),
    }


def _funnel(accepted: int, rejections: list[dict]) -> dict:
    """Tries into each stage, what each stage removed (by label), and the repairs that followed."""
    by_stage: dict[str, Counter] = {}
    repaired: Counter = Counter()  # by (stage, label)
    for row in rejections:
        stage = row.get("stage", "check")
        by_stage.setdefault(stage, Counter())[row["label"]] += 1
        repaired[stage, row["label"]] += bool(row.get("repaired"))
    remaining = accepted + len(rejections)
    stages = []
    for stage in sorted(by_stage, key=lambda s: STAGE_ORDER.index(s) if s in STAGE_ORDER else 99):
        removed = by_stage[stage]
        stages.append(
            {
                "stage": stage,
                "entered": remaining,
                "removed": sum(removed.values()),
                "labels": [
                    {"label": label, "count": n, "repaired": repaired[stage, label]}
                    for label, n in removed.most_common()
                ],
            }
        )
        remaining -= sum(removed.values())
    return {"tries": accepted + len(rejections), "accepted": accepted, "stages": stages}


def _timings(timings: dict) -> dict:
    wall, cpu = timings.get("stages") or {}, timings.get("cpu") or {}
    stages = [
        {"stage": s, "wall": wall.get(s), "cpu": cpu.get(s)} for s in STAGE_ORDER if s in wall or s in cpu
    ]
    return {
        "wall": timings.get("wall"),
        "workers": timings.get("workers"),
        "backend": timings.get("backend"),
        "stages": stages,
    }


def _check(check: dict) -> dict:
    metric = check.get("metric", "")
    return {
        "metric": metric,
        "value": check.get("value"),
        "threshold": check.get("threshold"),
        "comparison": check.get("comparison", "<="),
        "status": check.get("status", ""),
        "rule": RULES.get(metric, ""),
        "reference": (check.get("reference") or {}).get("source", ""),
        "samples": check.get("samples") or {},
    }


def tag_rates(scenes: list[dict], recipe: dict, reference: Path = REFERENCE) -> list[dict]:
    """Each tag's share of the batch's scenes against its share of the reference's training layouts,
    both with 95 % Wilson intervals; whether the request asked for it."""
    asked = (recipe.get("condition") or {}).get("tags") or {}
    table = pq.read_table(reference, columns=["split", *(f"tag_{t}" for t in TAGS)]).to_pydict()
    train = [i for i, split in enumerate(table["split"]) if split == "train"]
    rows = []
    for tag in TAGS:
        k = sum(tag in s["tags_held"] for s in scenes)
        ref_k = sum(bool(table[f"tag_{tag}"][i]) for i in train)
        rows.append(
            {
                "tag": tag,
                "asked": asked.get(tag, "unspecified"),
                "batch": _rate(k, len(scenes)),
                "reference": _rate(ref_k, len(train)),
            }
        )
    return rows


def _rate(k: int, n: int) -> dict:
    low, high = wilson_interval(k, n) if n else (0.0, 1.0)
    return {"k": k, "n": n, "rate": k / n if n else None, "low": low, "high": high}


def _scene(row: dict, folder: Path, batch: Path) -> dict:
    """One scene's facts from its scene.json (the index row says which folder and its sha256)."""
    path = folder / "scene.json"
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ReportError(f"{path}: unreadable ({exc.__class__.__name__}); is the batch complete?") from None
    objects = record.get("objects") or []
    target = next((o for o in objects if o.get("name") == record.get("target")), {})
    tags = record.get("tags") or {}
    return {
        "id": folder.name,  # the index's scene_id, checked by scene_dirs (never the record's own word)
        "folder": folder.relative_to(batch).as_posix(),
        "proposal_index": record.get("proposal_index"),
        "seed": record.get("seed"),
        "target": record.get("target"),
        "category": target.get("category", ""),
        "categories": sorted({o.get("category", "") for o in objects}),
        "tags_held": [t for t, v in tags.items() if isinstance(v, dict) and v.get("holds")],
        "tags": tags,
        "objects": [{k: o.get(k) for k in OBJECT_FACTS} for o in objects],
        "furniture": record.get("furniture") or [],
        "cameras": [c["name"] for c in record.get("cameras") or [] if CAMERA.match(str(c.get("name", "")))],
        "rendered": record.get("render") is not None,
        "provenance": record.get("provenance") or {},
        "checksums": {
            "scene.json": sha256_file(path),
            "index row": row.get("scene_json_sha256"),
            **{k: v for k, v in (record.get("files") or {}).items() if not k.startswith("../")},
        },
    }


def audit_facts(report, reason: str = NOT_AUDITED) -> dict:
    """An AuditReport as the page shows it (None: the audit did not run, for ``reason``)."""
    if report is None:
        return {"ran": False, "ok": None, "violations": [], "more_violations": 0, "warnings": 0} | {
            "reason": reason
        }
    return {
        "ran": True,
        "ok": report.ok,
        "violations": [str(v) for v in report.violations][:50],
        "more_violations": max(0, len(report.violations) - 50),
        "warnings": len(report.warnings),
        "verified": len(report.verified),
    }
