"""Version 2 of the evaluation panels (issue 33): test panels and a validation panel for a policy that
sees through a retrieval head. Version 1 (``panels.py``, assets/panels/panels.json) stays as it is.

A panel layout's target is the only object of its category in the scene ("retrieve the mug" names one
object) and some single primitive solves it with oracle perception within the time limit (the expert
labels, ``labels.solvable_scenes``). Layouts come from held-out reference layouts: the bundled table's
held-out split first, then a table drawn from the same recipe at a new seed (``NEW_SEED``, every row:
the generator and the retrieval head never train on it), in that order (``SOURCES``).

Pools are defined by the facts alone, so they do not depend on the order in which layouts were
labelled: for each rare tag but on_floor, in ``PANEL_TAGS`` order, the first ``PER_TAG`` solvable
layouts holding the tag (source order) that no earlier tag's pool holds; the common test pool, the
first ``COMMON_TEST`` solvable nominal layouts outside the retrieval head's tuning set (the first
``RETRIEVAL_VALIDATION`` unique-category nominal layouts of the held-out split, docs/retrieval.md);
the common validation pool, the first ``COMMON_VALIDATION`` inside it. A rare pool splits by a seeded
permutation into ``VALIDATION_PER_TAG`` validation layouts and the rest for test. A tag whose pool
stays under ``2 * MIN_PER_TAG`` once its sources are exhausted, or is projected to (its solvable
rate so far, over at least 10 labelled layouts, times the layouts left), is ``short``: it has no
panel of its own and is labelled no further (docs/policy.md says so); its layouts still count in
the retrieval head's offline metrics.

``fill_pools`` labels just enough to settle the pools (``labels.label_until_solved``, in waves);
``choose_panels_v2`` draws them; ``scenegen experiment panels`` does both and writes panels.json.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from scenegen.core.files import sha256_file
from scenegen.env.scenes import EnvScene, load_scenes, scene_sha256, unique_category
from scenegen.manipulation.task import feasible
from scenegen.paths import ASSETS_DIR
from scenegen.policy.panels import PANEL_TAGS, PANELS_V2_FILE, REFERENCE, SEED, panel_id  # noqa: F401

PANELS_V2 = PANELS_V2_FILE.parent
LABELS_V2 = PANELS_V2 / "heldout_labels.parquet"
NEW_SEED = 1
# the physics the panels' solvability was labelled under (assets/panels/v2/heldout_labels.parquet):
# transfer version 2's; the panels are redrawn from those labels, whatever the default physics is now
PANELS_PHYSICS = "exact"
NEW_LAYOUTS = PANELS_V2 / "reference_seed1.parquet"  # scenegen reference --n 5000 --seed 1
SOURCES = ((REFERENCE, "heldout"), (NEW_LAYOUTS, None))
TEST_PER_TAG, VALIDATION_PER_TAG, MIN_PER_TAG = 25, 15, 15
PER_TAG = TEST_PER_TAG + VALIDATION_PER_TAG
COMMON_TEST, COMMON_VALIDATION = 100, 50
RETRIEVAL_VALIDATION = (
    300  # the first unique-category nominal held-out layouts: docs/retrieval.md tuned on them
)


def source_layouts(sources: Sequence[tuple[Path, str | None]] = SOURCES) -> list[EnvScene]:
    """Every feasible unique-category layout of the sources, in source order."""
    scenes = [s for path, split in sources for s in load_scenes(path, split)]
    return [s for s in scenes if feasible(s) and unique_category(s)]


def _candidates(layouts: list[EnvScene]) -> dict[str, list[EnvScene]]:
    """Per pool, the layouts it may hold, in source order (rare pools before overlap is resolved)."""
    nominal = [s for s in layouts if s.tags.get("nominal")]
    first = layouts[0].source if layouts else None  # the bundled held-out split
    tuned = [s for s in nominal if s.source == first][:RETRIEVAL_VALIDATION]
    tuned_set = {panel_id(s) for s in tuned}
    pools = {tag: [s for s in layouts if s.tags.get(tag)] for tag in PANEL_TAGS}
    pools["common_test"] = [s for s in nominal if panel_id(s) not in tuned_set]
    pools["common_validation"] = tuned
    return pools


def _sizes() -> dict[str, int]:
    return {
        **{tag: PER_TAG for tag in PANEL_TAGS},
        "common_test": COMMON_TEST,
        "common_validation": COMMON_VALIDATION,
    }


def panel_pools(
    layouts: list[EnvScene], solvable: dict[str, bool]
) -> tuple[dict[str, list[EnvScene]], list[EnvScene]]:
    """The pools the facts settle so far, and the next layouts whose labels an unfinished pool needs
    (about 1.5 times its deficit over its solvable rate so far; empty once every pool is full or its
    candidates are labelled)."""
    answers = [solvable[k] for k in {scene_sha256(s) for s in layouts} if k in solvable]
    prior = max(0.2, sum(answers) / len(answers)) if answers else 0.5
    pools: dict[str, list[EnvScene]] = {}
    wanted: dict[str, EnvScene] = {}
    taken: set[str] = set()
    for name, candidates in _candidates(layouts).items():
        size = _sizes()[name]
        pool: list[EnvScene] = []
        unknown: list[EnvScene] = []
        known = later = 0  # later: solvable layouts past the first unknown one
        for scene in candidates:
            if len(pool) + later >= size:
                break
            if panel_id(scene) in taken:
                continue
            answer = solvable.get(scene_sha256(scene))
            if answer is None:
                unknown.append(scene)  # the pool is settled only once every layout before its end is known
                continue
            known += 1
            if answer and not unknown:
                pool.append(scene)
            elif answer:
                later += 1
        if unknown:
            deficit = size - len(pool) - later
            rate = max(0.2, (len(pool) + later) / known) if known >= 10 else prior
            n = len(unknown) if deficit <= 0 else math.ceil(1.5 * deficit / rate)  # all inside the prefix
            rare = name in PANEL_TAGS and known >= 10
            if rare and len(pool) + later + (len(pool) + later) / known * len(unknown) < 2 * MIN_PER_TAG:
                n = 0  # projected short: even its expected share of the rest leaves it without a panel
            for scene in unknown[:n]:
                wanted.setdefault(panel_id(scene), scene)
        pools[name] = pool
        taken.update(panel_id(s) for s in pool)
    return pools, list(wanted.values())


def fill_pools(
    layouts: list[EnvScene],
    labels: Path = LABELS_V2,
    workers: int = 1,
    progress: bool = True,
    max_waves: int = 20,
) -> dict[str, bool]:
    """Label (until solved) the layouts the pools need, wave after wave, until every pool is settled;
    returns the solvability the store then holds. Resumable: the label store keeps every row."""
    from scenegen.policy.labels import label_until_solved

    solvable = known_solvable(labels)
    for _ in range(max_waves):
        _, wanted = panel_pools(layouts, solvable)
        if not wanted:
            break
        if progress:
            print(f"panels: labelling {len(wanted)} layouts until solved", flush=True)
        label_until_solved(wanted, labels, workers=workers, progress=progress, physics=PANELS_PHYSICS)
        solvable = known_solvable(labels)
    return solvable


def known_solvable(labels: Path) -> dict[str, bool]:
    """What a label store (its Parquet file and its row log) settles: scene sha256 -> solvable."""
    from scenegen.policy.labels import solvable_scenes, stored_rows

    return solvable_scenes(stored_rows(labels), PANELS_PHYSICS)


def choose_panels_v2(layouts: list[EnvScene], solvable: dict[str, bool], seed: int = SEED) -> dict:
    """Test and validation panels from the settled pools (``panel_pools``); layouts by ``panel_id``."""
    pools, pending = panel_pools(layouts, solvable)
    test: dict[str, list[str]] = {}
    validation: dict[str, list[str]] = {}
    short = []
    for tag in PANEL_TAGS:
        ids = [panel_id(s) for s in pools[tag]]
        if len(ids) < 2 * MIN_PER_TAG:
            short.append(tag)
            continue
        rng = np.random.default_rng([seed, PANEL_TAGS.index(tag)])  # a tag's split depends on its pool alone
        order = [ids[i] for i in rng.permutation(len(ids))]
        validation[tag] = sorted(order[:VALIDATION_PER_TAG])
        test[tag] = sorted(order[VALIDATION_PER_TAG:])
    test["common"] = sorted(panel_id(s) for s in pools["common_test"])
    validation["common"] = sorted(panel_id(s) for s in pools["common_validation"])
    return {
        "description": "issue 33 panels (version 2): held-out reference layouts whose target's category is "
        "unique in the scene and that some single primitive solves within the time limit with oracle "
        "perception (expert labels); validation disjoint from test; simulated stand-ins for real rare "
        "cases. How they are drawn: scenegen/policy/panels_v2.py",
        "seed": seed,
        "test": test,
        "validation": validation,
        "short": short,
        "counts": {
            "test": {k: len(v) for k, v in test.items()},
            "validation": {k: len(v) for k, v in validation.items()},
            "pool": {k: len(v) for k, v in pools.items()},
            "usable_layouts": len(layouts),
            "labelled": sum(scene_sha256(s) in solvable for s in layouts),
            "solvable": sum(bool(solvable.get(scene_sha256(s))) for s in layouts),
            "pending": len(pending),
        },
    }


def write_panels_v2(layouts, solvable, out: Path = PANELS_V2_FILE, sources=SOURCES) -> dict:
    panels = choose_panels_v2(layouts, solvable)
    panels["sources"] = [
        {"path": str(Path(p).relative_to(ASSETS_DIR.parent)) if Path(p).is_absolute() else str(p),
         "split": split or "all", "sha256": sha256_file(Path(p))}
        for p, split in sources
    ]  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(panels, indent=1) + "\n")
    return panels


def load_panels_v2(path: Path = PANELS_V2_FILE) -> dict:
    return json.loads(Path(path).read_text())


def panel_scenes(panels: dict, side: str, sources=SOURCES) -> dict[str, list[EnvScene]]:
    """The EnvScenes of one side (``test`` or ``validation``) of version 2 panels, per panel (only
    the source tables the panels name are read)."""
    wanted = {i for ids in panels[side].values() for i in ids}
    tables = {i.split("/")[0] for i in wanted}
    by_id = {
        panel_id(s): s for s in source_layouts([(p, split) for p, split in sources if Path(p).stem in tables])
    }
    missing = sorted(wanted - set(by_id))
    if missing:
        raise ValueError(
            f"panels: {len(missing)} layouts not in the sources (e.g. {missing[0]}): rebuild them"
        )
    return {name: [by_id[i] for i in ids] for name, ids in panels[side].items()}


def panel_tags(panels: dict | None = None) -> tuple[str, ...]:
    """The rare tags that have a panel (``PANEL_TAGS`` order; not the ``short`` ones)."""
    panels = load_panels_v2() if panels is None else panels
    return tuple(t for t in PANEL_TAGS if t in panels["validation"])
