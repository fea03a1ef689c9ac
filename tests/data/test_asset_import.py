"""``scenegen assets add``: a user's meshes as they come (fixture meshes written here), each with its
one-line outcome; where an import stops, the catalog is byte for byte as it was."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from scenegen.assets.catalog import CatalogError, load_catalog, load_catalogs, read_obj
from scenegen.audit.manifest import _Audit as Audit
from scenegen.cli import main
from scenegen.data.asset_import import ImportOptions, add_asset
from scenegen.data.asset_meshes import VISUAL_MAX_FACES

BOX_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
BOX_QUADS = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]  # outward


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SCENEGEN_CACHE", str(tmp_path / "cache"))
    load_catalog.cache_clear()


def box_obj(size: tuple[float, float, float], quads: bool = True, drop: int = 0, extra: str = "") -> str:
    """An OBJ box with a corner at the origin: quads, or triangles with the last ``drop`` left out."""
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in BOX_CORNERS * np.asarray(size)]
    faces = (
        [q for q in BOX_QUADS] if quads else [t for a, b, c, d in BOX_QUADS for t in ((a, b, c), (a, c, d))]
    )
    faces = faces[: len(faces) - drop]
    lines += ["f " + " ".join(str(i) for i in face) for face in faces]
    return "\n".join(lines) + "\n" + extra


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def seed_catalog(tmp_path: Path) -> Path:
    """A user catalog holding one asset, as a starting point for imports that must not change it."""
    catalog = tmp_path / "mine" / "catalog.yaml"
    add_asset(write(tmp_path, "brick.obj", box_obj((4, 6, 10))), ImportOptions("brick", units="cm"), catalog)
    return catalog


def run_cli(*args: str) -> int:
    return main(["assets", *args])


def test_a_quad_mesh_in_centimetres_imports_centred_with_its_poses_and_loads(tmp_path):
    mesh = write(tmp_path, "carton.obj", box_obj((4, 6, 10)))
    _, faces = read_obj(mesh.read_bytes())
    assert len(faces) == 12  # six quads, each split into two triangles
    result = add_asset(mesh, ImportOptions("carton", units="cm", mass=0.2), tmp_path / "user")
    asset = result.asset
    assert asset.extents == pytest.approx((0.04, 0.06, 0.10))
    assert asset.mass == pytest.approx(0.2)
    assert asset.collision == "convex_decomposition" and len(asset.parts.files) == 1
    vertices, _ = read_obj(asset.file(asset.mesh).read_bytes())
    assert np.abs(vertices.min(0) + vertices.max(0)).max() < 1e-6  # centred on its centre of mass
    upright = asset.resting_poses[asset.upright_pose()]
    assert upright.height == pytest.approx(0.05, abs=1e-4)  # standing on its 4 x 6 cm face
    assert asset.source.scale == 0.01 and asset.source.file == "carton.obj"
    merged = load_catalogs([tmp_path / "user" / "catalog.yaml"])
    assert merged.get("carton").root == tmp_path / "user"
    assert merged.sha256 != load_catalog().sha256 and len(merged.files) == 2


def test_millimetres_without_units_stop_naming_the_file_and_the_fix(tmp_path, capsys):
    catalog = seed_catalog(tmp_path)
    before = catalog.read_bytes()
    mesh = write(tmp_path, "bracket.obj", box_obj((40, 60, 100)))
    assert run_cli("add", str(mesh), "--category", "bracket", "--catalog", str(catalog)) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and str(mesh) in error and "--units mm" in error
    assert catalog.read_bytes() == before and sorted(p.name for p in catalog.parent.iterdir()) == [
        "brick",
        "catalog.yaml",
    ]


def test_a_small_hole_is_filled_and_said(tmp_path):
    mesh = write(tmp_path, "open.obj", box_obj((4, 6, 10), quads=False, drop=1))
    result = add_asset(mesh, ImportOptions("box", units="cm"), tmp_path / "user")
    assert any("holes filled" in note for note in result.notes)
    assert result.asset.collision == "convex_decomposition"


def test_a_mesh_that_cannot_be_closed_gets_its_convex_hull_recorded(tmp_path):
    mesh = write(tmp_path, "tray.obj", box_obj((4, 6, 10), quads=True, drop=3))  # three sides gone
    result = add_asset(mesh, ImportOptions("tray", units="cm"), tmp_path / "user")
    assert any("convex hull" in note for note in result.notes)
    assert result.asset.collision == "convex_hull" and len(result.asset.parts.files) == 1
    assert load_catalog(tmp_path / "user").get("tray").collision == "convex_hull"


def test_degenerate_triangles_are_removed_and_said(tmp_path):
    mesh = write(tmp_path, "sliver.obj", box_obj((4, 6, 10), quads=False, extra="f 1 1 2\nf 3 3 3\n"))
    result = add_asset(mesh, ImportOptions("box", units="cm"), tmp_path / "user")
    assert any("degenerate" in note for note in result.notes)
    assert result.asset.collision == "convex_decomposition"


def test_two_bodies_in_one_file_become_one_rigid_object(tmp_path):
    a = trimesh.creation.box((0.04, 0.04, 0.04))
    b = trimesh.creation.box((0.04, 0.04, 0.04))
    b.apply_translation((0.08, 0, 0))
    mesh = tmp_path / "pair.glb"
    trimesh.Scene([a, b]).export(mesh)
    result = add_asset(mesh, ImportOptions("pair", density=1000), tmp_path / "user")
    assert any("2 bodies" in note for note in result.notes)
    assert result.asset.mass == pytest.approx(2 * 0.04**3 * 1000, rel=1e-3)
    assert result.asset.extents[0] == pytest.approx(0.12, abs=1e-4)


def test_a_million_triangles_render_decimated_and_keep_a_faithful_collision_input(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=8, radius=0.04)  # 1,310,720 triangles
    mesh = tmp_path / "ball.ply"
    sphere.export(mesh)
    result = add_asset(mesh, ImportOptions("ball", collision="hull"), tmp_path / "user")
    notes = " | ".join(result.notes)
    assert "visual mesh decimated from 1310720" in notes and "collision input decimated" in notes
    _, faces = read_obj(result.asset.file(result.asset.mesh).read_bytes())
    assert len(faces) <= VISUAL_MAX_FACES
    assert result.asset.hull_to_visual_mm < 1.0  # the hull of the collision input hugs the sphere
    assert result.asset.extents == pytest.approx((0.08, 0.08, 0.08), abs=5e-4)


def test_a_missing_texture_file_keeps_the_colour_and_says_so(tmp_path):
    write(tmp_path, "skin.mtl", "newmtl skin\nKd 0.9 0.2 0.1\nmap_Kd missing.png\n")
    uv = "".join(f"vt {u} {v}\n" for u, v in BOX_CORNERS[:, :2])
    mesh = write(tmp_path, "crate.obj", "mtllib skin.mtl\nusemtl skin\n" + uv + box_obj((4, 6, 10)))
    result = add_asset(mesh, ImportOptions("crate", units="cm"), tmp_path / "user")
    assert any("missing.png missing" in note for note in result.notes)
    assert result.asset.texture is None


def test_a_texture_image_with_uvs_is_kept_and_rendered(tmp_path, capsys):
    image = np.zeros((64, 64, 3), np.uint8)
    image[:, :32] = (0, 0, 255)  # red half (OpenCV writes BGR)
    image[:, 32:] = (255, 0, 0)  # blue half
    cv2.imwrite(str(tmp_path / "skin.png"), image)
    write(tmp_path, "skin.mtl", "newmtl skin\nKd 1 1 1\nmap_Kd skin.png\n")
    lines = box_obj((4, 6, 10), quads=False).splitlines()
    uv = "".join(f"vt {u} {v}\n" for u, v in BOX_CORNERS[:, :2])
    faces = [" ".join(f"{i}/{i}" for i in line.split()[1:]) for line in lines if line.startswith("f ")]
    text = (
        "mtllib skin.mtl\nusemtl skin\n"
        + "\n".join(lines[:8])
        + "\n"
        + uv
        + "".join(f"f {f}\n" for f in faces)
    )
    mesh = write(tmp_path, "crate.obj", text)
    result = add_asset(mesh, ImportOptions("crate", units="cm"), tmp_path / "user")
    assert result.asset.texture == "crate/texture.png" and result.asset.file(result.asset.texture).is_file()
    out = tmp_path / "sheet.png"
    assert run_cli("show", "crate", "--catalog", str(tmp_path / "user"), "--out", str(out)) == 0
    sheet = cv2.imread(str(out))
    assert sheet is not None and sheet.shape[0] > 200
    reds = (sheet[:, :, 2] > 150) & (sheet[:, :, 0] < 80)
    blues = (sheet[:, :, 0] > 150) & (sheet[:, :, 2] < 80)
    assert reds.sum() > 50 and blues.sum() > 50  # the texture's two colours are drawn


def test_an_unreadable_file_stops_with_one_line_and_writes_nothing(tmp_path, capsys):
    catalog = seed_catalog(tmp_path)
    before = catalog.read_bytes()
    bad = tmp_path / "garbage.stl"
    bad.write_bytes(b"\x00\x01 not a mesh" * 3)
    assert run_cli("add", str(bad), "--category", "junk", "--catalog", str(catalog)) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and str(bad) in error
    assert catalog.read_bytes() == before
    assert sorted(p.name for p in catalog.parent.iterdir()) == ["brick", "catalog.yaml"]


def test_names_that_clash_across_catalogs_are_refused(tmp_path):
    mesh = write(tmp_path, "mug.obj", box_obj((4, 6, 10)))
    with pytest.raises(CatalogError, match="'mug' is already in .*assets/catalog.yaml"):
        add_asset(mesh, ImportOptions("mug", units="cm"), tmp_path / "user")
    first, second = seed_catalog(tmp_path), tmp_path / "other"
    add_asset(tmp_path / "brick.obj", ImportOptions("brick", units="cm"), second)
    with pytest.raises(CatalogError, match="'brick' is in both"):
        load_catalogs([first, second])


def test_the_bundled_catalog_is_never_written(tmp_path):
    mesh = write(tmp_path, "x.obj", box_obj((4, 6, 10)))
    with pytest.raises(CatalogError, match="bundled catalog"):
        add_asset(mesh, ImportOptions("thing", units="cm"), load_catalog().root / "catalog.yaml")


def test_an_import_stopped_between_its_two_renames_leaves_the_catalog_and_is_cleaned_next_time(
    tmp_path, monkeypatch
):
    catalog = seed_catalog(tmp_path)
    before = catalog.read_bytes()
    mesh = write(tmp_path, "crate.obj", box_obj((4, 6, 10)))

    def killed(*args):
        raise OSError("killed")

    monkeypatch.setattr("scenegen.data.asset_import.os.replace", killed)
    with pytest.raises(OSError, match="killed"):
        add_asset(mesh, ImportOptions("crate", units="cm"), catalog)
    assert catalog.read_bytes() == before and (catalog.parent / "crate").is_dir()  # moved, not listed
    load_catalog.cache_clear()
    assert [a.name for a in load_catalog(catalog).assets] == ["brick"]
    monkeypatch.undo()
    monkeypatch.setenv("SCENEGEN_CACHE", str(tmp_path / "cache"))
    tin = add_asset(write(tmp_path, "tin.obj", box_obj((4, 4, 8))), ImportOptions("tin", units="cm"), catalog)
    assert not tin.notes or all("interrupted" not in n for n in tin.notes)  # crate's leftover: not a stranger
    result = add_asset(mesh, ImportOptions("crate", units="cm"), catalog)
    assert any("interrupted import" in note for note in result.notes)


def test_kill_9_during_an_import_leaves_the_catalog_as_it_was(tmp_path):
    catalog = seed_catalog(tmp_path)
    before = catalog.read_bytes()
    ring = trimesh.creation.torus(major_radius=0.05, minor_radius=0.015, major_sections=48, minor_sections=24)
    mesh = tmp_path / "ring.stl"
    ring.export(mesh)
    command = [
        sys.executable,
        "-m",
        "scenegen.cli",
        "assets",
        "add",
        str(mesh),
        "--category",
        "ring",
        "--catalog",
        str(catalog),
    ]
    env = {**os.environ, "SCENEGEN_CACHE": str(tmp_path / "cache"), "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
    line = proc.stdout.readline()  # printed just before coacd starts
    assert "convex decomposition" in line, line
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert catalog.read_bytes() == before
    load_catalog.cache_clear()
    assert [a.name for a in load_catalog(catalog).assets] == ["brick"]
    staging = [p.name for p in catalog.parent.iterdir() if p.name.startswith(".staging-")]
    audit = Audit(tmp_path / "unused.yaml")
    from scenegen.audit.files import audit_catalog_folder

    audit_catalog_folder(audit, "catalog", catalog)
    assert not audit.report.violations, (
        audit.report.violations
    )  # the killed import's staging folder is ignored
    assert len(staging) == 1


def test_a_round_object_is_upright_in_every_pose_and_never_toppled(tmp_path):
    from scenegen.tags.predicates import TagContext, TagSettings, toppled

    lemon = tmp_path / "lemon.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=0.02).apply_scale((1.12, 1.0, 1.0)).export(lemon)
    result = add_asset(lemon, ImportOptions("fruit", collision="hull"), tmp_path / "user")
    assert result.asset.orientation_free and all(p.upright for p in result.asset.resting_poses)
    assert any("round" in note for note in result.notes)
    can = tmp_path / "tin.stl"
    trimesh.creation.cylinder(radius=0.025, height=0.08, sections=24).export(can)
    tin = add_asset(can, ImportOptions("can", collision="hull"), tmp_path / "user").asset
    assert not tin.orientation_free  # 5 x 5 x 8 cm: not about as long as wide
    ctx = TagContext(None, None, "lemon", ["lemon"], (), None, np.zeros(3), (), np.zeros((0, 3)), True)
    assert not toppled(ctx, TagSettings()).holds  # whatever way a round target has rolled


def test_a_catalog_in_a_folder_that_holds_other_files_is_refused_with_one_line(tmp_path, capsys):
    folder = tmp_path / "project"
    folder.mkdir()
    (folder / "notes.txt").write_text("my notes\n")
    (folder / "scans").mkdir()
    mesh = write(tmp_path, "crate.obj", box_obj((4, 6, 10)))
    catalog = folder / "catalog.yaml"
    assert run_cli("add", str(mesh), "--category", "crate", "--units", "cm", "--catalog", str(catalog)) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "notes.txt, scans" in error and "a folder of its own" in error
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "scans"]  # nothing written
    own = seed_catalog(tmp_path)  # a catalog's own folder takes more assets; a stranger there is named
    add_asset(mesh, ImportOptions("crate", units="cm"), own)
    (own.parent / "stray.obj").write_text("v 0 0 0\n")
    with pytest.raises(CatalogError, match=r"holds stray\.obj, which catalog\.yaml does not own"):
        add_asset(write(tmp_path, "tin.obj", box_obj((4, 4, 8))), ImportOptions("tin", units="cm"), own)
    assert [a.name for a in load_catalog(own).assets] == ["brick", "crate"]


def test_a_folder_of_the_users_own_named_like_the_asset_is_never_removed(tmp_path):
    folder = tmp_path / "project"
    (folder / "lemon").mkdir(parents=True)
    mesh = write(folder / "lemon", "lemon.obj", box_obj((5, 5, 7)))  # the user's own source files
    with pytest.raises(CatalogError, match=r"holds lemon, which catalog\.yaml does not own"):
        add_asset(mesh, ImportOptions("lemon", units="cm"), folder / "catalog.yaml")
    assert mesh.is_file() and sorted(p.name for p in folder.iterdir()) == ["lemon"]
