"""The proposal model trained on labelled layouts and scored offline (issue 63, points 3 and 5): a
model's figure on a layout is the label of the candidate it ranks first among those labelled there
(no new simulation per model), through the simulator's masks or a retrieval head."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.experiment.proposal_data import Examples
from scenegen.policy.proposal_model import ProposalModel, train_model
from scenegen.schema.condition import RARE_TAGS


def train_on(
    data: Examples,
    steps: int = 3000,
    seed: int = 0,
    width: int = 16,
    device: str = "cpu",
    config: dict | None = None,
) -> ProposalModel:
    """A proposal model trained on ``data``; ValueError when it holds no example or no success."""
    if len(data) == 0:
        raise ValueError(
            "no labelled candidate in these layouts: run `scenegen proposals label` on them first"
        )
    if data.labels.sum() == 0:
        raise ValueError("no labelled candidate succeeded in these layouts: nothing to learn from")
    return train_model(data.crops, data.features, data.labels, steps=steps, seed=seed, width=width,
                       device=device, config=config)  # fmt: skip


def first_ranked(model: ProposalModel, data: Examples) -> dict[str, dict]:
    """Per layout (scene sha256): the candidate the model ranks first, its score and label, and the
    layout's best label (did any candidate work)."""
    scores = model.scores(data.crops, data.features)
    out: dict[str, dict] = {}
    for i, sha in enumerate(data.scene):
        best = out.get(sha)
        if best is None or scores[i] > best["score"]:
            out[sha] = {
                "score": float(scores[i]),
                "success": bool(data.labels[i]),
                "candidate": data.candidates[i],
                "any": bool(best and best["any"]) or bool(data.labels[i]),
            }
        else:
            best["any"] = best["any"] or bool(data.labels[i])
    return out


def by_tag(picks: dict[str, dict], scenes: Sequence[EnvScene]) -> dict[str, dict]:
    """First-ranked success per rare tag (and ``nominal``, ``rare`` pooled, ``all``) over the
    ``scenes`` that have picks: layouts, the success rate and the ceiling (any candidate worked)."""
    groups: dict[str, list[dict]] = {}
    for s in scenes:
        pick = picks.get(scene_sha256(s))
        if pick is None:
            continue
        tags = [t for t in RARE_TAGS if s.tags.get(t)]
        for name in [*tags, "rare" if tags else "nominal", "all"]:
            groups.setdefault(name, []).append(pick)
    return {
        name: {
            "layouts": len(rows),
            "success": float(np.mean([r["success"] for r in rows])),
            "ceiling": float(np.mean([r["any"] for r in rows])),
        }
        for name, rows in groups.items()
    }
