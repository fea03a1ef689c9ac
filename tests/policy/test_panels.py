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
    from scenegen.env.scenes import scene_sha256
    from scenegen.policy.panels_v2 import (
        RETRIEVAL_VALIDATION,
        TEST_PER_TAG,
        VALIDATION_PER_TAG,
        choose_panels_v2,
        panel_id,
        source_layouts,
    )

    layouts = source_layouts(((REFERENCE, "heldout"),))
    solvable = {scene_sha256(s): i % 3 != 0 for i, s in enumerate(layouts)}
    panels = choose_panels_v2(layouts, solvable)
    assert panels == choose_panels_v2(layouts, solvable) and panels["counts"]["pending"] == 0
    by_id = {panel_id(s): s for s in layouts}
    chosen = [i for side in ("test", "validation") for ids in panels[side].values() for i in ids]
    assert len(chosen) == len(set(chosen)) and chosen
    assert all(solvable[scene_sha256(by_id[i])] for i in chosen)
    first_nominal = [panel_id(s) for s in layouts if s.tags.get("nominal")][:RETRIEVAL_VALIDATION]
    assert not set(first_nominal) & {i for ids in panels["test"].values() for i in ids}
    assert set(panels["validation"]["common"]) <= set(first_nominal) and len(panels["test"]["common"]) == 100
    assert "under_overhang" in panels["short"] and "under_overhang" not in panels["test"]  # 17 layouts
    for tag, ids in panels["validation"].items():
        if tag != "common":
            assert len(ids) == VALIDATION_PER_TAG and len(panels["test"][tag]) <= TEST_PER_TAG
            assert all(by_id[i].tags.get(tag) for i in ids + panels["test"][tag])


def test_a_pool_waits_for_every_unknown_layout_before_its_end():
    """Pools are a function of the facts, not of the order of labelling: a layout whose label is not
    known cuts its pool short there and is asked for; once known, the pool is what full knowledge gives."""
    from scenegen.env.scenes import scene_sha256
    from scenegen.policy.panels_v2 import panel_id, panel_pools, source_layouts

    layouts = source_layouts(((REFERENCE, "heldout"),))
    solvable = {scene_sha256(s): i % 3 != 0 for i, s in enumerate(layouts)}
    full, wanted = panel_pools(layouts, solvable)
    assert not wanted
    hole = full["occluded"][5]
    partial = {k: v for k, v in solvable.items() if k != scene_sha256(hole)}
    pools, wanted = panel_pools(layouts, partial)
    assert [panel_id(s) for s in pools["occluded"]] == [panel_id(s) for s in full["occluded"][:5]]
    assert panel_id(hole) in {panel_id(s) for s in wanted}


def test_the_cli_names_the_files_the_module_names():
    from scenegen.cli import _parser
    from scenegen.policy.panels_v2 import LABELS_V2, NEW_LAYOUTS, PANELS_V2_FILE

    args = _parser().parse_args(["experiment", "panels"])
    assert (args.labels, args.new_layouts, args.out) == (LABELS_V2, NEW_LAYOUTS, PANELS_V2_FILE)


def test_a_panels_file_gives_its_scenes_and_the_head_is_scored_on_them(tmp_path, capsys):
    """`scenegen retrieval eval --scenes panels.json --side validation` scores the head on exactly the
    panel's layouts, per tag."""
    import json

    from scenegen.cli import main
    from scenegen.env.scenes import scene_sha256
    from scenegen.policy.panels_v2 import choose_panels_v2, panel_scenes, source_layouts

    layouts = source_layouts(((REFERENCE, "heldout"),))
    solvable = {scene_sha256(s): i % 3 != 0 for i, s in enumerate(layouts)}
    panels = choose_panels_v2(layouts, solvable)
    panels["validation"] = {
        "occluded": panels["validation"]["occluded"][:2],
        "common": panels["validation"]["common"][:1],
    }
    scenes = panel_scenes(panels, "validation")
    assert [len(v) for v in scenes.values()] == [2, 1] and scenes["occluded"][0].tags["occluded"]
    path = tmp_path / "panels.json"
    path.write_text(json.dumps(panels))
    out = tmp_path / "eval"
    argv = ["retrieval", "eval", "--checkpoint", "assets/retrieval/baseline", "--scenes", str(path)]
    assert main([*argv, "--out", str(out), "--cache", str(tmp_path / "frames"), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["all"]["scenes"] == 3 and summary["per_tag"]["occluded"]["scenes"] == 2
    panels["validation"]["common"] = ["reference/reference_999999"]
    path.write_text(json.dumps(panels))
    assert main([*argv, "--out", str(out), "--quiet"]) == 2
    assert "not in the sources" in capsys.readouterr().err


def test_no_command_that_reports_rare_held_out_figures_includes_a_panel_layout():
    """Issue 43, acceptance 5: `retrieval eval` on a table (rare and all selections), the designs
    benchmark's rare set, `--outside-panels` (which leaves out version 1's panels too) and the
    learning curves' curve set hold no layout of either side of the version 2 panels, and say what
    they left out."""
    from scenegen.cli.retrieval import held_out
    from scenegen.env.scenes import load_scenes, unique_category
    from scenegen.experiment.retrieval_curves import curve_set
    from scenegen.manipulation.task import feasible
    from scenegen.policy.panels import outside_panels, panel_ids, panel_scene_ids
    from scenegen.policy.panels_v2 import NEW_LAYOUTS, panel_id

    both, version1 = panel_ids(), panel_scene_ids()
    assert len(both) == 6 * 15 + 50 + 22 + 5 * 25 + 100  # every layout of both sides
    for table, split in ((REFERENCE, "heldout"), (NEW_LAYOUTS, None)):
        scenes = load_scenes(table, split)
        for select in ("rare", "all"):
            kept, said = held_out(scenes, select)
            assert not {panel_id(s) for s in kept} & both
            assert said.startswith("left out ") and "test and validation sides" in said
        kept, said = held_out(scenes, "nominal")  # the validation set's common layouts stay
        assert not {panel_id(s) for s in kept} & panel_ids(("test",))
    held = [s for s in load_scenes(REFERENCE, "heldout") if feasible(s)]
    rare = [s for s in held if not s.tags.get("nominal") and unique_category(s)]
    kept = held_out(rare, "rare")[0]
    test_side = panel_ids(("test",))
    assert len(rare) == 234 and sum(panel_id(s) in test_side for s in rare) == 97  # the count
    assert len(kept) == 85  # docs/retrieval.md's rare held-out set less both panel sides
    off = outside_panels(rare)  # --outside-panels: version 1's too
    assert not {s.scene_id for s in off} & version1 and not {panel_id(s) for s in off} & both
    assert not {panel_id(s) for s in curve_set()} & both
