"""Folders the audit checks file by file outside a manifest's sources: a user asset catalog (its
catalog.yaml and exactly the files its entries reference) and a WebDataset export (its export.json
and exactly the shards it lists). Real files in tmp_path; the audit's own recorder collects."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
import yaml

from scenegen.audit.files import WEBDATASET_DESCRIPTION, audit_catalog_folder, audit_export_folder
from scenegen.audit.manifest import _Audit

TRIANGLE = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nf 1 2 3\n"
TETRAHEDRON = TRIANGLE + "v 0 0 0.05\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def recorder(tmp_path: Path) -> _Audit:
    return _Audit(tmp_path / "unused.yaml")  # only its violation() and file_sha256() are used


def found(audit: _Audit) -> list[tuple[str, str]]:
    return [(v.check, v.where) for v in audit.report.violations]


@pytest.fixture
def catalog(tmp_path: Path) -> Path:
    """A user catalog of two assets: a mug (mesh, two parts, a texture) and a block (texture: null)."""
    root = tmp_path / "my_assets"
    for folder in ("meshes", "parts", "textures"):
        (root / folder).mkdir(parents=True)
    (root / "meshes/mug.obj").write_text(TETRAHEDRON)
    (root / "meshes/block.obj").write_text(TRIANGLE)
    (root / "parts/mug_000.obj").write_text(TETRAHEDRON)
    (root / "parts/mug_001.obj").write_text(TRIANGLE)
    (root / "textures/mug.png").write_bytes(b"\x89PNG\r\n\x1a\n not a real image")

    def sha(name: str) -> str:
        return hashlib.sha256((root / name).read_bytes()).hexdigest()

    assets = [
        {
            "name": "mug",
            "mesh": "meshes/mug.obj",
            "mesh_sha256": sha("meshes/mug.obj"),
            "parts": {"files": ["parts/mug_000.obj", "parts/mug_001.obj"], "count": 2},
            "texture": "textures/mug.png",
        },
        {
            "name": "block",
            "mesh": "meshes/block.obj",
            "mesh_sha256": sha("meshes/block.obj"),
            "parts": {"files": ["meshes/block.obj"]},  # its own mesh is its one convex part
            "texture": None,
        },
    ]
    (root / "catalog.yaml").write_text(yaml.safe_dump({"version": 1, "assets": assets}, sort_keys=False))
    return root / "catalog.yaml"


def test_a_clean_catalog_folder_passes(catalog: Path, tmp_path: Path):
    audit = recorder(tmp_path)
    audit_catalog_folder(audit, "catalog", catalog)
    assert found(audit) == []


@pytest.mark.parametrize(
    "stray, named",
    [
        ("meshes/mug_old.obj", "meshes/mug_old.obj"),
        (".DS_Store", ".DS_Store"),
        ("backup/meshes/mug.obj", "backup"),  # a folder with nothing referenced in it: named once
        ("parts/.staging-abc/mug_000.obj", "parts/.staging-abc"),  # staging is ignored at the top only
    ],
)
def test_a_stray_file_in_a_catalog_folder_is_named(catalog: Path, tmp_path: Path, stray: str, named: str):
    path = catalog.parent / stray
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(TRIANGLE)
    audit = recorder(tmp_path)
    audit_catalog_folder(audit, "catalog", catalog)
    assert found(audit) == [("unlisted_file", f"catalog: {named}")]


def test_a_staging_folder_in_a_catalog_folder_is_ignored(catalog: Path, tmp_path: Path):
    """An import in progress (or killed mid-way) writes into .staging-*/ at the catalog's top level."""
    staging = catalog.parent / ".staging-xyz"
    (staging / "meshes").mkdir(parents=True)
    (staging / "meshes/kettle.obj").write_text(TETRAHEDRON)
    (staging / "catalog.yaml").write_text("version: 1\nassets: [\n")  # half-written
    audit = recorder(tmp_path)
    audit_catalog_folder(audit, "catalog", catalog)
    assert found(audit) == []


def test_missing_changed_and_escaping_references(catalog: Path, tmp_path: Path):
    root = catalog.parent
    (root / "parts/mug_001.obj").unlink()
    (root / "meshes/mug.obj").write_text(TRIANGLE)  # no longer the mesh its sha256 names
    outside = tmp_path / "elsewhere.png"
    outside.write_bytes(b"outside")
    (root / "textures/mug.png").unlink()
    (root / "textures/mug.png").symlink_to(outside)  # a link out of the folder
    data = yaml.safe_load(catalog.read_text())
    data["assets"][1]["texture"] = "../elsewhere.png"
    catalog.write_text(yaml.safe_dump(data, sort_keys=False))
    audit = recorder(tmp_path)
    audit_catalog_folder(audit, "catalog", catalog)
    assert sorted(found(audit)) == [
        ("checksum", "catalog: meshes/mug.obj"),
        ("location", "catalog: ../elsewhere.png"),
        ("location", "catalog: textures/mug.png"),
        ("missing_file", "catalog: parts/mug_001.obj"),
    ]


def test_a_file_that_is_not_a_catalog_is_a_violation(tmp_path: Path):
    (tmp_path / "cat").mkdir()
    (tmp_path / "cat/catalog.yaml").write_text("assets: {mug: 1}\n")
    audit = recorder(tmp_path)
    audit_catalog_folder(audit, "catalog", tmp_path / "cat/catalog.yaml")
    assert found(audit) == [("schema", "catalog: catalog.yaml")]


# ---------------------------------------------------------------- WebDataset exports


def test_every_file_of_a_webdataset_export_is_listed_by_its_export_json(demo_batch: Path, tmp_path: Path):
    pytest.importorskip("webdataset")  # the `export` extra
    from scenegen.export.scene_shards import EXPORT_FILE, export_webdataset

    assert WEBDATASET_DESCRIPTION == EXPORT_FILE  # the audit repeats the exporter's name for it
    export = tmp_path / "shards"
    export_webdataset(demo_batch, export, scenes_per_shard=4)
    audit = recorder(tmp_path)
    audit_export_folder(audit, "export", export)
    assert found(audit) == []

    (export / "notes.txt").write_text("left here")
    shutil.copy(export / "scenes-000000.tar", export / "scenes-000000 (copy).tar")
    shard = export / "scenes-000001.tar"
    shard.write_bytes(shard.read_bytes()[:-1] + b"\x01")
    audit = recorder(tmp_path)
    audit_export_folder(audit, "export", export)
    assert sorted(found(audit)) == [
        ("checksum", "export: scenes-000001.tar"),
        ("unlisted_file", "export: notes.txt"),
        ("unlisted_file", "export: scenes-000000 (copy).tar"),
    ]
