"""Scene sources for the environment: a manifest's sources, labelled by name and origin, and the
mixture of a manifest's training recipe."""

from __future__ import annotations

import pytest

from scenegen.env.mixture import MixtureRecipe, MixtureSampler
from scenegen.env.scenes import SceneSourceError, load_scenes, source_scenes
from scenegen.manifest import read_manifest
from scenegen.paths import PROJECT_ROOT

MANIFEST = PROJECT_ROOT / "data_manifest.yaml"


def test_a_manifests_sources_come_labelled_with_their_name_and_origin():
    scenes = source_scenes(MANIFEST, ["reference"], split="heldout")
    assert (
        scenes and {s.source for s in scenes} == {"reference"} and {s.origin for s in scenes} == {"reference"}
    )
    table = load_scenes(PROJECT_ROOT / "assets" / "reference" / "reference.parquet", split="heldout")
    assert [s.scene_id for s in scenes] == [s.scene_id for s in table]


def test_the_mixture_of_the_manifests_training_recipe_has_its_recorded_shares():
    manifest = read_manifest(MANIFEST)
    recipe = next(r for r in manifest.recipes if r.name == "generator")
    scenes = source_scenes(MANIFEST, [c.source for c in recipe.components], split="heldout")
    mixture = MixtureRecipe.from_training_recipe(recipe, {"reference": len(scenes)})
    assert mixture.effective_shares() == pytest.approx(recipe.effective_shares)
    assert len(list(MixtureSampler(mixture, scenes, 100, seed=0))) == 100


def test_unknown_sources_and_missing_batches_are_named(tmp_path):
    with pytest.raises(SceneSourceError, match="no source named \\['nope'\\]"):
        source_scenes(MANIFEST, ["nope"])
    with pytest.raises(SceneSourceError, match="no index.jsonl"):
        load_scenes(tmp_path)
