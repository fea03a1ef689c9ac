"""The proposer interface and its registry (snapping onto resting poses: scenegen/core/placement.py).

A proposer maps (condition, proposal indices, batch seed) to scene proposals. Proposal ``i`` draws its
randomness from ``SeedSequence([seed, i])`` alone, so a proposal does not depend on how a batch is
chunked, resumed or spread over workers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar, Protocol

import numpy as np
from pydantic import BaseModel, field_validator, model_serializer

from scenegen.assets.catalog import Asset
from scenegen.core import layout
from scenegen.schema.condition import Condition
from scenegen.schema.scene import SceneProposal


class Proposer(Protocol):
    """Anything that proposes scenes for a condition."""

    kind: str

    def propose(self, condition: Condition, indices: Sequence[int], seed: int) -> list[SceneProposal]:
        """One proposal per index, each a pure function of (condition, index, seed)."""
        ...


PROPOSERS: dict[str, Callable[..., Proposer]] = {}


def register_proposer(kind: str):
    """Class decorator: make a proposer constructible by its config's ``kind``."""

    def decorate(cls):
        PROPOSERS[kind] = cls
        cls.kind = kind
        return cls

    return decorate


def non_upright(asset: Asset) -> list[int]:
    """Indices of the asset's resting poses that are not upright (where its target is ``toppled``)."""
    return [i for i, p in enumerate(asset.resting_poses) if not p.upright]


def impossible_request(
    condition: Condition, catalog, overhang_cover: float | None = None, furniture_on_table: bool = False
) -> str | None:
    """Why no scene of this catalog can meet the request whatever the proposer, or None.
    ``overhang_cover``: the under_overhang predicate's threshold (the recipe's tags); with
    ``furniture_on_table`` (the recipe's checks) furniture stands wholly on the table."""
    if "toppled" in condition.required() and not any(
        non_upright(a) for a in catalog.of_category(condition.target)
    ):
        return (
            f"required tag toppled: no {condition.target} asset has a non-upright resting pose, so no "
            "scene can hold it; request another target"
        )
    if {"near_edge", "on_floor"} <= set(condition.required()):
        return (
            "required tags near_edge and on_floor: near_edge holds only for a target resting on the "
            "table top (its lowest point within 1 cm of it), on_floor only for one 0.3 m or more below "
            "it, so no scene can hold both; ask for one of them"
        )
    if (
        furniture_on_table
        and overhang_cover is not None
        and {"on_floor", "under_overhang"} <= set(condition.required())
    ):
        reach = floor_cover_reach(catalog, condition.target)
        if reach < overhang_cover:
            return (
                f"required tags on_floor and under_overhang: a {condition.target} on the floor lies "
                f"{layout.FLOOR_GAP * 100:.0f}+ cm past the table, where furniture stands, so a board covers "
                f"at most {reach:.0%} of it (needs {overhang_cover:.0%}); ask for one"
            )
    return None


def floor_cover_reach(catalog, category: str) -> float:
    """The most of any ``category`` asset, in any resting pose and yaw, that furniture standing wholly
    on the table can cover while the asset lies on the floor strip (``layout.floor_cover_bound``)."""
    from scenegen.assets.catalog import convex_part_vertices
    from scenegen.core.rotations import quat_to_matrix

    best = 0.0
    for asset in catalog.of_category(category):
        points = np.concatenate(convex_part_vertices(catalog, asset.name))
        for pose in asset.resting_poses:
            best = max(best, layout.floor_cover_bound(points @ quat_to_matrix(pose.quat).T))
    return best


def proposal_rng(seed: int, index: int) -> np.random.Generator:
    """The random generator of proposal ``index`` in a batch with ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([seed, index]))


class AssetChoice(BaseModel):
    """``assets``: the only assets a proposer places (a user catalog's, say); None, the default, puts
    no limit and is left out of the settings' dump, so recipes without the key hash as before it
    existed (``OMITTED_AT``: such keys and their defaults). Shared by the procedural and diffusion
    settings."""

    assets: tuple[str, ...] | None = None
    # keys left out of the dump at these values: settings added later hash as before they existed
    OMITTED_AT: ClassVar[dict[str, object]] = {"assets": None}

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler):
        data = handler(self)
        for key, value in self.OMITTED_AT.items():
            if key in data and data[key] == value:
                del data[key]
        return data

    @field_validator("assets")
    @classmethod
    def _known_assets(cls, assets: tuple[str, ...] | None) -> tuple[str, ...] | None:
        from scenegen.assets.catalog import active_catalog

        valid = active_catalog().by_name
        for name in assets or ():
            if name not in valid:
                raise ValueError(f"unknown asset {name!r}; valid assets: {', '.join(sorted(valid))}")
        if assets is not None and not assets:
            raise ValueError("an empty list allows no object; leave the key out to allow every asset")
        return assets
