"""Cheaper physics for the control loop, screened: each setting's CPU and outcomes against today's.

    .venv/bin/python benchmarks/physics_screen.py [--layouts 100] [--offset 0]
        [--settings exact,dt5,...] [--workers 2] [--out runs/physics_screen]

Layouts: the reference set's training layouts that the committed label store of transfer v2
(assets/transfer/v2/labels.parquet) labelled with all five primitives under today's physics, that no
panel of either transfer version holds and whose target is reachable, in the reference table's order;
``--offset``/``--layouts`` pick a run of them (the screen takes the first 100, a confirmation a later,
disjoint run). Every setting executes every primitive from a reset into every layout, as `scenegen
label` labels a scene (the oracle's observation, ``run_primitive``), in worker processes (one
environment per setting each); each labelled scene's CPU-seconds (``time.process_time``, the whole
process: physics, controller, the decision renders, the planners) and, inside it, the physics
(``mj_step1`` + ``mj_step2``) and the controller (``_pre_action``). Rows go to ``<out>/rows.jsonl``
as they finish; a rerun continues (a setting is keyed by ``ControlPhysics.key()``, all its fields).

The report (``<out>/report.md``, printed): per setting, CPU per labelled scene and its ratio to
``exact`` measured in the same run, and per primitive the success rate against today's labels of the
same layouts, paired by layout: the difference with a 95 % interval (normal approximation of the
paired differences' mean), the share of flipped outcomes, and lift and duration quantiles. ``exact``
itself is compared with the stored labels too: it must reproduce them (the stored side is today's
physics only if it does).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scenegen.env.physics import PHYSICS, ControlPhysics  # noqa: E402

EXACT = PHYSICS["exact"]
# Each lever alone (issue 61's list); combinations are added by name with '+' (dt5+hull).
LEVERS: dict[str, dict] = {
    "exact": {},
    "dt2.5": {"timestep": 0.0025},
    "dt3.3": {"timestep": 1 / 300},
    "dt4.2": {"timestep": 1 / 240},
    "dt5": {"timestep": 0.005},
    "iter": {"iterations": 20, "ls_iterations": 10},
    "tol": {"tolerance": 1e-6},
    "cg": {"solver": "cg"},
    "pyramidal": {"cone": "pyramidal"},
    "hull": {"table_contact": "hull"},
    "ccd": {"ccd_iterations": 10, "ccd_tolerance": 1e-4},
    "nomulticcd": {"multiccd": False},
    "margin0": {"object_margin": 0.0},
}
PRIMITIVE_ORDER = (
    "top_grasp",
    "side_grasp",
    "toppled_grasp",
    "push_from_edge_then_grasp",
    "pull_out_then_grasp",
)


def setting(name: str) -> ControlPhysics:
    """A lever's physics, or several levers joined by '+'."""
    changes: dict = {}
    for part in name.split("+"):
        if part not in LEVERS:
            known = ", ".join(LEVERS)
            raise SystemExit(f"--settings: unknown lever {part!r}; choose from {known} (join with '+')")
        changes.update(LEVERS[part])
    return EXACT.with_changes(name, **changes)


# ------------------------------------------------------------------------------ in a worker
_CLOCK = {"physics": 0.0, "control": 0.0}


def _timed(fn, bucket):
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            _CLOCK[bucket] += time.process_time() - t0

    return wrapper


def init_worker() -> None:
    """A labelling worker (policy.labels) whose physics and controller are clocked."""
    from robosuite.utils.binding_utils import MjSim

    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.policy import labels

    labels._init_worker()
    MjSim.step1 = _timed(MjSim.step1, "physics")
    MjSim.step2 = _timed(MjSim.step2, "physics")
    SceneEnv._pre_action = _timed(SceneEnv._pre_action, "control")


def label_scene(job: tuple[dict, dict]) -> dict:
    """Every primitive from a reset into one layout under one physics: outcomes and CPU."""
    from scenegen.env.robosuite_env import worker_env
    from scenegen.env.scenes import reference_scene
    from scenegen.manipulation.rollout import run_primitive
    from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON

    physics, row = ControlPhysics.model_validate(job[0]), job[1]
    scene = reference_scene(row)
    options = {"cameras": CAMERAS, "camera_size": CAMERA_SIZE, "render_each_step": False, "horizon": HORIZON}
    env = worker_env(scene, physics=physics, **options)
    if not getattr(env, "_screen_warm", False):  # GL context, uploads, compiled kernels: off the clock
        env.reset_to(scene)
        run_primitive(env, "top_grasp")
        env._screen_warm = True
    _CLOCK.update(physics=0.0, control=0.0)
    c0, steps, outcomes = time.process_time(), 0, {}
    for name in PRIMITIVE_ORDER:
        env.reset_to(scene)
        outcome, _ = run_primitive(env, name)
        steps += env.timestep
        outcomes[name] = {
            "success": bool(outcome.success),
            "lift": round(float(outcome.lift), 6),
            "duration": round(float(outcome.time), 4),
            "failure": outcome.failure(),
        }
    return {
        "setting": physics.name,
        "key": physics.key(),
        "scene_id": scene.scene_id,
        "cpu": round(time.process_time() - c0, 4),
        "physics_cpu": round(_CLOCK["physics"], 4),
        "control_cpu": round(_CLOCK["control"], 4),
        "control_steps": steps,
        "outcomes": outcomes,
    }


# ------------------------------------------------------------------------------ the driver
def screen_layouts(offset: int, n: int) -> tuple[list[dict], dict[str, dict]]:
    """Reference rows (module doc) and today's stored labels of each, by scene id."""
    import pyarrow.parquet as pq

    from scenegen.core.files import load_rows
    from scenegen.env.scenes import reference_scene, scene_sha256
    from scenegen.manipulation.task import feasible
    from scenegen.policy.labels import current_rows
    from scenegen.policy.panels import outside_panels

    labels = pq.read_table(ROOT / "assets/transfer/v2/labels.parquet").to_pylist()
    stored, _ = current_rows([labels], physics="exact")  # the stored labels are exact's
    by_sha: dict[str, dict] = defaultdict(dict)
    for r in stored:
        by_sha[r["scene_sha256"]][r["primitive"]] = r
    rows = load_rows(ROOT / "assets/reference/reference.parquet", "train")
    scenes = {s.scene_id: (s, r) for r in rows for s in [reference_scene(r)]}
    kept = {s.scene_id for s in outside_panels([s for s, _ in scenes.values()])}
    chosen, labels = [], {}
    for scene_id, (scene, row) in scenes.items():
        if scene_id not in kept or not feasible(scene):
            continue
        done = by_sha.get(scene_sha256(scene), {})
        if set(done) >= set(PRIMITIVE_ORDER):
            chosen.append(row)
            labels[scene_id] = done
    picked = chosen[offset : offset + n]
    if len(picked) < n:
        raise SystemExit(f"--offset {offset} --layouts {n}: only {len(chosen)} layouts have stored labels")
    return picked, {reference_scene(r).scene_id: labels[reference_scene(r).scene_id] for r in picked}


def paired(a: list[bool], b: list[bool]) -> tuple[float, float, float, float]:
    """Rate difference b - a with a 95 % interval (paired by position) and the share that flipped."""
    d = [int(y) - int(x) for x, y in zip(a, b, strict=True)]
    n = len(d)
    mean = sum(d) / n
    sd = statistics.pstdev(d) if n > 1 else 0.0
    half = 1.96 * sd / math.sqrt(n) if n > 1 else float("nan")
    return mean, mean - half, mean + half, sum(1 for x in d if x) / n


def quantiles(values: list[float]) -> str:
    q = statistics.quantiles(values, n=4) if len(values) > 1 else [values[0]] * 3
    return f"{q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f}"


def _median(rows: dict[str, dict], scenes, field: str) -> float:
    return statistics.median(rows[s][field] for s in scenes)


def report(results: dict[str, dict[str, dict]], labels: dict[str, dict], scenes: list[str]) -> str:
    lines = [
        f"Physics screen: {len(scenes)} layouts (module doc), every primitive from a reset; "
        "CPU per labelled scene (median over layouts; inside it the physics and the controller); "
        "outcomes against today's stored labels, paired by layout.",
        "",
        "| setting | layouts | CPU-s / scene | ratio to exact (layouts) | physics | control | steps |",
        "|---|---|---|---|---|---|---|",
    ]
    exact = results.get("exact", {})
    for name, rows in results.items():
        got = [rows[s] for s in scenes if s in rows]
        if not got:
            continue
        # the ratio over the layouts both ran (exact may run on the first few only: its outcomes are
        # the stored labels', its CPU is what a ratio needs)
        both = [s for s in scenes if s in rows and s in exact]
        ratio = _median(rows, both, "cpu") / _median(exact, both, "cpu") if both else float("nan")
        by = {s: rows[s] for s in scenes if s in rows}
        lines.append(
            f"| {name} | {len(got)} | {_median(by, by, 'cpu'):.2f} | {ratio:.3f} ({len(both)}) "
            f"| {_median(by, by, 'physics_cpu'):.2f} | {_median(by, by, 'control_cpu'):.2f} "
            f"| {_median(by, by, 'control_steps'):.0f} |"
        )
    lines += [
        "",
        "Success against today's labels (same layouts): rate today -> rate under the setting, difference "
        "with 95 % interval, flipped share; lift (m) and duration (s) quartiles under the setting "
        "(today's in the first row of each primitive).",
        "",
        "| setting | primitive | today | setting | difference [95 %] | flipped "
        "| lift q1/q2/q3 | duration q1/q2/q3 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in results.items():
        done = [s for s in scenes if s in rows]
        if not done:
            continue
        for prim in PRIMITIVE_ORDER:
            a = [bool(labels[s][prim]["success"]) for s in done]
            b = [rows[s]["outcomes"][prim]["success"] for s in done]
            diff, lo, hi, flip = paired(a, b)
            lifts = [rows[s]["outcomes"][prim]["lift"] for s in done]
            durs = [rows[s]["outcomes"][prim]["duration"] for s in done]
            lines.append(
                f"| {name} | {prim} | {sum(a) / len(a):.3f} | {sum(b) / len(b):.3f} "
                f"| {diff:+.3f} [{lo:+.3f}, {hi:+.3f}] | {flip:.3f} "
                f"| {quantiles(lifts)} | {quantiles(durs)} |"
            )
    today = [
        f"| today (stored) | {p} | | | | | {quantiles([labels[s][p]['lift'] for s in scenes])} "
        f"| {quantiles([labels[s][p]['duration'] for s in scenes])} |"
        for p in PRIMITIVE_ORDER
    ]
    return "\n".join(lines + today) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layouts", type=int, default=100, help="layouts (default 100)")
    parser.add_argument("--offset", type=int, default=0, help="first layout of the run (default 0)")
    parser.add_argument(
        "--settings",
        default=",".join(LEVERS),
        help=f"comma-separated levers, '+' joins ({', '.join(LEVERS)}; default all, each alone)",
    )
    parser.add_argument(
        "--exact-layouts",
        type=int,
        default=None,
        help="run exact on the first N layouts only (its outcomes are the stored labels'; default all)",
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-run", action="store_true", help="report what the log holds, run nothing")
    parser.add_argument("--out", type=Path, default=ROOT / "runs/physics_screen")
    args = parser.parse_args()
    settings = [setting(s) for s in args.settings.split(",") if s]
    from tqdm import tqdm

    from scenegen.env.scenes import reference_scene
    from scenegen.runner.executors import ordered_map
    from scenegen.store.batch import recover_jsonl

    rows, labels = screen_layouts(args.offset, args.layouts)
    ids = [reference_scene(r).scene_id for r in rows]
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "rows.jsonl"
    done = {(r["key"], r["scene_id"]): r for r in recover_jsonl(log)}
    exact_n = args.layouts if args.exact_layouts is None else args.exact_layouts
    jobs = [
        (p.model_dump(), row)
        for i, (row, scene_id) in enumerate(zip(rows, ids, strict=True))
        for p in settings
        if (p.key(), scene_id) not in done and (p.name != "exact" or i < exact_n) and not args.no_run
    ]
    with open(log, "a") as sink:
        found_rows = ordered_map(label_scene, jobs, args.workers, init_worker)
        for found in tqdm(found_rows, total=len(jobs), desc="screen"):
            sink.write(json.dumps(found, sort_keys=True) + "\n")
            sink.flush()
            done[(found["key"], found["scene_id"])] = found
    results = {p.name: {s: done[(p.key(), s)] for s in ids if (p.key(), s) in done} for p in settings}
    text = report(results, labels, ids)
    (args.out / "report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
