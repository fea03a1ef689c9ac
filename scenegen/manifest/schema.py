"""Data manifest v2: the schema of data_manifest.yaml and of each batch's manifest.yaml.

One ledger for every source of scenes a trainer may use: where it came from (``origin``: ``real``,
``reference``, which stands in for real data and says so, or ``synthetic``), how many samples it holds
and their checksums (derived from the files, never typed by hand), how to replay it, how it is
weighted in training, whether it passed its realism checks, why proposals were rejected, and what it
did for the downstream policy. Which fields a source must carry depends on its origin (see
:class:`Source`). ``scenegen audit`` (scenegen/audit/manifest.py) trusts none of it and verifies all
of it against the files. The JSON Schema is exported to docs/manifest.schema.json.

Paths (``location``, checkpoint ``path``) are relative to the folder of the manifest that holds them
and must stay inside it.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from scenegen import __version__

SCHEMA_VERSION = 2
SHA256 = Field(pattern=r"^[0-9a-f]{64}$")
Origin = Literal["real", "reference", "synthetic"]
RealismMetric = Literal["layout_c2st", "layout_mmd", "image_stats"]
# The realism checks a synthetic source must carry (image_stats only when the batch is rendered).
REQUIRED_REALISM: tuple[str, ...] = ("layout_c2st", "layout_mmd")


class _Entry(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Counts(_Entry):
    """Sample counts, derived from the files: stored scenes (or Parquet rows), rejected proposals."""

    scenes: int = Field(ge=0)  # stored scenes (directories with a scene.json) or table rows
    rejected: int = Field(0, ge=0)  # rows of the rejection log
    proposals: int = Field(0, ge=0)  # scenes + rejected
    splits: dict[str, int] | None = None  # rows per split (train / heldout) of a table

    @model_validator(mode="after")
    def _consistent(self):
        if self.proposals != self.scenes + self.rejected:
            raise ValueError(
                f"proposals ({self.proposals}) must equal scenes + rejected ({self.scenes + self.rejected})"
            )
        if self.splits is not None and sum(self.splits.values()) != self.scenes:
            raise ValueError(f"splits {self.splits} must sum to scenes ({self.scenes})")
        return self


class FileChecksum(_Entry):
    """The sha256 of a single-file source (a Parquet table)."""

    kind: Literal["file"] = "file"
    sha256: str = SHA256


class BatchChecksum(_Entry):
    """Checksums of a batch directory, as a chain: every scene's files are hashed in its scene.json,
    every scene.json in its index.jsonl row, and the index, the rejection log and the recipe here.
    ``root`` is the sha256 of the lines ``"<sha256>  <file>\\n"`` of ``files``, sorted by file name:
    one value that changes when any stored byte does (realism checks record it)."""

    kind: Literal["batch"] = "batch"
    files: dict[str, str]  # index.jsonl, rejections.jsonl, pipeline.yaml -> sha256
    root: str = SHA256


Checksums = Annotated[FileChecksum | BatchChecksum, Field(discriminator="kind")]


class PipelineRef(_Entry):
    """The recipe that replays a source: its file (relative to the source's location for a batch,
    to the manifest's folder otherwise) and the sha256 of its resolved content
    (``PipelineConfig.digest()``)."""

    name: str
    file: str
    sha256: str = SHA256


class CheckpointRef(_Entry):
    """A generator checkpoint directory and the hashes of its two files."""

    path: str  # relative to the project root (scenegen.paths.PROJECT_ROOT), as recipes name it
    sha256: str = SHA256  # of model.safetensors
    config_sha256: str = SHA256  # of config.json
    predicate_version: str
    encoding_version: int = Field(ge=1)


class Guidance(_Entry):
    """Sampling settings of the diffusion generator (eps~ = (1 + w) eps(x, t, c) - w eps(x, t, null))."""

    guidance_weight: float = Field(ge=0.0)  # w
    cost_weight: float = Field(ge=0.0)
    request_cost: float = Field(ge=0.0)
    steps: int = Field(ge=1)
    unconditional: bool = False


class Generator(_Entry):
    """What proposed the scenes: the proposer kind, its settings, and for the diffusion generator the
    checkpoint and the guidance."""

    kind: str
    settings: dict = Field(default_factory=dict)
    checkpoint: CheckpointRef | None = None
    guidance: Guidance | None = None

    @model_validator(mode="after")
    def _diffusion_needs_checkpoint(self):
        if self.kind == "diffusion" and (self.checkpoint is None or self.guidance is None):
            raise ValueError("a diffusion generator needs its checkpoint and guidance")
        return self


class SeedPanel(_Entry):
    """The random streams a source used: proposal i drew from SeedSequence([seed, i]) for i in
    [first_index, last_index]."""

    seed: int = Field(ge=0)
    first_index: int = Field(0, ge=0)
    last_index: int = Field(ge=-1)  # -1: no proposal was made


class RealismReference(_Entry):
    """What a realism check compared against: a manifest source (or committed file), its checksum and
    the subset of it that was used."""

    source: str
    sha256: str = SHA256
    subset: str = "all"


class RealismCheck(_Entry):
    """One realism check of one source: ``value`` compared with ``threshold`` (``comparison``).

    ``status`` is ``passed`` or ``failed``, or ``insufficient`` when the source holds fewer samples
    than ``min_samples`` or the reference none (objects of a user catalog: the check is then recorded,
    but says nothing). ``batch_sha256`` is the
    checksum root of the source when the check was computed: a check copied from another batch, or a
    batch changed after its check, no longer matches.
    """

    metric: RealismMetric
    value: float
    threshold: float
    comparison: Literal["<=", ">="] = "<="
    status: Literal["passed", "failed", "insufficient"]
    batch_sha256: str = SHA256
    reference: RealismReference
    samples: dict[str, int]  # batch, reference
    min_samples: int = Field(ge=1)
    settings: dict = Field(default_factory=dict)
    details: dict = Field(default_factory=dict)

    def holds(self) -> bool:
        """Whether value meets threshold under the comparison."""
        return self.value <= self.threshold if self.comparison == "<=" else self.value >= self.threshold

    @model_validator(mode="after")
    def _status_agrees(self):
        if self.samples.get("batch", 0) < self.min_samples or self.samples.get("reference") == 0:
            if self.status != "insufficient":
                raise ValueError(
                    f"{self.metric}: {self.samples.get('batch', 0)} samples < min_samples "
                    f"{self.min_samples}, or no reference samples, so its status must be 'insufficient'"
                )
        elif self.status != ("passed" if self.holds() else "failed"):
            raise ValueError(
                f"{self.metric}: status {self.status!r} disagrees with value {self.value} "
                f"{self.comparison} threshold {self.threshold}"
            )
        return self


class Source(_Entry):
    """One source of scenes.

    Required by origin:
    - ``synthetic``: ``checksums`` of kind batch, ``generator`` (diffusion: with checkpoint and
      guidance), ``pipeline``, ``seed_panel``, ``packages``, ``predicate_version``; realism checks
      (``layout_c2st``, ``layout_mmd``, and ``image_stats`` when rendered) are required by the audit.
    - ``reference``: a description that says what real data it ``stands in`` for, ``generator``,
      ``pipeline``, ``seed_panel``, ``predicate_version``.
    - ``real``: ``collection`` (who measured it, where, how); no generator.
    """

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    origin: Origin
    location: str  # directory or file, relative to the manifest's folder
    description: str = ""
    counts: Counts
    checksums: Checksums
    predicate_version: str | None = None  # scenegen.tags.predicates.PREDICATE_VERSION of the stored tags
    catalog_sha256: str | None = None
    generator: Generator | None = None
    pipeline: PipelineRef | None = None
    seed_panel: SeedPanel | None = None
    packages: dict[str, str] | None = None  # versions of the packages that made it
    rejections_by_label: dict[str, int] = Field(default_factory=dict)
    rendered: bool = False  # scenes carry RGB images (then image_stats is a required realism check)
    # a depth sensor's frames stored beside the exact depth: {name, version} (docs/sensor.md); None: none
    sensor: dict[str, str] | None = None
    collection: str | None = None  # real: how the data was measured
    realism: list[RealismCheck] = Field(default_factory=list)
    scenegen_version: str = __version__

    @model_validator(mode="after")
    def _required_by_origin(self):
        needed = {
            "synthetic": ("generator", "pipeline", "seed_panel", "packages", "predicate_version"),
            "reference": ("generator", "pipeline", "seed_panel", "predicate_version"),
            "real": ("collection",),
        }[self.origin]
        missing = [f for f in needed if getattr(self, f) is None]
        if missing:
            raise ValueError(f"source {self.name!r}: a {self.origin} source needs {', '.join(missing)}")
        if (self.origin == "synthetic") != (self.checksums.kind == "batch"):
            raise ValueError(
                f"source {self.name!r}: a synthetic source is a batch directory, and a batch directory is "
                "synthetic (origin, checksums.kind)"
            )
        if self.origin == "reference" and "stands in" not in self.description:
            raise ValueError(
                f"source {self.name!r}: a reference source must say what real data it stands in for"
            )
        if self.origin == "real" and self.generator is not None:
            raise ValueError(f"source {self.name!r}: a real source has no generator")
        if sum(self.rejections_by_label.values()) != self.counts.rejected:
            raise ValueError(
                f"source {self.name!r}: rejections_by_label sum to {sum(self.rejections_by_label.values())}, "
                f"counts.rejected is {self.counts.rejected}"
            )
        return self


class RecipeComponent(_Entry):
    """One source in a training mixture; ``role`` says which expectation of the loss it feeds."""

    source: str
    role: Literal["real", "synthetic"]
    split: str | None = None  # a table's split (train / heldout); None: all of it


class TrainingRecipe(_Entry):
    """A training mixture: loss = E_real[l] + alpha * E_synthetic[l].

    Within each role, sources are concatenated (a source's weight is its share of that role's
    samples). ``effective_shares`` is the share of the loss's total weight each source receives,
    (1 / (1 + alpha)) * n_i / n_real for a real-role source and (alpha / (1 + alpha)) * n_i / n_synthetic
    for a synthetic-role one; ``manifest.recipes.effective_shares`` derives it and the audit recomputes
    it. ``rebalance`` records any re-weighting inside a source (e.g. the generator's oversampling of
    rare layouts to ``rare_share``).
    """

    name: str
    purpose: str
    alpha: float = Field(ge=0.0)
    components: list[RecipeComponent] = Field(min_length=1)
    effective_shares: dict[str, float]
    rebalance: dict = Field(default_factory=dict)

    @field_validator("alpha")
    @classmethod
    def _finite(cls, alpha: float) -> float:
        if not math.isfinite(alpha):
            raise ValueError("alpha must be a finite number >= 0 (loss = E_real[l] + alpha * E_synthetic[l])")
        return alpha

    @model_validator(mode="after")
    def _roles(self):
        roles = {c.role for c in self.components}
        if "real" not in roles:
            raise ValueError(f"recipe {self.name!r}: needs a real-role component (E_real[l])")
        if self.alpha > 0 and "synthetic" not in roles:
            raise ValueError(f"recipe {self.name!r}: alpha {self.alpha} > 0 but no synthetic component")
        return self


class ModelEntry(_Entry):
    """A trained model the project ships, with the recipe it was trained with."""

    name: str
    kind: Literal["diffusion_generator", "policy"]
    checkpoint: CheckpointRef
    recipe: str  # a TrainingRecipe name
    steps: int = Field(ge=0)


class TransferOutcome(_Entry):
    """What the data did for the downstream policy. ``panel`` says whether the evaluation panel is
    real or simulated (simulated stand-ins for real rare cases must say so)."""

    status: Literal["pending", "measured"]
    panel: Literal["real", "simulated"]
    note: str
    recipe: str | None = None
    metrics: dict = Field(default_factory=dict)
    artifact: str | None = None  # the experiment's artifact folder, relative to the manifest
    artifact_sha256: str | None = None  # core.files.folder_sha256 of that folder

    @model_validator(mode="after")
    def _measured_has_numbers(self):
        if self.status == "measured" and (
            not self.metrics or (self.recipe is None and self.artifact is None)
        ):
            raise ValueError("a measured transfer outcome names its metrics and its recipe or artifact")
        if (self.artifact is None) != (self.artifact_sha256 is None):
            raise ValueError("an artifact and its artifact_sha256 come together")
        return self


class Datasheet(_Entry):
    """Datasheet-style fields: what the data is for and where it is known to fall short."""

    intended_use: str
    known_limitations: list[str] = Field(min_length=1)
    out_of_scope: list[str] = Field(default_factory=list)


class Manifest(_Entry):
    """A project manifest (data_manifest.yaml) or a batch's manifest.yaml."""

    schema_version: Literal[2] = SCHEMA_VERSION
    kind: Literal["project", "batch"]
    datasheet: Datasheet | None = None
    sources: list[Source] = Field(default_factory=list)
    models: list[ModelEntry] = Field(default_factory=list)
    recipes: list[TrainingRecipe] = Field(default_factory=list)
    transfer: TransferOutcome | None = None

    @model_validator(mode="after")
    def _project_fields(self):
        if self.kind == "project" and (self.datasheet is None or self.transfer is None):
            raise ValueError("a project manifest needs a datasheet and a transfer section")
        if self.kind == "batch" and len(self.sources) != 1:
            raise ValueError(f"a batch manifest describes one source, not {len(self.sources)}")
        for what, names in (
            ("source", [s.name for s in self.sources]),
            ("model", [m.name for m in self.models]),
            ("recipe", [r.name for r in self.recipes]),
        ):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"{what} names must be unique; repeated: {', '.join(dup)}")
        return self
