"""The denoiser: a permutation-equivariant transformer over object slots, with condition tokens.

Tokens: one per object slot (no positional encoding, so permuting the slots permutes the output), one
scene token (furniture and lighting), and condition tokens: task, target category, one per rare tag
(tag identity + its state), robot initial joint pose, the diffusion timestep and, for a checkpoint
trained with ``n_spread`` > 0, the layout's spread (its bin of mean pair distance, see
diffusion/data.py). Every condition
field has a learned null value, distinct from any real value (the tag state ``null`` is not
``unspecified``, and neither is the tag ``nominal``); the null condition is all fields null.
One network gives both the conditional and the unconditional prediction. It predicts v (the
velocity parameterisation); :func:`predict_eps` turns that into the noise prediction eps that
guidance and the sampler work with.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

# Tag states as model inputs. NULL is the dropped field, used for the unconditional branch.
UNSPECIFIED, REQUIRED, FORBIDDEN, NULL = 0, 1, 2, 3
TAG_STATES = {"unspecified": UNSPECIFIED, "required": REQUIRED, "forbidden": FORBIDDEN}


class DenoiserConfig(BaseModel):
    """Sizes of the denoiser; stored with every checkpoint."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    object_width: int = Field(ge=1, le=4096)
    scene_width: int = Field(ge=1, le=4096)
    slots: int = Field(ge=1, le=1024)
    n_tasks: int = Field(ge=1, le=1024)
    n_targets: int = Field(ge=1, le=1024)
    n_tags: int = Field(ge=1, le=1024)
    pose_dim: int = Field(7, ge=1, le=64)
    d_model: int = Field(128, ge=1, le=4096)
    layers: int = Field(4, ge=1, le=64)
    heads: int = Field(4, ge=1, le=64)
    n_spread: int = Field(0, ge=0, le=64)  # spread values (0: no spread token, checkpoints before it)


@dataclass
class ConditionBatch:
    """A batch of conditions as indices: ``task`` (B,) and ``target`` (B,) with the null value at
    index n_tasks / n_targets, ``tags`` (B, n_tags) tag states, ``pose`` (B, pose_dim) radians and
    ``pose_null`` (B,) bool; ``spread`` (B,) the layout's spread bin, null at index n_spread or -1
    (None: null for every row)."""

    task: torch.Tensor
    target: torch.Tensor
    tags: torch.Tensor
    pose: torch.Tensor
    pose_null: torch.Tensor
    spread: torch.Tensor | None = None

    FIELDS = ("task", "target", "tags", "pose", "pose_null", "spread")

    def __len__(self) -> int:
        return len(self.task)

    def null_like(self, config: DenoiserConfig) -> ConditionBatch:
        """The null condition, for every row of this batch."""
        return ConditionBatch(
            task=torch.full_like(self.task, config.n_tasks),
            target=torch.full_like(self.target, config.n_targets),
            tags=torch.full_like(self.tags, NULL),
            pose=torch.zeros_like(self.pose),
            pose_null=torch.ones_like(self.pose_null),
        )

    def to(self, device) -> ConditionBatch:
        """The same conditions on ``device`` (itself when they are there already)."""
        moved = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return dataclasses.replace(self, **{k: None if v is None else v.to(device) for k, v in moved.items()})

    @staticmethod
    def cat(batches: list[ConditionBatch]) -> ConditionBatch:
        """The rows of ``batches`` in order; a batch without ``spread`` has it null (-1)."""
        spread = None
        if any(b.spread is not None for b in batches):
            spread = torch.cat(
                [torch.full_like(b.task, -1) if b.spread is None else b.spread for b in batches]
            )
        return ConditionBatch(
            *(torch.cat([getattr(b, f) for b in batches]) for f in ConditionBatch.FIELDS[:-1]), spread=spread
        )

    def index(self, rows) -> ConditionBatch:
        return ConditionBatch(
            *(None if getattr(self, f) is None else getattr(self, f)[rows] for f in self.FIELDS)
        )


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding (B, dim) of integer timesteps (B,)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=1)


class Denoiser(nn.Module):
    """v(x_t, t, c) for object tokens (B, slots, object_width) and the scene token (B, scene_width)."""

    def __init__(self, config: DenoiserConfig):
        super().__init__()
        self.config = config
        d = config.d_model
        self.object_in = nn.Linear(config.object_width, d)
        self.scene_in = nn.Linear(config.scene_width, d)
        self.kind = nn.Embedding(3, d)  # object slot, scene, condition token
        self.task = nn.Embedding(config.n_tasks + 1, d)  # last index: null
        self.target = nn.Embedding(config.n_targets + 1, d)
        self.tag_id = nn.Embedding(config.n_tags, d)
        self.tag_state = nn.Embedding(4, d)  # unspecified, required, forbidden, null
        self.pose_in = nn.Linear(config.pose_dim, d)
        self.pose_null = nn.Parameter(torch.zeros(d))
        if config.n_spread:
            self.spread = nn.Embedding(config.n_spread + 1, d)  # last index: null
        self.time = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        layer = nn.TransformerEncoderLayer(
            d, config.heads, 4 * d, dropout=0.0, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, config.layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d)
        self.object_out = nn.Linear(d, config.object_width)
        self.scene_out = nn.Linear(d, config.scene_width)
        for head in (self.object_out, self.scene_out):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def condition_tokens(self, c: ConditionBatch, t: torch.Tensor) -> torch.Tensor:
        """(B, 4 + n_tags (+ 1), d): task, target, pose, timestep (, spread), one per tag."""
        pose = torch.where(c.pose_null[:, None], self.pose_null.expand(len(c), -1), self.pose_in(c.pose))
        tags = self.tag_id.weight[None] + self.tag_state(c.tags)
        time = self.time(timestep_embedding(t, self.config.d_model))
        fixed = [self.task(c.task), self.target(c.target), pose, time]
        if self.config.n_spread:
            null = self.config.n_spread
            spread = (
                torch.full_like(c.task, null)
                if c.spread is None
                else torch.where(c.spread < 0, null, c.spread)
            )
            fixed.append(self.spread(spread))
        fixed = torch.stack(fixed, dim=1)
        return torch.cat([fixed, tags], dim=1) + self.kind.weight[2]

    def forward(
        self, objects: torch.Tensor, scene: torch.Tensor, t: torch.Tensor, c: ConditionBatch
    ) -> tuple[torch.Tensor, torch.Tensor]:
        time = self.time(timestep_embedding(t, self.config.d_model))[:, None]
        tokens = torch.cat(
            [
                self.object_in(objects) + self.kind.weight[0] + time,
                (self.scene_in(scene) + self.kind.weight[1])[:, None] + time,
                self.condition_tokens(c, t),
            ],
            dim=1,
        )
        h = self.norm(self.encoder(tokens))
        slots = self.config.slots
        return self.object_out(h[:, :slots]), self.scene_out(h[:, slots])


def predict_eps(
    model: Denoiser,
    objects: torch.Tensor,
    scene: torch.Tensor,
    t: torch.Tensor,
    c: ConditionBatch,
    alphas_cumprod: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """eps(x_t, t, c). The network predicts v = sqrt(a) eps - sqrt(1 - a) x_0 (a = alphas_cumprod[t]),
    which stays well conditioned where a -> 0; eps = sqrt(a) v + sqrt(1 - a) x_t. (An eps-predicting
    network made DDIM's x_0 estimate (x_t - sqrt(1 - a) eps) / sqrt(a) explode at t = T - 1.)"""
    v_o, v_s = model(objects, scene, t, c)
    a = alphas_cumprod[t].to(objects.dtype)
    return (
        a.sqrt()[:, None, None] * v_o + (1 - a).sqrt()[:, None, None] * objects,
        a.sqrt()[:, None] * v_s + (1 - a).sqrt()[:, None] * scene,
    )


def guided_eps(
    model: Denoiser,
    objects: torch.Tensor,
    scene: torch.Tensor,
    t: torch.Tensor,
    c: ConditionBatch,
    w: float,
    alphas_cumprod: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Classifier-free guidance: eps~ = (1 + w) eps(x, t, c) - w eps(x, t, null), in one forward pass.

    w = 0 is the conditional prediction alone (no unconditional pass is run)."""
    if w == 0:
        return predict_eps(model, objects, scene, t, c, alphas_cumprod)
    both = ConditionBatch.cat([c, c.null_like(model.config)])
    eps_o, eps_s = predict_eps(
        model,
        torch.cat([objects, objects]),
        torch.cat([scene, scene]),
        torch.cat([t, t]),
        both,
        alphas_cumprod,
    )
    n = len(c)
    return (
        (1 + w) * eps_o[:n] - w * eps_o[n:],
        (1 + w) * eps_s[:n] - w * eps_s[n:],
    )
