"""Fuzzing the data scenegen reads back: scene folders of a batch and data manifests, broken in the
ways files break (truncated, edited, missing, swapped for symlinks that leave their root), given to
every command that reads them (tests/fuzzing.py states what every answer must be)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import yaml
from fuzzing import ODD_VALUES, dump_yaml, example_dir, mutated_mapping, run_cli
from hypothesis import given
from hypothesis import strategies as st
from scenes import copy_batch, empty_project_manifest, project_with

OUTSIDE = ["/etc/hostname", "/etc", "../outside.txt", "../../etc/passwd"]


def _files(batch: Path) -> list[str]:
    """The batch's own files (not the shared meshes), relative to it, in a stable order."""
    return sorted(
        p.relative_to(batch).as_posix() for p in batch.rglob("*") if p.is_file() and "_assets" not in p.parts
    )


@st.composite
def broken_batch(draw, files: list[str]):
    """(what, function breaking a copy of the batch in one way)."""
    name = draw(st.sampled_from(files))
    kind = draw(
        st.sampled_from(["truncate", "edit", "missing", "symlink", "scene_symlink", "mesh_path", "manifest"])
    )
    if kind == "truncate":
        fraction = draw(st.floats(0, 1, exclude_max=True))

        def run(b: Path):
            data = (b / name).read_bytes()
            (b / name).write_bytes(data[: int(len(data) * fraction)])

    elif kind == "edit":
        name = draw(st.sampled_from([f for f in files if f.endswith("scene.json")]))
        seed = draw(st.integers(0, 2**32 - 1))

        def run(b: Path):
            scene = json.loads((b / name).read_text())
            (b / name).write_text(json.dumps(_edit(scene, seed)))

    elif kind == "missing":

        def run(b: Path):
            (b / name).unlink()

    elif kind == "symlink":
        target = draw(st.sampled_from(OUTSIDE))

        def run(b: Path):
            (b / name).unlink()
            (b.parent / "outside.txt").write_text("outside the batch\n")
            os.symlink(target if target.startswith("/") else b.parent / "outside.txt", b / name)

    elif kind == "scene_symlink":
        scene = draw(st.sampled_from(sorted({f.split("/")[0] for f in files if "/" in f})))
        name = scene

        def run(b: Path):
            shutil.move(b / scene, b.parent / "elsewhere")
            os.symlink(b.parent / "elsewhere", b / scene)

    elif kind == "mesh_path":
        name = draw(st.sampled_from([f for f in files if f.endswith("scene.xml")]))
        target = draw(st.sampled_from([*OUTSIDE, "/tmp", "../_assets", ""]))
        attribute = draw(st.sampled_from(["meshdir", "file"]))

        def run(b: Path):
            text = (b / name).read_text()
            if attribute == "meshdir":
                text = text.replace('meshdir="', f'meshdir="{target}/', 1)
            else:
                text = text.replace('file="', f'file="{target}/', 1)
            (b / name).write_text(text)

    else:
        name = "manifest.yaml"
        edits = draw(st.lists(st.tuples(st.integers(0, 10**6), ODD_VALUES), min_size=1, max_size=3))

        def run(b: Path):
            manifest = yaml.safe_load((b / name).read_text())
            (b / name).write_bytes(dump_yaml(_apply(manifest, edits)))

    return f"{kind} {name}", run


def _edit(data: dict, seed: int) -> dict:
    """``data`` with one value replaced by an odd one, chosen by ``seed`` (deterministic)."""
    import random

    rng = random.Random(seed)
    return _apply(
        data,
        [(rng.randrange(10**6), rng.choice([None, -1, 1e300, float("nan"), "x", [], {}, "../..", True]))],
    )


def _apply(data, edits: list[tuple[int, object]]):
    """Each (index, value): the value at path ``index`` mod the number of paths replaced by ``value``."""
    from fuzzing import leaf_paths

    for index, value in edits:
        paths = leaf_paths(data)
        if not paths:
            return data
        path = paths[index % len(paths)]
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        parent[path[-1]] = value
    return data


def _commands(batch: Path, root: Path) -> dict[str, list]:
    return {
        "audit": ["audit", batch / "manifest.yaml"],
        "show": ["show", batch, "--out", root / "sheet.png"],
        "export": ["export", batch, "--format", "webdataset", "--out", root / "wds"],
        "manifest add": ["manifest", "add", batch, "--to", root / "data_manifest.yaml"],
        "coverage": ["coverage", batch, "--out", root / "coverage.png"],
        "label": [
            "label",
            batch,
            "--out",
            root / "labels.parquet",
            "--limit",
            "1",
            "--primitives",
            "top_grasp",
            "--quiet",
        ],
    }


# label runs a grasp when the scene still loads (seconds): drawn a tenth as often as the others
COMMANDS = ["audit", "show", "export", "manifest add", "coverage"] * 2 + ["label"]


@pytest.fixture(scope="module")
def batch_files(demo_batch: Path) -> list[str]:
    return _files(demo_batch)


@given(data=st.data())
def test_scene_folders(demo_batch, batch_files, data):
    what, breaks = data.draw(broken_batch(batch_files), label="broken")
    command = data.draw(st.sampled_from(COMMANDS), label="command")
    with example_dir() as root:
        batch = copy_batch(demo_batch, root / "batch")
        breaks(batch)
        if command == "manifest add":  # a project the batch can join: the answer is about the batch
            empty_project_manifest(root / "data_manifest.yaml")
        run_cli(
            f"scene folder: {command}",
            _commands(batch, root)[command],
            root,
            ["batch"],
            report_ok=command == "audit",
        )


@pytest.fixture(scope="module")
def project(demo_batch: Path, tmp_path_factory) -> Path:
    """A project folder: a copy of the demo batch added to its data_manifest.yaml."""
    return project_with(demo_batch, tmp_path_factory.mktemp("project")).parent


@given(data=st.data())
def test_manifests(project, data):
    manifest = yaml.safe_load((project / "data_manifest.yaml").read_text())
    edited = data.draw(
        st.one_of(
            mutated_mapping(manifest),
            st.sampled_from(OUTSIDE + ["batch/..", "/tmp", "batch/../batch"]).map(
                lambda where: {**manifest, "sources": [{**manifest["sources"][0], "location": where}]}
            ),
        ),
        label="manifest",
    )
    command = data.draw(st.sampled_from(["audit", "coverage", "manifest add"]), label="command")
    with example_dir() as root:
        copy_batch(project / "batch", root / "batch")
        path = root / "data_manifest.yaml"
        path.write_bytes(dump_yaml(edited))
        argv = {
            "audit": ["audit", path],
            "coverage": ["coverage", path, "--out", root / "coverage.png"],
            "manifest add": ["manifest", "add", root / "batch", "--to", path, "--name", "again"],
        }[command]
        run_cli(
            f"manifest: {command}", argv, root, ["data_manifest.yaml", "batch"], report_ok=command == "audit"
        )
