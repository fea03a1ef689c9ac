"""The transfer experiment's configuration (``pipelines/transfer.yaml``; docs/transfer.md explains
version 2's keys, docs/transfer_v1.md version 1's). Unknown keys, wrong types and out-of-range
numbers are one-line errors naming the key."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.policy.panels import PANEL_TAGS, PANELS_V2_FILE

ARMS = ("A", "A+", "B", "C", "D", "E")


class TransferConfigError(ValueError):
    """A transfer configuration that cannot run; the message names the file and key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Sizes(_Strict):
    """Labelled layouts: ``a`` (arm A), ``a_plus`` (arm A+, A's plus more at the natural rate),
    ``extra`` (the rare scenes C, D and E add to A)."""

    a: int = Field(600, ge=1)
    a_plus: int = Field(1000, ge=1)
    extra: int = Field(400, ge=1)

    @model_validator(mode="after")
    def _order(self):
        if self.a_plus < self.a:
            raise ValueError(f"a_plus ({self.a_plus}) must be at least a ({self.a})")
        return self


class Training(_Strict):
    """The same policy, gradient steps and batch size for every arm; ``seeds`` at the default alpha."""

    steps: int = Field(500, ge=1)
    batch_size: int = Field(32, ge=1)
    lr: float = Field(1e-3, gt=0)
    seeds: tuple[int, ...] = Field((0, 1, 2), min_length=1)


class Generation(_Strict):
    """How D and E make their scenes: ``recipe`` (the distributions the reference set came from),
    ``diffusion`` (D's proposer settings: by default the current generator's, pipelines/demo.yaml;
    pipelines/transfer_v1.yaml and pipelines/transfer.yaml name the pinned ones their runs use) and
    ``max_proposals`` per requested scene before a cell gives up."""

    recipe: Path = Path("pipelines/reference.yaml")
    diffusion: Path = Path("pipelines/demo.yaml")
    max_proposals: int = Field(60, ge=1)
    calibration_proposals: int = Field(100, ge=1)  # C's cost: the reference recipe's CPU-s per layout


class Perturbation(_Strict):
    """The shift the rare panel is also evaluated under: every light and the ambient term scaled."""

    name: str = "dim_light"
    light_scale: float = Field(0.35, gt=0, le=3)
    arms: tuple[str, ...] = ("A+", "C", "D")


class TransferConfig(_Strict):
    name: str = "transfer"
    seed: int = 20
    reference: Path = Path("assets/reference/reference.parquet")
    panels: Path = Path("assets/panels/panels.json")
    rare_per_tag: int | None = Field(None, ge=1)  # None: the whole committed panel (25 per tag)
    common: int | None = Field(None, ge=1)  # None: the whole common panel (100)
    tags: tuple[str, ...] = PANEL_TAGS
    primitives: tuple[str, ...] = tuple(PRIMITIVES)
    sizes: Sizes = Sizes()
    alpha: float = 1.0
    alpha_sweep: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0)
    training: Training = Training()
    generation: Generation = Generation()
    perturbation: Perturbation | None = Perturbation()
    state_ablation: tuple[str, ...] = ("A+", "D")
    bootstrap: int = Field(2000, ge=100)
    workers: int = Field(2, ge=1)
    # what labelling and the closed loop simulate under (env.physics.PHYSICS); versions 1 and 2 ran
    # under ``exact``, and a configuration that leaves it there resolves as it did before the key
    physics: str = "exact"
    label_store: Path = Path("assets/transfer/labels.parquet")
    reuse_labels: tuple[Path, ...] = (  # label files of the recovery-task issue: their scenes count as done
        Path("assets/policy/labels/per_tag40.parquet"),
        Path("assets/policy/labels/cell_can.parquet"),
        Path("assets/policy/labels/cell_box.parquet"),
    )
    path_store: Path = Path("assets/transfer/paths.jsonl")
    # the retrieval head the evaluated policies see through (None: the oracle's masks, version 1)
    retrieval: Path | None = None
    cache: Path = Path("runs/transfer/cache")
    batches: Path | None = None  # D's and E's generated scenes, C's calibration (None: cache/batches)
    out: Path = Path("assets/transfer/result")
    manifest: Path | None = Path("data_manifest.yaml")

    @field_validator("tags", "primitives")
    @classmethod
    def _known(cls, values, info):
        allowed = PANEL_TAGS if info.field_name == "tags" else tuple(PRIMITIVES)
        unknown = [v for v in values if v not in allowed]
        if unknown or not values:
            raise ValueError(f"{unknown or 'none'}: choose from {', '.join(allowed)}")
        return values

    @field_validator("physics")
    @classmethod
    def _physics(cls, name):
        from scenegen.env.physics import PHYSICS

        if name not in PHYSICS:
            raise ValueError(f"{name!r}: choose from {', '.join(PHYSICS)}")
        return name

    def unset_defaults(self) -> set[str]:
        """Keys left out of the resolved configuration when they hold what runs before them did."""
        return {"physics"} if self.physics == "exact" else set()

    @field_validator("alpha", "alpha_sweep")
    @classmethod
    def _finite(cls, value):
        values = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError("alpha must be a finite number >= 0")
        return value

    @field_validator("state_ablation")
    @classmethod
    def _arms(cls, arms):
        unknown = [a for a in arms if a not in ARMS]
        if unknown:
            raise ValueError(f"{unknown}: arms are {', '.join(ARMS)}")
        return arms


class HeadSettings(_Strict):
    """Version 2: the retrieval head every arm trains on its own annotated scenes (the design's
    defaults unless step counts are given, for a tiny run)."""

    design: Literal["instances", "candidates"] = "instances"
    classifier_steps: int | None = Field(None, ge=1)
    separator_steps: int | None = Field(None, ge=1)

    def steps(self) -> dict:
        """The step counts given (retrieval_curves.train_head's ``steps``)."""
        counts = {"classifier": self.classifier_steps, "separator": self.separator_steps}
        return {k: v for k, v in counts.items() if v is not None}


class Shift(_Strict):
    """One condition the perturbed arms are also evaluated under (version 2): the lights scaled by
    ``light_scale`` and/or a depth ``sensor``'s errors (render/sensor.py), at evaluation only."""

    name: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    light_scale: float = Field(1.0, gt=0, le=3)
    sensor: Literal["structured_light", "active_stereo"] | None = None


class PlanGridSettings(_Strict):
    """Version 2: the resolution every evaluated plan is executed at (manipulation/primitives.py,
    ``PlanGrid``): positions to ``metres``, directions to ``degrees``. Heads whose plans fall in one
    cell execute one attempt, which the sequence store then serves to all (the cost lever of issue
    45, point 5); the expert labels and the choosers' training stay as planned."""

    metres: float = Field(gt=0, le=0.02)
    degrees: float = Field(gt=0, le=15)

    def grid(self):
        from scenegen.manipulation.primitives import PlanGrid

        return PlanGrid(self.metres, self.degrees)


class Perturbations(_Strict):
    """Version 2: the ``shifts`` every run of ``arms`` whose seed is in ``seeds`` (None: every
    training seed) is also evaluated under, on the rare panels, through its head and (with
    ``oracle_rows``) true masks."""

    shifts: tuple[Shift, ...] = (
        Shift(name="dim_light", light_scale=0.35),
        Shift(name="depth_noise", sensor="structured_light"),
    )
    arms: tuple[str, ...] | None = None  # None: those of A+, C and D that run
    seeds: tuple[int, ...] | None = None

    @field_validator("shifts")
    @classmethod
    def _named_once(cls, shifts):
        names = [s.name for s in shifts]
        if len(set(names)) < len(names) or "nominal" in names:
            raise ValueError(f"{names}: each shift needs its own name, not nominal")
        return shifts


V2_TAGS = tuple(t for t in PANEL_TAGS if t != "under_overhang")  # version 2's panels: no under_overhang


class TransferConfigV2(TransferConfig):
    """Version 2 (issue 45; docs/transfer.md): each arm and seed trains its own retrieval head and its
    chooser through that head's masks, and is evaluated through it on one ``side`` of the version 2
    panels (``panel_names``: which of its panels, None: all; ``per_panel``: the first N layouts of
    each, for a tiny run; ``panel_sizes``: the first N of the panels named, the cut order's
    "common panel to its first 50"); ``oracle_rows``: each chooser also through true masks, the
    panel's ceiling (``oracle_seeds``: only the runs of these seeds, None: all). ``arms``: the arms
    run (the pilot: A+ and C); ``arm_seeds``: fewer training seeds for the arms named (the cut
    order's "A, B and E to 3 seeds"); ``perturbations``: the shifts evaluated (None: none);
    ``plan_grid``: the resolution evaluated plans are executed at (None: as planned); ``parts``: where
    trained heads and choosers are kept (storage, like ``cache``: not part of what is run). Version
    1's keys that version 2 does not use (``V1_ONLY``) are refused unless at their version 2
    default, so none is silently ignored."""

    version: Literal[2] = 2
    tags: tuple[str, ...] = V2_TAGS  # C's extra layouts and D's and E's requests: the tags with a panel
    panels: Path = PANELS_V2_FILE
    side: Literal["validation", "test"] = "validation"
    panel_names: tuple[str, ...] | None = None
    per_panel: int | None = Field(None, ge=1)  # the first N layouts of each panel (None: all)
    panel_sizes: dict[str, int] = {}
    arms: tuple[str, ...] = ARMS
    arm_seeds: dict[str, tuple[int, ...]] = {}
    head: HeadSettings = HeadSettings()
    oracle_rows: bool = True
    oracle_seeds: tuple[int, ...] | None = None
    perturbations: Perturbations | None = None
    plan_grid: PlanGridSettings | None = None
    alpha_sweep: tuple[float, ...] = ()
    state_ablation: tuple[str, ...] = ()
    perturbation: Perturbation | None = None
    manifest: Path | None = None
    # where trained heads and choosers are kept (None: the cache): a folder committed beside the
    # artifact lets a run resumed on a fresh machine continue on the same parts without retraining
    parts: Path | None = None

    def parts_folder(self) -> Path:
        return Path(self.parts or self.cache)

    @field_validator("arms")
    @classmethod
    def _known_arms(cls, arms):
        unknown = [a for a in arms if a not in ARMS]
        if unknown or not arms:
            raise ValueError(f"{unknown or 'none'}: arms are {', '.join(ARMS)}")
        if len(set(arms)) < len(arms):
            raise ValueError(f"{list(arms)}: an arm named twice would count twice")
        return arms

    @model_validator(mode="after")
    def _version_2_keys(self):
        if len(set(self.training.seeds)) < len(self.training.seeds):
            raise ValueError(
                f"training.seeds {list(self.training.seeds)}: a seed named twice would count twice"
            )
        seeds = set(self.training.seeds)
        for key, value in (
            *((f"arm_seeds.{a}", v) for a, v in self.arm_seeds.items()),
            ("oracle_seeds", self.oracle_seeds or ()),
            ("perturbations.seeds", (self.perturbations and self.perturbations.seeds) or ()),
        ):
            if not set(value) <= seeds:
                raise ValueError(f"{key}: {list(value)}: seeds of training.seeds {sorted(seeds)} only")
        for arm, chosen in self.arm_seeds.items():
            if not chosen or len(set(chosen)) < len(chosen):
                raise ValueError(f"arm_seeds.{arm}: {list(chosen)}: at least one seed, each named once")
        for key, arms in (("arm_seeds", self.arm_seeds), ("perturbations.arms", self.perturbed_arms())):
            if not set(arms) <= set(self.arms):
                raise ValueError(f"{key}: {sorted(set(arms) - set(self.arms))} not among arms")
        if any(n < 1 for n in self.panel_sizes.values()):
            raise ValueError(f"panel_sizes {self.panel_sizes}: at least 1 layout each")
        used = [k for k in V1_ONLY if getattr(self, k) != TransferConfigV2.model_fields[k].default]
        if used:
            raise ValueError(f"{', '.join(used)}: not used by version 2 yet; remove them")
        return self

    def seeds_of(self, arm: str) -> tuple[int, ...]:
        return self.arm_seeds.get(arm, self.training.seeds)

    def perturbed_arms(self) -> tuple[str, ...]:
        if self.perturbations is None:
            return ()
        asked = self.perturbations.arms
        return asked if asked is not None else tuple(a for a in ("A+", "C", "D") if a in self.arms)


# version 1's keys that version 2 does not use (yet): refused when set
V1_ONLY = ("retrieval", "rare_per_tag", "common", "alpha_sweep", "state_ablation", "perturbation")


def load_transfer_config(path: Path | None, overrides: dict | None = None) -> TransferConfig:
    """The configuration in ``path`` (None: the defaults) with top-level ``overrides``."""
    raw: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise TransferConfigError(f"{path}: no such file; the default is pipelines/transfer.yaml")
        try:
            raw = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        except (OSError, UnicodeDecodeError) as exc:
            raise TransferConfigError(
                f"{path}: cannot read it as a text file ({exc.__class__.__name__})"
            ) from None
        except yaml.YAMLError as exc:
            raise TransferConfigError(f"{path}: not valid YAML ({getattr(exc, 'problem', exc)})") from None
        if not isinstance(raw, dict):
            raise TransferConfigError(f"{path}: a transfer configuration is a mapping of keys")
    raw.update({k: v for k, v in (overrides or {}).items() if v is not None})
    kind = TransferConfigV2 if raw.get("version") == 2 else TransferConfig
    if raw.get("version") not in (None, 1, 2):
        raise TransferConfigError(f"{path or 'configuration'}: version: 1 or 2, not {raw['version']!r}")
    if raw.get("version") == 1:
        raw.pop("version")
    try:
        return kind.model_validate(raw)
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(p) for p in error["loc"]) or "(top level)"
        message = error["msg"].removeprefix("Value error, ")
        raise TransferConfigError(f"{path or 'configuration'}: {where}: {message}"[:300]) from None


def check_inputs(config: TransferConfig) -> None:
    """The files a configuration names exist and its recipes validate; TransferConfigError (one
    line, naming the key) otherwise. Called before the run writes anything."""
    from scenegen.runner.config import ConfigError, load_pipeline

    for key, path in (("reference", config.reference), ("panels", config.panels)):
        if not Path(path).is_file():
            raise TransferConfigError(f"{key}: {path}: no such file")
    for i, path in enumerate(config.reuse_labels):
        if not Path(path).is_file():
            raise TransferConfigError(f"reuse_labels.{i}: {path}: no such label file")
    if config.retrieval is not None:
        from scenegen.core.files import CheckpointError
        from scenegen.perception.retrieval.perceive import RetrievalPerception

        try:
            RetrievalPerception.load(config.retrieval)
        except CheckpointError as exc:
            raise TransferConfigError(f"retrieval: {exc}") from None
    for key in ("recipe", "diffusion"):
        try:
            recipe = load_pipeline(getattr(config.generation, key))
        except ConfigError as exc:
            raise TransferConfigError(f"generation.{key}: {exc}") from None
        if key == "diffusion" and recipe.proposer.kind != "diffusion":
            raise TransferConfigError(
                f"generation.diffusion: a {recipe.proposer.kind} recipe; name one of the diffusion proposer"
            )
