"""The proposal model's learning curves (issue 63, point 5): for each training-set size and seed, a
model trained on the natural-rate set and one on the rare-rich set of that size (the retrieval
curves' sets, ``retrieval_curves.training_sets``), each scored offline on the curve set's rare
layouts (on no panel) by the label of the candidate it ranks first (no new simulation per model).

Two sights at scoring, one model: ``oracle`` (the crops' mask channel is the simulator's: the action
side alone) and ``head`` (the default retrieval head's mask, as a decision sees it). The candidates
ranked are the labelled ones in both, drawn on the simulator's masks (the labels' decision point):
through the head, what changes is what the model sees around them, not where they lie. The models
train through the oracle, as the labels were made.

Records have the retrieval curves' shape (``job``: ``sight/set_n_seed``), so their statistics,
tables and plot (``curve_results``, ``leads``, ``curve_table``, ``plot_curves``) serve here with
``value="success"``. Resumable: a model whose scores exist is not trained again.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.experiment.proposal_data import examples
from scenegen.experiment.proposal_labels import label_layouts, open_labels, proposed_at
from scenegen.experiment.proposal_offline import first_ranked, train_on
from scenegen.experiment.retrieval_curves import SEEDS, SETS
from scenegen.schema.condition import RARE_TAGS
from scenegen.store.batch import atomic_write

SIZES = (100, 300, 600)  # issue 63's: 600 is the largest the label budget covers
SIGHTS = ("oracle", "head")
STEPS = 3000  # the proposal model's training steps (proposals train's default)
STYLES = {  # (sight, set) -> BGR colour for plot_curves
    ("oracle", "natural"): (200, 120, 40),
    ("oracle", "rare_rich"): (40, 40, 200),
    ("head", "natural"): (230, 190, 150),
    ("head", "rare_rich"): (150, 150, 240),
}


@dataclass(frozen=True)
class ProposalJob:
    set_name: str  # natural | rare_rich
    n: int
    seed: int

    @property
    def name(self) -> str:
        return f"{self.set_name}_{self.n}_{self.seed}"


def proposal_jobs(sizes: Sequence[int] = SIZES, seeds: Sequence[int] = SEEDS) -> list[ProposalJob]:
    """Largest first: the figure issue 63 asks first (N = 600) lands first."""
    return [ProposalJob(s, n, seed) for n in sorted(sizes, reverse=True) for seed in seeds for s in SETS]


def training(set_name: str, n: int) -> list[EnvScene]:
    """The feasible layouts of a training set (those the labels cover)."""
    return label_layouts([f"{set_name}:{n}"])[f"{set_name}:{n}"]


def scoring() -> list[EnvScene]:
    """The curve set (rare layouts on no panel; feasible ones only)."""
    return label_layouts(["curve"])["curve"]


def _labelled(data, scenes: Sequence[EnvScene], what: str, views, config) -> None:
    """ValueError unless every layout of ``scenes`` has labels (a model trained or scored on part of
    its set would be another curve), or was proposed nothing: its first decision does not see the
    target (``views`` holds its empty proposal), so there is nothing to label."""
    missing = {scene_sha256(s) for s in scenes} - set(data.scene)
    unseen = {sha for sha in missing if proposed_at(views, sha, (), config.inputs(config.sampler)) == []}
    if missing - unseen:
        raise ValueError(
            f"{len(missing - unseen)} of the {len(scenes)} layouts of {what} have no labels: run `scenegen "
            "proposals label` to the end first (it resumes)"
        )


def prepare(labels: Path, head: Path | None, sizes: Sequence[int] = SIZES, workers: int = 1, progress=None):
    """Render every crop the jobs will read (the training sets through the oracle, the curve set
    through each sight) into the labels' cache with ``workers`` processes; ValueError where a layout
    lacks labels."""
    config, store, views = open_labels(labels)
    crops = Path(labels) / "crops"
    train = {scene_sha256(s): s for n in sizes for name in SETS for s in training(name, n)}
    curve = scoring()
    groups = [(list(train.values()), None, "the training sets"), (curve, None, "the curve set")]
    groups.append((curve, head, "the curve set"))
    for scenes, retrieval, what in groups:
        data = examples(scenes, store, views, crops, config, retrieval, workers, progress)
        _labelled(data, scenes, what, views, config)


def _rows(picks: dict[str, dict], scenes: Sequence[EnvScene], scored: str) -> list[dict]:
    """One row per scored layout, in ``scenes``' order: its first-ranked label; a failure where
    nothing was picked (the first decision did not see the target: no candidate to act on), so every
    policy is scored over the same layouts."""
    rows = []
    for s in scenes:
        pick = picks.get(scene_sha256(s), {"success": False, "any": False})
        tags = [t for t in RARE_TAGS if s.tags.get(t)]
        rows.append({"set": scored, "layout": scene_sha256(s), "tags": tags,
                     "success": bool(pick["success"]), "any": bool(pick["any"])})  # fmt: skip
    return rows


def run_job(
    job: ProposalJob,
    folder: Path,
    labels: Path,
    head: Path | None,
    scored: Sequence[EnvScene] | None = None,
    train: Sequence[EnvScene] | None = None,
    steps: int = STEPS,
    workers: int = 1,
) -> list[dict]:
    """Train ``job``'s model on its training set's labels (under ``labels``) and score it on
    ``scored`` (default the curve set) through each sight (``head``: the retrieval head's folder);
    skipped where its scores exist. One record per sight. ``train``: the training layouts (default
    the job's set)."""
    import torch

    torch.set_num_threads(1)  # CPU seconds are the budget; the same bytes on any machine
    out = Path(folder) / job.name
    done = out / "scores.json"
    if not done.exists():
        config, store, views = open_labels(labels)
        crops = Path(labels) / "crops"
        began = time.process_time()
        train = train if train is not None else training(job.set_name, job.n)
        data = examples(train, store, views, crops, config, workers=workers)
        _labelled(data, train, f"{job.name}'s training set", views, config)
        model = train_on(data, steps, job.seed, config={"job": job.name, "steps": steps})
        cpu = time.process_time() - began
        model.save(out / "model")
        scored = scored if scored is not None else scoring()
        per_sight = {}
        for sight, retrieval in zip(SIGHTS, (None, head), strict=True):
            seen = examples(scored, store, views, crops, config, retrieval=retrieval, workers=workers)
            _labelled(seen, scored, "the scored set", views, config)
            per_sight[sight] = _rows(first_ranked(model, seen), scored, "curve")
        record = {"training_cpu_s": round(cpu, 1), "candidates": len(data), "rows": per_sight}
        atomic_write(done, json.dumps(record) + "\n")
    record = json.loads(done.read_text())
    return [
        {"job": f"{sight}/{job.name}", "training_cpu_s": record["training_cpu_s"], "rows": rows}
        for sight, rows in record["rows"].items()
    ]


def chooser_rows(
    folder: Path, head: Path | None, scored: Sequence[EnvScene] | None = None, workers: int = 1
) -> dict[str, list[dict]]:
    """The hand chooser's (``assets/policy/baseline``) first-attempt success on ``scored`` (default
    the curve set), through each sight, as the models' rows: the baseline beside the curves. Its
    attempts are kept under ``folder`` (a sequence store; a rerun simulates nothing)."""
    from scenegen.experiment.closed_loop import Workers, evaluate_policies
    from scenegen.experiment.sequences import ObservationStore, PathStore
    from scenegen.paths import ASSETS_DIR
    from scenegen.policy.network import PrimitivePolicy

    scored = scored if scored is not None else scoring()
    folder = Path(folder)
    store, observations = PathStore(folder / "paths.jsonl"), ObservationStore(folder / "observations")
    policies = {"chooser": PrimitivePolicy.load(ASSETS_DIR / "policy" / "baseline")}
    out = {}
    with Workers(workers) as pool:
        for sight, retrieval in zip(SIGHTS, (None, head), strict=True):
            records = evaluate_policies(policies, scored, store, observations, workers=pool,
                                        retrieval=retrieval, attempts=1, experts=False)  # fmt: skip
            picks = {r["scene_sha256"]: {"success": r["success"], "any": r["success"]} for r in records}
            out[sight] = _rows(picks, scored, "curve")
    return out


def chooser_results(rows: dict[str, list[dict]], replicates: int = 2000) -> dict:
    """Per sight and tag (``all`` and each rare tag held): the chooser's first-attempt success with
    its 95 % bootstrap interval over layouts."""
    from scenegen.experiment.transfer_stats import interval

    out: dict = {}
    for sight, sight_rows in rows.items():
        tags = ["all", *sorted({t for r in sight_rows for t in r["tags"]})]
        for tag in tags:
            keep = [float(r["success"]) for r in sight_rows if tag == "all" or tag in r["tags"]]
            out.setdefault(sight, {})[tag] = interval(np.array([keep]), replicates, seed=len(keep))
    return out
