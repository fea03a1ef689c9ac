"""Manifest entries derived from files: counts, checksums, provenance. Nothing here is typed by hand.

- :func:`batch_checksum`: the checksum chain of a batch directory (index, rejection log, recipe).
- :func:`batch_source`: the ``synthetic`` source of a batch directory written by ``run_batch``.
- :func:`checkpoint_ref`: a generator checkpoint directory's hashes and versions.
- :func:`effective_shares`: the share of the loss each source of a training mixture receives.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
from collections import Counter
from pathlib import Path

from scenegen.manifest.schema import (
    BatchChecksum,
    CheckpointRef,
    Counts,
    Generator,
    Guidance,
    PipelineRef,
    RecipeComponent,
    SeedPanel,
    Source,
)
from scenegen.paths import PROJECT_ROOT
from scenegen.store.batch import INDEX, REJECTIONS, read_jsonl, sha256_file

RECIPE_FILE = "pipeline.yaml"
CHAINED_FILES = (INDEX, REJECTIONS, RECIPE_FILE)  # what a batch's checksum root covers directly
# Packages whose versions shape a stored scene (stamped into each scene.json), and those of a batch.
SCENE_PACKAGES = (
    "mujoco",
    "robosuite",
    "trimesh",
    "coacd",
    "python-fcl",
    "numpy",
    "pydantic",
    "opencv-python-headless",
)
PACKAGES = ("torch", *SCENE_PACKAGES)


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """Installed versions of ``names`` (default: every package that shapes a batch), in that order."""
    return dict(_versions(names))


@functools.lru_cache(maxsize=8)
def _versions(names: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    # read once per process: each lookup parses the package's METADATA (~5 ms per scene record)
    return tuple((name, importlib.metadata.version(name)) for name in names)


def checksum_root(files: dict[str, str]) -> str:
    """sha256 of the lines ``"<sha256>  <name>\\n"``, sorted by name."""
    text = "".join(f"{sha}  {name}\n" for name, sha in sorted(files.items()))
    return hashlib.sha256(text.encode()).hexdigest()


def batch_checksum(batch: Path) -> BatchChecksum:
    """The checksum chain of a batch: the sha256 of its index, rejection log and recipe, and their root.

    Each scene's files are hashed in its scene.json and each scene.json in its index row, so the root
    covers every stored byte.
    """
    files = {name: sha256_file(Path(batch) / name) for name in CHAINED_FILES}
    return BatchChecksum(files=files, root=checksum_root(files))


def checkpoint_ref(path: str) -> CheckpointRef:
    """Hashes and versions of a checkpoint directory (``path`` as recipes name it: relative to the
    project root, or absolute)."""
    directory = Path(path) if Path(path).is_absolute() else PROJECT_ROOT / path
    config = json.loads((directory / "config.json").read_text())
    return CheckpointRef(
        path=path,
        sha256=sha256_file(directory / "model.safetensors"),
        config_sha256=sha256_file(directory / "config.json"),
        predicate_version=config["predicate_version"],
        encoding_version=config.get("encoding", {}).get("version", 1),
    )


def generator_entry(proposer) -> Generator:
    """The generator entry of a recipe's proposer settings (``PipelineConfig.proposer``)."""
    settings = proposer.model_dump(mode="json")
    if proposer.kind != "diffusion":
        return Generator(kind=proposer.kind, settings=settings)
    return Generator(
        kind="diffusion",
        settings=settings,
        checkpoint=checkpoint_ref(proposer.checkpoint),
        guidance=Guidance(
            guidance_weight=proposer.guidance,
            cost_weight=proposer.cost_weight,
            request_cost=proposer.request_cost,
            steps=proposer.steps,
            unconditional=proposer.unconditional,
        ),
    )


def count_scenes(batch: Path) -> int:
    """Scene directories of a batch that hold a scene.json."""
    return sum(1 for d in Path(batch).glob("scene_*") if d.is_dir() and (d / "scene.json").is_file())


def batch_source(
    batch: Path, config, catalog_sha: str, predicate_version: str, name: str | None = None
) -> Source:
    """The ``synthetic`` source describing a batch directory, every count and checksum read from its
    files. ``config``: the batch's ``PipelineConfig``. Raises ValueError when the directory disagrees
    with its own index (a batch that a killed run left behind: rerun its command to repair it)."""
    batch = Path(batch)
    scenes = count_scenes(batch)
    index = read_jsonl(batch / INDEX)
    rejections = read_jsonl(batch / REJECTIONS)
    if len(index) != scenes:
        raise ValueError(f"{batch}: {scenes} scene directories but {len(index)} index rows")
    last = max((row["proposal_index"] for row in [*index, *rejections]), default=-1)
    return Source(
        name=name or config.name,
        origin="synthetic",
        location=".",
        description=f"scenes of pipeline {config.name!r}, request {config.condition.model_dump(mode='json')}",
        counts=Counts(scenes=scenes, rejected=len(rejections), proposals=scenes + len(rejections)),
        checksums=batch_checksum(batch),
        predicate_version=predicate_version,
        catalog_sha256=catalog_sha,
        generator=generator_entry(config.proposer),
        pipeline=PipelineRef(name=config.name, file=RECIPE_FILE, sha256=config.digest()),
        seed_panel=SeedPanel(seed=config.seed, first_index=0, last_index=last),
        packages=package_versions(),
        rejections_by_label=dict(sorted(Counter(r["label"] for r in rejections).items())),
        rendered=bool(config.render),
        sensor=sensor_entry(config),
    )


def sensor_entry(config) -> dict[str, str] | None:
    """The recipe's depth sensor as a manifest and a scene.json record it: name and version (the key
    of what decides its frames); None for exact depth only."""
    if not config.render or config.sensor == "exact":
        return None
    from scenegen.render.sensor import SENSORS

    return {"name": config.sensor, "version": SENSORS[config.sensor].key()}


def effective_shares(
    alpha: float, components: list[RecipeComponent], sizes: dict[str, int]
) -> dict[str, float]:
    """Share of the loss's total weight per source for loss = E_real[l] + alpha * E_synthetic[l].

    ``sizes``: samples each component contributes (by source name). Within a role, sources are
    concatenated, so a source's share of its role is its share of that role's samples. Rounded to 6
    decimals; the shares sum to 1.
    """
    role_weight = {"real": 1.0 / (1.0 + alpha), "synthetic": alpha / (1.0 + alpha)}
    totals = Counter()
    for c in components:
        totals[c.role] += sizes[c.source]
    shares = {}
    for c in components:
        share = role_weight[c.role] * sizes[c.source] / totals[c.role] if totals[c.role] else 0.0
        shares[c.source] = round(share, 6)
    return shares
