"""Training the denoiser: DDPM (v prediction) on reference layouts, EMA weights, resumable checkpoints.

A checkpoint directory holds:

    model.safetensors        EMA weights (what sampling uses)
    config.json              denoiser sizes, encoding, training settings, the training data's sha256,
                             the predicate version, the step reached and the loss curve
    train_state.safetensors  raw weights, optimizer moments and the random state (to resume)
    loss.png                 the loss curve

Everything is read back with safetensors and json (no pickle). Training is deterministic for a seed
on one machine, and a resumed run continues exactly where the killed one stopped (at the last
checkpoint).
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from scenegen.assets.catalog import load_catalogs
from scenegen.core.files import load_rows, sha256_file
from scenegen.diffusion.data import (
    batch_indices,
    bin_spread,
    layout_tensors,
    null_rows,
    tasks,
    training_conditions,
)
from scenegen.diffusion.encoding import ENCODING_VERSION, SceneEncoding
from scenegen.diffusion.model import Denoiser, DenoiserConfig
from scenegen.schema.condition import RARE_TAGS

CHECKPOINT_FORMAT = 1


class TrainSettings(BaseModel):
    """Settings of ``scenegen train`` (stored in the checkpoint's config.json)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    steps: int = Field(6000, ge=1)
    batch_size: int = Field(128, ge=2)
    lr: float = Field(1e-3, gt=0)
    # the last share of the steps over which the learning rate falls to 0 along a half cosine (0:
    # constant; then a run extended to more steps equals one of those steps)
    lr_decay: float = Field(0.0, ge=0, le=1)
    weight_decay: float = Field(1e-4, ge=0)
    ema_decay: float = Field(0.999, ge=0, lt=1)
    rare_share: float = Field(0.25, ge=0, le=1)  # share of each batch drawn by rare oversampling
    # the loss of a layout holding a rare tag counts 1 + tag_loss_weight times (0: plain MSE)
    tag_loss_weight: float = Field(0.0, ge=0)
    # the scene token's lighting numbers (ambient, light slots) count this many times (1: plain MSE)
    light_loss_weight: float = Field(1.0, gt=0)
    p_null: float = Field(0.1, ge=0, le=1)
    p_field: float = Field(0.1, ge=0, le=1)
    p_unspecified: float = Field(0.5, ge=0, le=1)
    # the layout's spread as a condition (diffusion/data.py): this many equal-count bins of its mean
    # pair distance (0: none), dropped to null with probability p_spread_null
    spread_bins: int = Field(0, ge=0, le=32)
    p_spread_null: float = Field(0.5, ge=0, le=1)
    train_timesteps: int = Field(1000, ge=10)
    beta_schedule: str = "squaredcos_cap_v2"
    d_model: int = Field(128, ge=8)
    layers: int = Field(4, ge=1)
    heads: int = Field(4, ge=1)
    seed: int = 0
    checkpoint_every: int = Field(500, ge=1)
    split: str = "train"  # which rows of the dataset to train on (train, heldout, all)


def ddpm_scheduler(settings: TrainSettings):
    """The training noise schedule (diffusers, pinned): DDPM, v prediction, no sample clipping."""
    from diffusers import DDPMScheduler

    return DDPMScheduler(
        num_train_timesteps=settings.train_timesteps,
        beta_schedule=settings.beta_schedule,
        clip_sample=False,
        prediction_type="v_prediction",
    )


def _flat_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    state = optimizer.state_dict()
    tensors, meta = {}, {"param_groups": state["param_groups"], "keys": {}}
    for index, entry in state["state"].items():
        meta["keys"][str(index)] = sorted(entry)
        for key, value in entry.items():
            tensors[f"optim.{index}.{key}"] = torch.as_tensor(value).detach().cpu().clone()
    return tensors, meta


def _unflat_optimizer(tensors: dict[str, torch.Tensor], meta: dict) -> dict:
    state = {
        int(index): {key: tensors[f"optim.{index}.{key}"] for key in keys}
        for index, keys in meta["keys"].items()
    }
    return {"state": state, "param_groups": meta["param_groups"]}


def _atomic(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    write(tmp)
    os.replace(tmp, path)


def save_checkpoint(out: Path, model, ema, optimizer, generator, config: dict) -> None:
    """Write the checkpoint files atomically (each renamed into place; config.json last)."""
    from safetensors.torch import save_file

    out.mkdir(parents=True, exist_ok=True)
    opt_tensors, opt_meta = _flat_optimizer(optimizer)
    state = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    state.update(opt_tensors)
    state["rng"] = generator.get_state()
    _atomic(out / "train_state.safetensors", lambda p: save_file(state, str(p)))
    _atomic(
        out / "model.safetensors",
        lambda p: save_file({k: v.detach().cpu().contiguous() for k, v in ema.state_dict().items()}, str(p)),
    )
    _atomic(out / "loss.png", lambda p: p.write_bytes(loss_curve_png(config["losses"])))
    config = {**config, "optimizer": opt_meta}
    _atomic(out / "config.json", lambda p: p.write_text(json.dumps(config, indent=1) + "\n"))


def loss_curve_png(losses: list[float], size: tuple[int, int] = (640, 360)) -> bytes:
    """A plain loss curve (log scale, moving average over 50 steps) as PNG bytes."""
    import cv2

    w, h = size
    image = np.full((h, w, 3), 255, np.uint8)
    values = np.asarray(losses, float)
    if len(values) >= 2:
        k = min(50, len(values))
        smooth = np.convolve(values, np.ones(k) / k, mode="valid")
        logs = np.log10(np.clip(smooth, 1e-6, None))
        lo, hi = logs.min(), max(logs.max(), logs.min() + 1e-3)
        xs = 50 + (w - 70) * np.arange(len(logs)) / max(len(logs) - 1, 1)
        ys = h - 40 - (h - 70) * (logs - lo) / (hi - lo)
        cv2.polylines(image, [np.stack([xs, ys], 1).astype(np.int32)], False, (180, 60, 20), 2, cv2.LINE_AA)
        for value, y in ((10**hi, 30), (10**lo, h - 40)):
            cv2.putText(image, f"{value:.3g}", (2, y + 4), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(image, (50, 30), (w - 20, h - 40), (0, 0, 0), 1)
    cv2.putText(image, f"training loss (moving average), {len(values)} steps", (60, 20), 0, 0.5, (0, 0, 0), 1)
    ok, png = cv2.imencode(".png", image)
    return png.tobytes()


def _unextendable(section: dict, key: str) -> dict:
    """A checkpoint config section without what a resumed run may change: the number of steps when
    the learning rate is constant (6,000 steps extended to 12,000 then equal 12,000 in one run; a
    decaying rate depends on the total)."""
    if key != "train" or section.get("lr_decay", 0.0):
        return section
    return {k: v for k, v in section.items() if k != "steps"}


def learning_rate(settings: TrainSettings, step: int) -> float:
    """The learning rate of (0-based) ``step``: ``lr``, falling along a half cosine to 0 over the last
    ``lr_decay`` share of the steps."""
    decay = round(settings.lr_decay * settings.steps)
    start = settings.steps - decay
    if step < start or decay == 0:
        return settings.lr
    return settings.lr * 0.5 * (1.0 + math.cos(math.pi * (step - start) / decay))


def loss_weights(data, encoding: SceneEncoding, settings: TrainSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Per layout (N,) and per scene-token column (scene_width,), the loss's weights: a layout holding
    a rare tag counts 1 + ``tag_loss_weight`` (where its condition is not wholly null: the training
    loop sets those rows to 1), the lighting columns ``light_loss_weight``."""
    rows = 1.0 + settings.tag_loss_weight * data.tags.any(dim=1).float()
    columns = torch.ones(encoding.scene_width)
    columns[encoding.light_cols] = settings.light_loss_weight
    return rows, columns


def weighted_loss(
    err_objects: torch.Tensor, err_scene: torch.Tensor, rows: torch.Tensor, columns: torch.Tensor
) -> torch.Tensor:
    """The weighted mean of the squared errors (objects (B, slots, width), scene (B, scene_width)):
    each layout's numbers weighted by ``rows`` (B,), the scene token's by ``columns`` too. With every
    weight 1 it is the plain MSE over all numbers, to the bit."""
    if bool((rows == 1).all()) and bool((columns == 1).all()):
        return torch.cat([err_objects.flatten(1), err_scene], dim=1).pow(2).mean()
    squared = err_objects.flatten(1).pow(2).sum(1) + (err_scene.pow(2) * columns).sum(1)
    count = err_objects[0].numel() + columns.sum()
    return (rows * squared).sum() / (rows.sum() * count)


def _data_predicate_version(path: Path) -> str:
    """The predicate version stamped into a layout table's metadata (the tags the model learns from)."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(path).metadata or {}
    version = meta.get(b"predicate_version")
    if version is None:
        raise ValueError(f"{path}: no predicate_version in its metadata; build it with scenegen reference")
    return version.decode()


def data_catalog(path: Path):
    """The catalog a layout table was made with: the bundled one, merged with the user catalogs its
    metadata names (``catalogs``, written by ``scenegen reference`` for a recipe with ``catalogs``);
    ValueError naming the table when those catalogs changed since."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(path).metadata or {}
    locations = json.loads(meta.get(b"catalogs", b"[]").decode())
    catalog = load_catalogs([Path(p) for p in locations])
    recorded = meta.get(b"catalog_sha256", b"").decode()
    if recorded and recorded != catalog.sha256:
        raise ValueError(
            f"{path}: made with other asset catalogs than {', '.join(locations) or 'the bundled one'} hold "
            "now; rebuild it with `scenegen reference`"
        )
    return catalog


def _resume(out: Path, config: dict, settings, model, ema, optimizer, generator) -> None:
    """Load a checkpoint directory's weights, optimizer and random state into the given objects and
    its step, losses and CPU time into ``config``; ValueError when it was trained otherwise."""
    from safetensors.torch import load_file

    saved = json.loads((out / "config.json").read_text())
    try:  # settings added since a checkpoint was made are at their defaults in it
        saved["train"] = TrainSettings(**saved["train"]).model_dump()
        saved["denoiser"] = DenoiserConfig(**saved["denoiser"]).model_dump()
    except (KeyError, TypeError, ValidationError) as exc:
        reason = str(exc).splitlines()[0]
        raise ValueError(
            f"{out}/config.json: not a checkpoint this scenegen resumes ({reason}); use a new --out"
        ) from None
    for key in ("denoiser", "encoding", "train", "data", "predicate_version", "spread"):
        if _unextendable(saved.get(key), key) != _unextendable(config[key], key):
            raise ValueError(f"{out}: checkpoint was trained with another {key}; use a new --out")
    if saved["step"] > settings.steps:
        raise ValueError(f"{out}: already trained {saved['step']} steps; --steps must be at least that")
    state = load_file(str(out / "train_state.safetensors"))
    model.load_state_dict({k[6:]: v for k, v in state.items() if k.startswith("model.")})
    ema.load_state_dict(load_file(str(out / "model.safetensors")))
    optimizer.load_state_dict(_unflat_optimizer(state, saved["optimizer"]))
    generator.set_state(state["rng"])
    config.update(step=saved["step"], losses=saved["losses"], cpu_seconds=saved["cpu_seconds"])


def _fresh_config(data_path: Path, settings, denoiser_config, encoding, catalog, rows: int, spread) -> dict:
    """A new run's config.json: settings, encoding, the data's provenance, step 0."""
    return {
        "format": CHECKPOINT_FORMAT,
        "denoiser": denoiser_config.model_dump(),
        "encoding": {
            "version": ENCODING_VERSION,
            "slots": encoding.slots,
            "assets": list(encoding.assets),
            "categories": list(catalog.categories),
        },
        "tasks": list(tasks()),
        "tags": list(RARE_TAGS),
        "train": settings.model_dump(),
        "data": {"path": str(data_path), "sha256": sha256_file(data_path), "rows": rows},
        "predicate_version": _data_predicate_version(data_path),
        "spread": spread,
        "catalog_sha256": catalog.sha256,
        "step": 0,
        "losses": [],
        "cpu_seconds": 0.0,
    }


def train(
    data_path: Path,
    out: Path,
    settings: TrainSettings,
    progress: bool = True,
    stop_after: int | None = None,
    device: str = "cpu",
) -> dict:
    """Train (or resume training) a denoiser on the layouts of ``data_path`` into checkpoint dir ``out``.

    ``stop_after``: return after this many steps of this call (tests use it to interrupt a run);
    ``device``: ``cpu`` (default), ``cuda`` or ``auto`` (scenegen/devices.py): the weights and each
    batch live there, every random draw stays on the CPU."""
    from tqdm import tqdm

    from scenegen.devices import resolve_device

    on = resolve_device(device)
    torch.manual_seed(settings.seed)
    catalog = data_catalog(data_path)
    encoding = SceneEncoding(catalog)
    data = layout_tensors(load_rows(data_path, None if settings.split == "all" else settings.split), encoding)
    spread = bin_spread(data, encoding, settings.spread_bins)
    denoiser_config = DenoiserConfig(
        object_width=encoding.object_width,
        scene_width=encoding.scene_width,
        slots=encoding.slots,
        n_tasks=len(tasks()),
        n_targets=len(catalog.categories),
        n_tags=len(RARE_TAGS),
        d_model=settings.d_model,
        layers=settings.layers,
        heads=settings.heads,
        n_spread=0 if spread is None else len(spread["counts"]),
    )
    model = Denoiser(denoiser_config).to(on)  # initialised on the CPU by the seed, then moved
    ema = copy.deepcopy(model).requires_grad_(False)
    optimizer = torch.optim.AdamW(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    generator = torch.Generator().manual_seed(settings.seed)
    config = _fresh_config(data_path, settings, denoiser_config, encoding, catalog, len(data), spread)
    if on.type != "cpu":  # a CPU run's config stays as it was before devices existed
        config["device"] = on.type
    if (out / "config.json").is_file():
        _resume(out, config, settings, model, ema, optimizer, generator)

    scheduler = ddpm_scheduler(settings)
    alphas = scheduler.alphas_cumprod
    weights, columns = loss_weights(data, encoding, settings)
    start, cpu0 = config["step"], time.process_time()
    end = settings.steps if stop_after is None else min(settings.steps, start + stop_after)
    bar = tqdm(range(start, end), initial=start, total=settings.steps, desc="train", disable=not progress)
    model.train()
    for step in bar:
        rows, rare = batch_indices(data, settings.batch_size, settings.rare_share, generator)
        c = training_conditions(
            data,
            rows,
            rare,
            denoiser_config.n_tasks,
            denoiser_config.n_targets,
            generator,
            settings.p_null,
            settings.p_field,
            settings.p_unspecified,
            settings.p_spread_null,
        )
        x_o, x_s = data.objects[rows].to(on), data.scene[rows].to(on)
        noise_o = torch.randn(x_o.shape, generator=generator).to(on)
        noise_s = torch.randn(x_s.shape, generator=generator).to(on)
        t = torch.randint(0, settings.train_timesteps, (len(rows),), generator=generator)
        a, t, c = alphas[t].to(on), t.to(on), c.to(on)
        xt_o = a.sqrt()[:, None, None] * x_o + (1 - a).sqrt()[:, None, None] * noise_o
        xt_s = a.sqrt()[:, None] * x_s + (1 - a).sqrt()[:, None] * noise_s
        v_o, v_s = model(xt_o, xt_s, t, c)  # v target: sqrt(a) noise - sqrt(1 - a) x_0
        target_o = a.sqrt()[:, None, None] * noise_o - (1 - a).sqrt()[:, None, None] * x_o
        target_s = a.sqrt()[:, None] * noise_s - (1 - a).sqrt()[:, None] * x_s
        # a wholly null row counts 1 whatever its tags: the unconditional model learns the data's rates
        row_weights = torch.where(
            null_rows(c, denoiser_config.n_tasks, denoiser_config.n_targets).cpu(), 1.0, weights[rows]
        )
        loss = weighted_loss(v_o - target_o, v_s - target_s, row_weights.to(on), columns.to(on))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(settings, step)
        optimizer.step()
        with torch.no_grad():
            for p_ema, p in zip(ema.parameters(), model.parameters(), strict=True):
                p_ema.lerp_(p, 1 - settings.ema_decay)
        config["losses"].append(round(loss.item(), 6))
        config["step"] = step + 1
        bar.set_postfix_str(f"loss={np.mean(config['losses'][-50:]):.4f}", refresh=False)
        if config["step"] % settings.checkpoint_every == 0 or config["step"] == end:
            config["cpu_seconds"] = round(config["cpu_seconds"] + time.process_time() - cpu0, 2)
            cpu0 = time.process_time()
            save_checkpoint(out, model, ema, optimizer, generator, config)
    bar.close()
    return config
