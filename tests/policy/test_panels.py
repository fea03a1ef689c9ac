"""The transfer experiment's panels: committed, reproducible from the seed, drawn from held-out layouts
only, every rare tag but on_floor with 25 scenes, 100 nominal scenes."""

from __future__ import annotations

from scenegen.core.files import load_rows
from scenegen.policy.panels import COMMON, PANEL_TAGS, RARE_PER_TAG, REFERENCE, choose_panels, load_panels


def test_the_committed_panels_are_what_the_seed_draws():
    assert load_panels() == choose_panels()


def test_panels_hold_their_tags_and_come_from_the_held_out_split_only():
    panels = load_panels()
    rows = {r["index"]: r for r in load_rows(REFERENCE, None)}
    assert set(panels["rare"]) == set(PANEL_TAGS) and "on_floor" not in panels["rare"]
    for tag, ids in panels["rare"].items():
        assert len(ids) == RARE_PER_TAG == len(set(ids))
        assert all(rows[i]["split"] == "heldout" and rows[i][f"tag_{tag}"] for i in ids), tag
        assert not any(rows[i]["tag_on_floor"] for i in ids), tag
    assert len(panels["common"]) == COMMON
    assert all(rows[i]["split"] == "heldout" and rows[i]["tag_nominal"] for i in panels["common"])
    assert not set(panels["common"]) & set(panels["rare_layouts"])
