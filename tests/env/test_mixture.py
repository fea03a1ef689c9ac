"""Mixtures of labelled sources: 20,000 draws land on each entry at its effective share (within three
standard errors) for the seed's loss at several alphas and for a re-weighted part of one source; the
shares are the ones the manifest records; the same seed draws the same indices."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from scenegen.env.mixture import MixtureEntry, MixtureError, MixtureRecipe, MixtureSampler, scene_weights
from scenegen.env.scenes import EnvScene
from scenegen.manifest.derive import effective_shares
from scenegen.manifest.schema import RecipeComponent
from scenegen.schema.scene import Lighting

DRAWS = 20_000


def scenes_of(source: str, n: int, rare_every: int = 0) -> list[EnvScene]:
    """``n`` placeholder scenes of ``source``; every ``rare_every``-th holds ``toppled``."""
    return [
        EnvScene(
            scene_id=f"{source}_{i}",
            origin="synthetic" if source.startswith("gen") else "reference",
            source=source,
            target="mug",
            objects=(),
            furniture=(),
            lighting=Lighting(ambient=(0.3, 0.3, 0.3), lights=()),
            cameras=(),
            robot_pose=(0.0,) * 7,
            tags={"toppled": bool(rare_every) and i % rare_every == 0},
        )
        for i in range(n)
    ]


SCENES = scenes_of("reference", 600, rare_every=25) + scenes_of("gen_a", 150) + scenes_of("gen_b", 250)
SIZES = {"reference": 600, "gen_a": 150, "gen_b": 250}


def assert_shares_hold(sampler: MixtureSampler) -> None:
    counts = Counter()
    labels = [e.label for e in sampler.recipe.entries]
    for index in sampler:
        counts[labels[sampler.entry_of[index]]] += 1
    assert counts == sampler.last_counts["entries"]
    for label, share in sampler.effective_shares().items():
        standard_error = np.sqrt(share * (1 - share) / DRAWS)
        assert abs(counts[label] / DRAWS - share) <= 3 * standard_error + 1e-12, (label, counts[label], share)


@pytest.mark.parametrize("alpha", [0.0, 0.25, 1.0, 4.0])
def test_the_seed_loss_draws_each_source_at_its_effective_share(alpha: float):
    recipe = MixtureRecipe.seed_loss({"reference": 600}, {"gen_a": 150, "gen_b": 250}, alpha)
    sampler = MixtureSampler(recipe, SCENES, DRAWS, seed=1)
    assert_shares_hold(sampler)
    components = [
        RecipeComponent(source="reference", role="real"),
        RecipeComponent(source="gen_a", role="synthetic"),
        RecipeComponent(source="gen_b", role="synthetic"),
    ]
    recorded = effective_shares(alpha, components, SIZES)  # what the manifest records
    assert recorded == pytest.approx(recipe.effective_shares(), abs=1e-6)
    # Each synthetic scene weighs alpha / N_synthetic against 1 / N_real for a real one.
    weights = scene_weights(recipe, SCENES)
    assert weights[700] * (1 + alpha) == pytest.approx(alpha / 400)
    assert weights[0] * (1 + alpha) == pytest.approx(1 / 600)


def test_re_weighting_one_sources_rare_scenes():
    recipe = MixtureRecipe.rebalanced("reference", ["toppled"], share=0.3)
    sampler = MixtureSampler(recipe, SCENES, DRAWS, seed=2)
    assert sampler.effective_shares() == pytest.approx({"reference[toppled]": 0.3, "reference": 0.7})
    assert_shares_hold(sampler)
    drawn = [SCENES[i] for i in sampler]
    assert all(s.source == "reference" for s in drawn)
    assert sum(s.tags["toppled"] for s in drawn) / DRAWS == pytest.approx(0.3, abs=0.02)


def test_the_same_seed_draws_the_same_indices_and_epochs_differ():
    recipe = MixtureRecipe.seed_loss({"reference": 600}, {"gen_a": 150, "gen_b": 250}, 1.0)
    a, b = MixtureSampler(recipe, SCENES, 500, seed=7), MixtureSampler(recipe, SCENES, 500, seed=7)
    first = list(a)
    assert first == list(b)
    assert list(a) != first  # the next epoch
    assert list(MixtureSampler(recipe, SCENES, 500, seed=8)) != first


def test_a_torch_dataloader_takes_the_sampler():
    from torch.utils.data import DataLoader

    recipe = MixtureRecipe.seed_loss({"reference": 600}, {"gen_a": 150, "gen_b": 250}, 0.5)
    loader = DataLoader(
        list(range(len(SCENES))), batch_size=50, sampler=MixtureSampler(recipe, SCENES, 200, 0)
    )
    batches = list(loader)
    assert len(batches) == 4 and all(len(b) == 50 for b in batches)


def test_bad_recipes_name_what_to_fix():
    with pytest.raises(ValueError, match="weight"):
        MixtureEntry(source="reference", weight=-1.0)
    with pytest.raises(ValueError, match="every weight is 0"):
        MixtureRecipe(entries=[MixtureEntry(source="reference", weight=0.0)])
    with pytest.raises(MixtureError, match="entry typo: no scene matches it"):
        scene_weights(MixtureRecipe(entries=[MixtureEntry(source="typo", weight=1.0)]), SCENES)
    with pytest.raises(MixtureError, match="share 1.5"):
        MixtureRecipe.rebalanced("reference", ["toppled"], 1.5)
