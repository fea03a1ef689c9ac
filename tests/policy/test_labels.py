"""Expert labels: deterministic (the same file whatever the worker count), resumable after a kill,
and cached by (scene sha256, primitive, version)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from scenegen.cli import main
from scenegen.policy.labels import LabelError, label

PRIMITIVES = ["top_grasp", "toppled_grasp"]


@pytest.fixture(scope="module")
def labelled(demo_batch: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("labels") / "labels.parquet"
    argv = ["label", str(demo_batch), "--out", str(out), "--limit", "2", "--primitives", *PRIMITIVES]
    assert main([*argv, "--quiet"]) == 0
    return out


def test_one_row_per_scene_and_primitive_measured_by_the_simulator(labelled: Path):
    rows = pq.read_table(labelled).to_pylist()
    assert [(r["scene_id"], r["primitive"]) for r in rows][:2] == [
        (rows[0]["scene_id"], p) for p in PRIMITIVES
    ]
    assert len(rows) == 4 and len({r["scene_sha256"] for r in rows}) == 2
    for row in rows:
        assert row["success"] == (row["failure"] == "") and row["duration"] > 0
        if row["success"]:
            assert row["lift"] >= 0.05


def test_a_rerun_reuses_every_row_and_writes_the_same_bytes(labelled: Path, demo_batch: Path, capsys):
    before = labelled.read_bytes()
    stats = label(demo_batch, labelled, PRIMITIVES, limit=2, progress=False)
    assert (stats["ran"], stats["reused"]) == (0, 4)
    assert labelled.read_bytes() == before


def test_a_killed_run_resumes_from_its_log_and_two_workers_give_the_same_file(
    labelled: Path, demo_batch: Path, tmp_path: Path
):
    out = tmp_path / "labels.parquet"
    done = pq.read_table(labelled).to_pylist()[:2]  # what a run killed after two rows left behind
    log = out.with_name(out.name + ".rows.jsonl")
    log.write_text("".join(json.dumps(r) + "\n" for r in done) + '{"scene_id": "torn')
    stats = label(demo_batch, out, PRIMITIVES, limit=2, workers=2, progress=False)
    assert (stats["ran"], stats["reused"]) == (2, 2)
    assert out.read_bytes() == labelled.read_bytes() and not log.exists()


def test_bad_input_is_named(demo_batch: Path, tmp_path: Path):
    with pytest.raises(LabelError, match="unknown; choose from"):
        label(demo_batch, tmp_path / "x.parquet", ["fly"], progress=False)
    with pytest.raises(LabelError, match="no index.jsonl"):
        label(tmp_path, tmp_path / "x.parquet", progress=False)


def test_the_state_ablation_is_labelled_apart_and_recorded(labelled: Path, demo_batch: Path, tmp_path: Path):
    out = tmp_path / "labels.parquet"
    shutil.copy(labelled, out)  # the rgbd rows do not answer for the state ablation
    stats = label(demo_batch, out, ["top_grasp"], limit=1, observation="state", progress=False)
    assert (stats["ran"], stats["reused"]) == (1, 0)
    assert [r["observation"] for r in pq.read_table(out).to_pylist()] == ["state"]
    with pytest.raises(LabelError, match="--observation x"):
        label(demo_batch, out, ["top_grasp"], observation="x", progress=False)


def test_per_cell_fills_each_reportable_cell_of_the_named_categories_in_source_order():
    from scenegen.env.scenes import load_scenes
    from scenegen.policy.labels import feasible, per_cell_selection, target_category
    from scenegen.policy.success_table import MIN_CELL
    from scenegen.schema.condition import RARE_TAGS

    scenes = load_scenes(Path("assets/reference/reference.parquet"), "train")
    chosen = per_cell_selection(scenes, MIN_CELL, ["can"])
    assert {target_category(s) for s in chosen} == {"can"} and all(feasible(s) for s in chosen)
    order = {id(s): i for i, s in enumerate(scenes)}
    assert [order[id(s)] for s in chosen] == sorted(order[id(s)] for s in chosen)
    for tag in (*RARE_TAGS, "nominal"):
        available = [s for s in scenes if target_category(s) == "can" and feasible(s) and s.tags.get(tag)]
        picked = [s for s in chosen if s.tags.get(tag)]
        if len(available) >= MIN_CELL:  # the first MIN_CELL of the cell, perhaps more through other tags
            assert all(s in picked for s in available[:MIN_CELL]), tag
        else:  # too few to report alone: only scenes chosen for another tag hold it
            assert all(any(s.tags.get(t) for t in RARE_TAGS if t != tag) for s in picked), tag


def test_per_cell_needs_its_categories_and_names_unknown_ones(tmp_path: Path, capsys):
    out = tmp_path / "x.parquet"
    assert main(["label", "assets/reference/reference.parquet", "--out", str(out), "--per-cell", "3"]) == 2
    assert "--per-cell N and --categories go together" in capsys.readouterr().err
    argv = ["label", "assets/reference/reference.parquet", "--out", str(out), "--per-cell", "3"]
    assert main([*argv, "--categories", "can", "teapot"]) == 2
    assert "--categories: no target of category teapot" in capsys.readouterr().err
    assert not out.exists()


def test_outside_panels_labels_held_out_scenes_that_no_panel_holds(tmp_path: Path):
    from scenegen.policy.panels import load_panels, panel_scene_ids

    first = min(load_panels()["rare_layouts"] + load_panels()["common"])
    out = tmp_path / "heldout.parquet"
    argv = ["label", "assets/reference/reference.parquet", "--out", str(out), "--split", "heldout"]
    assert main([*argv, "--outside-panels", "--limit", "1", "--primitives", "top_grasp", "--quiet"]) == 0
    (row,) = pq.read_table(out).to_pylist()
    assert row["scene_id"] not in panel_scene_ids() and "on_floor" not in row["tags"]
    assert f"reference_{first:06d}" in panel_scene_ids()


def test_a_store_keeps_every_row_and_reuses_other_label_files(tmp_path: Path):
    """``label_scenes(keep=True, reuse=...)``: rows of another label file with the same scene content,
    primitive, version and observation count as done (nothing runs), and the store keeps every row it
    was ever given."""
    from scenegen.core.files import load_rows
    from scenegen.env.scenes import reference_scene
    from scenegen.policy.labels import label_scenes, scene_sha256

    committed = Path("assets/policy/labels/per_tag40.parquet")
    known = {r["scene_sha256"] for r in pq.read_table(committed).to_pylist()}
    rows = [r for r in load_rows(Path("assets/reference/reference.parquet"), "train")]
    scenes = [s for s in map(reference_scene, rows[:400]) if scene_sha256(s) in known][:3]
    assert len(scenes) == 3
    store = tmp_path / "store.parquet"
    # the committed rows were simulated under exact: only a run under exact may reuse them
    first, ran = label_scenes(
        scenes[:2], store, progress=False, keep=True, reuse=[committed], physics="exact"
    )
    assert ran == 0 and len(first) == 10
    second, ran = label_scenes(
        scenes[2:], store, progress=False, keep=True, reuse=[committed], physics="exact"
    )
    assert ran == 0 and len(second) == 5
    stored = pq.read_table(store).to_pylist()
    assert {r["scene_sha256"] for r in first + second} <= {r["scene_sha256"] for r in stored}
    by_key = {(r["scene_sha256"], r["primitive"]): r["success"] for r in pq.read_table(committed).to_pylist()}
    assert all(by_key[(r["scene_sha256"], r["primitive"])] == r["success"] for r in first + second)


def test_ray_actors_label_the_same_file(labelled: Path, demo_batch: Path, tmp_path: Path):
    """`scenegen label --backend ray` (a local Ray cluster, 2 actors) writes the local run's bytes."""
    pytest.importorskip("ray")  # the `ray` extra: CI installs it (make setup)
    out = tmp_path / "labels.parquet"
    argv = ["label", str(demo_batch), "--out", str(out), "--limit", "2", "--primitives", *PRIMITIVES]
    assert main([*argv, "--workers", "2", "--backend", "ray", "--quiet"]) == 0
    assert out.read_bytes() == labelled.read_bytes()


def test_the_committed_label_stores_obey_the_time_limit():
    """Every success in the committed label stores ended within the task's time limit (the rows keep
    each execution's duration; version 1 let a success count whenever it came)."""
    import pyarrow.parquet as pq

    from scenegen.manipulation.task import TIME_LIMIT
    from scenegen.policy.labels import timed

    root = Path(__file__).resolve().parents[2] / "assets"
    stores = [root / "transfer" / "labels.parquet", *sorted((root / "policy" / "labels").glob("*.parquet"))]
    for store in stores:
        rows = pq.read_table(store).to_pylist()
        assert rows and all(timed(r) for r in rows), store
        assert max(r["duration"] for r in rows if r["success"]) <= TIME_LIMIT, store


def test_a_scene_is_solvable_once_a_current_primitive_succeeds_and_unsolvable_when_all_fail():
    from scenegen.manipulation.primitives import PRIMITIVES
    from scenegen.policy.labels import solvable_scenes

    def row(sha, name, success, version=None):
        version = PRIMITIVES[name].version if version is None else version
        return {"scene_sha256": sha, "primitive": name, "primitive_version": version, "success": success,
                "duration": 10.0, "observation": "rgbd"}  # fmt: skip

    rows = [row("a", p, p == "side_grasp") for p in PRIMITIVES]  # one success
    rows += [row("b", p, False) for p in PRIMITIVES]  # none
    rows += [row("c", p, True) for p in list(PRIMITIVES)[:1]]  # solved by its first row
    rows += [row("d", p, p == "top_grasp", version=0 if p == "top_grasp" else None) for p in PRIMITIVES]
    rows += [row("e", p, False) for p in list(PRIMITIVES)[:-1]]  # one primitive unlabelled: unknown
    assert solvable_scenes(rows, "exact") == {"a": True, "b": False, "c": True}  # no physics column: exact


def test_labelling_until_solved_stops_each_scene_at_its_first_success(tmp_path: Path):
    """``label_until_solved``: a scene solved by the first primitive of the order gets one row, one
    solved by the second two, an unsolvable one every primitive; the store says which is which."""
    from collections import defaultdict

    from scenegen.core.files import load_rows
    from scenegen.env.scenes import reference_scene
    from scenegen.policy.labels import SOLVE_ORDER, label_until_solved, scene_sha256, solvable_scenes

    committed = Path("assets/policy/labels/per_tag40.parquet")
    outcome: dict[str, dict[str, bool]] = defaultdict(dict)
    for r in pq.read_table(committed).to_pylist():
        outcome[r["scene_sha256"]][r["primitive"]] = r["success"]
    first, second = SOLVE_ORDER[:2]
    kinds = {
        "first": lambda o: o[first],
        "second": lambda o: not o[first] and o[second],
        "none": lambda o: not any(o.values()),
    }
    chosen: dict[str, object] = {}
    for row in load_rows(Path("assets/reference/reference.parquet"), "train")[:600]:
        scene = reference_scene(row)
        o = outcome.get(scene_sha256(scene))
        if o is None or len(o) < len(SOLVE_ORDER):
            continue
        for kind, test in kinds.items():
            if kind not in chosen and test(o):
                chosen[kind] = scene
    assert set(chosen) == set(kinds)
    store = tmp_path / "store.parquet"
    rows, ran = label_until_solved(
        list(chosen.values()), store, progress=False, reuse=[committed], physics="exact"
    )
    per_scene = defaultdict(list)
    for r in rows:
        per_scene[r["scene_sha256"]].append(r["primitive"])
    sha = {kind: scene_sha256(scene) for kind, scene in chosen.items()}
    assert ran == 0
    assert per_scene[sha["first"]] == [first] and per_scene[sha["second"]] == [first, second]
    assert per_scene[sha["none"]] == list(SOLVE_ORDER)
    stored = solvable_scenes(pq.read_table(store).to_pylist(), "exact")  # it keeps the reused rows too
    assert {k: stored[v] for k, v in sha.items()} == {"first": True, "second": True, "none": False}
    assert solvable_scenes(rows, "exact") == {sha["first"]: True, sha["second"]: True, sha["none"]: False}
    assert solvable_scenes(rows) == {}  # nothing of exact's answers for the default physics


def test_rows_say_their_physics_and_another_physics_is_labelled_apart(
    labelled: Path, demo_batch: Path, tmp_path: Path, monkeypatch
):
    from scenegen.env.physics import DEFAULT_PHYSICS, PHYSICS
    from scenegen.policy.labels import current

    coarse = PHYSICS["exact"].with_changes("coarse", timestep=0.0025)
    monkeypatch.setitem(PHYSICS, "coarse", coarse)
    out = tmp_path / "labels.parquet"
    shutil.copy(labelled, out)  # the default physics' rows do not answer for another physics
    assert {r["physics"] for r in pq.read_table(out).to_pylist()} == {PHYSICS[DEFAULT_PHYSICS].key()}
    stats = label(demo_batch, out, ["top_grasp"], limit=1, physics="coarse", progress=False)
    assert (stats["ran"], stats["reused"]) == (1, 0)
    (row,) = pq.read_table(out).to_pylist()
    assert row["physics"] == coarse.key() and current(row, physics="coarse") and not current(row)
    # a row written before the physics was a setting was made under exact
    old = {k: v for k, v in pq.read_table(labelled).to_pylist()[0].items() if k != "physics"}
    assert current(old, physics="exact") and not current(old) and not current(old, physics="coarse")
    with pytest.raises(LabelError, match="--physics fast: unknown; choose from exact"):
        label(demo_batch, out, ["top_grasp"], limit=1, physics="fast", progress=False)


def test_a_decision_token_names_a_physics_other_than_exact():
    from scenegen.env.physics import PHYSICS
    from scenegen.experiment.sequences import decision_token

    plan = {"position": [0.1, 0.2, 0.9]}
    exact = decision_token("top_grasp", plan, PHYSICS["exact"])
    assert exact == decision_token("top_grasp", plan)  # what stores made before the setting hold
    coarse = PHYSICS["exact"].with_changes("coarse", timestep=0.005)
    assert decision_token("top_grasp", plan, coarse) == exact.replace(":", f"~{coarse.key()}:", 1)
