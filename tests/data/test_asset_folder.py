"""``scenegen assets add DIR``: a folder of meshes (fixture meshes written here, one broken) imported on
two workers with a sidecar, one table at the end; the same catalog for any worker count; a rerun
skips what is present; killed midway, the catalog holds exactly the imports that completed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh
import yaml

from scenegen.assets.catalog import load_catalog
from scenegen.audit.files import audit_catalog_folder
from scenegen.audit.manifest import _Audit as Audit
from scenegen.cli import main

SIDECAR = {
    "carton.obj": {"category": "box", "mass": 0.2},
    "tin.stl": {"category": "can", "name": "tin_can"},
    "ball.ply": {"category": "ball", "units": "mm"},  # over the flags: --units cm
    "pill.glb": {"category": "pill", "collision": "hull"},
}
GOOD = ["ball", "carton", "pill", "stick", "tin_can"]  # in the files' order: ball, broken, carton, ...


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SCENEGEN_CACHE", str(tmp_path / "cache"))
    load_catalog.cache_clear()


def mesh_folder(root: Path, rings: int = 0) -> Path:
    """Five good meshes in four formats, sizes in cm, one broken file and one that is no mesh;
    ``rings`` tori more (non-convex: coacd takes seconds each)."""
    folder = root / "meshes"
    folder.mkdir()
    trimesh.creation.box((4, 6, 10)).export(folder / "carton.obj")
    trimesh.creation.cylinder(3, 9, sections=24).export(folder / "tin.stl")
    trimesh.creation.icosphere(2, 4).export(folder / "ball.ply")
    trimesh.creation.box((2, 2, 12)).export(folder / "stick.obj")
    trimesh.creation.capsule(6, 2).export(folder / "pill.glb")
    for i in range(rings):
        ring = trimesh.creation.torus(5 + i, 1.5, major_sections=48, minor_sections=24)
        ring.export(folder / f"ring_{i}.stl")
    (folder / "broken.stl").write_bytes(b"\x00\x01 not a mesh" * 3)
    (folder / "notes.txt").write_text("not a mesh: not read")
    return folder


def add(folder: Path, catalog: Path, *extra: str) -> int:
    return main(
        [
            "assets",
            "add",
            str(folder),
            "--units",
            "cm",
            "--category",
            "thing",
            *extra,
            "--catalog",
            str(catalog),
        ]
    )


def test_a_folder_imports_the_good_meshes_names_the_bad_one_and_a_rerun_skips_them(tmp_path, capsys):
    folder = mesh_folder(tmp_path)
    sidecar = folder / "objects.yaml"
    sidecar.write_text(yaml.safe_dump(SIDECAR))
    catalog = tmp_path / "mine" / "catalog.yaml"
    assert add(folder, catalog, "--sidecar", str(sidecar), "--workers", "2") == 1  # one refused
    table = capsys.readouterr().out.strip().splitlines()
    assert table[-1] == "5 imported, 1 refused, 0 skipped as present"
    broken = next(line for line in table[-7:] if line.startswith("broken.stl"))
    assert "refused" in broken and "holds no triangles" in broken
    assets = load_catalog(catalog).assets
    assert [a.name for a in assets] == GOOD  # listed in the files' order
    by_name = {a.name: a for a in assets}
    assert by_name["carton"].category == "box" and by_name["carton"].mass == pytest.approx(0.2)
    assert by_name["tin_can"].category == "can" and by_name["stick"].category == "thing"  # the flag
    assert by_name["ball"].extents == pytest.approx((0.008, 0.008, 0.008), abs=2e-4)  # radius 4
    assert by_name["pill"].collision == "convex_hull"
    before = catalog.read_bytes()

    assert add(folder, catalog, "--sidecar", str(sidecar)) == 1
    assert capsys.readouterr().out.strip().splitlines()[-1] == "0 imported, 1 refused, 5 skipped as present"
    assert catalog.read_bytes() == before

    sidecar.write_text(yaml.safe_dump({**SIDECAR, "carton.obj": {"category": "box", "mass": 0.25}}))
    assert add(folder, catalog, "--sidecar", str(sidecar)) == 1  # the fixed mass is not skipped over
    table = capsys.readouterr().out.strip().splitlines()
    assert table[-1] == "0 imported, 2 refused, 4 skipped as present"
    assert "with another mass; remove it" in next(line for line in table if line.startswith("carton.obj  "))
    assert catalog.read_bytes() == before
    sidecar.write_text(yaml.safe_dump(SIDECAR))

    serial = tmp_path / "serial" / "catalog.yaml"  # one worker: the same catalog, byte for byte
    assert add(folder, serial, "--sidecar", str(sidecar), "--workers", "1") == 1
    assert serial.read_bytes() == before


def test_a_csv_sidecar_and_bad_sidecars(tmp_path, capsys):
    folder = mesh_folder(tmp_path)
    (folder / "broken.stl").unlink()
    csv = folder / "objects.csv"
    csv.write_text("file,category,mass,collision\ncarton.obj,box,0.3,hull\nstick.obj,,,hull\n")
    catalog = tmp_path / "mine" / "catalog.yaml"
    assert add(folder, catalog, "--sidecar", str(csv), "--collision", "hull") == 0
    assets = {a.name: a for a in load_catalog(catalog).assets}
    assert assets["carton"].category == "box" and assets["carton"].mass == pytest.approx(0.3)
    assert assets["stick"].category == "thing"  # an empty cell takes the flag
    capsys.readouterr()
    for text, words in (
        ("nothing.obj: {category: a}\n", "'nothing.obj' is not a mesh file of"),
        ("carton.obj: {categry: a}\n", "carton.obj: categry"),
        ("carton.obj: {units: inch}\n", "carton.obj: units"),
        ("- carton.obj\n", "must map each file name"),
        ("carton.obj: {mass: true}\n", "carton.obj: mass"),  # not read as 1 kg
        ("carton.obj: {mass: 0.3}\ncarton.obj: {mass: 3}\n", "line 2: 'carton.obj' named a second time"),
        ("carton.obj: {mass: [0.3\n", "not YAML (line 2"),
        ("file,mass\ncarton.obj,0.3\ncarton.obj,3\n", "line 3 names 'carton.obj' a second time"),
    ):
        bad = tmp_path / ("bad.csv" if text.startswith("file,") else "bad.yaml")
        bad.write_text(text)
        other = tmp_path / "other" / "catalog.yaml"
        assert main(["assets", "add", str(folder), "--sidecar", str(bad), "--catalog", str(other)]) == 2
        error = capsys.readouterr().err.strip()
        assert error.count("\n") == 0 and words in error, error
        assert not other.parent.exists()  # refused before any import
    assert main(["assets", "add", str(folder), "--catalog", str(tmp_path / "x" / "catalog.yaml")]) == 1
    assert "no category: give --category" in capsys.readouterr().out


def test_killed_midway_the_catalog_holds_exactly_the_completed_imports(tmp_path):
    folder = mesh_folder(tmp_path, rings=3)
    catalog = tmp_path / "mine" / "catalog.yaml"
    command = [sys.executable, "-m", "scenegen.cli", "assets", "add", str(folder), "--units", "cm"]
    command += ["--category", "thing", "--workers", "2", "--catalog", str(catalog)]
    env = {**os.environ, "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True, start_new_session=True
    )
    said = []
    for line in proc.stdout:  # "[k/n] FILE: imported NAME" as each is listed
        said.append(line)
        if "ring_0.stl: imported" in line:  # the rings take seconds each: more are under way
            break
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    imported = [line.split()[-1] for line in said if ": imported " in line]
    load_catalog.cache_clear()
    listed = [a.name for a in load_catalog(catalog).assets]  # loading checks every file's sha256
    assert listed[: len(imported)] == imported and len(listed) < 8, (listed, said)
    audit = Audit(tmp_path / "unused.yaml")
    audit_catalog_folder(audit, "catalog", catalog)  # no file the catalog does not own but staging
    assert not audit.report.violations, audit.report.violations

    rerun = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    assert rerun.returncode == 1, rerun.stderr  # broken.stl
    assert (
        rerun.stdout.strip().splitlines()[-1]
        == f"{8 - len(listed)} imported, 1 refused, {len(listed)} skipped as present"
    )
    load_catalog.cache_clear()
    assert [a.name for a in load_catalog(catalog).assets] == [
        "ball",
        "carton",
        "pill",
        "ring_0",
        "ring_1",
        "ring_2",
        "stick",
        "tin",
    ]
    assert not [p for p in catalog.parent.iterdir() if p.name.startswith(".staging-")]
