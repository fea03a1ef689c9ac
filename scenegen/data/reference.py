"""The reference dataset: a stand-in for real data, built from the procedural proposer.

Layouts go through the same check, settle and tag stages as any batch (no rendering, no MJCF) and
are stored compactly as one Parquet table, one row per accepted layout, in proposal-index order.
Each layout's request (task, target category) is drawn from its own seed, so the set covers every
(task x target) and the rare tags occur at their natural rates under the recipe's distributions.
Every fifth layout by proposal index is held out for evaluation (``split`` column).

It stands in for real data and says so: its manifest entry has origin ``reference``.
"""

from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from scenegen.analysis.realism import HELDOUT_EVERY, layout_row  # noqa: F401 - both are part of this module's face
from scenegen.assets.catalog import using_catalogs
from scenegen.core.files import sha256_file
from scenegen.runner.config import PipelineConfig
from scenegen.runner.executors import LOCAL, Backend, ordered_outcomes
from scenegen.runner.pipeline import make_proposer
from scenegen.schema.condition import ROBOT_POSES, TAGS, TASKS, Condition
from scenegen.schema.scene import SceneProposal
from scenegen.tags.predicates import PREDICATE_VERSION


def request_for(config: PipelineConfig, index: int, categories: tuple[str, ...]) -> Condition:
    """The (task, target, robot pose) of reference layout ``index``: each uniform over the task
    registry, the catalog's categories and the named robot poses, from SeedSequence([seed, index, 1])."""
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, index, 1]))
    tasks, poses = sorted(TASKS), sorted(ROBOT_POSES)
    return Condition(
        task=tasks[int(rng.integers(len(tasks)))],
        target=categories[int(rng.integers(len(categories)))],
        robot_pose=poses[int(rng.integers(len(poses)))],
    )


def _proposals(config: PipelineConfig) -> Iterator[SceneProposal]:
    catalog = config.catalog()
    proposer = make_proposer(config, catalog)
    for index in range(config.proposal_cap):
        yield from proposer.propose(request_for(config, index, catalog.categories), [index], config.seed)


def build_reference(
    config: PipelineConfig, out: Path, workers: int = 1, progress: bool = True, backend: Backend = LOCAL
) -> dict:
    """Generate ``config.n`` accepted reference layouts into the Parquet file ``out`` (atomically),
    with ``workers`` workers of ``backend``."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    if config.render:
        config = config.model_copy(update={"render": False})
    rows, rejections = [], Counter()
    bar = tqdm(total=config.n, desc=f"reference {config.name}", unit="layout", disable=not progress)
    outcomes = ordered_outcomes(_proposals(config), config, workers, export=False, backend=backend)
    proposals = 0
    with using_catalogs([Path(c) for c in config.catalogs]):  # requests of user categories are valid
        try:
            for outcome in outcomes:
                proposals = outcome.proposal_index + 1
                if outcome.record is None:
                    rejections[outcome.rejection.label] += 1
                    continue
                rows.append(layout_row(outcome.record))
                bar.update(1)
                if len(rows) == config.n:
                    break
        finally:
            outcomes.close()
            bar.close()
    metadata = {
        "scenegen.reference": "stands in for real data: procedural layouts through check, settle and tag",
        "predicate_version": PREDICATE_VERSION,
        "pipeline_sha256": config.digest(),
        "catalog_sha256": config.catalog().sha256,
        **({"catalogs": json.dumps(list(config.catalogs))} if config.catalogs else {}),
        "seed": str(config.seed),
        "proposals": str(proposals),
        "rejections": ",".join(f"{k}={v}" for k, v in sorted(rejections.items())),
    }
    table = pa.Table.from_pylist(rows).replace_schema_metadata(metadata)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    pq.write_table(table, tmp, compression="zstd")
    os.replace(tmp, out)
    return {"rows": len(rows), "proposals": proposals, "rejections": dict(rejections), **metadata}


def read_reference(path: Path):
    """The reference table (pyarrow.Table) and its metadata."""
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    return table, {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}


def tag_rates(table) -> dict[str, tuple[int, float]]:
    """Per tag: (count of rows holding it, share of rows)."""
    rates = {}
    for tag in TAGS:
        count = int(sum(table.column(f"tag_{tag}").to_pylist()))
        rates[tag] = (count, count / max(table.num_rows, 1))
    return rates


file_sha256 = sha256_file  # the name tests and importer use; one implementation (core/files.py)


REFERENCE_DESCRIPTION = (
    "stands in for real tabletop data: procedural layouts (pipelines/reference.yaml) through check, "
    "settle and tag, no images; rare tags at natural rates of 1-5 %; every fifth layout held out"
)


def reference_source(path: Path, manifest_dir: Path, name: str = "reference", recipe: Path | None = None):
    """The manifest entry of a reference Parquet file, counts and provenance read from the file;
    ``recipe``: the recipe file that rebuilds it (default pipelines/reference.yaml)."""
    from scenegen.manifest.schema import FileChecksum, Generator, PipelineRef, SeedPanel, Source
    from scenegen.paths import PIPELINES_DIR

    table, meta = read_reference(path)
    proposals = int(meta["proposals"])
    labels = dict(item.split("=") for item in meta["rejections"].split(",") if item)
    splits = Counter(table.column("split").to_pylist())
    return Source(
        name=name,
        origin="reference",
        location=os.path.relpath(Path(path).resolve(), Path(manifest_dir).resolve()),
        description=REFERENCE_DESCRIPTION,
        counts={
            "scenes": table.num_rows,
            "rejected": proposals - table.num_rows,
            "proposals": proposals,
            "splits": dict(sorted(splits.items())),
        },
        checksums=FileChecksum(sha256=file_sha256(path)),
        predicate_version=meta["predicate_version"],
        catalog_sha256=meta["catalog_sha256"],
        generator=Generator(kind="procedural"),
        pipeline=PipelineRef(
            name="reference",
            file=os.path.relpath(
                Path(recipe or PIPELINES_DIR / "reference.yaml").resolve(), Path(manifest_dir).resolve()
            ),
            sha256=meta["pipeline_sha256"],
        ),
        seed_panel=SeedPanel(seed=int(meta["seed"]), first_index=0, last_index=proposals - 1),
        rejections_by_label={k: int(v) for k, v in sorted(labels.items())},
    )
