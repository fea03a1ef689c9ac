"""The evaluation panels of the transfer experiment, chosen once, before any policy exists.

From the held-out split of the reference set (the generator trains on the train split, so it never saw
a panel layout): a **rare panel**, ``RARE_PER_TAG`` scenes for every rare tag but ``on_floor`` (out of a
table-top arm's reach), drawn per tag with a fixed seed among the layouts holding that tag and not
``on_floor``; and a **common panel**, ``COMMON`` nominal layouts. Both are lists of the reference
layouts' ``index`` values, committed in ``assets/panels/panels.json`` with the reference table's
sha256; nothing in the recovery-task issue tunes on them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scenegen.core.files import load_rows, sha256_file
from scenegen.paths import ASSETS_DIR
from scenegen.schema.condition import RARE_TAGS

PANELS_FILE = ASSETS_DIR / "panels" / "panels.json"
REFERENCE = ASSETS_DIR / "reference" / "reference.parquet"
RARE_PER_TAG, COMMON, SEED = 25, 100, 20261124
PANEL_TAGS = tuple(t for t in RARE_TAGS if t != "on_floor")


def choose_panels(reference: Path = REFERENCE, seed: int = SEED) -> dict:
    """The panels (layout indices, sorted) drawn from ``reference``'s held-out split."""
    rows = [r for r in load_rows(reference, "heldout") if not r["tag_on_floor"]]
    rng = np.random.default_rng(seed)
    rare: dict[str, list[int]] = {}
    for tag in PANEL_TAGS:
        holding = [r["index"] for r in rows if r[f"tag_{tag}"]]
        if len(holding) < RARE_PER_TAG:
            raise ValueError(
                f"{reference}: only {len(holding)} held-out layouts hold {tag}; need {RARE_PER_TAG}"
            )
        rare[tag] = sorted(int(i) for i in rng.choice(holding, RARE_PER_TAG, replace=False))
    nominal = [r["index"] for r in rows if r["tag_nominal"]]
    common = sorted(int(i) for i in rng.choice(nominal, COMMON, replace=False))
    return {
        "description": "evaluation panels of the transfer experiment: reference held-out layout indices; "
        "simulated stand-ins for real rare cases (panel_origin: reference), never real",
        "reference": {"path": "assets/reference/reference.parquet", "sha256": sha256_file(reference)},
        "seed": seed,
        "rare_per_tag": RARE_PER_TAG,
        "rare": rare,
        "rare_layouts": sorted({i for ids in rare.values() for i in ids}),
        "common": common,
    }


def load_panels(path: Path = PANELS_FILE) -> dict:
    return json.loads(Path(path).read_text())


def write_panels(path: Path = PANELS_FILE) -> dict:
    panels = choose_panels()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(panels, indent=1) + "\n")
    return panels


def panel_scene_ids(path: Path = PANELS_FILE) -> set[str]:
    """The scene ids (``reference_NNNNNN``) of every layout on either panel: what a run that must not
    touch the transfer experiment's panels leaves out."""
    panels = load_panels(path)
    return {f"reference_{i:06d}" for i in panels["rare_layouts"] + panels["common"]}


# ------------------------------------------------------------------------------------ version 2
# Issue 33's panels: unique-category targets ("retrieve the mug" must name one object), solvable with
# oracle perception (some single primitive succeeds within the time limit by the expert labels), a
# validation panel disjoint from the test panels and drawn the same way. Version 1 stays as it is.
PANELS_V2_FILE = ASSETS_DIR / "panels" / "v2" / "panels.json"
TEST_PER_TAG, VALIDATION_PER_TAG, MIN_PER_TAG = 25, 15, 15
COMMON_TEST, COMMON_VALIDATION = 100, 50
RETRIEVAL_VALIDATION = (
    300  # the first unique-category nominal held-out layouts: docs/retrieval.md tuned on them
)


def choose_panels_v2(scenes, solvable: dict[str, bool], seed: int = SEED) -> dict:
    """Version 2 panels from held-out ``scenes`` (EnvScenes of the reference, in index order) and
    whether each is ``solvable`` (``labels.solvable_scenes`` of their expert labels).

    Per rare tag (but on_floor), ``TEST_PER_TAG`` test and up to ``VALIDATION_PER_TAG`` validation
    layouts, drawn in a seeded order among the feasible, unique-category, solvable layouts holding
    the tag; a common test panel of ``COMMON_TEST`` nominal layouts from outside the retrieval
    validation set and a common validation panel of ``COMMON_VALIDATION`` from inside it. A layout
    sits on one panel at most. Tags with fewer than ``MIN_PER_TAG`` test layouts are listed in
    ``short`` (merge, drop, or draw new layouts)."""
    from scenegen.env.scenes import scene_sha256, unique_category
    from scenegen.manipulation.task import feasible

    usable = [s for s in scenes if feasible(s) and unique_category(s)]
    unlabelled = sum(scene_sha256(s) not in solvable for s in usable)
    good = [s for s in usable if solvable.get(scene_sha256(s))]
    nominal = [s for s in usable if s.tags.get("nominal")]
    tuned = {s.scene_id for s in nominal[:RETRIEVAL_VALIDATION]}
    rng = np.random.default_rng(seed)
    taken: set[str] = set()
    test: dict[str, list[str]] = {}
    validation: dict[str, list[str]] = {}

    def draw(pool, n):
        order = [pool[i] for i in rng.permutation(len(pool))]
        chosen = [s.scene_id for s in order if s.scene_id not in taken][:n]
        taken.update(chosen)
        return sorted(chosen)

    for tag in PANEL_TAGS:
        holding = [s for s in good if s.tags.get(tag)]
        test[tag] = draw([s for s in holding if s.scene_id not in tuned], TEST_PER_TAG)
        validation[tag] = draw(holding, VALIDATION_PER_TAG)
    common_good = [s for s in good if s.tags.get("nominal")]
    test["common"] = draw([s for s in common_good if s.scene_id not in tuned], COMMON_TEST)
    validation["common"] = draw([s for s in common_good if s.scene_id in tuned], COMMON_VALIDATION)
    return {
        "description": "issue 33 panels: held-out reference layouts whose target's category is unique in "
        "the scene and that some single primitive solves within the time limit (expert labels); "
        "validation disjoint from test; simulated stand-ins for real rare cases",
        "seed": seed,
        "test": test,
        "validation": validation,
        "counts": {
            "test": {k: len(v) for k, v in test.items()},
            "validation": {k: len(v) for k, v in validation.items()},
            "usable": len(usable),
            "solvable": len(good),
            "unlabelled": unlabelled,
        },
        "short": sorted(t for t in PANEL_TAGS if len(test[t]) < MIN_PER_TAG),
    }
