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


PANELS_V2_FILE = ASSETS_DIR / "panels" / "v2" / "panels.json"  # version 2's panels (panels_v2.py)


def panel_id(scene) -> str:
    """A layout's name on a version 2 panel: its table's stem and its id (two tables hold
    ``reference_000012``)."""
    return f"{scene.source}/{scene.scene_id}"


def panel_ids(sides=("test", "validation"), path: Path = PANELS_V2_FILE) -> set[str]:
    """The ``panel_id`` of every layout on the given sides of the version 2 panels."""
    panels = json.loads(Path(path).read_text())
    return {i for side in sides for ids in panels[side].values() for i in ids}


def outside_panels(scenes, sides=("test", "validation"), version1: bool = True) -> list:
    """``scenes`` less every layout of the transfer experiment's panels: the given ``sides`` of
    version 2's (by ``panel_id``) and, with ``version1``, version 1's (by scene id). What a command
    that labels or evaluates a policy outside the panels keeps (both versions), and what a head's
    held-out figures are computed on (version 2's: version 1's panels served the transfer experiment
    of then, which looked through the oracle, not a head)."""
    first, second = panel_scene_ids() if version1 else set(), panel_ids(sides)
    return [s for s in scenes if s.scene_id not in first and panel_id(s) not in second]
