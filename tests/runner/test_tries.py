"""labelled_tries (runner/tries.py) makes exactly the tries run_batch makes, first passes and
projection repairs in the same order with the same outcomes, and hands each proposal over with its
outcome; it writes nothing."""

from __future__ import annotations

import json

from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import run_batch
from scenegen.runner.tries import labelled_tries


def test_the_tries_are_the_batch_s_tries(tmp_path):
    overrides = {"n": 2, "max_tries": 16, "render": False, "realism": None}
    config = load_pipeline("pipelines/generator_v3.yaml", overrides, "retrieve the mug near_edge occluded")
    run_batch(config, tmp_path / "batch", workers=1, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "batch" / "rejections.jsonl").read_text().splitlines()]
    scenes = []
    for line in (tmp_path / "batch" / "index.jsonl").read_text().splitlines():
        row = json.loads(line)
        path = json.loads((tmp_path / "batch" / row["scene_id"] / "scene.json").read_text())["provenance"]
        scenes.append((row["proposal_index"], len(path.get("repairs") or ()), "accepted"))
    logged = sorted([(r["proposal_index"], r.get("attempt", 0), r["label"]) for r in rows] + scenes)
    tried = [
        (p.index, p.attempt, "accepted" if o.record is not None else o.rejection.label)
        for p, o in labelled_tries(config)
    ]
    assert tried == logged
    assert any(attempt > 0 for _, attempt, _ in tried)  # repairs among them
    assert [p.name for p in tmp_path.iterdir()] == ["batch"]  # it wrote nothing
