"""Paths read from data files stay inside the file's root: a manifest's source locations (its folder),
a batch's scene folders, scene.xml's mesh and texture files and images (the batch folder), and an
export's members (the folder it is rebuilt in). '..', absolute paths and symlinks that leave the root
are refused with one line naming the file, before anything is read or written."""

from __future__ import annotations

import io
import os
import shutil
import tarfile
from pathlib import Path

import pytest
import yaml
from scenes import project_with

from scenegen.cli import main
from scenegen.store.batch import StoreError, check_scene_xml, measure_stored_scene, scene_dirs


@pytest.fixture
def batch(demo_batch: Path, tmp_path: Path) -> Path:
    """A copy of the session's demo batch in a project folder, added to the folder's manifest."""
    return project_with(demo_batch, tmp_path / "project").parent / "batch"


def _error(argv: list, capsys) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, (code, err)
    return err


# ---------------------------------------------------------------- manifests


@pytest.mark.parametrize("location", ["../outside", "/tmp", "link"])
def test_a_manifest_location_outside_its_folder_is_refused(location, batch: Path, tmp_path: Path, capsys):
    project = batch.parent
    outside = tmp_path / "outside"
    shutil.copytree(batch, outside, symlinks=True)
    if location == "link":
        os.symlink(outside, project / "link")  # inside by name, outside once resolved
    manifest = yaml.safe_load((project / "data_manifest.yaml").read_text())
    manifest["sources"][0]["location"] = location
    (project / "data_manifest.yaml").write_text(yaml.safe_dump(manifest))
    capsys.readouterr()

    assert main(["audit", str(project / "data_manifest.yaml")]) == 1
    assert "[location]" in capsys.readouterr().out
    err = _error(["coverage", project / "data_manifest.yaml", "--out", tmp_path / "c.png"], capsys)
    assert "outside the manifest's folder" in err and not (tmp_path / "c.png").exists()

    from scenegen.env.scenes import SceneSourceError, source_scenes

    with pytest.raises(SceneSourceError, match="outside the manifest's folder"):
        source_scenes(project / "data_manifest.yaml")


# ---------------------------------------------------------------- scene folders


def test_an_index_naming_a_folder_outside_the_batch_is_refused(batch: Path, tmp_path: Path, capsys):
    index = batch / "index.jsonl"
    index.write_text(index.read_text().replace('"scene_id": "scene_000001"', '"scene_id": "../../etc"', 1))
    with pytest.raises(StoreError, match="line 1: scene_id '../../etc' is not a scene name"):
        scene_dirs(batch)
    for argv in (
        ["show", batch, "--out", tmp_path / "sheet.png"],
        ["export", batch, "--format", "webdataset", "--out", tmp_path / "wds"],
        ["coverage", batch, "--out", tmp_path / "c.png"],
        ["label", batch, "--out", tmp_path / "l.parquet", "--quiet"],
    ):
        assert "index.jsonl: line 1" in _error(argv, capsys), argv
    assert not [p for p in tmp_path.iterdir() if p.name != "project"]


def test_a_scene_folder_linked_outside_the_batch_is_refused(batch: Path, tmp_path: Path, capsys):
    shutil.move(batch / "scene_000001", tmp_path / "elsewhere")
    os.symlink(tmp_path / "elsewhere", batch / "scene_000001")
    with pytest.raises(StoreError, match="the scene directory lies outside"):
        scene_dirs(batch)
    err = _error(["export", batch, "--format", "webdataset", "--out", tmp_path / "wds"], capsys)
    assert "scene_000001: the scene directory lies outside" in err and not (tmp_path / "wds").exists()


@pytest.mark.parametrize(
    "edit",
    [('meshdir="../_assets/"', 'meshdir="/etc/"'), ('meshdir="../_assets/"', 'meshdir="../../../"')],
)
def test_a_scene_xml_naming_files_outside_the_batch_is_refused(edit, batch: Path):
    scene_xml = batch / "scene_000001" / "scene.xml"
    text = scene_xml.read_text()
    assert edit[0] in text
    scene_xml.write_text(text.replace(*edit))
    with pytest.raises(StoreError, match="lies outside"):
        check_scene_xml(batch / "scene_000001", batch)
    with pytest.raises(StoreError, match="lies outside"):  # before MuJoCo opens any file
        measure_stored_scene(batch / "scene_000001")
    assert check_scene_xml(batch / "scene_000003", batch) == batch / "scene_000003" / "scene.xml"


def test_an_image_linked_outside_the_batch_is_refused(batch: Path, tmp_path: Path, capsys):
    secret = tmp_path / "secret.png"
    shutil.copyfile(batch / "scene_000001" / "front_rgb.png", secret)
    (batch / "scene_000001" / "front_rgb.png").unlink()
    os.symlink(secret, batch / "scene_000001" / "front_rgb.png")
    err = _error(["show", batch, "--out", tmp_path / "sheet.png"], capsys)
    assert "front_rgb.png: an image lies outside" in err and not (tmp_path / "sheet.png").exists()
    err = _error(["export", batch, "--format", "webdataset", "--out", tmp_path / "wds"], capsys)
    assert "front_rgb.png: a file to export lies outside" in err and not (tmp_path / "wds").exists()
    assert main(["audit", str(batch / "manifest.yaml")]) == 1
    assert "scene_000001/front_rgb.png" in capsys.readouterr().out


# ---------------------------------------------------------------- exports


def _add(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tar.addfile(info, io.BytesIO(data))


@pytest.mark.parametrize("member", ["scene_000001.../../escaped.txt", "scene_000001./tmp/escaped.txt"])
def test_an_export_member_leaving_its_folder_is_refused(member, batch: Path, tmp_path: Path, capsys):
    from scenegen.export.scene_shards import ExportError, rebuild_scene

    assert main(["export", str(batch), "--format", "webdataset", "--out", str(tmp_path / "wds")]) == 0
    shard = tmp_path / "wds" / "scenes-000000.tar"
    with tarfile.open(shard, "a") as tar:
        _add(tar, member, b"outside")
    into = tmp_path / "rebuilt"
    with pytest.raises(ExportError, match="is not a plain file name"):
        rebuild_scene(tmp_path / "wds", "scene_000001", into)
    assert not list(tmp_path.rglob("escaped.txt")) and not Path("/tmp/escaped.txt").exists()
