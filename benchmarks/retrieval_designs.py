"""The retrieval head's two designs side by side (docs/retrieval.md), trained on the same reference
scenes and measured on the same held-out ones: (a) the segmenter with a plane per category
(perception/retrieval/model.py) and (b) depth candidates with a crop classifier
(perception/retrieval/candidates.py). Reports the training CPU seconds of each and, per tag, scene
hit, IoU, hit, wrong-object, miss and false-alarm rates on nominal held-out layouts and on every
unique-category held-out rare layout (a scene with two mugs makes "the mug" ambiguous).

    .venv/bin/python benchmarks/retrieval_designs.py [--train 1000] [--nominal 300] [--steps 1500]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from scenegen.assets.catalog import load_catalog
from scenegen.env.scenes import load_scenes
from scenegen.env.scenes import unique_category as unique
from scenegen.manipulation.task import feasible
from scenegen.perception.retrieval.candidates import CandidatePicker, train_classifier
from scenegen.perception.retrieval.evaluate import head_predictor, scene_metrics, summarise, summary_table
from scenegen.perception.retrieval.frames import scene_frames
from scenegen.perception.retrieval.model import RetrievalHead
from scenegen.perception.retrieval.train import retrieval_data, train_head
from scenegen.policy.panels import outside_panels

REFERENCE = Path("assets/reference/reference.parquet")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=int, default=1000, help="reference training scenes (default 1000)")
    parser.add_argument("--nominal", type=int, default=300, help="held-out nominal scenes (default 300)")
    parser.add_argument("--steps", type=int, default=2000, help="segmenter steps (default 2000)")
    parser.add_argument(
        "--segmenter", type=Path, help="a segmenter checkpoint trained on the same scenes (skips training it)"
    )
    parser.add_argument("--cache", type=Path, default=Path("runs/cache/frames"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/retrieval_designs"))
    parser.add_argument(
        "--heads", type=Path, default=Path("runs/retrieval_designs"), help="the trained heads (untracked)"
    )
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)  # CPU seconds are the budget: one thread, no oversubscription

    train = [s for s in load_scenes(REFERENCE, "train") if feasible(s)][: args.train]
    held = [s for s in load_scenes(REFERENCE, "heldout") if feasible(s)]
    panels = {
        "nominal": [s for s in held if s.tags.get("nominal") and unique(s)][: args.nominal],
        # no layout of either side of the version 2 panels: the rare figures are held-out reporting
        "rare_unique": outside_panels(
            [s for s in held if not s.tags.get("nominal") and unique(s)], version1=False
        ),
    }
    everything = train + [s for p in panels.values() for s in p]
    list(scene_frames(everything, args.cache, args.workers, progress=True))  # render what is missing
    categories = list(load_catalog().categories)

    results = {}
    if args.segmenter is None:
        args.segmenter = args.heads / "segmenter"
        data = retrieval_data(train, scene_frames(train, args.cache), categories)
        train_head(data, args.segmenter, steps=args.steps, progress=True)
        del data
    head = RetrievalHead.load(args.segmenter)
    predictors = {"a_segmenter": head_predictor(head)}
    results["a_segmenter"] = {
        "checkpoint": str(args.segmenter),
        "train_cpu_seconds": head.trained_on["cpu_seconds"],
    }
    summary = train_classifier(train, scene_frames(train, args.cache), categories, args.heads / "candidates")
    predictors["b_candidates"] = CandidatePicker(args.heads / "candidates").predict
    results["b_candidates"] = {
        "train_cpu_seconds": summary["cpu_seconds"],
        "candidates": summary["candidates"],
        "no_object_share": summary["no_object_share"],
    }
    for design, predict in predictors.items():
        for panel, scenes in panels.items():
            started = time.process_time()
            rows = [
                scene_metrics(predict, s, f)
                for s, f in zip(scenes, scene_frames(scenes, args.cache), strict=True)
            ]
            results[design][panel] = summarise(rows)
            results[design][f"{panel}_cpu_seconds_per_scene"] = round(
                (time.process_time() - started) / len(rows), 4
            )
            print(f"\n## {design}, {panel} ({len(rows)} scenes)\n")
            print(
                summary_table(
                    {"all": results[design][panel]["all"], "per_tag": results[design][panel]["per_tag"]}
                )
            )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps({d: {k: v for k, v in r.items() if "cpu" in k} for d, r in results.items()}, indent=1))


if __name__ == "__main__":
    main()
