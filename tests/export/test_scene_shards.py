"""WebDataset export of a stored batch: read back by webdataset's own reader, byte for byte, and a
scene rebuilt from the shards alone loads in MuJoCo at its stored settled state."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from scenegen.cli import main
from scenegen.core.files import sha256_file
from scenegen.export.scene_shards import EXPORT_FILE, ExportError, export_webdataset, rebuild_scene
from scenegen.store.batch import INDEX, read_jsonl

wds = pytest.importorskip("webdataset")  # the `export` extra; CI installs it


@pytest.fixture(scope="module")
def export(demo_batch: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "shards"
    assert (
        main(
            [
                "export",
                str(demo_batch),
                "--format",
                "webdataset",
                "--out",
                str(out),
                "--scenes-per-shard",
                "4",
            ]
        )
        == 0
    )
    return out


def test_webdatasets_reader_returns_every_scene_byte_for_byte(export: Path, demo_batch: Path):
    shards = sorted(str(p) for p in export.glob("scenes-*.tar"))
    assert len(shards) == 2  # 6 scenes, 4 per shard
    samples = list(wds.WebDataset(shards, shardshuffle=False))
    ids = [row["scene_id"] for row in read_jsonl(demo_batch / INDEX)]
    assert [s["__key__"] for s in samples] == ids
    for sample in samples:
        folder = demo_batch / sample["__key__"]
        stored = {p.name for p in folder.iterdir() if p.name.endswith((".json", ".xml", ".png"))}
        assert {k for k in sample if not k.startswith("__")} == stored
        for name in stored:
            assert sample[name] == (folder / name).read_bytes(), name


def test_export_json_describes_the_export(export: Path, demo_batch: Path):
    description = json.loads((export / EXPORT_FILE).read_text())
    assert description["format"] == "webdataset" and description["counts"]["scenes"] == 6
    assert description["counts"]["assets"] == len(list((demo_batch / "_assets").iterdir()))
    assert description["shards"] == {p.name: sha256_file(p) for p in sorted(export.glob("*.tar"))}
    manifest = (demo_batch / "manifest.yaml").read_text()
    assert description["source"]["checksum_root"] in manifest


def test_a_scene_rebuilt_from_the_shards_alone_loads_at_its_settled_state(
    export: Path, demo_batch: Path, tmp_path
):
    scene_id = read_jsonl(demo_batch / INDEX)[3]["scene_id"]
    folder = rebuild_scene(export, scene_id, tmp_path / "rebuilt")
    rebuilt = mujoco.MjModel.from_xml_path(str(folder / "scene.xml"))
    original = mujoco.MjModel.from_xml_path(str(demo_batch / scene_id / "scene.xml"))
    assert (rebuilt.nbody, rebuilt.ngeom, rebuilt.nmesh) == (original.nbody, original.ngeom, original.nmesh)
    np.testing.assert_array_equal(rebuilt.key_qpos, original.key_qpos)
    np.testing.assert_array_equal(rebuilt.mesh_vert, original.mesh_vert)


def test_bad_exports_are_one_line_errors_and_write_nothing(demo_batch: Path, tmp_path: Path, capsys):
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "keep.txt").write_text("mine")
    assert main(["export", str(demo_batch), "--format", "webdataset", "--out", str(taken)]) == 2
    assert "exists and is not an empty folder" in capsys.readouterr().err
    assert [p.name for p in taken.iterdir()] == ["keep.txt"]
    with pytest.raises(ExportError, match="no index.jsonl"):
        export_webdataset(tmp_path, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.tmp*"))


def test_a_batch_manifest_that_does_not_read_is_a_one_line_error(demo_batch: Path, tmp_path: Path, capsys):
    # found by the long fuzz profile: a ManifestError escaped as a traceback, after the shards were written
    from scenes import copy_batch

    batch = copy_batch(demo_batch, tmp_path / "batch")
    manifest = batch / "manifest.yaml"
    manifest.write_text(manifest.read_text().replace("schema_version: 2", "schema_version: -108833"))
    assert main(["export", str(batch), "--format", "webdataset", "--out", str(tmp_path / "wds")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("scenegen: error: ") and "manifest.yaml: schema_version -108833" in err, err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "wds").exists() and not list(tmp_path.glob(".wds.tmp*"))


def test_a_rerun_onto_the_same_complete_export_is_a_no_op(demo_batch: Path, tmp_path: Path, capsys):
    out = tmp_path / "wds"
    assert main(["export", str(demo_batch), "--format", "webdataset", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(["export", str(demo_batch), "--format", "webdataset", "--out", str(out)]) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # and a second export of the same batch has the same bytes (tar headers carry no clock time)
    assert main(["export", str(demo_batch), "--format", "webdataset", "--out", str(tmp_path / "again")]) == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "again").iterdir()} == before
    # another shard size, or a shard that no longer has its recorded bytes, is not the same export
    assert (
        main(
            [
                "export",
                str(demo_batch),
                "--format",
                "webdataset",
                "--out",
                str(out),
                "--scenes-per-shard",
                "2",
            ]
        )
        == 2
    )
    (out / "scenes-000000.tar").write_bytes(b"torn")
    capsys.readouterr()
    assert main(["export", str(demo_batch), "--format", "webdataset", "--out", str(out)]) == 2
    assert "exists and is not an empty folder" in capsys.readouterr().err
