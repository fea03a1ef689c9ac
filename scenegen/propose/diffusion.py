"""The diffusion proposer: scenes sampled from a trained denoiser (scenegen/diffusion/), decoded onto
resting poses, behind the same interface as the procedural proposer.

Proposal ``i`` of a batch with seed ``s`` draws its initial noise and camera jitter from
``SeedSequence([s, i])`` alone and is sampled in the fixed group of indices 8k .. 8k + 7 that holds
it (one batch), so it does not depend on how a batch is chunked, resumed or spread over workers.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from scenegen.assets.catalog import Catalog
from scenegen.paths import PROJECT_ROOT
from scenegen.propose.base import AssetChoice, proposal_rng, register_proposer
from scenegen.propose.procedural import DEFAULT_CAMERAS, jitter_cameras
from scenegen.propose.separate import separate
from scenegen.schema.condition import RARE_TAGS, Condition
from scenegen.schema.scene import Camera, RejectionLabel, SceneProposal


def require_encoding(config: dict, checkpoint: str) -> None:
    """Raise ValueError when a checkpoint's config.json was made with another scene encoding."""
    from scenegen.diffusion.encoding import ENCODING_VERSION

    encoding = config.get("encoding", {})
    version = encoding.get("version", 1) if isinstance(encoding, dict) else None
    if version != ENCODING_VERSION:
        raise ValueError(
            f"{checkpoint}: made with scene encoding v{str(version)[:20]}, this scenegen reads "
            f"v{ENCODING_VERSION}; retrain it (scenegen train --out DIR, see docs/generator.md)"
        )


def require_spread(config: dict, settings: DiffusionSettings) -> None:
    """Raise ValueError when ``draw_spread`` is asked of a checkpoint trained without the spread."""
    if settings.draw_spread and not config.get("spread"):
        raise ValueError(
            f"draw_spread: {settings.checkpoint} was trained without the layout's spread; retrain it "
            "with `scenegen train --spread-bins 8` or turn draw_spread off"
        )


def _pinned(key: str, name: str, folder: Path, sha256: str | None) -> None:
    """Raise ValueError when ``folder``'s model.safetensors is not the one ``key`` pins (None: any)."""
    from scenegen.core.files import sha256_file

    if sha256 is None:
        return
    found = sha256_file(folder / "model.safetensors")
    if found != sha256:
        raise ValueError(
            f"{key}: {name}/model.safetensors has sha256 {found[:12]}..., "
            f"the recipe pins {sha256[:12]}...; restore that file or unpin it"
        )


class DiffusionSettings(AssetChoice):
    """Settings of the diffusion proposer (``proposer.kind: diffusion``). ``assets``
    (:class:`~scenegen.propose.base.AssetChoice`): only these are placed; an object the model decodes
    as another asset becomes one of these of its category (user assets of a category the model
    knows), or is left out."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    OMITTED_AT: ClassVar[dict[str, object]] = {
        "assets": None,
        "repairs": 0,
        "repair_width": 1,
        "repair_strength": 0.75,
        "repair_labels": None,
        "project": False,
        "denoise": True,
        "anticipate": False,
        "anticipate_occluded": False,
        "light_projection": "scale",
        "verifier": None,
        "verifier_sha256": None,
        "verifier_weight": 0.0,
        "solver": "ddim",
        "soft_occluded": False,
        "arm_clearance": False,
        "spacing": False,
        "upright_off_table": False,
        "checkpoint_sha256": None,
        "draw_spread": False,
    }

    kind: Literal["diffusion"] = "diffusion"
    checkpoint: str = "assets/generator"  # checkpoint directory (relative paths: to the project root)
    # the sha256 its model.safetensors must have (None: any); a recipe that must reproduce pins it
    checkpoint_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    guidance: float = Field(1.0, ge=0.0, le=20.0)  # w in eps~ = (1 + w) eps(c) - w eps(null)
    steps: int = Field(20, ge=1, le=1000)  # sampling steps
    solver: Literal["ddim", "dpm"] = "ddim"  # DDIM, or DPM-Solver++ 2M (as good at half the steps)
    cost_weight: float = Field(0.1, ge=0.0)  # cost guidance step (scenegen/diffusion/cost.py); 0: off
    request_cost: float = Field(10.0, ge=0.0)  # weight of the soft required predicates within the cost
    # Cost terms of generator v2 (issue 35), off by default so that recipes and the scenes made with
    # them (the transfer experiment's D arm) stay as they were: the line-of-sight term for a required
    # occluded, and the term keeping objects off the arm's geoms at the request's pose (cost.py)
    soft_occluded: bool = False
    arm_clearance: bool = False
    unconditional: bool = False  # sample the null condition (the model's own distribution)
    # a request that requires no tag (and the null condition) is given a layout spread drawn from the
    # training data's histogram, a checkpoint trained with `--spread-bins` (diffusion/data.py)
    draw_spread: bool = False
    repairs: int = Field(0, ge=0, le=64)  # re-samplings of a failed proposal's culprits (propose/repair.py)
    repair_width: int = Field(1, ge=1, le=8)  # repairs per expansion: 1 a chain, more a best-first search
    repair_strength: float = Field(0.75, gt=0.0, le=1.0)  # a repair starts this far into the schedule
    # the rejection labels that are repaired (None: all but unrealistic and render_failed); a repair of
    # a missing tag succeeded less often than a fresh proposal (docs/generator.md), one of a geometric
    # failure more often
    repair_labels: tuple[RejectionLabel, ...] | None = None
    # a repair first moves what a rejection names by the margin it measured (propose/project.py), and
    # re-denoises only what has no projection or after PROJECT_RUN projections in a row
    project: bool = False
    # re-denoise what no projection fixes; False: only projections repair, and a try nothing can be
    # projected for ends its index (the next proposal is a fresh one: a re-denoised repair succeeded
    # less often than a fresh proposal, docs/generator.md)
    denoise: bool = True
    # project each proposal before its first check on what the proposer can measure itself: the
    # request's near_edge and clutter, the workspace (propose/project.py ``anticipated``)
    anticipate: bool = False
    # with anticipate: a required occluded, which only the settled scene measures, projected on every
    # proposal (the tallest other object set between the target and the camera, as its repair does)
    anticipate_occluded: bool = False
    # how a required low_light is reached (repairs, anticipation, the soft cost): "scale" the whole
    # lighting (generator v3's), "aim" the lights that reach the target away from it first, as the
    # reference darkens a target, brightness kept (tag_projection.low_light_aimed, cost aim_lights)
    light_projection: Literal["scale", "aim"] = "scale"
    # the learned verifier (diffusion/verifier.py: a checkpoint folder) whose log p(accepted) gradient
    # steers sampling beside the cost, with this weight; its weights pinned by sha256 when given
    verifier: str | None = None
    verifier_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    verifier_weight: float = Field(0.0, ge=0.0, le=100.0)
    separate: bool = True  # push overlapping objects apart after decoding (propose/separate.py)
    max_shift: float = Field(0.05, ge=0.0, le=0.5)  # m, the most separating may move one object
    spacing: bool = False  # separating also spaces same-support objects as the reference sampler does
    upright_off_table: bool = False  # objects on the floor, shelf or in the bin decoded upright
    camera_jitter: float = Field(0.03, ge=0.0, le=0.2)
    cameras: tuple[Camera, ...] = DEFAULT_CAMERAS

    def known_categories(self) -> list[str]:
        """The target categories the checkpoint was trained with."""
        from scenegen.core.files import read_checkpoint_config

        config = read_checkpoint_config(self.checkpoint_dir(), "generator", "train one with `scenegen train`")
        return list(config["encoding"]["categories"])

    @field_validator("checkpoint")
    @classmethod
    def _exists(cls, checkpoint: str) -> str:
        from scenegen.core.files import read_checkpoint_config

        path = Path(checkpoint) if Path(checkpoint).is_absolute() else PROJECT_ROOT / checkpoint
        if not (path / "model.safetensors").is_file() or not (path / "config.json").is_file():
            raise ValueError(
                f"{checkpoint}: no checkpoint there (model.safetensors + config.json); "
                "train one with `scenegen train --out DIR`"
            )
        config = read_checkpoint_config(path, "generator", "train one with `scenegen train --out DIR`")
        require_encoding(config, checkpoint)
        return checkpoint

    @model_validator(mode="after")
    def _fits_checkpoint(self):
        """The checkpoint has what the settings ask of it: the spread for ``draw_spread``, the pinned
        weights for ``checkpoint_sha256``."""
        from scenegen.core.files import read_checkpoint_config

        if self.draw_spread:
            require_spread(read_checkpoint_config(self.checkpoint_dir(), "generator", "train one"), self)

        if self.verifier is not None:
            from scenegen.diffusion.verifier import load_verifier

            load_verifier(self.verifier_dir())  # one line naming the file when it does not load
            _pinned("verifier_sha256", self.verifier, self.verifier_dir(), self.verifier_sha256)
        elif self.verifier_weight > 0:
            raise ValueError("verifier_weight: no verifier to weigh; name its folder in `verifier`")
        _pinned("checkpoint_sha256", self.checkpoint, self.checkpoint_dir(), self.checkpoint_sha256)
        return self

    def checkpoint_dir(self) -> Path:
        path = Path(self.checkpoint)
        return path if path.is_absolute() else PROJECT_ROOT / path

    def verifier_dir(self) -> Path:
        path = Path(self.verifier or "")
        return path if path.is_absolute() else PROJECT_ROOT / path


GROUP = 8  # proposals sampled together: indices 8k .. 8k + 7, whatever the caller asks for
PROJECT_RUN = 3  # projections in a row on one repair path before a repair re-denoises
REPAIR_STREAM = 7  # SeedSequence([seed, index, REPAIR_STREAM, attempt]): a repair's own noise
SPREAD_STREAM = 11  # SeedSequence([seed, index, SPREAD_STREAM]): a proposal's drawn spread


@functools.lru_cache(maxsize=4)
def _load(checkpoint: str):
    from scenegen.diffusion.sample import load_denoiser

    return load_denoiser(Path(checkpoint))


def load_generator(settings: DiffusionSettings):
    """The denoiser and config of the settings' checkpoint, loaded once per process; ValueError
    (one line, naming the file) when it does not load or was made with another scene encoding."""
    model, config = _load(str(settings.checkpoint_dir()))
    require_encoding(config, settings.checkpoint)
    return model, config


@register_proposer("diffusion")
class DiffusionProposer:
    """Samples whole scenes from the denoiser for a condition."""

    wants_arm = True  # the runner passes ``arm``: check/geometry.py's arm_discs (no MuJoCo here)

    def __init__(self, settings: DiffusionSettings, catalog: Catalog, arm=None):
        """``arm(robot_pose) -> (G, 4)``: the arm's geoms as discs (check.geometry.arm_discs), for the
        cost's arm clearance; None leaves that term out."""
        from scenegen.diffusion.encoding import SceneEncoding

        self.settings = settings
        self.catalog = catalog
        self.arm = arm
        self.model, self.config = load_generator(settings)
        trained = list(self.config["encoding"].get("assets") or [])
        missing = [name for name in trained if name not in catalog.by_name]
        if missing:
            raise ValueError(
                f"{settings.checkpoint}: trained with assets the recipe's catalogs lack "
                f"({', '.join(missing[:3])}); add their catalog to `catalogs`, or retrain it"
            )
        self.encoding = SceneEncoding(catalog, assets=trained)
        if self.encoding.object_width != self.config["denoiser"]["object_width"]:
            raise ValueError(
                f"{settings.checkpoint}: trained on other resting poses of its assets; retrain it"
            )
        require_spread(self.config, settings)
        self.allowed = None if settings.assets is None else tuple(catalog.get(a) for a in settings.assets)
        self._group_key: tuple | None = None
        self._group: list = []

    @functools.lru_cache(maxsize=16)  # noqa: B019 - one cost per request, for the proposer's lifetime
    def _cost(self, required: tuple[str, ...], robot_pose: tuple[float, ...]):
        from scenegen.core.layout import SHOULDER
        from scenegen.diffusion.cost import SceneCost

        s = self.settings
        weights = dict.fromkeys(required, s.request_cost)
        camera = s.cameras[0].position if s.soft_occluded else None  # `occluded` is seen from the main camera
        arm = None if self.arm is None or not s.arm_clearance else self.arm(robot_pose)
        aim = s.light_projection == "aim"
        return SceneCost(
            self.encoding, required, weights, shoulder=SHOULDER, camera=camera, arm=arm, aim_lights=aim
        )

    def describe(self) -> dict:
        return {"kind": self.kind, "settings": self.settings.model_dump(mode="json")}

    def condition_batch(self, condition: Condition):
        import torch

        from scenegen.diffusion.model import TAG_STATES, ConditionBatch

        c = ConditionBatch(
            task=torch.tensor([self.config["tasks"].index(condition.task)]),
            target=torch.tensor([self.config["encoding"]["categories"].index(condition.target)]),
            tags=torch.tensor([[TAG_STATES[condition.tags.get(t, "unspecified")] for t in RARE_TAGS]]),
            pose=torch.tensor([condition.robot_pose], dtype=torch.float32),
            pose_null=torch.zeros(1, dtype=torch.bool),
        )
        return c.null_like(self.model.config) if self.settings.unconditional else c

    def _conditions(self, condition: Condition, indices: Sequence[int], seed: int):
        """The model's condition for proposals ``indices``: the request's (:meth:`condition_batch`)
        and, with ``draw_spread`` and a request that requires no tag, each proposal's spread bin,
        drawn from the checkpoint's training histogram with SeedSequence([seed, index, SPREAD_STREAM])
        (a required tag leaves the spread to the model: the tag decides it, clutter close together)."""
        import torch

        from scenegen.diffusion.model import ConditionBatch

        c = ConditionBatch.cat([self.condition_batch(condition)] * len(indices))
        if self.settings.draw_spread and (self.settings.unconditional or not condition.required()):
            counts = np.asarray(self.config["spread"]["counts"], float)
            draws = [
                np.random.default_rng(np.random.SeedSequence([seed, i, SPREAD_STREAM])).choice(
                    len(counts), p=counts / counts.sum()
                )
                for i in indices
            ]
            c.spread = torch.tensor(draws, dtype=torch.long)
        return c

    def propose(self, condition: Condition, indices: Sequence[int], seed: int) -> list[SceneProposal]:
        return [self.decoded(condition, i, seed).proposal for i in indices]

    def _substitute(self, seed: int, index: int):
        """The ``substitute`` of decoding proposal ``index`` (None without ``assets``): an object the
        model decodes as an asset outside ``assets`` becomes one of ``assets`` of its category, drawn
        from SeedSequence([seed, index, 5]), in the resting pose matched by uprightness and height
        (``encoding.matched_pose``); without one of its category, it is left out."""
        if self.allowed is None:
            return None
        from scenegen.diffusion.encoding import matched_pose

        allowed = {a.name for a in self.allowed}
        rng = np.random.default_rng(np.random.SeedSequence([seed, index, 5]))

        def swap(asset, pose: int, slot: int):
            if asset.name in allowed:
                return asset, pose
            pool = [a for a in self.allowed if a.category == asset.category]
            if not pool:
                return None
            other = pool[int(rng.integers(len(pool)))]
            return other, matched_pose(asset, pose, other)

        return swap

    def decoded(self, condition: Condition, index: int, seed: int):
        """Proposal ``index`` with its projection distances (``encoding.Decoded``).

        Proposals are sampled in fixed groups of ``GROUP`` consecutive indices (one batch, ~3x
        cheaper per sample than one at a time on a CPU); the last group is kept, so a caller that
        walks the indices in order samples each group once. With ``unconditional`` the target is the
        sample's own and the proposal's condition names its category; the request's tags still
        decide acceptance."""
        key = (condition.model_dump_json(), index // GROUP, seed)
        if self._group_key != key:
            self._group = self._sample_group(condition, index // GROUP, seed)
            self._group_key = key
        return self._group[index % GROUP]

    def repair(self, parent: SceneProposal, rejection, attempt: int) -> SceneProposal | None:
        """Attempt ``attempt`` of ``parent``'s index: with ``project``, what ``rejection`` names moved
        by the margin it measured (:meth:`_projected`) where it can be; else the parts it blames
        (``repair.resampled_for``) re-denoised with the rest of the scene held fixed (inpainting),
        then decoded and separated like a first-pass proposal; None when the rejection is not
        repaired or the scene cannot be encoded. Its noise comes from
        SeedSequence([seed, index, REPAIR_STREAM, attempt]) alone, so a repair does not depend on
        the order repairs are made in."""
        import torch

        from scenegen.diffusion.sample import Inpaint, sample
        from scenegen.propose.repair import repair_step, resampled_for

        projected = self._projected(parent, rejection, attempt)
        if projected is not None or not self.settings.denoise:
            return projected
        resampled = resampled_for(rejection, parent)
        if not resampled:
            return None
        try:
            tokens, scene, slot_of = self.encoding.encode_proposal(parent)
        except ValueError:
            return None
        s, cfg = self.settings, self.model.config
        regenerate_objects, regenerate_scene = self.encoding.regenerate_masks(slot_of, resampled)
        stream = np.random.SeedSequence([parent.seed, parent.index, REPAIR_STREAM, attempt])
        rng = np.random.default_rng(stream)
        generator = torch.Generator().manual_seed(int(rng.integers(2**63)))
        noise_o = torch.randn(1, cfg.slots, cfg.object_width, generator=generator)
        noise_s = torch.randn(1, cfg.scene_width, generator=generator)
        width = cfg.slots * cfg.object_width + cfg.scene_width
        inpaint = Inpaint(
            objects=torch.tensor(tokens, dtype=torch.float32)[None],
            scene=torch.tensor(scene, dtype=torch.float32)[None],
            regenerate_objects=torch.tensor(regenerate_objects)[None],
            regenerate_scene=torch.tensor(regenerate_scene)[None],
            noise=torch.randn(s.steps + 1, 1, width, generator=generator),
            strength=s.repair_strength,
        )
        required, pose = tuple(parent.condition.required()), tuple(parent.condition.robot_pose)
        cost = self._cost(required, pose) if s.cost_weight > 0 else None
        objects, scene_out = sample(
            self.model,
            self.config["train"],
            self._conditions(parent.condition, [parent.index], parent.seed),
            noise_o,
            noise_s,
            w=s.guidance,
            steps=s.steps,
            cost=cost,
            cost_weight=s.cost_weight,
            inpaint=inpaint,
            solver=s.solver,
            **self._verifier(),
        )
        proposal = self._placed(
            objects[0], scene_out[0], parent.condition, parent.cameras, parent.index, parent.seed, False
        ).proposal
        step = repair_step(rejection, parent, attempt, resampled)
        return proposal.model_copy(update={"attempt": attempt, "repairs": (*parent.repairs, step)})

    def _verifier(self) -> dict:
        """sample()'s verifier arguments: the settings' verifier, loaded once, and its weight."""
        if self.settings.verifier is None or self.settings.verifier_weight <= 0:
            return {}
        from scenegen.diffusion.verifier import load_verifier

        if getattr(self, "_loaded_verifier", None) is None:
            self._loaded_verifier = load_verifier(self.settings.verifier_dir())
        return {"verifier": self._loaded_verifier, "verifier_weight": self.settings.verifier_weight}

    def _projected(self, parent: SceneProposal, rejection, attempt: int) -> SceneProposal | None:
        """With ``project``: ``parent`` moved by what ``rejection`` measured (propose/project.py), as
        attempt ``attempt``; None when it has no projection, or the path's last PROJECT_RUN repairs
        were projections already (then the repair re-denoises)."""
        from scenegen.propose.project import project
        from scenegen.propose.repair import repair_step

        recent = parent.repairs[-PROJECT_RUN:]
        if not self.settings.project or (
            len(recent) == PROJECT_RUN and all(r.method == "project" for r in recent)
        ):
            return None
        moved = project(
            parent, rejection, self.catalog, self.settings.max_shift, self.settings.light_projection
        )
        if moved is None:
            return None
        proposal, names = moved
        step = repair_step(rejection, parent, attempt, names, "project")
        return proposal.model_copy(update={"attempt": attempt, "repairs": (*parent.repairs, step)})

    def _sample_group(self, condition: Condition, group: int, seed: int) -> list:
        import torch

        from scenegen.diffusion.sample import sample

        s = self.settings
        cfg = self.model.config
        indices = range(group * GROUP, (group + 1) * GROUP)
        rngs = [proposal_rng(seed, i) for i in indices]
        noise_o, noise_s = [], []
        for rng in rngs:  # each proposal's noise from its own SeedSequence([seed, index])
            generator = torch.Generator().manual_seed(int(rng.integers(2**63)))
            noise_o.append(torch.randn(1, cfg.slots, cfg.object_width, generator=generator))
            noise_s.append(torch.randn(1, cfg.scene_width, generator=generator))
        required = tuple(condition.required())
        cost = self._cost(required, tuple(condition.robot_pose)) if s.cost_weight > 0 else None
        objects, scene = sample(
            self.model,
            self.config["train"],
            self._conditions(condition, indices, seed),
            torch.cat(noise_o),
            torch.cat(noise_s),
            w=s.guidance,
            steps=s.steps,
            cost=cost,
            cost_weight=s.cost_weight,
            solver=s.solver,
            **self._verifier(),
        )
        out = []
        for k, (index, rng) in enumerate(zip(indices, rngs, strict=True)):
            cameras = jitter_cameras(rng, s.cameras, s.camera_jitter)
            out.append(self._placed(objects[k], scene[k], condition, cameras, index, seed, s.unconditional))
        return out

    def _placed(self, objects, scene, condition: Condition, cameras, index: int, seed: int, own_target: bool):
        """One sample's tokens (slots, object_width), (scene_width) decoded onto resting poses and,
        with ``separate``, pushed apart: an ``encoding.Decoded``."""
        from scenegen.diffusion.encoding import Decoded

        s = self.settings
        decoded = self.encoding.decode(
            objects.numpy().astype(np.float64),
            scene.numpy().astype(np.float64),
            condition,
            cameras,
            index,
            seed,
            own_target=own_target,
            substitute=self._substitute(seed, index),
            upright_off_table=s.upright_off_table,
        )
        if not s.separate and not s.anticipate:
            return decoded
        proposal = decoded.proposal
        if s.separate:
            proposal = separate(proposal, self.catalog, max_shift=s.max_shift, spacing=s.spacing)
        if s.anticipate:
            from scenegen.propose.project import anticipated

            proposal = anticipated(
                proposal, self.catalog, s.max_shift, s.light_projection, s.anticipate_occluded
            )
        return Decoded(proposal, tuple(o.projection_distance for o in proposal.objects))
