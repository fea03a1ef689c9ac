"""Sampling scenes from a trained denoiser: DDIM (diffusers, pinned), classifier-free guidance in our
code, and an optional cost gradient on the predicted clean scene.

Per step, with a_t the cumulative alpha of timestep t:

    eps~   = (1 + w) eps(x_t, t, c) - w eps(x_t, t, null)          (model.guided_eps)
    x0_hat = (x_t - sqrt(1 - a_t) eps~) / sqrt(a_t)
    x0_hat -= cost_weight * grad_x0 cost(x0_hat)                   (only when cost_weight > 0)
    eps~   = (x_t - sqrt(a_t) x0_hat) / sqrt(1 - a_t)
    x_{t-1} = DDIM step (eta 0, clip_sample off, trailing spacing), or DPM-Solver++ (``solver``)

The cost step is taken on the clean-scene estimate, in token units, and eps~ is re-derived from it.
Adding a gradient to eps~ instead would be divided by sqrt(a_t) (~1e-4 at the first steps) in the
DDIM step's own x0 estimate and throw samples hundreds of metres away.

A fresh scheduler is made for every call (schedulers keep state). Sampling is deterministic for the
initial noise, which the caller draws from its own generator per sample.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from scenegen.diffusion.model import ConditionBatch, Denoiser, DenoiserConfig, guided_eps

Cost = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (objects, scene) -> (B,) cost


def load_denoiser(checkpoint: Path) -> tuple[Denoiser, dict]:
    """The EMA denoiser of a checkpoint directory and its config.json (safetensors + JSON only);
    CheckpointError (one line, naming the file) when the folder does not hold a loadable generator."""
    from safetensors.torch import load_file

    from scenegen.core.files import checkpoint_error, read_checkpoint_config

    checkpoint = Path(checkpoint)
    remedy = "retrain it (scenegen train --out DIR) or restore it"
    config = read_checkpoint_config(checkpoint, "generator", remedy)
    try:
        model = Denoiser(DenoiserConfig(**config["denoiser"]))
    except (KeyError, TypeError, ValueError, AssertionError, RuntimeError) as exc:  # torch asserts sizes
        raise checkpoint_error(checkpoint / "config.json", exc, remedy) from None
    weights = checkpoint / "model.safetensors"
    try:
        model.load_state_dict(load_file(str(weights)))
    except Exception as exc:  # noqa: BLE001 - safetensors' own error type, shape mismatches, I/O
        raise checkpoint_error(weights, exc, remedy) from None
    return model.eval().requires_grad_(False), config


SOLVERS = ("ddim", "dpm")


def scheduler_for(train_config: dict, steps: int, solver: str = "ddim"):
    """A fresh scheduler of ``solver`` for ``steps`` sampling steps: ``ddim`` (:func:`ddim_scheduler`)
    or ``dpm``, DPM-Solver++ of order 2 (Lu et al. 2022; diffusers' DPMSolverMultistepScheduler,
    deterministic, trailing spacing, first order at the last step). Both take eps and keep state:
    one per sampling call."""
    if solver == "ddim":
        return ddim_scheduler(train_config, steps)
    if solver != "dpm":
        raise ValueError(f"solver {solver!r}: choose one of {', '.join(SOLVERS)}")
    from diffusers import DPMSolverMultistepScheduler

    scheduler = DPMSolverMultistepScheduler(
        num_train_timesteps=train_config["train_timesteps"],
        beta_schedule=train_config["beta_schedule"],
        algorithm_type="dpmsolver++",
        solver_order=2,
        timestep_spacing="trailing",
        prediction_type="epsilon",
        lower_order_final=True,
    )
    scheduler.set_timesteps(steps)
    return scheduler


def ddim_scheduler(train_config: dict, steps: int):
    """A fresh DDIM scheduler matching the training schedule, set to ``steps`` sampling steps."""
    from diffusers import DDIMScheduler

    scheduler = DDIMScheduler(
        num_train_timesteps=train_config["train_timesteps"],
        beta_schedule=train_config["beta_schedule"],
        clip_sample=False,
        set_alpha_to_one=False,
        timestep_spacing="trailing",
        prediction_type="epsilon",
    )
    scheduler.set_timesteps(steps)
    return scheduler


@dataclass(frozen=True)
class Inpaint:
    """What :func:`sample` keeps of a known scene (RePaint-style inpainting: Lugmayr et al. 2022).

    ``objects`` (B, slots, object_width) and ``scene`` (B, scene_width): the known clean tokens;
    ``regenerate_objects`` / ``regenerate_scene``: boolean masks of the same shapes, True where the
    model samples afresh, False where the known value is held. ``noise``: (steps + 1, B, D) standard
    normal draws, one per step, that noise the known part to each step's level (drawn by the caller
    from each row's own generator, so a row does not depend on its batch)."""

    objects: torch.Tensor
    scene: torch.Tensor
    regenerate_objects: torch.Tensor
    regenerate_scene: torch.Tensor
    noise: torch.Tensor
    strength: float = 1.0  # start from the known scene noised this far into the schedule (1: pure noise)

    def flat(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The known clean scene and the regenerate mask, flattened to (B, D) as :func:`sample`'s x."""
        b = len(self.objects)
        known = torch.cat([self.objects.reshape(b, -1), self.scene], dim=1)
        mask = torch.cat([self.regenerate_objects.reshape(b, -1), self.regenerate_scene], dim=1)
        return known, mask


def sample(
    model: Denoiser,
    train_config: dict,
    condition: ConditionBatch,
    noise_objects: torch.Tensor,
    noise_scene: torch.Tensor,
    w: float = 0.0,
    steps: int = 20,
    cost: Cost | None = None,
    cost_weight: float = 0.0,
    inpaint: Inpaint | None = None,
    solver: str = "ddim",
    verifier=None,
    verifier_weight: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Denoise the initial noise (B, slots, object_width), (B, scene_width) under ``condition``.

    ``verifier`` (diffusion/verifier.py): the clean-scene estimate also moves up the gradient of its
    log p(accepted | x_t, t, c), by ``verifier_weight * sqrt(a_t) * grad_{x_t}`` (the gradient taken
    through x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps, as the cost's is taken on x0).

    Rows whose condition is the null condition are unconditional samples whatever ``w``. With
    ``inpaint``, after every step the held part of x is replaced by the known scene noised to the
    next step's level, the cost gradient moves only the regenerated part, and the result holds the
    known values exactly where they are held."""
    scheduler = scheduler_for(train_config, steps, solver)
    alphas = scheduler.alphas_cumprod
    cfg = model.config
    b, n_obj = len(noise_objects), cfg.slots * cfg.object_width
    x = torch.cat([noise_objects.reshape(b, -1), noise_scene], dim=1)
    known, regenerate = inpaint.flat() if inpaint is not None else (None, None)
    timesteps = [int(t) for t in scheduler.timesteps]
    if known is not None:
        # SDEdit-style start (Meng et al. 2022): the regenerated part begins as the known scene noised
        # to the first kept step, so a re-sampled object keeps being an object (from pure noise, a
        # freed slot often collapsed into an empty one: x = y = -0.5 m, measured)
        skip = len(timesteps) - max(1, round(inpaint.strength * len(timesteps)))
        timesteps = timesteps[skip:]
        noise = inpaint.noise[skip:]
        start = _noised(known, alphas[timesteps[0]], noise[0])
        x = start if inpaint.strength < 1.0 else torch.where(regenerate, x, start)
    for i, t in enumerate(timesteps):
        objects, scene = x[:, :n_obj].reshape(b, cfg.slots, cfg.object_width), x[:, n_obj:]
        tt = torch.full((b,), t, dtype=torch.long)
        with torch.no_grad():
            eps_o, eps_s = guided_eps(model, objects, scene, tt, condition, w, alphas)
        eps = torch.cat([eps_o.reshape(b, -1), eps_s], dim=1)
        if cost is not None and cost_weight > 0:
            a = alphas[t]
            x0 = ((x - (1 - a).sqrt() * eps) / a.sqrt()).detach().requires_grad_(True)
            value = cost(x0[:, :n_obj].reshape(b, cfg.slots, cfg.object_width), x0[:, n_obj:]).sum()
            (grad,) = torch.autograd.grad(value, x0)
            if regenerate is not None:
                grad = grad * regenerate
            eps = (x - a.sqrt() * (x0.detach() - cost_weight * grad)) / (1 - a).sqrt()
        if verifier is not None and verifier_weight > 0:
            eps = _verifier_step(verifier, verifier_weight, x, eps, tt, condition, alphas[t], regenerate)
        x = scheduler.step(eps, t, x, **({"eta": 0.0} if solver == "ddim" else {})).prev_sample
        if known is not None:
            last = i + 1 == len(timesteps)
            held = known if last else _noised(known, alphas[timesteps[i + 1]], noise[i + 1])
            x = torch.where(regenerate, x, held)
    return x[:, :n_obj].reshape(b, cfg.slots, cfg.object_width), x[:, n_obj:]


def _verifier_step(verifier, weight: float, x, eps, t, condition, a, regenerate) -> torch.Tensor:
    """eps~ re-derived from the clean-scene estimate moved by ``weight * sqrt(a) * grad_x log p``
    (log p: the verifier's log p(accepted | x_t, t, c)); only the regenerated part moves."""
    xt = x.detach().requires_grad_(True)
    with torch.enable_grad():
        (grad,) = torch.autograd.grad(verifier.log_accept(xt, t, condition).sum(), xt)
    if regenerate is not None:
        grad = grad * regenerate
    x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
    return (x - a.sqrt() * (x0 + weight * a.sqrt() * grad)) / (1 - a).sqrt()


def _noised(x0: torch.Tensor, alpha_bar: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """x0 diffused to the level of cumulative alpha ``alpha_bar``: q(x_t | x0) with the given noise."""
    return alpha_bar.sqrt() * x0 + (1 - alpha_bar).sqrt() * noise
