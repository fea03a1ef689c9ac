"""Transfer version 2 (issue 45; ``scenegen experiment transfer`` with ``version: 2``; docs/transfer.md):
every arm sees through its own retrieval head. Version 1 trained only the chooser, on the simulator's
masks, so more real rare data could not help it (C - A+ = -0.020 [-0.054, +0.014]).

Per arm and training seed (a **run**, ``{arm}_s{seed}``):
1. its retrieval **head**, trained on the arm's annotated scenes drawn by the arm's mixture
   (:func:`arm_mixture`; the design and steps of ``config.head``; retrieval_curves.train_head);
2. its **chooser**, trained on the arm's expert labels, each scene's input seen through that head
   (transfer.train_run with ``retrieval``);
3. its **evaluation** in closed loop through the head, on each panel of one side of the version 2
   panels (validation for the pilot and everything tuned, test for the declared run), and, with
   ``oracle_rows``, the same chooser through true masks: the panel's ceiling for that chooser.

Sources and expert labels are version 1's stages (transfer.build_sources, labels.label_scenes), for
the arms asked only. Every step is resumable: a head, a chooser and a run's episodes on one panel
are each written whole (a folder renamed into place, a file written atomically) and skipped when
there. ``metrics.json``: each arm's success on the rare panels pooled and per panel, with 95 %
hierarchical bootstrap intervals over seeds and layouts (transfer_stats), and the contrasts of
:data:`CONTRASTS` present among the arms, paired by layout.
"""

from __future__ import annotations

import contextlib
import functools
import json
import shutil
import time
from pathlib import Path

import yaml

from scenegen.env.mixture import MixtureRecipe
from scenegen.env.scenes import EnvScene
from scenegen.experiment.closed_loop import Workers
from scenegen.experiment.sequences import NOMINAL, ObservationStore, PathStore, Variant
from scenegen.experiment.transfer import (
    TransferError,
    arm_data,
    build_sources,
    claim_out,
    expert_bits,
    train_run,
    write_json,
)
from scenegen.experiment.transfer_config import TransferConfigV2, check_inputs
from scenegen.policy.labels import label_scenes, scene_sha256
from scenegen.policy.panels import panel_id
from scenegen.store.batch import atomic_write, recover_jsonl

# (first, second): first minus second, in the report's order (issue 45, point 6)
CONTRASTS = (("C", "A+"), ("D", "A+"), ("D", "C"), ("D", "E"), ("D", "B"), ("A+", "A"))
SIGHTS = ("head", "oracle")  # through the run's own head; through true masks (the ceiling)


def arm_mixture(
    arm: str, alpha: float, scenes: dict[str, list[EnvScene]], tags
) -> tuple[list, MixtureRecipe]:
    """The scenes a version 2 arm trains its head and chooser on, and the mixture it draws them by:
    version 1's (transfer.arm_data), except C, whose extra layouts are more real data, drawn scene by
    scene with A's weight (as the learning curves' rare-rich set) rather than a second term at alpha."""
    if arm == "C":
        a, extra = scenes["A"], scenes["C"]
        return a + extra, MixtureRecipe.seed_loss({"A": len(a), "C": len(extra)}, {}, 0.0)
    return arm_data(arm, alpha, scenes, tags)


def runs_v2(config: TransferConfigV2) -> list[dict]:
    """Every run: one per arm and training seed (``arm_seeds``: fewer for an arm), at the
    configured alpha."""
    return [
        {"name": f"{arm}_s{seed}", "arm": arm, "alpha": config.alpha, "seed": seed, "inputs": "rgbd"}
        for arm in config.arms
        for seed in config.seeds_of(arm)
    ]


ENDPOINT_ARMS = ("A+", "C", "D")  # the positive control's and the primary endpoint's: never cut


def evaluation_order(runs: list[dict]) -> list[dict]:
    """The runs of the endpoints' arms first (each arm's seeds in order), then the others: a run
    stopped across sessions has what the endpoints need before the secondary contrasts. Each (run,
    panel, condition) is evaluated alone, so the order changes no episode."""
    return sorted(runs, key=lambda run: run["arm"] not in ENDPOINT_ARMS)


def conditions(config: TransferConfigV2, run: dict, panel: str) -> list[tuple[str, Variant]]:
    """What ``run`` is evaluated under on ``panel``: (condition, variant) pairs, a condition being
    the sight (``head``; ``oracle``, the chooser through true masks) and, under a shift, ``@name``."""
    oracle = config.oracle_rows and (config.oracle_seeds is None or run["seed"] in config.oracle_seeds)
    sights = SIGHTS if oracle else SIGHTS[:1]
    out = [(sight, NOMINAL) for sight in sights]
    shifts = config.perturbations
    if shifts and panel != "common" and run["arm"] in config.perturbed_arms():
        if shifts.seeds is None or run["seed"] in shifts.seeds:
            for shift in shifts.shifts:
                variant = Variant(shift.name, shift.light_scale, shift.sensor)
                out += [(f"{sight}@{shift.name}", variant) for sight in sights]
    return out


def generated_kinds(arms) -> tuple[str, ...]:
    """The generated sources the arms need (B is re-weighted to D's rare share)."""
    return tuple(k for k in ("D", "E") if k in arms or (k == "D" and "B" in arms))


def train_head(run: dict, config: TransferConfigV2, data, recipe, folder: Path, frames: Path) -> Path:
    """The run's retrieval head, trained into ``folder`` (skipped when it is there): the arm's scenes
    ``data`` drawn by ``recipe``, their frames rendered into (or read from) ``frames``."""
    import torch

    from scenegen.experiment import retrieval_curves

    if (folder / "config.json").is_file():
        return folder
    partial = folder.with_name(folder.name + ".partial")  # renamed into place when whole
    shutil.rmtree(partial, ignore_errors=True)
    job = retrieval_curves.CurveJob(config.head.design, run["arm"], len(data), run["seed"])
    described = {"transfer_run": run["name"], "scenes": [scene_sha256(s) for s in data]}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the same bytes on any machine (as the curves' heads)
    try:
        retrieval_curves.train_head(job, data, partial, frames, config.head.steps(), recipe, described)
    finally:
        torch.set_num_threads(threads)
    partial.rename(folder)
    return folder


def _head_job(job: tuple) -> float:
    """One head trained in a worker (``train_head``'s arguments); its wall seconds."""
    began = time.perf_counter()
    train_head(*job)
    return time.perf_counter() - began


def train_heads(config: TransferConfigV2, runs: list[dict], data: dict, out: Path, progress: bool) -> None:
    """Every run's head not in the cache yet, ``config.workers`` at a time (each at one thread, as
    alone: the same bytes), after the frames of all their scenes are rendered once; each head's wall
    seconds appended to ``costs.jsonl`` as it lands."""
    from tqdm import tqdm

    from scenegen.perception.retrieval.frames import render_missing
    from scenegen.runner.executors import ordered_map

    cache, parts = Path(config.cache), config.parts_folder()
    pending = [r for r in runs if not (parts / "heads" / r["head"] / "config.json").is_file()]
    if not pending:
        return
    scenes = list({scene_sha256(s): s for r in pending for s in data[r["arm"]][0]}.values())
    render_missing(scenes, cache / "frames", config.workers, progress)
    jobs = [(r, config, *data[r["arm"]], parts / "heads" / r["head"], cache / "frames") for r in pending]
    walls = ordered_map(_head_job, jobs, config.workers)
    for run, wall in zip(
        pending, tqdm(walls, total=len(jobs), desc="heads", disable=not progress), strict=True
    ):
        at_once = min(config.workers, len(jobs))  # a lone head left after a resume ran alone
        _log_cost(out, {"run": run["name"], "stage": "head", "wall_s": round(wall, 1), "parallel": at_once})


def panels_v2(config: TransferConfigV2) -> dict[str, list[EnvScene]]:
    """The panels of the configured side (``panel_names``: those only), rare tags first, common last."""
    from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes

    panels = panel_scenes(load_panels_v2(config.panels), config.side)
    names = config.panel_names or tuple(panels)
    unknown = [n for n in names if n not in panels]
    if unknown:
        raise TransferError(f"panel_names: {unknown} not among the panels: {', '.join(panels)}")
    unknown = [n for n in config.panel_sizes if n not in names]
    if unknown:
        raise TransferError(f"panel_sizes: {unknown} not among the panels run: {', '.join(names)}")
    return {name: panels[name][: config.panel_sizes.get(name, config.per_panel)] for name in names}


def resolved_config(config: TransferConfigV2) -> str:
    """The configuration as its out folder's config.yaml holds it: what is run, not the workers or
    the manifest its outcome is also written to (naming one later does not make another run)."""
    return yaml.safe_dump(
        config.model_dump(mode="json", exclude={"workers", "manifest", "parts"} | config.unset_defaults()),
        sort_keys=False,
    )


def run_transfer_v2(config: TransferConfigV2, progress: bool = True, stop_after: str | None = None) -> dict:
    """Run (or continue) version 2; returns the metrics. ``stop_after``: ``sources``, ``labels``,
    ``training`` or ``evaluation:N`` (after N runs' evaluations), for tests of resume."""
    from tqdm import tqdm

    from scenegen.policy.network import PrimitivePolicy

    check_inputs(config)
    panels = panels_v2(config)  # a wrong panel name fails now, not after the training
    out, cache = Path(config.out), Path(config.cache)
    out.mkdir(parents=True, exist_ok=True)
    resolved = resolved_config(config)
    claim_out(out, resolved)
    recover_jsonl(out / "costs.jsonl")  # a line torn by a kill is cut before anything is appended
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(stage: str) -> bool:
        timings[stage] = round(timings.get(stage, 0.0) + time.perf_counter() - clock[0], 1)
        clock[0] = time.perf_counter()
        return stop_after == stage

    scenes, sources = build_sources(config, progress, generated_kinds(config.arms))
    write_json(out / "sources.json", sources)
    if lap("sources"):
        return {}
    data = {arm: arm_mixture(arm, config.alpha, scenes, config.tags) for arm in config.arms}
    every = list({scene_sha256(s): s for arm in config.arms for s in data[arm][0]}.values())
    store, reuse = config.label_store, config.reuse_labels
    physics = config.physics
    rows, _ = label_scenes(
        every, store, config.primitives, "rgbd", config.workers, progress, True, reuse, physics=physics
    )
    labels = expert_bits(rows, physics)
    if lap("labels"):
        return {}
    observations = ObservationStore(cache / "observations")
    all_runs = runs_v2(config)
    for run in all_runs:
        arm_scenes, recipe = data[run["arm"]]
        run["parts"] = f"{run['name']}-{parts_digest(run, config, arm_scenes, recipe)}"
        run["head"] = f"{run['name']}-{parts_digest(run, config, arm_scenes, recipe, head=True)}"
    train_heads(config, all_runs, data, out, progress)
    trained: dict[str, tuple] = {}
    with Workers(config.workers, config.physics) as workers:
        for run in tqdm(all_runs, desc="choosers", disable=not progress):
            head = config.parts_folder() / "heads" / run["head"]
            folder = config.parts_folder() / "policies" / run["parts"]
            with _spent(out, run, "chooser", folder):
                train_run(run, config, scenes, labels, observations, workers, folder, head, data[run["arm"]])
            trained[run["name"]] = (PrimitivePolicy.load(folder), head)
            run["head_sha256"] = weights_sha256(head)
            run["chooser_sha256"] = weights_sha256(folder)
        if lap("training"):
            return {}
        paths = PathStore(config.path_store)
        for number, run in enumerate(evaluation_order(all_runs)):
            _evaluate_run(config, run, *trained[run["name"]], panels, paths, observations, workers, out)
            if stop_after == f"evaluation:{number + 1}":
                return {}
        lap("evaluation")
    from scenegen.experiment.transfer_report_v2 import finish_v2

    metrics = metrics_v2(config, all_runs, panels, out)
    write_json(out / "metrics.json", metrics)  # no wall times here (costs.jsonl has them, and the
    # artifact's checksum covers it: the checksum differs between machines, the episodes do not)
    return metrics | finish_v2(config, metrics, out) | {"timings": timings}


@contextlib.contextmanager
def _spent(out: Path, run: dict, stage: str, folder: Path):
    """Append the wall seconds of training ``stage`` of ``run`` into ``folder`` to ``costs.jsonl``
    (nothing when the folder was there: a cached part costs nothing)."""
    cached, began = (folder / "config.json").is_file(), time.perf_counter()
    yield
    if not cached:
        _log_cost(out, {"run": run["name"], "stage": stage, "wall_s": round(time.perf_counter() - began, 1)})


def _log_cost(out: Path, row: dict) -> None:
    """Append one row to ``costs.jsonl`` (its torn last line, if a kill left one, was cut at the
    run's start)."""
    with open(out / "costs.jsonl", "a", encoding="utf-8") as log:
        log.write(json.dumps(row, sort_keys=True) + "\n")


def parts_digest(run: dict, config: TransferConfigV2, data, recipe: MixtureRecipe, head: bool = False) -> str:
    """What decides a run's head and chooser (its scenes, mixture, seed, the head's settings; for the
    chooser also alpha, the primitives and the training's settings), digested; ``head``: what decides
    the head alone. Their cache folders are named by it, so a cache shared by two configurations (a
    pilot's and the declared run's) never hands one the other's parts, and two that differ in the
    chooser's training only share their heads."""
    import hashlib

    decided = {
        "scenes": [scene_sha256(s) for s in data],
        "recipe": recipe.model_dump(mode="json"),
        "seed": run["seed"],
        "head": config.head.model_dump(mode="json"),
    }
    if not head:
        decided |= {
            "alpha": run["alpha"],
            "primitives": list(config.primitives),
            "training": config.training.model_dump(mode="json"),
        }
        if config.physics != "exact":  # its labels were simulated under another physics
            decided["physics"] = config.physics
    return hashlib.sha256(json.dumps(decided, sort_keys=True).encode()).hexdigest()[:12]


def weights_sha256(folder: Path) -> str:
    """The sha256 of a checkpoint's weight files (``*.safetensors``, by name): what a run resumed
    elsewhere must find again (config.json records measured CPU-seconds, which differ)."""
    import hashlib

    from scenegen.core.files import sha256_file

    lines = [f"{p.name} {sha256_file(p)}" for p in sorted(Path(folder).glob("*.safetensors"))]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def _evaluate_run(config, run, policy, head, panels, store, observations, workers, out: Path) -> None:
    """One run's episodes on every panel under each of its :func:`conditions`; a (panel, condition)
    whose file exists is skipped, each file written whole, and what it cost (closed_loop.Cost: CPU
    per kind of job, attempts served by the sequence store) appended to ``costs.jsonl``, which no
    figure of ``metrics.json`` reads (CPU differs between machines; the episodes do not)."""
    from scenegen.experiment.closed_loop import Cost, evaluate_policies

    grid = config.plan_grid and config.plan_grid.grid()
    for panel, scenes in panels.items():
        for condition, variant in conditions(config, run, panel):
            target = episodes_file(out, panel, run["name"], condition)
            if target.exists():
                continue
            retrieval = head if condition.startswith("head") else None
            cost, began = Cost(), time.perf_counter()
            records = evaluate_policies(
                {run["name"]: policy},
                scenes,
                store,
                observations,
                variant,
                workers,
                None,
                retrieval,
                cost,
                grid=grid,
            )
            spent = {"run": run["name"], "panel": panel, "condition": condition, "cpu": cpu_model()}
            spent |= cost.summary(len(records)) | {"wall_s": round(time.perf_counter() - began, 1)}
            tagged = [  # one policy: the records follow the scenes
                r | {"panel": panel, "sight": condition, "layout": panel_id(s)}
                for r, s in zip(records, scenes, strict=True)
            ]
            target.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(target, "".join(json.dumps(r, sort_keys=True) + "\n" for r in tagged).encode())
            _log_cost(out, spent)  # after the episodes: once per file


def _grid(records: list[dict], runs: list[str], layouts: list[str]):
    """(runs, layouts) 0/1 success; a layout is its panel id (two source tables share scene ids)."""
    import numpy as np

    index = {(r["policy"], r["layout"]): r["success"] for r in records}
    missing = [(run, i) for run in runs for i in layouts if (run, i) not in index]
    if missing:
        raise TransferError(f"no episode of {missing[0][0]} on {missing[0][1]} ({len(missing)} missing)")
    return np.array([[float(index[(run, i)]) for i in layouts] for run in runs])


@functools.cache
def cpu_model() -> str:
    """The processor's name and the vector instructions it offers of ``VECTOR_FLAGS`` (/proc/cpuinfo,
    read once per process), recorded with each evaluation's costs: parts trained and episodes
    simulated on another processor may differ in their last bits (docs/transfer.md), and a virtual
    machine's name ("Intel(R) Xeon(R) Processor") does not tell two generations apart."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        import platform

        return platform.processor() or platform.machine()
    name = next((x.split(":", 1)[1].strip() for x in lines if x.startswith("model name")), "")
    flags = set(next((x.split(":", 1)[1].split() for x in lines if x.startswith("flags")), []))
    offered = [f for f in VECTOR_FLAGS if f in flags]
    return f"{name} ({' '.join(offered)})" if offered else name


# the instruction sets whose presence changes which kernels torch and numpy run
VECTOR_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile")


def episodes_file(out: Path, panel: str, run: str, condition: str) -> Path:
    return Path(out) / "episodes" / panel / f"{run}_{condition}.jsonl"


def read_episodes(out: Path, panel: str, run: str, condition: str) -> list[dict]:
    return [json.loads(line) for line in episodes_file(out, panel, run, condition).read_text().splitlines()]


def metrics_v2(config: TransferConfigV2, all_runs: list[dict], panels: dict, out: Path) -> dict:
    """Per condition (the run's head; true masks; each under a shift, ``head@dim_light``): each
    arm's success on the rare panels pooled and on each panel, and the contrasts of
    :data:`CONTRASTS` whose arms both ran, paired by layout; 95 % hierarchical bootstrap intervals
    over seeds and layouts (``config.bootstrap`` replicates); each run's rate beside them."""
    from scenegen.experiment.transfer_stats import difference, interval, share

    result: dict = {
        "version": 2,
        "side": config.side,
        "plan_grid": config.plan_grid and config.plan_grid.model_dump(),  # None: plans as planned
        "panels": {p: [panel_id(s) for s in scenes] for p, scenes in panels.items()},
        "runs": all_runs,
    }
    evaluated: dict[str, dict[str, dict[str, list[str]]]] = {}  # condition -> panel -> arm -> runs
    for run in all_runs:
        for panel in panels:
            for condition, _ in conditions(config, run, panel):
                arms = evaluated.setdefault(condition, {}).setdefault(panel, {})
                arms.setdefault(run["arm"], []).append(run["name"])
    for condition, by_panel in evaluated.items():
        rare = [p for p in by_panel if p != "common"]
        groups = {**({"rare": rare} if rare else {}), **{p: [p] for p in by_panel}}
        grids = {}
        for group, members in groups.items():
            for arm, names in by_panel[members[0]].items():
                records = [e for p in members for n in names for e in read_episodes(out, p, n, condition)]
                ids = [panel_id(s) for p in members for s in panels[p]]
                grids[(group, arm)] = (_grid(records, names, ids), names)
        arms_in = {g: [a for a in config.arms if (g, a) in grids] for g in groups}
        result[condition] = {
            "rates": {
                g: {a: interval(grids[(g, a)][0], config.bootstrap, seed=i) for a in arms_in[g]}
                for i, g in enumerate(groups)
            },
            "contrasts": {
                g: {
                    f"{a} - {b}": difference(grids[(g, a)][0], grids[(g, b)][0], config.bootstrap, seed=i)
                    | {"seeds_second": len(grids[(g, b)][1])}  # "seeds" counts the first arm's
                    for a, b in CONTRASTS
                    if a in arms_in[g] and b in arms_in[g]
                }
                for i, g in enumerate(groups)
            },
            "share": (  # D's share of C's gain over A+ on the rare panels pooled
                share(
                    grids[("rare", "C")][0],
                    grids[("rare", "A+")][0],
                    grids[("rare", "D")][0],
                    config.bootstrap,
                    7,
                )
                if "rare" in groups and {"A+", "C", "D"} <= set(arms_in["rare"])
                else None
            ),
            "per_seed": {
                g: {
                    name: round(float(grids[(g, a)][0][k].mean()), 4)
                    for a in arms_in[g]
                    for k, name in enumerate(grids[(g, a)][1])
                }
                for g in groups
            },
        }
    return result
