"""The sequence store under today's rules: the time limit held on a success, features per attempt, and
sequences keyed by the plans executed, so that policies seeing through different heads share exactly
what they execute alike."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from scenegen.experiment.closed_loop import Cost
from scenegen.experiment.sequences import SEQUENCE_RULES, ObservationStore, PathStore, match

ROOT = Path(__file__).resolve().parents[2] / "assets"
VERSION_1 = ROOT / "transfer" / "paths.jsonl"


def test_version_1_sequences_are_not_served_under_todays_rules(tmp_path: Path):
    """Version 1's store (assets/transfer/paths.jsonl) counted a success after the 30 s limit (41 of
    its 360 successes end after 31.5 s) and kept features over the whole episode: none of its rows
    answers a question asked under today's rules, which re-simulate instead."""
    rows = [json.loads(line) for line in VERSION_1.read_text().splitlines()]
    late = [r for r in rows if r["success"] and r["time"] > 31.5]
    assert len(late) == 41
    copy = tmp_path / "paths.jsonl"
    copy.write_bytes(VERSION_1.read_bytes())
    store = PathStore(copy)
    assert len(store.entries) == len(rows) and not store.decisions
    assert all(store.get(r["scene_sha256"], r["prefix"]) is None for r in rows)


def _row(decision: str, regrasp: str | None, success: bool) -> dict:
    tokens = [decision + (f"+{regrasp}" if regrasp else "")]
    return {
        "key": f"s|rules{SEQUENCE_RULES}|{tokens[0]}", "rules": SEQUENCE_RULES, "scene_sha256": "s",
        "prefix": ["pull_out_then_grasp"], "tokens": tokens, "decision": decision, "success": success,
        "time": 20.0, "regrasp": None if regrasp is None else {"qpos": [0.0], "plan": regrasp},
    }  # fmt: skip


def test_an_attempt_is_served_only_when_its_decision_and_its_re_observation_plans_match(tmp_path: Path):
    store = PathStore(tmp_path / "paths.jsonl")
    store.add(
        [_row("pull@3:aaa", "r1", True), _row("pull@3:aaa", "r2", False), _row("top@1:bbb", None, True)]
    )
    assert match(store, "s", (), "pull@3:aaa", "r1")["success"] is True
    assert match(store, "s", (), "pull@3:aaa", "r2")["success"] is False
    assert match(store, "s", (), "pull@3:aaa", "r3") is None  # another plan at the re-observation
    assert match(store, "s", (), "pull@3:ccc", "r1") is None  # another plan at the decision
    assert match(store, "s", (), "top@1:bbb", None)["success"] is True
    again = PathStore(tmp_path / "paths.jsonl")  # read back from the file
    assert again.candidates("s", (), "pull@3:aaa") == store.candidates("s", (), "pull@3:aaa")
    again.add([{**_row("top@1:bbb", None, False)}])  # the same plans measured otherwise: counted
    assert again.mismatches == 1


@pytest.fixture(scope="module")
def learned_run(demo_batch: Path, tmp_path_factory):
    from scenegen.env.scenes import batch_scenes
    from scenegen.experiment.closed_loop import evaluate_policies
    from scenegen.policy.network import PrimitivePolicy

    folder = tmp_path_factory.mktemp("closed_loop")
    policies = {"baseline": PrimitivePolicy.load(ROOT / "policy" / "baseline")}
    scenes = batch_scenes(demo_batch)[:1]
    store, observations = PathStore(folder / "paths.jsonl"), ObservationStore(folder / "obs")
    cost = Cost()
    head = ROOT / "retrieval" / "baseline"
    records = evaluate_policies(policies, scenes, store, observations, retrieval=head, cost=cost)
    return folder, policies, scenes, store, observations, records, cost


def test_a_learned_evaluation_is_reused_whole_and_counts_its_cost(learned_run):
    from scenegen.experiment.closed_loop import evaluate_policies

    _, policies, scenes, store, observations, records, cost = learned_run
    assert all(r["choices"] and len(r["plans"]) == len(r["choices"]) for r in records)
    assert all(len(r["perception"]) == len(r["choices"]) and "hit_iou" in r["perception"][0] for r in records)
    assert cost.attempts == sum(len(r["choices"]) for r in records) and cost.simulated >= 1
    assert cost.cpu["simulate"] > 0 and cost.cpu["observe"] > 0
    keys = set(store.entries)
    again = Cost()
    head = ROOT / "retrieval" / "baseline"
    assert evaluate_policies(policies, scenes, store, observations, retrieval=head, cost=again) == records
    assert set(store.entries) == keys and again.simulated == 0 and again.shared == again.attempts
    assert store.mismatches == 0


def test_a_head_with_other_bytes_but_the_same_plans_shares_every_attempt(learned_run, tmp_path: Path):
    """Another checkpoint (here: the same weights saved with other metadata, so its own observation
    keys) that makes the same plans executes nothing new: the store is keyed by plans, not heads."""
    from safetensors.torch import load_file, save_file

    from scenegen.experiment.closed_loop import evaluate_policies

    _, policies, scenes, store, observations, records, _ = learned_run
    twin = tmp_path / "twin"
    shutil.copytree(ROOT / "retrieval" / "baseline", twin)
    save_file(load_file(twin / "model.safetensors"), twin / "model.safetensors", metadata={"twin": "1"})
    cost = Cost()
    twins = evaluate_policies(policies, scenes, store, observations, retrieval=twin, cost=cost)
    assert [r["plans"] for r in twins] == [r["plans"] for r in records]
    assert cost.simulated == 0 and cost.shared == cost.attempts and cost.cpu["observe"] > 0


def test_the_perception_gap_runs_both_settings_on_one_store(demo_batch: Path, tmp_path: Path):
    """``run_gap``: the same layouts through the head and through the oracle, each setting's
    success, perception failures and cost in the summary, episodes written per setting."""
    from scenegen.env.scenes import batch_scenes
    from scenegen.experiment.perception_gap import run_gap

    scenes = batch_scenes(demo_batch)[1:2]  # not the fixture's: this one is simulated here
    panel = {"common": scenes, "again": scenes}
    summary = run_gap(
        ROOT / "policy" / "baseline", ROOT / "retrieval" / "baseline", panel, tmp_path, progress=False
    )
    for setting in ("learned", "oracle"):
        block = summary["settings"][setting]
        assert block["success"]["all"]["episodes"] == 1 and block["success"]["again"]["episodes"] == 1
        assert block["cost"]["attempts"] >= 1 and block["cost"]["cpu_per_episode"] > 0
        lines = (tmp_path / f"episodes_{setting}.jsonl").read_text().splitlines()
        assert len(lines) == 1
    assert summary["settings"]["learned"]["success"]["all"]["first_decision_hit"] is not None
    assert summary["settings"]["oracle"]["success"]["all"]["first_decision_hit"] is None
    assert summary["store_mismatches"] == 0 and "| common | 1 |" in (tmp_path / "summary.md").read_text()


def test_on_a_plan_grid_the_decision_observed_and_the_attempt_simulated_share_their_plans(
    learned_run, tmp_path: Path
):
    """Evaluated on a ``PlanGrid``, every decision's plan token is the snapped plan's, the simulated
    attempt is keyed by the same token (nothing measured twice otherwise), and a second evaluation is
    served whole from the store."""
    from scenegen.experiment.closed_loop import evaluate_policies
    from scenegen.manipulation.primitives import PlanGrid

    _, policies, scenes, _, _, records, _ = learned_run
    grid = PlanGrid(metres=0.005, degrees=5.0)
    store, observations = PathStore(tmp_path / "paths.jsonl"), ObservationStore(tmp_path / "obs")
    head = ROOT / "retrieval" / "baseline"
    snapped = evaluate_policies(policies, scenes, store, observations, retrieval=head, grid=grid)
    assert [r["choices"][0] for r in snapped] == [r["choices"][0] for r in records]  # same decision
    assert snapped[0]["plans"][0] != records[0]["plans"][0]  # executed on the grid: another plan
    assert store.mismatches == 0
    again = Cost()
    repeat = evaluate_policies(policies, scenes, store, observations, retrieval=head, cost=again, grid=grid)
    assert repeat == snapped and again.simulated == 0 and again.shared == again.attempts


def test_one_attempt_without_experts_is_each_episodes_first_decision(learned_run):
    """``attempts=1, experts=False`` (the chooser's first-attempt figure beside the proposal model's
    curves): each record is its full episode's first attempt, served from the store, and no expert
    row is simulated for a failure."""
    from scenegen.experiment.closed_loop import evaluate_policies

    _, policies, scenes, store, observations, records, _ = learned_run
    keys, cost = set(store.entries), Cost()
    head = ROOT / "retrieval" / "baseline"
    first = evaluate_policies(
        policies, scenes, store, observations, retrieval=head, cost=cost, attempts=1, experts=False
    )
    assert [r["choices"] for r in first] == [r["choices"][:1] for r in records]
    assert [r["success"] for r in first] == [r["first_attempt"] for r in records]
    assert set(store.entries) == keys and cost.simulated == 0 and cost.attempts == len(records)
