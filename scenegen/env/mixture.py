"""Weighted mixtures of labelled scene sources: a recipe (:class:`MixtureRecipe`) and a PyTorch sampler
that draws by it (:class:`MixtureSampler`).

A recipe is a list of entries (source, optional tag filter, weight). Each scene belongs to the first
entry that matches it (its source, and at least one of the entry's tags if it names any), so entries
partition the scenes; an entry's scenes share its weight equally. The entry's **effective share**,
``weight / sum(weights)``, is the expected fraction of draws that land in it.

The seed's loss, ``E_real[l] + alpha * E_synthetic[l]`` (real: the reference or real data; synthetic:
generated batches), is :meth:`MixtureRecipe.seed_loss`: within each role the sources are concatenated,
so every real scene is drawn with weight ``1 / N_real`` and every synthetic one with ``alpha /
N_synthetic``, and the shares equal ``manifest.derive.effective_shares`` (what the manifest records).
Re-weighting part of one source (say its rare-tag scenes) is an entry with a tag filter placed before
the entry for the rest of that source (:meth:`MixtureRecipe.rebalanced`).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterator, Sequence

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from torch.utils.data import Sampler, WeightedRandomSampler

from scenegen.env.scenes import EnvScene

log = logging.getLogger(__name__)


class MixtureError(ValueError):
    """A recipe that cannot be drawn from the given scenes; the message names the entry."""


class MixtureEntry(BaseModel):
    """``weight`` (>= 0) of the scenes of ``source`` that hold any of ``tags`` (all its scenes when
    ``tags`` is empty) and that no earlier entry claimed."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: str
    tags: tuple[str, ...] = ()
    weight: float = Field(ge=0.0)

    @field_validator("weight")
    @classmethod
    def _finite(cls, weight: float) -> float:
        if not math.isfinite(weight):
            raise ValueError("weight must be a finite number >= 0")
        return weight

    @property
    def label(self) -> str:
        return f"{self.source}[{'|'.join(self.tags)}]" if self.tags else self.source

    def matches(self, scene: EnvScene) -> bool:
        return scene.source == self.source and (not self.tags or any(scene.tags.get(t) for t in self.tags))


class MixtureRecipe(BaseModel):
    """An ordered list of entries; see the module docstring for what a draw means."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    entries: tuple[MixtureEntry, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _some_weight(self) -> MixtureRecipe:
        if sum(e.weight for e in self.entries) <= 0:
            raise ValueError("entries: every weight is 0; give at least one entry a positive weight")
        labels = [e.label for e in self.entries]
        if len(set(labels)) != len(labels):
            raise ValueError(f"entries: {labels} name the same (source, tags) twice; merge them")
        return self

    def effective_shares(self) -> dict[str, float]:
        """Expected fraction of draws per entry label."""
        total = sum(e.weight for e in self.entries)
        return {e.label: e.weight / total for e in self.entries}

    @classmethod
    def seed_loss(cls, real: dict[str, int], synthetic: dict[str, int], alpha: float) -> MixtureRecipe:
        """loss = E_real[l] + alpha * E_synthetic[l] over sources given as {name: number of scenes}."""
        if alpha < 0 or not math.isfinite(alpha):
            raise MixtureError(f"alpha {alpha}: must be a finite number >= 0")
        n_real, n_syn = sum(real.values()), sum(synthetic.values())
        if n_real == 0 or (synthetic and n_syn == 0):
            raise MixtureError(f"sources {real | synthetic}: every role needs at least one scene")
        entries = [MixtureEntry(source=s, weight=n / n_real) for s, n in real.items()]
        entries += [MixtureEntry(source=s, weight=alpha * n / n_syn) for s, n in synthetic.items()]
        return cls(entries=entries)

    @classmethod
    def from_training_recipe(cls, recipe, sizes: dict[str, int]) -> MixtureRecipe:
        """The mixture of a manifest's training recipe (``manifest.schema.TrainingRecipe``: alpha and
        components with roles); ``sizes``: scenes per source. Its shares are the recipe's
        ``effective_shares``."""
        real = {c.source: sizes[c.source] for c in recipe.components if c.role == "real"}
        synthetic = {c.source: sizes[c.source] for c in recipe.components if c.role == "synthetic"}
        return cls.seed_loss(real, synthetic, recipe.alpha)

    @classmethod
    def rebalanced(cls, source: str, tags: Sequence[str], share: float) -> MixtureRecipe:
        """One source whose scenes holding any of ``tags`` get ``share`` of the draws (0 < share < 1)."""
        if not 0.0 < share < 1.0:
            raise MixtureError(f"share {share}: must lie strictly between 0 and 1")
        return cls(
            entries=[
                MixtureEntry(source=source, tags=tuple(tags), weight=share),
                MixtureEntry(source=source, weight=1.0 - share),
            ]
        )


def assign(recipe: MixtureRecipe, scenes: Sequence[EnvScene]) -> np.ndarray:
    """The entry index of every scene (-1: no entry claims it)."""
    out = np.full(len(scenes), -1, dtype=np.int64)
    for i, scene in enumerate(scenes):
        for k, entry in enumerate(recipe.entries):
            if entry.matches(scene):
                out[i] = k
                break
    return out


def scene_weights(recipe: MixtureRecipe, scenes: Sequence[EnvScene]) -> np.ndarray:
    """Per-scene draw probability (sums to 1): an entry's weight split equally over its scenes."""
    entry_of = assign(recipe, scenes)
    sizes = np.bincount(entry_of[entry_of >= 0], minlength=len(recipe.entries))
    for k, entry in enumerate(recipe.entries):
        if entry.weight > 0 and sizes[k] == 0:
            sources = sorted({s.source for s in scenes})
            raise MixtureError(
                f"entry {entry.label}: no scene matches it (sources given: {', '.join(sources)}); "
                "fix its source name or tags, or give it weight 0"
            )
    weights = np.zeros(len(scenes))
    claimed = entry_of >= 0
    weights[claimed] = [recipe.entries[k].weight / sizes[k] for k in entry_of[claimed]]
    return weights / weights.sum()


class MixtureSampler(Sampler[int]):
    """Draws ``num_samples`` scene indices per epoch, with replacement, by a recipe's weights.

    Reproducible: epoch ``e`` of a sampler with ``seed`` draws the same indices every time
    (torch.Generator seeded with ``(seed, e)``). After each epoch ``last_counts`` holds the draws
    per entry label and per source, which are also logged at INFO level.
    """

    def __init__(self, recipe: MixtureRecipe, scenes: Sequence[EnvScene], num_samples: int, seed: int):
        if num_samples < 1:
            raise MixtureError(f"num_samples {num_samples}: must be at least 1")
        self.recipe = recipe
        self.scenes = list(scenes)
        self.weights = scene_weights(recipe, self.scenes)
        self.entry_of = assign(recipe, self.scenes)
        self.num_samples = num_samples
        self.seed = seed
        self.epoch = 0
        self.last_counts: dict[str, Counter] = {}

    def effective_shares(self) -> dict[str, float]:
        return self.recipe.effective_shares()

    def __len__(self) -> int:
        return self.num_samples

    def __iter__(self) -> Iterator[int]:
        generator = torch.Generator().manual_seed(
            int(np.random.SeedSequence([self.seed, self.epoch]).generate_state(1)[0])
        )
        draws = list(
            WeightedRandomSampler(self.weights.tolist(), self.num_samples, True, generator=generator)
        )
        labels = [e.label for e in self.recipe.entries]
        self.last_counts = {
            "entries": Counter(labels[self.entry_of[i]] for i in draws),
            "sources": Counter(self.scenes[i].source for i in draws),
        }
        log.info("mixture epoch %d: %s", self.epoch, dict(self.last_counts["sources"]))
        self.epoch += 1
        return iter(draws)
