"""CPU per decision of the proposal model (issue 63, point 3: the goal is under 0.2 CPU-s), split into
what every policy pays to see (the frames: render, depth, the target's mask through the oracle or a
head) and what the proposal model adds (sampling the candidates, their crops and features, scoring).
The frames are the baseline: the hand chooser pays them too (its network on them costs little).

    .venv/bin/python benchmarks/proposal_decision.py [--layouts 12] [--model assets/proposals/natural600]
        [--retrieval oracle|head|FOLDER] [--json benchmarks/results/proposal_decision.json]

On the first ``--layouts`` validation layouts (feasible ones) at their settled state: each stage's
process CPU-s per decision, one thread (torch and BLAS), after one warm-up decision that loads the
models. The candidates are the closed loop's (``proposal_loop.DECISIONS``: 24 from above, 8 from the
side, 2 pushes, 2 pulls).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def measure(scenes, model: Path, retrieval: Path | None) -> dict[str, list[float]]:
    """Per scene, the CPU-s of each stage of one decision at its settled state."""
    from scenegen.env.physics import DEFAULT_PHYSICS, physics_named
    from scenegen.env.scenes import scene_sha256
    from scenegen.experiment.closed_loop import episode_env, loaded_perception
    from scenegen.experiment.proposal_data import seen_frames
    from scenegen.experiment.proposal_labels import point_rng
    from scenegen.experiment.proposal_loop import DECISIONS, loaded_model
    from scenegen.manipulation.proposals import sample_candidates

    physics = physics_named(DEFAULT_PHYSICS)
    perception = loaded_perception(retrieval)
    proposals = loaded_model(model)
    stages: dict[str, list[float]] = {"frames": [], "sample": [], "score": []}
    for number, scene in enumerate([scenes[0], *scenes]):  # the first: a warm-up, not counted
        env = episode_env(scene, physics)
        env.reset_to(scene)
        clock = time.process_time()
        frames, cameras, view = seen_frames(env, perception)
        seen = time.process_time()
        if view is None:
            continue
        candidates = sample_candidates(view, point_rng(0, scene_sha256(scene), []), DECISIONS.sampler)
        sampled = time.process_time()
        proposals.rank(candidates, view, frames, cameras)
        scored = time.process_time()
        if number:
            for name, value in zip(stages, (seen - clock, sampled - seen, scored - sampled), strict=True):
                stages[name].append(value)
    return stages


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--layouts", type=int, default=12, help="validation layouts (default 12)")
    parser.add_argument("--model", type=Path, default=ROOT / "assets" / "proposals" / "natural600")
    parser.add_argument(
        "--retrieval", default="oracle", help="oracle (true masks), head (the default), or a head folder"
    )
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    import torch

    from scenegen.core.files import CheckpointError
    from scenegen.experiment.proposal_labels import label_layouts
    from scenegen.perception.retrieval import DEFAULT_HEAD

    torch.set_num_threads(1)
    scenes = label_layouts(["validation"], limit=args.layouts)["validation"]
    retrieval = {"oracle": None, "head": DEFAULT_HEAD}.get(args.retrieval, Path(args.retrieval))
    try:
        stages = measure(scenes, args.model, retrieval)
    except CheckpointError as exc:
        parser.error(str(exc))
    n = len(stages["frames"])
    summary = {name: round(statistics.mean(v), 4) for name, v in stages.items()}
    summary["proposal_model"] = round(summary["sample"] + summary["score"], 4)
    print(f"{n} decisions, {args.retrieval}: CPU-s per decision (mean)")
    for name, value in summary.items():
        print(f"  {name:15s} {value:.4f}")
    print(f"  proposal model / frames: {summary['proposal_model'] / summary['frames']:.2f}x")
    if args.json:
        record = {"decisions": n, "retrieval": args.retrieval, "layouts": args.layouts, **summary}
        args.json.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
