"""The retrieval head's learning curves at a tiny size (issue 43): the natural-rate and rare-rich
training sets, real trainings of both designs, scoring by the overlap rule, the bootstrap table and
the plot; a job whose scores exist is not run again."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from scenegen.experiment.retrieval_curves import (
    CurveJob,
    curve_results,
    curve_table,
    leads,
    plot_curves,
    run_job,
    scoring_scenes,
    training_sets,
)
from scenegen.experiment.transfer_sources import choose_reference_sets
from scenegen.policy.panels import panel_id, panel_ids
from scenegen.policy.panels_v2 import panel_tags


def test_the_sets_are_the_transfer_experiments_a_plus_and_c_of_their_size():
    from scenegen.core.files import load_rows
    from scenegen.experiment.retrieval_curves import REFERENCE

    sets = training_sets(100)
    natural, rare = sets["natural"], sets["rare_rich"]
    assert len(natural) == len(rare) == 100 and natural[:60] == rare[:60]
    chosen = choose_reference_sets(load_rows(REFERENCE, "train"), 60, 100, 40, 20, panel_tags())
    assert [s.scene_id for s in natural] == [f"reference_{i:06d}" for i in (*chosen.a, *chosen.a_plus_extra)]
    extra = rare[60:]
    assert len({s.scene_id for s in extra} & {s.scene_id for s in natural}) == 0
    per_tag = Counter(tag for tag in chosen.c_tags)
    assert sorted(per_tag.values()) == [6, 6, 7, 7, 7, 7] and "under_overhang" not in per_tag
    assert all(any(s.tags.get(t) for t in panel_tags()) for s in extra)


def test_tiny_curves_train_score_and_report(tmp_path: Path):
    scored = {name: scenes[:3] for name, scenes in scoring_scenes().items()}
    assert not {panel_id(s) for s in scored["curve"]} & panel_ids()
    cache, heads = tmp_path / "frames", tmp_path / "heads"
    steps = {"classifier": 20, "separator": 15}
    records = [
        run_job(CurveJob(design, set_name, 10, seed), heads, cache, scored, steps)
        for design in ("instances", "candidates")
        for set_name in ("natural", "rare_rich")
        for seed in (0, 1)
    ]
    assert all(len(r["rows"]) == 6 and r["training_cpu_s"] > 0 for r in records)
    scores = heads / "instances" / "natural_10_s0" / "scores.jsonl"
    stamp = scores.stat().st_mtime_ns
    again = run_job(CurveJob("instances", "natural", 10, 0), heads, cache, scored, steps)
    assert scores.stat().st_mtime_ns == stamp and again["rows"] == records[0]["rows"]  # resumed, not rerun
    results = curve_results(records, replicates=200)
    cell = results["scored"]["curve"]["instances"]["all"][10]
    assert cell["natural"]["seeds"] == 2 and cell["natural"]["scenes"] == 3
    hits = np.mean([[r["hit_iou"] for r in rec["rows"] if r["set"] == "curve"] for rec in records[:2]])
    assert cell["natural"]["mean"] == round(float(hits), 4)
    assert cell["lead"]["low"] <= cell["lead"]["mean"] <= cell["lead"]["high"]
    assert "all" in results["scored"]["validation"]["candidates"]
    table = curve_table(results)
    assert table.count("\n") > 2 and "| instances | all | 3 | 10 |" in table
    assert set(leads(results)) == {"instances", "candidates"}
    png = plot_curves(results)
    import cv2

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (720, 1400, 3) and (image < 250).any()
    json.dumps(results)  # the benchmark writes it as JSON


def test_a_curve_job_through_a_sensor_trains_and_scores_on_its_frames_under_its_depth_rule(tmp_path: Path):
    from scenegen.perception.retrieval.frames import FrameCache, frames_key
    from scenegen.perception.retrieval.regions import DEPTH_RULES, SENSOR_RULE

    scored = {name: scenes[:1] for name, scenes in scoring_scenes().items()}
    cache, heads = tmp_path / "frames", tmp_path / "heads"
    job = CurveJob("instances", "natural", 6, 0)
    record = run_job(job, heads, cache, scored, {"classifier": 10, "separator": 100}, sensor="active_stereo")
    assert len(record["rows"]) == 2
    config = json.loads((heads / job.name / "config.json").read_text())
    assert config["depth_rule"] == DEPTH_RULES[SENSOR_RULE].config()
    store = FrameCache(cache)
    for scene in training_sets(6)["natural"]:
        sensed = store.get(frames_key(scene, sensor="active_stereo"))
        assert sensed is not None and (sensed.depth == 0).any()  # the sensor's frames, with its holes
        assert store.get(frames_key(scene)) is None  # and no exact ones
