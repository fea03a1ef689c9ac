"""Cost of the recovery task's pieces: CPU-seconds per primitive execution (by primitive) and per
labelled scene (every primitive once), and the decision-point observation's render time, against one
control step of the same environment (the baseline, measured in the same run).

    .venv/bin/python benchmarks/primitives.py [--scenes 6] [--split train]

Scenes: the first N nominal layouts of the training split of the reference set. CPU-seconds are this
process's (time.process_time), wall seconds beside them. Prints a table and saves JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from scenegen.core.files import load_rows
from scenegen.env.robosuite_env import SceneEnv
from scenegen.env.scenes import reference_scene
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.rollout import run_primitive
from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON

REFERENCE = Path("assets/reference/reference.parquet")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--split", default="train")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/primitives.json"))
    args = parser.parse_args()

    rows = [r for r in load_rows(REFERENCE, args.split) if r["tag_nominal"]][: args.scenes]
    scenes = [reference_scene(r) for r in rows]
    env = SceneEnv(
        scenes[0], cameras=CAMERAS, camera_size=CAMERA_SIZE, render_each_step=False, horizon=HORIZON
    )
    env.reset_to(scenes[0])
    env.camera_observations()  # GL context and upload made
    for _ in range(20):  # robosuite's numba warm-up
        env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))
    cpu, wall, steps = defaultdict(list), defaultdict(list), defaultdict(list)
    render_cpu, render_wall, step_cpu = [], [], []
    for scene in scenes:
        for name in PRIMITIVES:
            env.reset_to(scene)
            c0, w0 = time.process_time(), time.perf_counter()
            env.camera_observations()
            render_cpu.append(time.process_time() - c0)
            render_wall.append(time.perf_counter() - w0)
            c0 = time.process_time()
            env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))
            step_cpu.append(time.process_time() - c0)
            env.reset_to(scene)
            c0, w0, t0 = time.process_time(), time.perf_counter(), env.timestep
            run_primitive(env, name)
            cpu[name].append(time.process_time() - c0)
            wall[name].append(time.perf_counter() - w0)
            steps[name].append(env.timestep - t0)
    env.close()
    step = float(np.median(step_cpu))
    result = {
        "scenes": len(scenes),
        "cameras": f"{len(CAMERAS)} x {CAMERA_SIZE[0]}x{CAMERA_SIZE[1]}",
        "control_step_cpu_s": round(step, 5),
        "observation_render_cpu_s": round(float(np.median(render_cpu)), 4),
        "observation_render_wall_s": round(float(np.median(render_wall)), 4),
        "observation_over_step": round(float(np.median(render_cpu)) / step, 1),
        "per_primitive": {
            name: {
                "cpu_s": round(float(np.mean(cpu[name])), 3),
                "wall_s": round(float(np.mean(wall[name])), 3),
                "control_steps": round(float(np.mean(steps[name])), 1),
                "cpu_over_steps_x_step": round(float(np.mean(cpu[name])) / (np.mean(steps[name]) * step), 2),
            }
            for name in PRIMITIVES
        },
        "per_labelled_scene_cpu_s": round(sum(float(np.mean(v)) for v in cpu.values()), 2),
        "machine": platform.processor() or platform.machine(),
    }
    print(json.dumps(result, indent=1))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {args.json}")


if __name__ == "__main__":
    main()
