"""Cost of the recovery task's control loop, the code at a baseline commit against this checkout, in
the same run, outcomes compared bit for bit.

    .venv/bin/python benchmarks/primitives.py [--scenes 4] [--episodes 12] [--repeats 2]
        [--baseline c20c117 | --no-baseline] [--physics NAME]

Two measurements, each in a fresh process per code version (the baseline's files extracted with
`git archive` and run with this virtual environment), alternated ``--repeats`` times:
- ``label``: a labelled scene, what `scenegen label` runs per scene: each of the five primitives from
  a reset into the first ``--scenes`` nominal layouts of the reference set's training split, through
  the oracle (``run_primitive``). CPU-seconds (time.process_time, every thread of the process) per
  scene, control steps, and per attempt the outcome (success, lift, times, contacts, events) and the
  full ``qpos`` at every decision point (the first observation and each re-observation) and at the end.
- ``episode``: closed-loop episodes of the committed policy through the committed retrieval head on
  the first ``--episodes`` layouts of the version 2 validation panels, fresh sequence and
  observation stores (``evaluate_policies`` in this process), CPU-seconds per episode, and every
  episode record and every stored sequence row (its ``qpos`` included).
This checkout runs under ``--physics`` (default: the control loop's default physics, env/physics.py).
Under ``exact``, outcomes must be equal between the versions (the script says so, and exits 1 if they
differ); under another physics they are expected to move, and the script counts the attempts and
episodes whose outcome differs (whether they move beyond their noise is benchmarks/physics_screen.py's
question, on hundreds of layouts). The ratio is this checkout's CPU over the baseline's, medians over
the repeats. Prints a table and saves JSON. (Issue 44 measured against 9430f21, issue 61 against
c20c117.)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

from baseline import ROOT, add_child_arguments, baseline_tree, child_main, run_child

# ------------------------------------------------------------------------------ in the child


def measure_label(scenes: int, physics: str | None = None) -> dict:
    import numpy as np

    import scenegen.manipulation.rollout as rollout
    from scenegen.core.files import load_rows
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.env.scenes import reference_scene
    from scenegen.manipulation.primitives import PRIMITIVES
    from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON

    rows = [r for r in load_rows(ROOT / "assets/reference/reference.parquet", "train") if r["tag_nominal"]]
    layouts = [reference_scene(r) for r in rows[:scenes]]
    options = {"cameras": CAMERAS, "camera_size": CAMERA_SIZE, "render_each_step": False, "horizon": HORIZON}
    if physics is not None:  # this checkout's; a baseline from before the setting knows none
        options["physics"] = physics
    env = SceneEnv(layouts[0], **options)
    seen: list[list[float]] = []
    observe = rollout.observe

    def recording(env, *args, **kwargs):  # every decision point's state, then the real observation
        seen.append(env.sim.data._data.qpos.tolist())
        return observe(env, *args, **kwargs)

    rollout.observe = recording
    env.reset_to(layouts[0])
    rollout.run_primitive(env, "top_grasp")  # GL context, uploads, compiled kernels: outside the clock
    cpu, steps, outcomes = [], [], []
    for scene in layouts:
        c0, n = time.process_time(), 0
        for name in PRIMITIVES:
            seen.clear()
            env.reset_to(scene)  # each label job starts from a reset
            outcome, params = rollout.run_primitive(env, name)
            n += env.timestep
            outcomes.append(
                {
                    "scene": scene.scene_id,
                    "primitive": name,
                    "outcome": {k: v for k, v in vars(outcome).items()},
                    "steps": env.timestep,
                    "decision_qpos": list(seen),
                    "final_qpos": env.sim.data._data.qpos.tolist(),
                    "params": json.loads(json.dumps(params, default=lambda x: np.asarray(x).tolist())),
                }
            )
        cpu.append(time.process_time() - c0)
        steps.append(n)
    env.close()
    return {"cpu_per_scene": cpu, "steps_per_scene": steps, "outcomes": outcomes}


def measure_episode(episodes: int, physics: str | None = None) -> dict:
    from scenegen.experiment.closed_loop import Cost, Workers, evaluate_policies
    from scenegen.experiment.sequences import ObservationStore, PathStore
    from scenegen.paths import ASSETS_DIR
    from scenegen.perception.retrieval import DEFAULT_HEAD
    from scenegen.policy.network import PrimitivePolicy
    from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes

    panel = panel_scenes(load_panels_v2(ASSETS_DIR / "panels" / "v2" / "panels.json"), "validation")
    unique = {}
    for scenes in panel.values():
        for s in scenes:
            unique.setdefault(s.scene_id, s)
    layouts = list(unique.values())[:episodes]
    policy = PrimitivePolicy.load(ASSETS_DIR / "policy" / "baseline")
    with tempfile.TemporaryDirectory() as tmp:
        store, observations = (
            PathStore(Path(tmp) / "paths.jsonl"),
            ObservationStore(Path(tmp) / "observations"),
        )
        cost = Cost()
        c0 = time.process_time()
        with Workers(1, physics) if physics is not None else Workers(1) as workers:
            records = evaluate_policies(
                {"policy": policy},
                layouts,
                store,
                observations,
                retrieval=DEFAULT_HEAD,
                cost=cost,
                workers=workers,
            )
        cpu = time.process_time() - c0
        rows = [json.loads(line) for line in (Path(tmp) / "paths.jsonl").read_text().splitlines()]
    return {
        "cpu_per_episode": cpu / len(layouts),
        "cost": cost.summary(len(layouts)),
        "outcomes": {"records": records, "rows": sorted(rows, key=lambda r: r["key"])},
    }


def measure(spec: dict) -> dict:
    if spec["kind"] == "label":
        return measure_label(spec["scenes"], spec.get("physics"))
    return measure_episode(spec["episodes"], spec.get("physics"))


# ------------------------------------------------------------------------------ the driver
def moved(kind: str, mine, theirs) -> str:
    """``identical``, or how many successes differ: of the attempts (label) or the episodes."""
    if mine == theirs:
        return "identical"
    if kind == "label":
        pairs = [
            (m["outcome"]["success"], t["outcome"]["success"]) for m, t in zip(mine, theirs, strict=True)
        ]
    else:
        pairs = [
            (m["success"], t["success"]) for m, t in zip(mine["records"], theirs["records"], strict=True)
        ]
    return f"{sum(a != b for a, b in pairs)} of {len(pairs)} successes differ"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=4, help="labelled scenes (default 4)")
    parser.add_argument("--episodes", type=int, default=12, help="closed-loop episodes (default 12; 0: none)")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each version, alternated (default 2)")
    parser.add_argument(
        "--baseline", default="c20c117", help="commit whose code is the baseline (default c20c117)"
    )
    parser.add_argument(
        "--physics", default=None, help="the physics this checkout runs under (default: its default physics)"
    )
    parser.add_argument("--no-baseline", dest="baseline", action="store_const", const=None)
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/primitives.json"))
    add_child_arguments(parser)
    args = parser.parse_args()
    if child_main(args, measure):
        return
    sys.path.insert(0, str(ROOT))
    from scenegen.env.physics import DEFAULT_PHYSICS, physics_named

    physics = args.physics or DEFAULT_PHYSICS
    exact = physics_named(physics).key() == physics_named("exact").key()

    kinds = [{"kind": "label", "scenes": args.scenes}]
    if args.episodes > 0:
        kinds.append({"kind": "episode", "episodes": args.episodes})
    results: dict[str, dict[str, list]] = {k["kind"]: {} for k in kinds}
    with tempfile.TemporaryDirectory() as tmp:
        code = {"current": ROOT}
        if args.baseline:
            code = {"baseline": baseline_tree(args.baseline, Path(tmp) / "baseline"), **code}
        for repeat in range(args.repeats):
            for spec in kinds:
                for version in code if repeat % 2 == 0 else reversed(list(code)):
                    print(f"{spec['kind']} {version} (run {repeat + 1}) ...", flush=True)
                    child = spec if version == "baseline" else {**spec, "physics": physics}
                    results[spec["kind"]].setdefault(version, []).append(
                        run_child(__file__, child, code[version])[0]
                    )

    summary, differ = {}, []
    for kind, by_version in results.items():
        per = "cpu_per_scene" if kind == "label" else "cpu_per_episode"
        row = {}
        for version, runs in by_version.items():
            values = [statistics.mean(r[per]) if kind == "label" else r[per] for r in runs]
            row[version] = {
                "cpu_s": round(statistics.median(values), 3),
                "runs": [round(v, 3) for v in values],
            }
            if kind == "label":
                row[version]["control_steps_per_scene"] = statistics.mean(runs[0]["steps_per_scene"])
            else:
                row[version]["cost"] = runs[0]["cost"]
            reference = runs[0]["outcomes"]
            if any(r["outcomes"] != reference for r in runs[1:]):
                differ.append(f"{kind}: {version}'s repeats differ among themselves")
        if "baseline" in row:
            row["ratio"] = round(row["current"]["cpu_s"] / row["baseline"]["cpu_s"], 3)
            mine, theirs = by_version["current"][0]["outcomes"], by_version["baseline"][0]["outcomes"]
            row["outcomes_identical"] = mine == theirs
            row["outcomes_moved"] = moved(kind, mine, theirs)
            if mine != theirs and exact:
                differ.append(f"{kind}: outcomes differ between the baseline and this checkout")
        summary[kind] = row

    unit = {"label": "CPU-s per labelled scene", "episode": "CPU-s per closed-loop episode"}
    print(f"\nthis checkout under physics {physics_named(physics).key()}")
    print(f"| measure | baseline ({args.baseline}) | this checkout | ratio | outcomes |")
    print("|---|---|---|---|---|")
    for kind, row in summary.items():
        base = row.get("baseline", {}).get("cpu_s", "-")
        print(
            f"| {unit[kind]} | {base} | {row['current']['cpu_s']} | {row.get('ratio', '-')} "
            f"| {row.get('outcomes_moved', '-')} |"
        )
    payload = {
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "processor": platform.processor(),
        },
        "baseline": args.baseline,
        "physics": physics_named(physics).key(),
        "scenes": args.scenes,
        "episodes": args.episodes,
        "repeats": args.repeats,
        "summary": summary,
        "differences": differ,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(payload, indent=1) + "\n")
    print(f"-> {args.json}")
    if differ:
        print("\n".join(differ), file=sys.stderr)
        raise SystemExit(1)


if __name__ == "__main__":
    main()
