"""The transfer experiment's labelled sources: which reference layouts each arm trains on, the
generated rare scenes of arms D and E, and their expert labels (one label store, cached by content).

Reference sets (all from the training split, never a panel layout, never ``on_floor``): the feasible
training layouts in one seeded shuffle are a natural-rate sample; **A** is its first ``a`` layouts,
**A+**'s extra its next ``a_plus - a``. **C**'s extra is "more real rare data": for every panel tag in
turn, the next layouts of that shuffle holding the tag and not yet chosen, ``c`` in all, shared as
evenly as the tags allow (the rare panel is balanced per tag too). C's (tag, target category)
histogram is the request list of D (the diffusion generator) and E (the hand-targeted proposer): one
batch per cell, asking for that many scenes of "retrieve the CATEGORY TAG".
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.policy.panels import PANEL_TAGS
from scenegen.store.batch import atomic_write


@dataclass(frozen=True)
class ReferenceSets:
    """Row ``index`` values of the reference layouts of each set, and the tag each C layout was
    chosen for (its cell is ``(tag, target category)``)."""

    a: tuple[int, ...]
    a_plus_extra: tuple[int, ...]
    c_extra: tuple[int, ...]
    c_tags: tuple[str, ...]

    def c_cells(self, rows: Sequence[dict]) -> Counter:
        """C's histogram: scenes per (tag, target category)."""
        category = {r["index"]: r["target_category"] for r in rows}
        return Counter((tag, category[i]) for i, tag in zip(self.c_extra, self.c_tags, strict=True))


def shares(total: int, parts: int) -> list[int]:
    """``total`` split into ``parts`` integers as evenly as possible, larger ones first."""
    return [total // parts + (k < total % parts) for k in range(parts)]


def choose_reference_sets(
    train_rows: Sequence[dict], a: int, a_plus: int, c: int, seed: int, tags: Sequence[str] = PANEL_TAGS
) -> ReferenceSets:
    """The reference sets of the arms from the training split's rows (see the module docstring)."""
    rows = [r for r in train_rows if r["split"] == "train" and not r["tag_on_floor"]]
    order = [rows[i] for i in np.random.default_rng(seed).permutation(len(rows))]
    if a_plus < a or len(order) < a_plus:
        raise ValueError(f"a={a}, a_plus={a_plus}: need a <= a_plus <= {len(order)} feasible layouts")
    taken = {r["index"] for r in order[:a_plus]}
    c_extra, c_tags = [], []
    for tag, n in zip(tags, shares(c, len(tags)), strict=True):
        holding = [r["index"] for r in order if r[f"tag_{tag}"] and r["index"] not in taken][:n]
        if len(holding) < n:
            raise ValueError(f"c={c}: only {len(holding)} more training layouts hold {tag}; need {n}")
        taken.update(holding)
        c_extra += holding
        c_tags += [tag] * n
    return ReferenceSets(
        a=tuple(r["index"] for r in order[:a]),
        a_plus_extra=tuple(r["index"] for r in order[a:a_plus]),
        c_extra=tuple(c_extra),
        c_tags=tuple(c_tags),
    )


def cpu_seconds() -> float:
    """CPU-seconds of this process and its reaped children (a batch's worker pool)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def generate_cells(
    kind: str, cells: Counter, config, folder: Path, progress: bool = False
) -> dict[tuple[str, str], dict]:
    """D's or E's scenes: per (tag, category) cell of C a batch of that many scenes asking for
    "retrieve the CATEGORY TAG" from the reference recipe, proposed by the diffusion generator (``D``,
    the settings of ``config.generation.diffusion``) or the hand-targeted proposer (``E``); no images.
    Returns per cell its batch folder, accepted count, proposals and CPU-seconds. A cell that holds
    its record (``cell.json``) is not run again; a killed cell's batch resumes."""
    import yaml

    from scenegen.runner.config import load_pipeline
    from scenegen.runner.pipeline import run_batch

    generation = config.generation
    proposer: str | dict = "targeted"
    if kind == "D":
        proposer = yaml.safe_load(Path(generation.diffusion).read_text())["proposer"]
    out = {}
    for number, ((tag, category), n) in enumerate(sorted(cells.items())):
        batch = folder / kind / f"{tag}_{category}"
        record = batch.parent / f"{batch.name}.cell.json"
        if record.exists():
            out[(tag, category)] = json.loads(record.read_text())
            continue
        overrides = {
            "n": n,
            "seed": config.seed * 1000 + number,
            "max_proposals": n * generation.max_proposals,
            "render": False,
            "name": f"transfer_{kind}_{tag}_{category}",
        }
        if isinstance(proposer, dict):
            overrides["proposer"] = proposer
        pipeline = load_pipeline(
            generation.recipe,
            overrides,
            f"retrieve the {category} {tag}",
            None if isinstance(proposer, dict) else proposer,
        )
        start = cpu_seconds()
        summary = run_batch(pipeline, batch, workers=config.workers, progress=progress)
        cell = {
            "batch": str(batch),
            "requested": n,
            "accepted": summary.accepted,
            "proposals": summary.proposals,
            "cpu_s": round(cpu_seconds() - start, 2),
        }
        atomic_write(record, json.dumps(cell, indent=1).encode())
        out[(tag, category)] = cell
    return out


def rejection_sampling_cost(config, rows: Sequence[dict], cells: Counter, folder: Path) -> dict:
    """C's generation cost, as rejection sampling of the reference process pays it: CPU-s per accepted
    layout of the reference recipe (measured now on ``calibration_proposals`` proposals, no images)
    divided by the rate of the cell's tag among reference layouts of the cell's target category, summed
    over C's cells."""
    from scenegen.runner.config import load_pipeline
    from scenegen.runner.pipeline import run_batch

    record = folder / "calibration.json"
    if record.exists():
        calibration = json.loads(record.read_text())
    else:
        n = config.generation.calibration_proposals
        pipeline = load_pipeline(
            config.generation.recipe, {"n": n, "max_proposals": n, "render": False, "seed": config.seed}
        )
        start = cpu_seconds()
        summary = run_batch(pipeline, folder / "calibration", workers=1, progress=False)
        calibration = {
            "proposals": summary.proposals,
            "accepted": summary.accepted,
            "cpu_s": round(cpu_seconds() - start, 2),
        }
        atomic_write(record, json.dumps(calibration, indent=1).encode())
    per_layout = calibration["cpu_s"] / max(calibration["accepted"], 1)
    total, per_cell = 0.0, {}
    for (tag, category), n in sorted(cells.items()):
        same = [r for r in rows if r["target_category"] == category]
        rate = sum(r[f"tag_{tag}"] for r in same) / max(len(same), 1)
        per_cell[f"{tag}/{category}"] = round(n * per_layout / rate, 2) if rate else None
        total += n * per_layout / rate if rate else math.inf
    return {
        "calibration": calibration,
        "cpu_s_per_layout": round(per_layout, 4),
        "cells": per_cell,
        "cpu_s": round(total, 2),
    }
