"""The transfer experiment (``scenegen experiment transfer [CONFIG]``; version 1: docs/transfer_v1.md):
do generated rare-case scenes, added to a small labelled reference set, make a policy succeed more
often in closed loop on held-out rare cases?

Stages, each resumable (a killed run continues where it stopped):

1. sources (``transfer_sources``): the reference sets of A, A+ and C; D's and E's generated batches,
   one per (tag, category) cell of C, with their CPU-seconds; C's cost as rejection sampling's.
2. labels: every scene of every arm, every primitive, into the shared label store (cached by content).
3. observations: each labelled scene's policy input at its settled state (rendered once, cached).
4. training: every arm and seed at the default alpha, the alpha sweep on D, the state-observation
   ablation; one checkpoint per run, skipped when it exists.
5. evaluation (``closed_loop``): every run on the rare and the common panel, and the perturbation's
   arms on the rare panel shifted; the episodes of each (panel, variant) are written when it is done.
6. metrics with hierarchical bootstrap intervals (``transfer_stats``), the report and the plot
   (``transfer_report``), the artifact's checksum, and the manifest's transfer outcome.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from scenegen.core.files import load_rows
from scenegen.env.mixture import MixtureRecipe
from scenegen.env.scenes import EnvScene, batch_scenes, reference_scene
from scenegen.experiment.closed_loop import Workers
from scenegen.experiment.sequences import NOMINAL, ObservationStore, PathStore, Variant
from scenegen.experiment.transfer_config import TransferConfig, check_inputs
from scenegen.experiment.transfer_sources import (
    choose_reference_sets,
    generate_cells,
    rejection_sampling_cost,
)
from scenegen.manipulation.task import feasible
from scenegen.policy.labels import current, label_scenes, scene_sha256
from scenegen.policy.panels import load_panels
from scenegen.store.batch import atomic_write


class TransferError(ValueError):
    """A transfer run that cannot go on; the message names the file or key and what to do."""


def claim_out(out: Path, resolved: str) -> None:
    """Write the resolved configuration into ``out``, or refuse (TransferError) when ``out`` holds
    another configuration's run."""
    if (out / "config.yaml").exists() and (out / "config.yaml").read_text() != resolved:
        raise TransferError(
            f"{out}: holds another configuration's run (config.yaml differs); use another out or delete it"
        )
    atomic_write(out / "config.yaml", resolved.encode())


def expert_bits(rows: list[dict], physics: str = "exact") -> dict[str, dict[str, bool]]:
    """Per scene (sha256), each primitive's success from the label rows of the current rules under
    ``physics``."""
    labels: dict[str, dict[str, bool]] = {}
    for row in rows:
        if current(row, physics=physics):
            labels.setdefault(row["scene_sha256"], {})[row["primitive"]] = bool(row["success"])
    return labels


def write_json(path: Path, value) -> None:
    atomic_write(path, (json.dumps(value, indent=1, sort_keys=True) + "\n").encode())


# ------------------------------------------------------------------------------------------ sources
def build_sources(
    config: TransferConfig, progress: bool = False, generated_kinds: tuple[str, ...] = ("D", "E")
) -> tuple[dict[str, list[EnvScene]], dict]:
    """The scenes of every source (A, A+ extra, C, D, E; each scene's ``source`` is that name) and
    the sources' description (ids, cells, generation counts and CPU-seconds). ``generated_kinds``:
    the generated sources made (a run of some arms only needs theirs)."""
    every = load_rows(config.reference, None)
    train = [r for r in every if r["split"] == "train"]
    sizes = config.sizes
    sets = choose_reference_sets(train, sizes.a, sizes.a_plus, sizes.extra, config.seed, config.tags)
    cells = sets.c_cells(train)
    by_index = {r["index"]: r for r in train}
    scenes = {
        "A": [reference_scene(by_index[i], source="A") for i in sets.a],
        "A+": [reference_scene(by_index[i], source="A+") for i in sets.a_plus_extra],
        "C": [reference_scene(by_index[i], source="C") for i in sets.c_extra],
    }
    batches = config.batches or config.cache / "batches"  # the declared run commits its scenes
    generated = {kind: generate_cells(kind, cells, config, batches, progress) for kind in generated_kinds}
    for kind, per_cell in generated.items():
        scenes[kind] = [
            s for _, cell in sorted(per_cell.items()) for s in batch_scenes(Path(cell["batch"]), kind)
        ]
    cost = {
        "C": rejection_sampling_cost(config, every, cells, batches),
        **{
            kind: {"cpu_s": round(sum(c["cpu_s"] for c in per_cell.values()), 2)}
            for kind, per_cell in generated.items()
        },
    }
    description = {
        "reference": {"A": list(sets.a), "A+ extra": list(sets.a_plus_extra), "C": list(sets.c_extra)},
        "c_cells": {f"{t}/{c}": n for (t, c), n in sorted(cells.items())},
        "generated": {
            kind: {
                f"{t}/{c}": {k: v for k, v in cell.items() if k != "batch"}
                for (t, c), cell in sorted(per_cell.items())
            }
            for kind, per_cell in generated.items()
        },
        "generation_cpu_s": cost,
        "scenes": {name: len(group) for name, group in scenes.items()},
    }
    return scenes, description


# ------------------------------------------------------------------------------------------- arms
def rare(scene: EnvScene, tags) -> bool:
    return any(scene.tags.get(t) for t in tags)


def arm_data(
    arm: str, alpha: float, scenes: dict[str, list[EnvScene]], tags
) -> tuple[list[EnvScene], MixtureRecipe]:
    """The scenes an arm trains on and the mixture it draws them by (env/mixture.py)."""
    a = scenes["A"]
    if arm == "A":
        return a, MixtureRecipe.seed_loss({"A": len(a)}, {}, 0.0)
    if arm == "A+":
        return a + scenes["A+"], MixtureRecipe.seed_loss({"A": len(a), "A+": len(scenes["A+"])}, {}, 0.0)
    if arm == "B":  # A, its rare scenes up-weighted to D's effective rare share at this alpha
        if not any(rare(s, tags) for s in a):  # nothing to up-weight: B is A
            return a, MixtureRecipe.seed_loss({"A": len(a)}, {}, 0.0)
        d = scenes["D"]
        share_a, share_d = 1 / (1 + alpha), alpha / (1 + alpha)
        target = share_a * np.mean([rare(s, tags) for s in a]) + share_d * np.mean([rare(s, tags) for s in d])
        return a, MixtureRecipe.rebalanced("A", tuple(tags), float(min(target, 0.99)))
    extra = scenes[arm]
    return a + extra, MixtureRecipe.seed_loss({"A": len(a)}, {arm: len(extra)}, alpha)


def runs(config: TransferConfig) -> list[dict]:
    """Every training run: arm, alpha, seed, inputs and its name."""
    out = []

    def add(arm, alpha, seed, inputs="rgbd"):
        name = f"{arm}_a{alpha:g}_s{seed}" + ("_state" if inputs == "state" else "")
        if name not in {r["name"] for r in out}:
            out.append({"name": name, "arm": arm, "alpha": alpha, "seed": seed, "inputs": inputs})

    for arm in ("A", "A+", "B", "C", "D", "E"):
        for seed in config.training.seeds:
            add(arm, config.alpha, seed)
    for alpha in config.alpha_sweep:
        add("D", alpha, config.training.seeds[0])
    for arm in config.state_ablation:
        for seed in config.training.seeds:
            add(arm, config.alpha, seed, "state")
    return out


# ------------------------------------------------------------------------------------- observations
def settled_inputs(
    scenes: list[EnvScene],
    inputs: str,
    observations: ObservationStore,
    workers: Workers,
    retrieval: Path | None = None,
) -> np.ndarray:
    """Each scene's policy input at its settled state (rendered where the store lacks it), its mask
    the ``retrieval`` head's prediction (None: the oracle's)."""
    from scenegen.experiment.sequences import sight

    seen = sight(retrieval, NOMINAL)
    keys = [ObservationStore.key(scene_sha256(s), (), NOMINAL, inputs, seen) for s in scenes]
    extra = () if retrieval is None else (retrieval,)
    jobs = [
        ("observe", s, (None, NOMINAL, inputs, k, *extra))
        for s, k in zip(scenes, keys, strict=True)
        if observations.get(k) is None
    ]
    for _, (key, value, meta), _ in workers.map(jobs):
        observations.put(key, value, meta)
    return np.stack([observations.get(k) for k in keys])


def train_run(
    run: dict,
    config: TransferConfig,
    scenes,
    labels,
    observations,
    workers,
    folder: Path,
    retrieval: Path | None = None,
    arm=None,
) -> Path:
    """Train one run's policy into ``folder`` (skipped when its checkpoint is there), on inputs seen
    through ``retrieval`` (None: the oracle's masks); ``arm``: the (scenes, mixture) it trains on
    (default :func:`arm_data`'s)."""
    from scenegen.policy.train import Examples, train_policy

    if (folder / "config.json").exists() and (folder / "model.safetensors").exists():
        return folder
    data, recipe = arm or arm_data(run["arm"], run["alpha"], scenes, config.tags)
    data = [s for s in data if scene_sha256(s) in labels]
    primitives = list(config.primitives)
    bits = [labels[scene_sha256(s)] for s in data]
    examples = Examples(
        x=settled_inputs(data, run["inputs"], observations, workers, retrieval),
        y=np.array([[b.get(p, False) for p in primitives] for b in bits], dtype=np.float32),
        known=np.array([[p in b for p in primitives] for b in bits]),
        scenes=data,
        primitives=primitives,
        inputs=run["inputs"],
    )
    training = config.training
    partial = folder.with_name(folder.name + ".partial")  # renamed into place when whole
    shutil.rmtree(partial, ignore_errors=True)
    train_policy(
        examples,
        partial,
        training.steps,
        training.batch_size,
        run["alpha"],
        run["seed"],
        training.lr,
        recipe,
        data={"arm": run["arm"], "recipe": recipe.model_dump(mode="json")},
    )
    partial.rename(folder)
    return folder


# --------------------------------------------------------------------------------------- evaluation
def panel_scenes(config: TransferConfig) -> dict[str, list[EnvScene]]:
    """The rare panel (unique layouts over the configured tags, ``rare_per_tag`` each) and the common
    panel, as committed in ``config.panels``."""
    panels = load_panels(config.panels)
    heldout = {r["index"]: r for r in load_rows(config.reference, "heldout")}
    chosen: list[int] = []
    for tag in config.tags:
        ids = panels["rare"][tag][: config.rare_per_tag] if config.rare_per_tag else panels["rare"][tag]
        chosen += [i for i in ids if i not in chosen]
    common = panels["common"][: config.common] if config.common else panels["common"]
    out = {
        "rare": [reference_scene(heldout[i]) for i in sorted(chosen)],
        "common": [reference_scene(heldout[i]) for i in common],
    }
    return {name: [s for s in group if feasible(s)] for name, group in out.items()}


def evaluations(config: TransferConfig, all_runs: list[dict]) -> list[tuple[str, Variant, list[str]]]:
    """(panel, variant, run names) of every evaluation."""
    names = [r["name"] for r in all_runs]
    out = [("rare", NOMINAL, names), ("common", NOMINAL, names)]
    if config.perturbation is not None:
        p = config.perturbation
        shifted = [
            r["name"]
            for r in all_runs
            if r["arm"] in p.arms and r["alpha"] == config.alpha and r["inputs"] == "rgbd"
        ]
        out.append(("rare", Variant(p.name, p.light_scale), shifted))
    return out


# ------------------------------------------------------------------------------------------- the run
def run_transfer(config: TransferConfig, progress: bool = True, stop_after: str | None = None) -> dict:
    """Run (or continue) the experiment; returns the metrics. ``stop_after``: a stage name to stop
    after (sources, labels, training, or ``evaluation:N`` after N evaluations), for tests of resume."""
    from tqdm import tqdm

    from scenegen.experiment.transfer_report import finish
    from scenegen.policy.network import PrimitivePolicy

    check_inputs(config)  # a configuration naming missing files fails before anything is written
    out, cache = Path(config.out), Path(config.cache)
    out.mkdir(parents=True, exist_ok=True)
    # what decides the results (the worker count does not: the run's outputs do not depend on it)
    # (nor do an unset retrieval head or batches folder: a version 1 configuration resolves as it did)
    ignored = {"workers"} | {k for k in ("retrieval", "batches") if getattr(config, k) is None}
    ignored |= config.unset_defaults()
    resolved = yaml.safe_dump(config.model_dump(mode="json", exclude=ignored), sort_keys=False)
    claim_out(out, resolved)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage):
        nonlocal clock
        timings[stage] = round(time.perf_counter() - clock, 1)
        clock = time.perf_counter()
        return stop_after == stage

    scenes, sources = build_sources(config, progress)
    write_json(out / "sources.json", sources)
    if lap("sources"):
        return {}
    every = [s for name in ("A", "C", "D", "E", "A+") for s in scenes[name]]  # most informative first
    rows, _ = label_scenes(
        every,
        config.label_store,
        config.primitives,
        "rgbd",
        config.workers,
        progress,
        True,
        config.reuse_labels,
        physics=config.physics,
    )

    labels = expert_bits(rows, config.physics)
    if lap("labels"):
        return {}
    observations = ObservationStore(cache / "observations")
    all_runs = runs(config)
    policies = {}
    with Workers(config.workers, config.physics) as workers:
        for run in tqdm(all_runs, desc="training", disable=not progress):
            folder = train_run(
                run, config, scenes, labels, observations, workers, cache / "policies" / run["name"]
            )
            policies[run["name"]] = policy = PrimitivePolicy.load(folder)
            run["recipe"] = policy.trained_on["data"]["recipe"]  # the mixture it drew its batches by
            run["effective_shares"] = policy.trained_on["effective_shares"]
        if lap("training"):
            return {}
        panels = panel_scenes(config)
        store = PathStore(config.path_store)
        (out / "episodes").mkdir(exist_ok=True)
        for number, (panel, variant, names) in enumerate(evaluations(config, all_runs)):
            target = out / "episodes" / f"{panel}_{variant.name}.jsonl"
            if not target.exists():
                chosen = {name: policies[name] for name in names}
                records = _evaluate(
                    chosen, panels[panel], store, observations, variant, workers, progress, config.retrieval
                )
                lines = "".join(
                    json.dumps(r | {"panel": panel, "variant": variant.name}, sort_keys=True) + "\n"
                    for r in records
                )
                atomic_write(target, lines.encode())
            if stop_after == f"evaluation:{number + 1}":
                return {}
        lap("evaluation")
    log = cache / "timings.jsonl"  # wall seconds per stage of every invocation, for the report's cost
    with open(log, "a") as sink:
        sink.write(json.dumps({"config": config.name, "workers": config.workers, "seconds": timings}) + "\n")
    return finish(config, all_runs, panels, sources, timings, len(store.entries))


def _evaluate(
    policies, scenes, store, observations, variant, workers, progress, retrieval=None
) -> list[dict]:
    from tqdm import tqdm

    from scenegen.experiment.closed_loop import evaluate_policies

    bar = tqdm(desc=f"evaluation ({variant.name})", unit=" runs", disable=not progress)
    try:
        return evaluate_policies(
            policies, scenes, store, observations, variant, workers, lambda _: bar.update(), retrieval
        )
    finally:
        bar.close()
