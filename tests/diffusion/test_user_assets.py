"""The generator and user assets: a user asset of a category the model knows is placed through
decoding's substitution; a category the model does not know is refused with both ways forward; a
generator trained on a reference set with the user catalog knows the new category."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh
import yaml

from scenegen.assets.catalog import load_catalog
from scenegen.cli import main
from scenegen.data.asset_import import ImportOptions, add_asset
from scenegen.diffusion.encoding import matched_pose
from scenegen.paths import PROJECT_ROOT
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import validate_config

OTHERS = ("teaspoon", "tablespoon", "fork", "knife", "mug", "bowl", "plate", "bottle", "cereal_box")


@pytest.fixture(scope="module")
def user_catalog(tmp_path_factory) -> Path:
    """A user catalog of a tin (category can, which the model knows) and a pear (category fruit)."""
    root = tmp_path_factory.mktemp("user_catalog")
    tin, pear = root / "tin.stl", root / "pear.stl"
    trimesh.creation.cylinder(radius=0.035, height=0.11, sections=24).export(tin)
    trimesh.creation.icosphere(subdivisions=2, radius=0.035).apply_scale((1.0, 1.0, 1.3)).export(pear)
    catalog = root / "catalog" / "catalog.yaml"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SCENEGEN_CACHE", str(root / "cache"))
        add_asset(tin, ImportOptions("can", mass=0.3, collision="hull"), catalog)
        add_asset(pear, ImportOptions("fruit", mass=0.15, collision="hull"), catalog)
    return catalog


def _proposals(recipe: dict, n: int = 8):
    config = validate_config({"name": "t", **recipe})
    proposer = PROPOSERS[config.proposer.kind](config.proposer, config.catalog())
    return proposer.propose(config.condition, range(n), seed=3)


def test_a_user_asset_of_a_known_category_takes_the_place_of_the_models(user_catalog):
    recipe = {
        "catalogs": [str(user_catalog)],
        "condition": {"task": "retrieve", "target": "can"},
        "proposer": {"kind": "diffusion", "assets": ["tin", *OTHERS]},
    }
    proposals = _proposals(recipe)
    cans = [o for p in proposals for o in p.objects if o.category == "can"]
    assert cans and {o.asset for o in cans} == {"tin"}
    assert all(next(o for o in p.objects if o.name == p.target).asset == "tin" for p in proposals)
    tin = load_catalog(user_catalog).get("tin")
    for o in cans:  # standing on one of the tin's own resting poses, at its height
        assert 0 <= o.resting_pose < len(tin.resting_poses)
    assert [p.model_dump() for p in _proposals(recipe)] == [p.model_dump() for p in proposals]  # seeded


def test_a_matched_pose_keeps_uprightness_and_relative_height():
    catalog = load_catalog()
    mug, can = catalog.get("mug"), catalog.get("soup_can")
    upright = mug.upright_pose()
    assert can.resting_poses[matched_pose(mug, upright, can)].upright
    lying = next(i for i, p in enumerate(mug.resting_poses) if not p.upright)
    assert not can.resting_poses[matched_pose(mug, lying, can)].upright


def test_a_category_the_generator_does_not_know_names_both_ways_forward(user_catalog, tmp_path, capsys):
    recipe = tmp_path / "pear.yaml"
    recipe.write_text(
        yaml.safe_dump(
            {
                "name": "pear",
                "catalogs": [str(user_catalog)],
                "condition": {"task": "retrieve", "target": "fruit"},
                "proposer": {"kind": "diffusion"},
            }
        )
    )
    assert main(["generate", str(recipe), "--out", str(tmp_path / "out"), "--no-render"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "'fruit'" in error
    assert "--proposer procedural" in error and "scenegen train" in error
    assert not (tmp_path / "out").exists()


def test_a_generator_trained_with_the_user_catalog_knows_the_new_category(
    user_catalog, tmp_path, monkeypatch
):
    from scenegen.diffusion.train import TrainSettings, train

    recipe = yaml.safe_load((PROJECT_ROOT / "pipelines" / "reference.yaml").read_text())
    recipe.update(name="reference_pear", n=12, catalogs=[str(user_catalog)])
    (tmp_path / "reference.yaml").write_text(yaml.safe_dump(recipe))
    table = tmp_path / "reference.parquet"
    argv = ["reference", str(tmp_path / "reference.yaml"), "--out", str(table), "--quiet"]
    assert main(argv) == 0
    out = tmp_path / "generator"
    train(
        table, out, TrainSettings(steps=20, batch_size=16, d_model=32, layers=1, heads=2, split="all"), False
    )
    config = json.loads((out / "config.json").read_text())
    assert "fruit" in config["encoding"]["categories"] and "pear" in config["encoding"]["assets"]
    recipe = {
        "catalogs": [str(user_catalog)],
        "condition": {"task": "retrieve", "target": "fruit"},
        "proposer": {"kind": "diffusion", "checkpoint": str(out), "steps": 5},
    }
    proposals = _proposals(recipe, n=8)
    assert all(next(o for o in p.objects if o.name == p.target).asset == "pear" for p in proposals)
