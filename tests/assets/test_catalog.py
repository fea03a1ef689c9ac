"""The bundled asset catalog and its validation of broken assets (real files, no mocks)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from scenegen.assets.catalog import Catalog, CatalogError, load_catalog, parts_key
from scenegen.assets.measure import coacd_version, hull_to_visual_distance

REQUIRED_CATEGORIES = ("spoon", "fork", "knife", "mug", "bowl", "plate", "can", "bottle", "box")
MAX_HULL_TO_VISUAL_MM = 3.0
# Fewer surface samples than the authoring default (20,000) keep the mug under 2 s on 2 cores; a
# sampled Hausdorff distance only underestimates with fewer samples, by < 0.1 mm here.
HAUSDORFF_SAMPLES = 5000

BUNDLED = load_catalog()
ASSET_NAMES = [a.name for a in BUNDLED.assets]


def _load_obj(catalog: Catalog, relative: str) -> trimesh.Trimesh:
    return trimesh.load(catalog.path(relative), file_type="obj", process=False)


def _copy_assets(tmp_path: Path) -> Path:
    """A private copy of the bundled assets (each test gets its own root: load_catalog caches per root)."""
    root = tmp_path / "assets"
    shutil.copytree(BUNDLED.root, root)
    return root


def _set_sha(root: Path, old: str, new: str) -> None:
    text = (root / "catalog.yaml").read_text()
    assert text.count(old) == 1
    (root / "catalog.yaml").write_text(text.replace(old, new))


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_bundled_catalog_covers_the_required_categories():
    assert len(BUNDLED.assets) >= 12
    assert len(set(ASSET_NAMES)) == len(ASSET_NAMES), "asset names must be unique"
    assert len(BUNDLED.categories) >= 6
    missing = set(REQUIRED_CATEGORIES) - set(BUNDLED.categories)
    assert not missing, f"categories missing from the catalog: {sorted(missing)}"
    for category in REQUIRED_CATEGORIES:
        assert all(a.category == category for a in BUNDLED.of_category(category))


def test_unknown_asset_names_the_valid_ones():
    with pytest.raises(CatalogError, match="unknown asset 'spork'") as info:
        BUNDLED.get("spork")
    assert "small_box" in str(info.value) and "mug" in str(info.value)


@pytest.mark.parametrize("name", ASSET_NAMES)
def test_asset_is_physically_described(name):
    asset = BUNDLED.get(name)
    assert 0.0 <= asset.hull_to_visual_mm <= MAX_HULL_TO_VISUAL_MM
    assert asset.mass > 0 and asset.density > 0 and asset.friction > 0
    assert len(asset.resting_poses) >= 1
    for pose in asset.resting_poses:
        assert np.linalg.norm(pose.quat) == pytest.approx(1.0, abs=1e-5)
        assert pose.height > 0
        assert 0.0 < pose.probability <= 1.0
    assert asset.parts.files, f"{name} has no convex parts"
    for part in asset.parts.files:
        assert BUNDLED.path(part).is_file(), part
    # The mass is the solid's: density x volume of the committed (watertight) mesh.
    mesh = _load_obj(BUNDLED, asset.mesh)
    assert mesh.is_watertight
    assert asset.mass == pytest.approx(asset.density * mesh.volume, rel=1e-3)
    assert np.asarray(asset.extents) == pytest.approx(mesh.extents, abs=1e-4)
    # Body frame = centre-of-mass frame.
    assert np.abs(mesh.center_mass).max() < 1e-4


@pytest.mark.parametrize("name", ASSET_NAMES)
def test_parts_directory_is_keyed_by_mesh_and_parameters(name):
    asset = BUNDLED.get(name)
    mesh_sha = _sha(BUNDLED.path(asset.mesh))
    assert mesh_sha == asset.mesh_sha256
    assert asset.parts.coacd_version == coacd_version()
    key = parts_key(mesh_sha, coacd_version(), asset.parts.params)
    assert asset.parts.key == key
    for part in asset.parts.files:
        assert Path(part).parent == Path("parts") / name / key


@pytest.mark.parametrize("name", ["fork", "mug"])  # a thin utensil and a concave shell
def test_hull_to_visual_distance_recomputed_from_committed_files(name):
    asset = BUNDLED.get(name)
    mesh = _load_obj(BUNDLED, asset.mesh)
    parts = [_load_obj(BUNDLED, p) for p in asset.parts.files]
    distance_mm = hull_to_visual_distance(mesh, parts, n=HAUSDORFF_SAMPLES) * 1000
    assert distance_mm <= MAX_HULL_TO_VISUAL_MM
    assert distance_mm == pytest.approx(asset.hull_to_visual_mm, abs=0.5)


def test_hull_to_visual_distance_sees_a_missing_part():
    # The measure must be able to fail: without its larger part the fork loses its handle or head.
    asset = BUNDLED.get("fork")
    mesh = _load_obj(BUNDLED, asset.mesh)
    parts = [_load_obj(BUNDLED, p) for p in asset.parts.files]
    parts.remove(max(parts, key=lambda p: p.volume))
    assert hull_to_visual_distance(mesh, parts, n=HAUSDORFF_SAMPLES) * 1000 > MAX_HULL_TO_VISUAL_MM


def test_copied_catalog_loads(tmp_path):
    root = _copy_assets(tmp_path)
    catalog = load_catalog(root)
    assert catalog.root == root
    assert [a.name for a in catalog.assets] == ASSET_NAMES
    assert catalog.sha256 == BUNDLED.sha256


def test_truncated_mesh_is_a_catalog_error_naming_the_asset(tmp_path):
    root = _copy_assets(tmp_path)
    mesh = root / BUNDLED.get("fork").mesh
    data = mesh.read_bytes()
    mesh.write_bytes(data[: len(data) // 2])
    with pytest.raises(CatalogError, match="sha256") as info:
        load_catalog(root)
    assert "asset 'fork'" in str(info.value)


def test_garbled_mesh_with_updated_sha_is_a_parse_error_naming_the_asset(tmp_path):
    root = _copy_assets(tmp_path)
    asset = BUNDLED.get("knife")
    mesh = root / asset.mesh
    lines = mesh.read_text().splitlines()
    lines[3] = "v 0.01 garbage 0.02"
    mesh.write_text("\n".join(lines) + "\n")
    _set_sha(root, asset.mesh_sha256, _sha(mesh))
    with pytest.raises(CatalogError, match="cannot parse OBJ") as info:
        load_catalog(root)
    assert "asset 'knife'" in str(info.value)


def test_non_watertight_mesh_is_a_catalog_error_naming_the_asset(tmp_path):
    root = _copy_assets(tmp_path)
    asset = BUNDLED.get("mug")
    mesh = root / asset.mesh
    lines = mesh.read_text().splitlines()
    last_face = max(i for i, line in enumerate(lines) if line.startswith("f "))
    del lines[last_face]  # one triangle missing: its three edges now border a hole
    mesh.write_text("\n".join(lines) + "\n")
    _set_sha(root, asset.mesh_sha256, _sha(mesh))
    with pytest.raises(CatalogError, match="watertight") as info:
        load_catalog(root)
    assert "asset 'mug'" in str(info.value)


def test_missing_part_file_is_a_catalog_error_naming_the_asset(tmp_path):
    root = _copy_assets(tmp_path)
    asset = BUNDLED.get("bottle")
    (root / asset.parts.files[-1]).unlink()
    with pytest.raises(CatalogError, match="missing") as info:
        load_catalog(root)
    assert "asset 'bottle'" in str(info.value)
    assert asset.parts.files[-1] in str(info.value)


def test_missing_catalog_file_says_how_to_build_it(tmp_path, monkeypatch):
    with pytest.raises(CatalogError, match="scenegen assets add"):
        load_catalog(tmp_path / "nowhere")
    monkeypatch.setattr("scenegen.assets.catalog.ASSETS_DIR", tmp_path / "bundled")
    with pytest.raises(CatalogError, match="make assets"):
        load_catalog(tmp_path / "bundled")


def test_stack_bases_and_box_like_bases_by_geometry_are_the_bundled_lists():
    from scenegen.core.layout import is_box_like, is_stack_base

    # The names core/layout.py and propose/targeted.py listed before geometry decided.
    assert {a.name for a in BUNDLED.assets if is_stack_base(a)} == {
        "small_box",
        "cereal_box",
        "plate",
        "soup_can",
        "soda_can",
    }
    assert {a.name for a in BUNDLED.assets if is_box_like(a)} == {"small_box", "cereal_box"}
