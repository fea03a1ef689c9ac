"""The learned verifier's data and training (issue 46, point 3): every try the generator makes on the
request suite's tuning half and on the bundled recipes' own requests, labelled by what the checks,
settling and predicates said (scenegen/diffusion/verifier.py), then a verifier fitted to them.

Never the held-out half: :func:`requests_for` refuses it. Tries are collected per request into
``OUT/tries/NNN.npz`` (written whole, atomically: a killed collection resumes at the first request
without its file), each with the request, the tries' tokens and labels and the CPU-s they took;
:func:`train` reads them all and writes the verifier (``OUT/verifier``: model.safetensors,
config.json with the data's size, the CPU-s of collecting and training, and the generator's sha256).
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from scenegen.core.files import sha256_file
from scenegen.experiment.request_suite import Request, suite
from scenegen.runner.config import ConfigError, load_pipeline
from scenegen.store.batch import atomic_write

ARRAYS = ("x0", "target", "tags", "pose", "values", "known")
VALIDATION_EVERY = 5  # every fifth job's tries are held out of training, to measure the verifier


def requests_for(rows, half: str, count: int) -> list[Request]:
    """The suite's ``half``, which must be the tuning half: the verifier never sees held-out requests."""
    if not half.startswith("tuning"):
        raise ValueError(f"half {half!r}: the verifier trains on the tuning half only (held-out: reporting)")
    return suite(rows, half, count)


def jobs(recipe: Path, requests: Sequence[Request], bundled: Sequence[Path]) -> list[tuple[Path, dict]]:
    """(recipe, condition overrides) per collection job: each request under ``recipe``, then each
    bundled recipe with its own request."""
    asked = [{"condition": r.condition().model_dump(mode="json", exclude={"text"})} for r in requests]
    return [(Path(recipe), o) for o in asked] + [(Path(p), {}) for p in bundled]


def collect(job: tuple[Path, dict], tries: int, scenes: int, seed: int = 0) -> dict[str, np.ndarray] | None:
    """Every try of one job (``tries`` at most, until ``scenes`` are accepted), encoded and labelled;
    None when the recipe refuses the request."""
    from scenegen.diffusion.verifier import try_labels
    from scenegen.experiment.transfer_sources import cpu_seconds
    from scenegen.runner.pipeline import make_proposer
    from scenegen.runner.tries import labelled_tries

    recipe, overrides = job
    try:
        caps = {"n": scenes, "seed": seed, "max_tries": tries, "max_proposals": tries, "render": False}
        config = load_pipeline(recipe, {**overrides, **caps})
    except ConfigError:
        return None
    proposer = make_proposer(config, config.catalog())
    columns: dict[str, list] = {k: [] for k in ARRAYS}
    start = cpu_seconds()
    for proposal, outcome in labelled_tries(config):
        try:
            tokens, scene, _ = proposer.encoding.encode_proposal(proposal)
        except ValueError:
            continue
        c = proposer.condition_batch(proposal.condition)
        values, known = try_labels(
            proposal.condition,
            outcome.record.tags if outcome.record is not None else None,
            outcome.rejection,
        )
        columns["x0"].append(np.concatenate([tokens.reshape(-1), scene]).astype(np.float32))
        columns["target"].append(int(c.target[0]))
        columns["tags"].append(c.tags[0].numpy())
        columns["pose"].append(c.pose[0].numpy())
        columns["values"].append(values)
        columns["known"].append(known)
    data = {k: np.asarray(v) for k, v in columns.items()}
    data["cpu_s"] = np.asarray(cpu_seconds() - start)
    return data


def collect_all(out: Path, job_list: Sequence[tuple[Path, dict]], tries: int, scenes: int, log=print) -> None:
    """Each job's tries into ``out/tries/NNN.npz``; jobs with a file already are skipped (resume)."""
    folder = Path(out) / "tries"
    folder.mkdir(parents=True, exist_ok=True)
    for number, job in enumerate(job_list):
        target = folder / f"{number:03d}.npz"
        if target.exists():
            continue
        data = collect(job, tries, scenes)
        if data is None:
            data = {"refused": np.asarray(True), "cpu_s": np.asarray(0.0)}
        buffer = io.BytesIO()
        np.savez(buffer, job=np.asarray(json.dumps([str(job[0]), job[1]], sort_keys=True)), **data)
        atomic_write(target, buffer.getvalue())
        asked = json.dumps(job[1].get("condition", {}).get("tags", {}))
        shown = f"{len(data.get('x0', []))} tries, {float(data['cpu_s']):.1f} CPU-s"
        log(f"[{number + 1}/{len(job_list)}] {job[0].name} {asked}: {shown}")


def load_tries(out: Path) -> tuple[dict[str, np.ndarray], float]:
    """Every collected try (the arrays concatenated, ``job``: its job's number) and the CPU-s their
    collection took."""
    parts, cpu = {k: [] for k in (*ARRAYS, "job")}, 0.0
    for number, path in enumerate(sorted((Path(out) / "tries").glob("*.npz"))):
        with np.load(path) as z:
            cpu += float(z["cpu_s"])
            if "x0" in z and len(z["x0"]):
                for k in ARRAYS:
                    parts[k].append(z[k])
                parts["job"].append(np.full(len(z["x0"]), number))
    if not parts["x0"]:
        raise ValueError(f"{out}/tries: no tries collected; run the collection first")
    return {k: np.concatenate(v) for k, v in parts.items()}, cpu


def train(out: Path, recipe: Path, steps: int = 3000, seed: int = 0) -> dict:
    """Fit the verifier to the collected tries (every fifth job's held out) and write it to
    ``out/verifier``; returns its summary (examples, accuracy on the held-out jobs' tries at a few
    noise levels against their base rates, CPU-s of collecting and training, sha256)."""
    import torch

    from scenegen.diffusion.sample import scheduler_for
    from scenegen.diffusion.verifier import VerifierConfig, accuracy, save_verifier, train_verifier
    from scenegen.experiment.transfer_sources import cpu_seconds
    from scenegen.propose.diffusion import load_generator

    torch.set_num_threads(1)
    config = load_pipeline(recipe, {"n": 1})
    model, generator = load_generator(config.proposer)
    data, collect_cpu = load_tries(out)
    held = data.pop("job") % VALIDATION_EVERY == VALIDATION_EVERY - 1  # every fifth job: validation
    fit = {k: v[~held] for k, v in data.items()}
    check = {k: v[held] for k, v in data.items()}
    alphas = scheduler_for(generator["train"], 20).alphas_cumprod
    cfg = model.config
    verifier_config = VerifierConfig(
        width=cfg.slots * cfg.object_width + cfg.scene_width,
        n_targets=cfg.n_targets,
        n_tags=cfg.n_tags,
        pose_dim=cfg.pose_dim,
        train_timesteps=generator["train"]["train_timesteps"],
    )
    start = cpu_seconds()
    verifier, losses = train_verifier(fit, verifier_config, alphas, steps=steps, seed=seed)
    train_cpu = cpu_seconds() - start
    levels = {str(t): accuracy(verifier, check, alphas, t) for t in (0, 250, 500, 750)} if held.any() else {}
    summary = {
        "examples": len(fit["x0"]),
        "validation_examples": int(held.sum()),
        "accepted": int(fit["values"][:, 0].sum()),
        "collect_cpu_s": round(collect_cpu, 1),
        "train_cpu_s": round(train_cpu, 1),
        "steps": steps,
        "seed": seed,
        "losses": losses,
        "validation_accuracy_at_t": levels,
        "generator": str(config.proposer.checkpoint),
        "generator_sha256": sha256_file(config.proposer.checkpoint_dir() / "model.safetensors"),
    }
    summary["sha256"] = save_verifier(verifier, Path(out) / "verifier", {"training": summary})
    return summary
