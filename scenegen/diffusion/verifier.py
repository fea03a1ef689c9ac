"""A learned verifier: the chance that a proposal is accepted (and that each rare tag holds on it),
predicted from the noisy scene tokens x_t, the timestep t and the request, so that its gradient can
steer sampling where no hand-written cost says what fails (classifier guidance: Dhariwal & Nichol,
2021; universal guidance: Bansal et al., 2023).

Data: every try of batches the generator made (runner/tries.py), each encoded as the generator's
tokens (``encoding.encode_proposal``) with its labels (:func:`try_labels`): ``accepted`` for every
try; a rare tag's ``holds`` where the try was measured (an accepted scene: every tag; a rejection for
the request's tags: the tags it names, and the required ones it does not). Training noises each
example to a random timestep of the generator's own schedule and fits every known label (binary
cross-entropy, masked where unknown).

Guidance (diffusion/sample.py): with a_t the cumulative alpha, the clean-scene estimate moves up
the gradient of log p(accepted | x_t, t, c) taken through x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps,
that is by ``weight * sqrt(a_t) * grad_{x_t} log p``: early, noisy steps barely move, as the
verifier can tell little there. Weights ship as safetensors with a config.json, pinned by sha256.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from scenegen.diffusion.model import timestep_embedding
from scenegen.schema.condition import RARE_TAGS, Condition
from scenegen.schema.scene import Rejection

LABELS = ("accepted", *RARE_TAGS)
TIME_FEATURES = 16
_STATES = 4  # unspecified, required, forbidden, null


class VerifierConfig(BaseModel):
    """Sizes of the verifier and the schedule it was trained on; stored with its weights."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    width: int = Field(ge=1, le=65536)  # flattened tokens: slots x object_width + scene_width
    n_targets: int = Field(ge=1, le=1024)
    n_tags: int = Field(ge=1, le=1024)
    pose_dim: int = Field(7, ge=1, le=64)
    hidden: int = Field(128, ge=1, le=4096)
    layers: int = Field(2, ge=1, le=16)
    train_timesteps: int = Field(ge=1)
    labels: tuple[str, ...] = LABELS


class Verifier(nn.Module):
    """Logits (B, len(labels)) of the labels for x_t (B, width), t (B,) and the request."""

    def __init__(self, config: VerifierConfig):
        super().__init__()
        self.config = config
        cond = (config.n_targets + 1) + config.n_tags * _STATES + config.pose_dim
        sizes = [config.width + TIME_FEATURES + cond, *[config.hidden] * config.layers]
        blocks: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:], strict=True):
            blocks += [nn.Linear(a, b), nn.SiLU()]
        self.body = nn.Sequential(*blocks)
        self.head = nn.Linear(config.hidden, len(config.labels))

    def forward(self, x, t, target, tags, pose) -> torch.Tensor:
        c = self.config
        features = [
            x,
            timestep_embedding(t, TIME_FEATURES) if TIME_FEATURES else x[:, :0],
            nn.functional.one_hot(target.clamp(max=c.n_targets), c.n_targets + 1).float(),
            nn.functional.one_hot(tags, _STATES).float().reshape(len(x), -1),
            pose,
        ]
        return self.head(self.body(torch.cat(features, dim=1)))

    def log_accept(self, x: torch.Tensor, t: torch.Tensor, condition) -> torch.Tensor:
        """log p(accepted) (B,) under a ``model.ConditionBatch``."""
        pose = torch.where(condition.pose_null[:, None], torch.zeros_like(condition.pose), condition.pose)
        logits = self(x, t, condition.target, condition.tags, pose)
        return nn.functional.logsigmoid(logits[:, 0])


def try_labels(condition: Condition, tags: dict | None, rejection: Rejection | None):
    """(values, known) over LABELS for one try: accepted; each rare tag's holds where measured
    (``tags``: an accepted scene's {tag: TagValue}; a ``condition_unmet`` rejection names the
    required tags that failed and the forbidden ones that held)."""
    values = np.zeros(len(LABELS), np.float32)
    known = np.zeros(len(LABELS), bool)
    known[0], values[0] = True, float(rejection is None)
    for i, tag in enumerate(RARE_TAGS, start=1):
        if tags is not None:
            known[i], values[i] = True, float(tags[tag].holds)
        elif rejection is not None and rejection.label == "condition_unmet":
            state = condition.tags.get(tag, "unspecified")
            named = f"required {tag} =" in rejection.detail or f"forbidden {tag} =" in rejection.detail
            if state == "required":
                known[i], values[i] = True, float(not named)
            elif state == "forbidden":
                known[i], values[i] = True, float(named)
    return values, known


def train_verifier(
    data: dict[str, np.ndarray],
    config: VerifierConfig,
    alphas: torch.Tensor,
    steps: int = 2000,
    batch: int = 256,
    lr: float = 2e-3,
    seed: int = 0,
) -> tuple[Verifier, list[float]]:
    """Fit a verifier to ``data`` (x0 (N, width), target (N,), tags (N, n_tags), pose (N, pose_dim),
    values and known (N, labels)), each draw noised to a uniform timestep of ``alphas`` (the
    generator's cumulative alphas); returns it (eval mode) and the loss every 100 steps."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = Verifier(config)
    tensors = {k: torch.as_tensor(v) for k, v in data.items()}
    n = len(tensors["x0"])
    positive = tensors["values"].sum(0) / tensors["known"].sum(0).clamp(min=1)
    weight = (1 - positive) / positive.clamp(min=1e-3)  # balance each label's rare class
    optimiser = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    losses = []
    for step in range(steps):
        rows = torch.randint(n, (min(batch, n),), generator=generator)
        t = torch.randint(config.train_timesteps, (len(rows),), generator=generator)
        a = alphas[t][:, None].float()
        noise = torch.randn(len(rows), config.width, generator=generator)
        x = a.sqrt() * tensors["x0"][rows] + (1 - a).sqrt() * noise
        logits = model(x, t, tensors["target"][rows], tensors["tags"][rows], tensors["pose"][rows])
        known = tensors["known"][rows].float()
        loss = nn.functional.binary_cross_entropy_with_logits(
            logits, tensors["values"][rows], pos_weight=weight.clamp(0.1, 10.0), reduction="none"
        )
        loss = (loss * known).sum() / known.sum().clamp(min=1)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % 100 == 0 or step == steps - 1:
            losses.append(round(float(loss.detach()), 5))
    return model.eval().requires_grad_(False), losses


def save_verifier(model: Verifier, out: Path, extra: dict | None = None) -> str:
    """model.safetensors + config.json in ``out``; returns the weights' sha256."""
    from safetensors.torch import save_file

    from scenegen.core.files import sha256_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out / "model.safetensors"))
    config = {"kind": "verifier", "verifier": model.config.model_dump(mode="json"), **(extra or {})}
    (out / "config.json").write_text(json.dumps(config, indent=1, sort_keys=True) + "\n")
    return sha256_file(out / "model.safetensors")


def load_verifier(path: Path) -> Verifier:
    """A verifier saved by :func:`save_verifier` (safetensors and JSON only); ValueError (one line,
    naming the file) when it does not load."""
    from safetensors.torch import load_file

    from scenegen.core.files import checkpoint_error, read_checkpoint_config

    path = Path(path)
    remedy = "retrain it (scenegen experiment verifier) or restore it"
    config = read_checkpoint_config(path, "verifier", remedy)
    try:
        model = Verifier(VerifierConfig(**config["verifier"]))
        model.load_state_dict(load_file(str(path / "model.safetensors")))
    except Exception as exc:  # noqa: BLE001 - config keys, shapes, safetensors' own errors
        raise checkpoint_error(path / "model.safetensors", exc, remedy) from None
    return model.eval().requires_grad_(False)


def accuracy(model: Verifier, data: dict[str, np.ndarray], alphas: torch.Tensor, t: int) -> dict:
    """Per label, the share of known examples predicted right at timestep ``t`` (noise seeded 0) and
    the base rate: how much the verifier knows at that noise level."""
    generator = torch.Generator().manual_seed(0)
    x0 = torch.as_tensor(data["x0"])
    a = alphas[t].float()
    x = a.sqrt() * x0 + (1 - a).sqrt() * torch.randn(x0.shape, generator=generator)
    tt = torch.full((len(x0),), t, dtype=torch.long)
    with torch.no_grad():
        logits = model(x, tt, *(torch.as_tensor(data[k]) for k in ("target", "tags", "pose")))
    out = {}
    for i, label in enumerate(model.config.labels):
        known = data["known"][:, i]
        if known.any():
            truth = data["values"][known, i] > 0.5
            hit = (logits[known, i].numpy() > 0) == truth
            out[label] = {
                "n": int(known.sum()),
                "accuracy": round(float(hit.mean()), 4),
                "base_rate": round(float(truth.mean()), 4),
            }
    return out
