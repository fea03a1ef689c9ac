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
