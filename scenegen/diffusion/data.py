"""Training data for the diffusion generator: layouts as tensors, and the conditions they are trained with.

Each layout (a reference Parquet row) gives its tokens (:mod:`scenegen.diffusion.encoding`) and its
*full* condition: its task, target category and robot pose, and for every rare tag ``required`` if
the measured tag holds and ``forbidden`` if it does not. Training shows the model partial versions of
that condition (:func:`training_conditions`): each tag independently becomes ``unspecified`` with
probability ``p_unspecified`` (so a request that leaves a tag open gets that tag's natural rate), each
field is independently dropped to its null value with probability ``p_field``, and the whole
condition is null with probability ``p_null`` (the unconditional branch of classifier-free guidance).

A model trained with spread bins (``TrainSettings.spread_bins``) also sees the layout's *spread*
(:func:`layout_spread`: the mean xy distance between its objects' centres, in quantile bins of the
training data, one more value for fewer than two objects), dropped to null with probability
``p_spread_null`` on its own draw (so the null condition is seen with a spread and without). The
reference recipe clusters half its layouts, so that distance is bimodal; a model without it blended
the two modes into one (docs/generator.md). At sampling a proposal draws its spread from the
training data's histogram (``proposer.draw_spread``), which is the data's own mixture.

Rare examples may be oversampled for the conditional branch only (:func:`batch_indices`): the rare
draws are never given the null condition, so the unconditional model still learns the data's rates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from scenegen.diffusion.encoding import XY_SCALE, SceneEncoding
from scenegen.diffusion.model import FORBIDDEN, NULL, REQUIRED, UNSPECIFIED, ConditionBatch
from scenegen.schema.condition import RARE_TAGS, TASKS


@dataclass
class LayoutTensors:
    """A dataset of N layouts: tokens (N, slots, object_width), scene (N, scene_width), task (N,),
    target (N,), tags (N, n_tags) bool (measured), pose (N, 7), spread (N,) its spread bin (None:
    trained without)."""

    objects: torch.Tensor
    scene: torch.Tensor
    task: torch.Tensor
    target: torch.Tensor
    tags: torch.Tensor
    pose: torch.Tensor
    spread: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.task)


def tasks() -> tuple[str, ...]:
    return tuple(sorted(TASKS))


def layout_tensors(rows: list[dict], encoding: SceneEncoding) -> LayoutTensors:
    """Tensors of reference-style rows (``reference.layout_row``), in row order."""
    categories = encoding.catalog.categories
    objects, scene = zip(*(encoding.encode_row(r) for r in rows), strict=True)
    return LayoutTensors(
        objects=torch.tensor(np.stack(objects), dtype=torch.float32),
        scene=torch.tensor(np.stack(scene), dtype=torch.float32),
        task=torch.tensor([tasks().index(r["task"]) for r in rows]),
        target=torch.tensor([categories.index(r["target_category"]) for r in rows]),
        tags=torch.tensor([[bool(r[f"tag_{t}"]) for t in RARE_TAGS] for r in rows]),
        pose=torch.tensor([r["robot_pose"] for r in rows], dtype=torch.float32),
    )


def layout_spread(objects: torch.Tensor, encoding: SceneEncoding) -> torch.Tensor:
    """(N,) the mean xy distance (m) between the centres of each layout's present objects, NaN with
    fewer than two (``realism``'s ``pair_distance_mean``); ``objects`` (N, slots, object_width) tokens."""
    present = objects[..., 0] > 0
    xy = objects[..., encoding.xyz_cols.start : encoding.xyz_cols.start + 2] * XY_SCALE
    dist = torch.cdist(xy, xy)
    pairs = present[:, :, None] & present[:, None, :] & ~torch.eye(objects.shape[1], dtype=torch.bool)
    n = pairs.sum((1, 2))
    return torch.where(n > 0, (dist * pairs).sum((1, 2)) / n.clamp_min(1), torch.tensor(float("nan")))


def spread_edges(spread: torch.Tensor, bins: int) -> list[float]:
    """The ``bins - 1`` inner edges (m) of ``bins`` equal-count bins of the finite ``spread`` values."""
    finite = spread[torch.isfinite(spread)].double()
    if len(finite) < bins:
        raise ValueError(f"--spread-bins {bins}: only {len(finite)} layouts with two objects or more to bin")
    return [
        round(float(q), 6) for q in torch.quantile(finite, torch.arange(1, bins, dtype=torch.float64) / bins)
    ]


def spread_bin(spread: torch.Tensor, edges: list[float]) -> torch.Tensor:
    """(N,) the bin of each spread value: 0 .. len(edges) by the edges, len(edges) + 1 for NaN (fewer
    than two objects)."""
    index = torch.bucketize(spread, torch.tensor(edges, dtype=spread.dtype), right=True)
    return torch.where(torch.isnan(spread), len(edges) + 1, index)


def bin_spread(data: LayoutTensors, encoding: SceneEncoding, bins: int) -> dict | None:
    """Give ``data`` its spread bins (``bins`` equal-count bins; 0: none) and return the checkpoint's
    ``spread`` section: the bins' inner edges (m) and the layouts' count per spread value."""
    if not bins:
        return None
    values = layout_spread(data.objects, encoding)
    edges = spread_edges(values, bins)
    data.spread = spread_bin(values, edges)
    return {"edges": edges, "counts": torch.bincount(data.spread, minlength=len(edges) + 2).tolist()}


def rare_weights(tags: torch.Tensor) -> torch.Tensor:
    """Sampling weight per layout: 1 / (rate of its rarest held tag), 0 for layouts holding none."""
    rates = tags.float().mean(0).clamp_min(1.0 / max(len(tags), 1))
    inverse = torch.where(tags, 1.0 / rates, torch.zeros_like(rates))
    return inverse.max(dim=1).values


def batch_indices(
    data: LayoutTensors, size: int, rare_share: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of a training batch and a bool mask of the rows drawn by rare oversampling.

    ``rare_share`` of the batch is drawn with :func:`rare_weights`, the rest uniformly."""
    n_rare = int(round(size * rare_share))
    uniform = torch.randint(0, len(data), (size - n_rare,), generator=generator)
    weights = rare_weights(data.tags)
    if n_rare and weights.sum() > 0:
        rare = torch.multinomial(weights, n_rare, replacement=True, generator=generator)
    else:
        rare = torch.randint(0, len(data), (n_rare,), generator=generator)
    mask = torch.cat([torch.zeros(len(uniform), dtype=torch.bool), torch.ones(len(rare), dtype=torch.bool)])
    return torch.cat([uniform, rare]), mask


def full_condition(data: LayoutTensors, rows: torch.Tensor) -> ConditionBatch:
    """The full condition of layouts ``rows``: every tag required or forbidden as measured."""
    tags = torch.where(data.tags[rows], torch.tensor(REQUIRED), torch.tensor(FORBIDDEN))
    return ConditionBatch(
        task=data.task[rows].clone(),
        target=data.target[rows].clone(),
        tags=tags,
        pose=data.pose[rows].clone(),
        pose_null=torch.zeros(len(rows), dtype=torch.bool),
        spread=None if data.spread is None else data.spread[rows].clone(),
    )


def training_conditions(
    data: LayoutTensors,
    rows: torch.Tensor,
    rare: torch.Tensor,
    n_tasks: int,
    n_targets: int,
    generator: torch.Generator,
    p_null: float = 0.1,
    p_field: float = 0.1,
    p_unspecified: float = 0.5,
    p_spread_null: float = 0.5,
) -> ConditionBatch:
    """Partial conditions for a batch (see the module docstring); ``rare`` rows are never fully null."""
    c = full_condition(data, rows)
    n, n_tags = c.tags.shape

    def draw(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator)

    c.tags = torch.where(draw(n, n_tags) < p_unspecified, torch.tensor(UNSPECIFIED), c.tags)
    c.tags = torch.where(draw(n, n_tags) < p_field, torch.tensor(NULL), c.tags)
    c.task = torch.where(draw(n) < p_field, torch.tensor(n_tasks), c.task)
    c.target = torch.where(draw(n) < p_field, torch.tensor(n_targets), c.target)
    c.pose_null = draw(n) < p_field
    null = (draw(n) < p_null) & ~rare
    c.task = torch.where(null, torch.tensor(n_tasks), c.task)
    c.target = torch.where(null, torch.tensor(n_targets), c.target)
    c.tags = torch.where(null[:, None], torch.tensor(NULL), c.tags)
    c.pose_null = c.pose_null | null
    if c.spread is not None:  # -1: the null spread (ConditionBatch.cat)
        # on its own draw, also where the rest is null: the null condition with a drawn spread is what
        # draw_spread samples (nulled with the rest, the model never saw it: followed in part, measured)
        c.spread = torch.where(draw(n) < p_spread_null, -1, c.spread)
    return c


def null_rows(c: ConditionBatch, n_tasks: int, n_targets: int) -> torch.Tensor:
    """(B,) bool: the rows of ``c`` whose condition is wholly null (task, target, every tag, pose):
    what the model learns the unconditional distribution from."""
    return (c.task == n_tasks) & (c.target == n_targets) & (c.tags == NULL).all(dim=1) & c.pose_null
