"""Data manifest v1: the ledger of where data came from (data_manifest.yaml and each batch's manifest).

Counts are derived from the files of a batch, never typed by hand; manifests are written atomically.
Which fields a source must have depends on its origin: a ``synthetic`` source names its generator,
pipeline and seed; ``reference`` stands in for real data and says so; ``real`` names where it came from.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from scenegen import __version__
from scenegen.store import INDEX, REJECTIONS, atomic_write, read_jsonl

SCHEMA_VERSION = 1


class Counts(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scenes: int = Field(ge=0)  # stored scenes (directories with a scene.json)
    rejected: int = Field(0, ge=0)  # rows of the rejection log
    proposals: int = Field(0, ge=0)  # scenes + rejected


class Source(BaseModel):
    """One data source in a manifest."""

    model_config = ConfigDict(extra="forbid")
    name: str
    origin: Literal["real", "reference", "synthetic"]
    location: str  # directory or file, relative to the manifest's folder
    sha256: str | None = None  # of the file, for a single-file source (a Parquet table)
    counts: Counts
    description: str = ""
    generator: dict | None = None  # synthetic: proposer kind and settings
    pipeline: dict | None = None  # synthetic: name, sha256 of the resolved recipe
    seed: int | None = None
    rejections_by_label: dict[str, int] = Field(default_factory=dict)
    catalog_sha256: str | None = None
    predicate_version: str | None = None  # scenegen.tags.PREDICATE_VERSION of the tags in this source
    scenegen_version: str = __version__

    @model_validator(mode="after")
    def _required_by_origin(self):
        if self.origin == "synthetic":
            missing = [f for f in ("generator", "pipeline", "seed") if getattr(self, f) is None]
            if missing:
                raise ValueError(f"source {self.name!r}: a synthetic source needs {', '.join(missing)}")
        if self.origin == "reference" and "stands in" not in self.description:
            raise ValueError(
                f"source {self.name!r}: a reference source must say what real data it stands in for"
            )
        return self


class Manifest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    schema_version: Literal[1] = SCHEMA_VERSION
    kind: Literal["project", "batch"]
    sources: list[Source] = Field(default_factory=list)


def batch_source(
    batch: Path,
    name: str,
    pipeline: dict,
    generator: dict,
    seed: int,
    catalog_sha: str,
    predicate_version: str,
) -> Source:
    """A synthetic source describing a batch directory, with counts derived from its files."""
    scenes = sum(1 for d in batch.iterdir() if d.is_dir() and (d / "scene.json").is_file())
    rejections = read_jsonl(batch / REJECTIONS)
    labels = Counter(r["label"] for r in rejections)
    indexed = len(read_jsonl(batch / INDEX))
    if indexed != scenes:
        raise ValueError(f"{batch}: {scenes} scene directories but {indexed} index rows")
    return Source(
        name=name,
        origin="synthetic",
        location=".",
        counts=Counts(scenes=scenes, rejected=len(rejections), proposals=scenes + len(rejections)),
        generator=generator,
        pipeline=pipeline,
        seed=seed,
        rejections_by_label=dict(sorted(labels.items())),
        catalog_sha256=catalog_sha,
        predicate_version=predicate_version,
    )


def write_manifest(path: Path, manifest: Manifest) -> None:
    header = (
        f"# scenegen data manifest, schema v{SCHEMA_VERSION} (scenegen/manifest.py). Counts from files.\n"
    )
    atomic_write(path, header + yaml.safe_dump(manifest.model_dump(mode="json"), sort_keys=False, width=100))


def read_manifest(path: Path) -> Manifest:
    return Manifest(**yaml.safe_load(Path(path).read_text()))


def register_source(path: Path, source: Source) -> Manifest:
    """Add ``source`` to the project manifest at ``path`` (replacing one of the same name), atomically."""
    path = Path(path)
    manifest = read_manifest(path) if path.is_file() else Manifest(kind="project")
    sources = [s for s in manifest.sources if s.name != source.name]
    manifest = manifest.model_copy(update={"sources": [*sources, source]})
    write_manifest(path, manifest)
    return manifest
