"""The file half of ``scenegen audit``: a source's files against what the manifest says of them.

- :func:`audit_table`: a single-file source (the reference Parquet table, imported real data): its
  sha256, rows and splits, the counts, seed and recipe digest stamped into its metadata, the recipe
  file (inside the manifest's folder, same digest).
- :func:`audit_batch`: a batch directory: the checksum chain (every file a scene.json lists, every
  scene.json against its index row, the index, rejection log and recipe against the manifest), files
  nobody lists (at any depth: a top-level entry the writer does not make, such as a copied scene
  folder or a ``.DS_Store``, is one), recounts, and then the whole source re-derived from the files and
  its realism checks recomputed (scenegen/manifest/derive.py, realism_checks.py) and compared field by
  field, so that a hand-edited threshold, sample count, origin or provenance field, or a consistently
  re-chained edit of a scene, cannot pass.
- :func:`audit_export_folder`: a WebDataset export folder: exactly ``export.json`` and the shards it
  lists, each with its recorded sha256 (not wired into a manifest yet: a manifest names no exports).
- :func:`audit_catalog_folder`: a user asset catalog folder: exactly ``catalog.yaml`` and the files its
  entries reference, inside the folder, meshes with their recorded sha256 (to be wired in).

All report through ``audit.violation(where, check, message)`` / ``audit.warning``; malformed files
are violations, never tracebacks.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path, PurePosixPath

import yaml

from scenegen.audit.scenes import check_scenes, compare_image_sample
from scenegen.manifest.derive import CHAINED_FILES, RECIPE_FILE, checksum_root
from scenegen.manifest.io import inside
from scenegen.manifest.schema import Source
from scenegen.store.batch import ASSETS, INDEX, MANIFEST, REJECTIONS, REPORT, REPORT_FILES, TIMINGS

# Fields of a batch source that must equal the source re-derived from the batch's files.
DERIVED_FIELDS = (
    "origin",
    "counts",
    "checksums",
    "catalog_sha256",
    "generator",
    "pipeline",
    "seed_panel",
    "rejections_by_label",
    "rendered",
)
REALISM_FIELDS = ("value", "threshold", "comparison", "status", "reference", "samples", "min_samples")
# What a WebDataset export names its description (scenegen/export/scene_shards.py EXPORT_FILE; the
# export family sits above the audit's, so the name is repeated here).
WEBDATASET_DESCRIPTION = "export.json"
CATALOG_STAGING = ".staging-"  # a catalog import in progress, or killed mid-way: not the catalog's


def _rows(audit, where: str, path: Path) -> list[dict] | None:
    """The rows of a JSON-lines log, each a mapping; None (and a violation) when unreadable."""
    try:
        lines = path.read_text().splitlines()
        rows = [json.loads(line) for line in lines if line.strip()]
    except (OSError, ValueError) as exc:  # ValueError: JSON and UTF-8 decoding errors
        audit.violation(f"{where}: {path.name}", "count", f"not readable JSON lines ({exc})"[:300])
        return None
    for n, row in enumerate(rows, 1):
        if not isinstance(row, dict) or not isinstance(row.get("proposal_index"), int):
            audit.violation(f"{where}: {path.name}", "count", f"line {n} is not a row with a proposal_index")
            return None
    return rows


def audit_table(audit, where: str, source: Source, path: Path) -> None:
    """A single-file source: a Parquet table of layouts."""
    at = f"{where}: {source.location}"
    if not path.is_file():
        audit.violation(at, "location", "a table source must be a file")
        return
    if audit.file_sha256(path) != source.checksums.sha256:
        audit.violation(at, "checksum", "sha256 differs from the manifest's")
    try:
        import pyarrow.parquet as pq

        table = pq.read_table(path)
    except Exception as exc:  # noqa: BLE001 - any unreadable table is a violation, not a crash
        audit.violation(at, "count", f"not a readable Parquet table ({exc})"[:300])
        return
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    counts = source.counts
    if table.num_rows != counts.scenes:
        audit.violation(where, "count", f"counts.scenes {counts.scenes}, the table has {table.num_rows} rows")
    if "split" in table.column_names:
        found = dict(sorted(Counter(table.column("split").to_pylist()).items()))
        if found != counts.splits:
            audit.violation(where, "count", f"counts.splits {counts.splits}, the table has {found}")
    try:
        proposals = int(meta["proposals"]) if "proposals" in meta else None
        labels = {k: int(v) for k, v in (i.split("=") for i in meta.get("rejections", "").split(",") if i)}
        seed = int(meta["seed"]) if "seed" in meta else None
    except ValueError:
        audit.violation(at, "count", "its metadata (proposals, rejections, seed) is not readable")
        return
    if proposals is not None and proposals != counts.proposals:
        audit.violation(where, "count", f"counts.proposals {counts.proposals}, the table records {proposals}")
    if "rejections" in meta and labels != source.rejections_by_label:
        audit.violation(where, "rejections", f"rejections_by_label differ from the table's {labels}")
    recorded = meta.get("predicate_version")
    if recorded is not None and recorded != source.predicate_version:
        audit.violation(
            where,
            "predicate_version",
            f"the table was tagged by predicates {recorded}, the manifest says {source.predicate_version}",
        )
    panel = source.seed_panel
    if (
        panel is not None
        and seed is not None
        and (panel.seed, panel.last_index) != (seed, counts.proposals - 1)
    ):
        audit.violation(
            where, "provenance", f"seed_panel {panel.seed}/{panel.last_index}, the table records {seed}"
        )
    if source.pipeline is not None:
        if meta.get("pipeline_sha256", source.pipeline.sha256) != source.pipeline.sha256:
            audit.violation(where, "provenance", "pipeline.sha256 differs from the table's recipe digest")
        _recipe_digest(audit, where, audit.folder / source.pipeline.file, source.pipeline.sha256)


def _recipe_digest(audit, where: str, recipe: Path, sha256: str):
    """The recipe file at ``recipe``, validated, its digest compared with ``sha256``; None if bad."""
    from scenegen.runner.config import validate_config

    if not inside(recipe, audit.folder):
        audit.violation(where, "provenance", f"pipeline file {recipe} lies outside {audit.folder}")
        return None
    try:
        config = validate_config(yaml.safe_load(recipe.read_text()))
    except FileNotFoundError:
        audit.violation(where, "provenance", f"pipeline file {recipe.name} is missing")
        return None
    except Exception as exc:  # noqa: BLE001 - an unreadable recipe is a violation
        audit.violation(where, "provenance", f"{recipe.name} is not a valid recipe ({exc})"[:300])
        return None
    if config.digest() != sha256:
        audit.violation(where, "provenance", f"{recipe.name}: its digest differs from pipeline.sha256")
    return config


def audit_batch(audit, where: str, source: Source, batch: Path) -> None:
    """A batch directory written by ``scenegen generate``."""
    if not batch.is_dir():
        audit.violation(where, "location", f"{source.location} is not a batch directory")
        return
    for name in CHAINED_FILES:
        if not (batch / name).is_file():
            audit.violation(f"{where}: {name}", "location", f"{name} is missing from {source.location}")
            return
    for name in CHAINED_FILES:
        if source.checksums.files.get(name) != audit.file_sha256(batch / name):
            audit.violation(f"{where}: {name}", "checksum", "sha256 differs from the manifest's")
    if checksum_root(source.checksums.files) != source.checksums.root:
        audit.violation(where, "checksum", "checksums.root is not the root of checksums.files")
    index, rejections = _rows(audit, where, batch / INDEX), _rows(audit, where, batch / REJECTIONS)
    if index is None or rejections is None:
        return
    counts = source.counts
    dirs = sorted(d.name for d in batch.iterdir() if d.name.startswith("scene_") and d.is_dir())
    if counts.scenes != len(dirs):
        audit.violation(where, "count", f"counts.scenes {counts.scenes}, {len(dirs)} scene directories")
    if len(index) != counts.scenes:
        audit.violation(where, "count", f"counts.scenes {counts.scenes}, {INDEX} has {len(index)} rows")
    if len(rejections) != counts.rejected:
        audit.violation(
            where, "count", f"counts.rejected {counts.rejected}, {REJECTIONS} has {len(rejections)} rows"
        )
    labels = dict(Counter(str(r.get("label")) for r in rejections))
    if labels != source.rejections_by_label:
        audit.violation(
            where, "rejections", f"rejections_by_label {source.rejections_by_label}, the log has {labels}"
        )
    # A proposal index ends once (a scene or a rejection without `repaired`); each of its repairs is
    # one more row with its own attempt number (propose/repair.py).
    ends = [r for r in rejections if not r.get("repaired")]
    twice = [i for i, n in Counter(r["proposal_index"] for r in [*index, *ends]).items() if n > 1]
    tries = Counter((r["proposal_index"], r.get("attempt", 0)) for r in rejections)
    twice += [i for (i, _), n in tries.items() if n > 1]
    if twice:
        audit.violation(where, "count", f"proposal indices {sorted(set(twice))[:5]} appear more than once")
    unfinished = sorted(
        {r["proposal_index"] for r in rejections} - {r["proposal_index"] for r in [*index, *ends]}
    )
    if unfinished:
        audit.violation(where, "count", f"proposal indices {unfinished[:5]} were repaired but never ended")
    end_attempt = {r["proposal_index"]: r.get("attempt", 0) for r in ends}
    late = sorted({i for (i, a) in tries if i in end_attempt and a > end_attempt[i]})
    if late:
        audit.violation(where, "count", f"proposal indices {late[:5]} have tries after their last one")
    repaired = {(r["proposal_index"], r.get("attempt", 0)) for r in rejections if r.get("repaired")}
    ids = Counter(row.get("scene_id") for row in index)
    for scene_id in sorted(str(s) for s, n in ids.items() if n > 1):
        audit.violation(f"{where}: {scene_id}", "count", f"listed {ids[scene_id]} times in {INDEX}")
    for extra in sorted(set(dirs) - set(ids)):
        audit.violation(f"{where}: {extra}", "count", f"a scene directory {INDEX} does not list")
    batch = batch.resolve()  # once: below, a path is inside it unless a link (each one checked)
    listed, images = check_scenes(audit, where, source, batch, index, repaired)
    _unlisted(audit, where, batch, dirs, listed)
    _unlisted_top_level(audit, where, batch)
    config = _recipe_digest(audit, f"{where}: {RECIPE_FILE}", batch / RECIPE_FILE, source.pipeline.sha256)
    if config is not None:
        from scenegen.assets.catalog import catalog_file, is_bundled

        for location in config.catalogs:  # the user catalogs it was made with (paths: working directory)
            if is_bundled(Path(location)):  # listed by a recipe of before it was refused: not a user's
                continue
            audit_catalog_folder(audit, f"{where}: catalog {location}", catalog_file(Path(location)))
        _rederive(audit, where, source, batch, config, images)


def _unlisted(audit, where: str, batch: Path, dirs: list[str], listed: set[str]) -> None:
    """Files in scene directories or _assets/ that no scene.json lists (``batch`` resolved, as the
    listed paths are)."""
    for folder in [*(batch / d for d in dirs), batch / ASSETS]:
        for path in sorted(folder.iterdir()) if folder.is_dir() else []:
            if path.name != "scene.json" and str(path) not in listed:
                audit.violation(
                    f"{where}: {path.relative_to(batch)}", "unlisted_file", "a file no scene.json lists"
                )


def _unlisted_top_level(audit, where: str, batch: Path) -> None:
    """Top-level entries of a batch that its writer (store/batch.py, runner/pipeline.py) does not make:
    anything but the chained files, the manifest, timings, ``_assets/``, ``scene_*`` folders (checked
    against the index above) and the two views scenegen writes into a batch by default. Hidden entries
    count: a finished batch holds no temporary file (a resumed run removes a killed one's)."""
    from scenegen.analysis.contact_sheet import CONTACT_SHEET
    from scenegen.data import CHART_NAME

    files = {*CHAINED_FILES, MANIFEST, TIMINGS, CONTACT_SHEET, CHART_NAME, REPORT}
    for path in sorted(batch.iterdir()):
        if path.name.startswith("scene_") and path.is_dir():
            continue
        if path.name == REPORT_FILES:  # the report's thumbnails: plain files, none a link out
            _report_files(audit, where, path, batch)
            continue
        expected = path.is_dir() if path.name == ASSETS else path.name in files and path.is_file()
        if not expected:
            audit.violation(f"{where}: {path.name}", "unlisted_file", "not a file or folder a batch holds")
        elif not inside(path, batch):
            audit.violation(f"{where}: {path.name}", "location", "a link out of the batch")


def _report_files(audit, where: str, folder: Path, batch: Path) -> None:
    if not folder.is_dir() or folder.is_symlink():
        audit.violation(f"{where}: {folder.name}", "unlisted_file", "not a file or folder a batch holds")
        return
    for path in sorted(folder.iterdir()):
        if not path.is_file() or path.is_symlink() or not inside(path, batch):
            audit.violation(f"{where}: {REPORT_FILES}/{path.name}", "location", "not a thumbnail file")


def _unlisted_under(audit, where: str, folder: Path, accounted: set[PurePosixPath], ignored=()) -> None:
    """Every entry under ``folder`` that is neither an ``accounted`` file (relative path) nor a folder
    on the way to one is a violation naming its relative path; a folder holding nothing accounted for
    is named once, not file by file. Top-level names in ``ignored`` are skipped; links are not followed."""
    on_the_way = {parent for rel in accounted for parent in rel.parents}

    def visit(directory: Path, at: PurePosixPath) -> None:
        for path in sorted(directory.iterdir()):
            rel = at / path.name
            if rel in accounted or (at == PurePosixPath() and path.name in ignored):
                continue
            if rel in on_the_way and path.is_dir() and not path.is_symlink():
                visit(path, rel)
            else:
                audit.violation(f"{where}: {rel}", "unlisted_file", "a file or folder nothing lists")

    visit(folder, PurePosixPath())


def audit_export_folder(audit, where: str, export: Path) -> None:
    """A WebDataset export (``scenegen export --format webdataset``): its ``export.json`` lists every
    shard with its sha256; a listed shard missing or changed, or any other file or folder, is a
    violation. (A LeRobot export's ``meta/scenegen_export.json`` lists its source episodes, not its
    files, so it cannot be audited file by file.)"""
    description_file = export / WEBDATASET_DESCRIPTION
    try:
        shards = json.loads(description_file.read_text())["shards"]
        assert isinstance(shards, dict) and all(isinstance(v, str) for v in shards.values())
    except FileNotFoundError:
        audit.violation(f"{where}: {WEBDATASET_DESCRIPTION}", "missing_file", "not a WebDataset export")
        return
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        audit.violation(f"{where}: {WEBDATASET_DESCRIPTION}", "schema", "not a description with shards")
        return
    accounted = {PurePosixPath(WEBDATASET_DESCRIPTION)}
    for name, sha in sorted(shards.items()):
        path, at = export / name, f"{where}: {name}"
        accounted.add(PurePosixPath(name))  # named once: a link out is a location, not also unlisted
        if "/" in name or name in ("", ".", "..") or not inside(path, export):
            audit.violation(at, "location", "a shard must be a file of the export folder")
            continue
        if not path.is_file():
            audit.violation(at, "missing_file", f"listed in {WEBDATASET_DESCRIPTION} but missing")
        elif audit.file_sha256(path) != sha:
            audit.violation(at, "checksum", f"sha256 differs from {WEBDATASET_DESCRIPTION}'s")
    _unlisted_under(audit, where, export, accounted)


def _catalog_references(audit, where: str, catalog_file: Path) -> dict[str, str | None] | None:
    """{relative path: expected sha256 or None} of every file a user catalog's entries reference
    (``mesh`` with ``mesh_sha256``, ``parts.files``, ``texture``); None (and a violation) when
    ``catalog_file`` is not a catalog."""
    at = f"{where}: {catalog_file.name}"
    try:
        data = yaml.safe_load(catalog_file.read_text())
    except FileNotFoundError:
        audit.violation(at, "missing_file", "the catalog file is missing")
        return None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        audit.violation(at, "schema", f"not readable YAML ({str(exc).splitlines()[0]})"[:300])
        return None
    assets = data.get("assets") if isinstance(data, dict) else None
    if not isinstance(assets, list) or not isinstance(data.get("version"), int):
        audit.violation(at, "schema", "not a catalog: a mapping with version and an assets list")
        return None
    from scenegen.assets.catalog import entry_files

    references: dict[str, str | None] = {}
    for i, asset in enumerate(assets):
        files = entry_files(asset)
        if files is None or not isinstance(asset.get("mesh_sha256"), str):
            audit.violation(f"{at}: assets[{i}]", "schema", "needs mesh, mesh_sha256 and parts.files (texts)")
            continue
        for name in files[1:]:  # parts and texture; the mesh has its sha256
            references.setdefault(name, None)
        references[asset["mesh"]] = asset["mesh_sha256"]
    return references


def audit_catalog_folder(audit, where: str, catalog_file: Path) -> None:
    """A user asset catalog: the folder of ``catalog_file`` (``catalog.yaml``) holds that file and
    exactly the files its entries reference. A reference that is absolute, climbs out with ``..`` or
    leads out through a link is a ``location`` violation; a missing one ``missing_file``; a mesh whose
    sha256 is not its ``mesh_sha256`` ``checksum``; any other file or folder ``unlisted_file``, except
    top-level ``.staging-*`` folders (an import in progress, or killed mid-way)."""
    folder = catalog_file.parent
    references = _catalog_references(audit, where, catalog_file)
    if references is None:
        return
    accounted = {PurePosixPath(catalog_file.name)}
    for name, sha in sorted(references.items()):
        rel, path, at = PurePosixPath(name), folder / name, f"{where}: {name}"
        accounted.add(rel)  # PurePosixPath drops "." parts ("./a.obj" is "a.obj"); a link out is named once
        climbs = rel.is_absolute() or ".." in rel.parts or "\\" in name
        if not rel.parts or climbs or not inside(path, folder):
            audit.violation(at, "location", "a catalog may reference only files inside its folder")
            continue
        if not path.is_file():
            audit.violation(at, "missing_file", f"referenced by {catalog_file.name} but missing")
        elif sha is not None and audit.file_sha256(path) != sha:
            audit.violation(at, "checksum", "sha256 differs from the entry's mesh_sha256")
    staging = {
        p.name
        for p in folder.iterdir()
        if p.name.startswith(CATALOG_STAGING) and p.is_dir() and not p.is_symlink()
    }
    _unlisted_under(audit, where, folder, accounted, ignored=staging)


def _rederive(audit, where: str, source: Source, batch: Path, config, images=None) -> None:
    """Re-derive the source from the batch's files and recompute its realism checks; every field
    that differs from the manifest is a violation (packages and scenegen version: warnings).
    ``images``: what the scene checks measured (audit/scenes.py's ImageSample); a sample of the
    batch's scenes rather than all of them is compared by ``compare_image_sample``'s rule."""
    from scenegen.manifest.derive import batch_source
    from scenegen.manifest.realism_checks import batch_realism

    try:
        derived = batch_source(batch, config, config.catalog().sha256, source.predicate_version or "")
    except Exception as exc:  # noqa: BLE001 - e.g. index and directories disagree (already reported)
        audit.violation(where, "provenance", f"cannot re-derive the source from its files ({exc})"[:300])
        return
    for name in DERIVED_FIELDS:
        theirs = getattr(derived, name)
        if getattr(source, name) != theirs:
            shown = theirs.model_dump(mode="json") if hasattr(theirs, "model_dump") else theirs
            audit.violation(
                f"{where}.{name}", "provenance", f"differs from the files: they give {shown}"[:400]
            )
    for name in ("packages", "scenegen_version"):
        if getattr(source, name) != getattr(derived, name):
            audit.warning(f"{where}.{name}", "provenance", "made with other versions than this scenegen's")
    recorded = {c.metric: c for c in source.realism}
    measured = images.measured() if images is not None else None
    for check in batch_realism(batch, config, source.checksums.root, measured):
        mine = recorded.get(check.metric)
        if mine is None:
            continue  # a missing check is reported by the realism audit
        if check.metric == "image_stats" and images is not None and not images.whole:
            compare_image_sample(audit, where, mine, check, images)
            continue
        differ = [f for f in REALISM_FIELDS if not _same(getattr(mine, f), getattr(check, f))]
        if differ:
            audit.violation(
                f"{where}.realism {check.metric}",
                "realism",
                f"recomputed from the files, {', '.join(differ)} differ: value {check.value:.6g}, "
                f"status {check.status}, threshold {check.threshold}",
            )


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=0.0, abs_tol=1e-6)
    return a == b
