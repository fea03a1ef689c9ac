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


def test_version_2_panels_hold_unique_solvable_layouts_and_keep_validation_apart():
    """Drawn from the real held-out split with hand-made solvability (every third layout unsolvable):
    unique-category targets only, solvable only, no layout on two panels, the retrieval's tuning set
    only on the validation side, and the same draw for the same seed."""
    from scenegen.env.scenes import load_scenes, scene_sha256, unique_category
    from scenegen.policy.panels import RETRIEVAL_VALIDATION, choose_panels_v2

    scenes = load_scenes(REFERENCE, "heldout")
    solvable = {scene_sha256(s): i % 3 != 0 for i, s in enumerate(scenes)}
    panels = choose_panels_v2(scenes, solvable)
    assert panels == choose_panels_v2(scenes, solvable)
    by_id = {s.scene_id: s for s in scenes}
    chosen = [i for side in ("test", "validation") for ids in panels[side].values() for i in ids]
    assert len(chosen) == len(set(chosen)) and chosen
    assert all(unique_category(by_id[i]) and solvable[scene_sha256(by_id[i])] for i in chosen)
    nominal = [
        s for s in scenes if unique_category(s) and s.tags.get("nominal") and not s.tags.get("on_floor")
    ]
    tuned = {s.scene_id for s in nominal[:RETRIEVAL_VALIDATION]}
    assert not tuned & {i for ids in panels["test"].values() for i in ids}
    assert set(panels["validation"]["common"]) <= tuned and len(panels["test"]["common"]) == 100
    assert panels["counts"]["test"]["under_overhang"] < 25 and "under_overhang" in panels["short"]
