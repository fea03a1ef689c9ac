"""The sequence store under today's rules (the time limit held on a success, features per attempt)."""

from __future__ import annotations

import json
from pathlib import Path

from scenegen.experiment.closed_loop import PathStore

VERSION_1 = Path(__file__).resolve().parents[2] / "assets" / "transfer" / "paths.jsonl"


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
    assert len(store.entries) == len(rows)
    assert all(store.get(r["scene_sha256"], r["prefix"]) is None for r in rows)


def test_policies_seeing_through_a_retrieval_head_keep_their_own_sequences(demo_batch: Path, tmp_path: Path):
    """The plan depends on what the planners see: sequences measured through the retrieval head are
    keyed apart from the oracle's, carry the perception rule's input, and a second evaluation of the
    same policies reuses every one of them."""
    from scenegen.env.scenes import batch_scenes
    from scenegen.experiment.closed_loop import ObservationStore, evaluate_policies
    from scenegen.policy.network import PrimitivePolicy

    root = Path(__file__).resolve().parents[2] / "assets"
    policies = {"baseline": PrimitivePolicy.load(root / "policy" / "baseline")}
    scenes = batch_scenes(demo_batch)[:1]
    store, observations = PathStore(tmp_path / "paths.jsonl"), ObservationStore(tmp_path / "obs")
    learned = evaluate_policies(
        policies, scenes, store, observations, retrieval=root / "retrieval" / "baseline"
    )
    keys = set(store.entries)
    assert learned[0]["choices"] and all("|retrieval:" in k or "|oracle|" in k for k in keys)
    seen = [row for key, row in store.entries.items() if "|retrieval:" in key]
    assert seen and all("mask_missed" in row["features"] for row in seen)
    again = evaluate_policies(
        policies, scenes, store, observations, retrieval=root / "retrieval" / "baseline"
    )
    assert again == learned and set(store.entries) == keys
    oracle = evaluate_policies(policies, scenes, store, observations)
    assert oracle[0]["choices"] and any("|oracle|" in k for k in set(store.entries) - keys)
