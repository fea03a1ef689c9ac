"""Environment and export costs: reset into a new scene, a control step without and with camera
observations, each against plain MuJoCo doing the same physics in the same run (the baseline); and
the WebDataset export of the batch (scenes/s, MB/s) against copying its files (the baseline).

    .venv/bin/python benchmarks/env_step.py [--batch runs/demo] [--scenes 6] [--steps 100]
        [--camera-size 128 128]

A batch is generated into a temporary directory when none is given (pipelines/procedural.yaml, 6
scenes). The first environment's construction and its first steps (robosuite's numba warm-up) are
reported apart. Baseline: 25 mj_step calls of the same compiled model per control step (20 Hz control,
2 ms physics), i.e. the physics alone; the ratio is the environment's overhead (controller,
observables, rendering). Prints a table and saves JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np

from scenegen.env.robosuite_env import SceneEnv
from scenegen.env.scenes import batch_scenes
from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import run_batch

HOLD = np.array([0, 0, 0, 0, 0, 0, -1.0])


def timed(fn, repeat: int) -> float:
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat


def measure(scenes, steps: int, camera_size: tuple[int, int]) -> dict:
    start = time.perf_counter()
    env = SceneEnv(scenes[0])
    construct = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(20):
        env.step(HOLD)
    warm_up = (time.perf_counter() - start) / 20
    resets = [timed(lambda s=s: env.reset_to(s), 1) for s in scenes]
    rng = np.random.default_rng(0)
    step = timed(lambda: env.step(rng.uniform(-1, 1, 7)), steps)
    model, data = env.sim.model._model, env.sim.data._data
    substeps = int(round(env.control_timestep / env.model_timestep))
    physics = timed(lambda: [mujoco.mj_step(model, data) for _ in range(substeps)], steps)
    env.close()

    cam = SceneEnv(scenes[0], cameras=[scenes[0].cameras[0].name], camera_size=camera_size)
    cam.reset_to(scenes[0])
    cam.step(HOLD)  # renderer and context made
    camera_step = timed(lambda: cam.step(rng.uniform(-1, 1, 7)), max(steps // 4, 5))
    camera_reset = timed(lambda: cam.reset_to(scenes[1 % len(scenes)]), 3)
    cam.close()
    return {
        "construct_s": round(construct, 3),
        "first_steps_s_per_step": round(warm_up, 4),
        "reset_s": round(float(np.median(resets)), 4),
        "step_s": round(step, 5),
        "physics_baseline_s": round(physics, 5),
        "step_over_physics": round(step / physics, 2),
        "camera": f"1 camera at {camera_size[0]}x{camera_size[1]}",
        "step_with_camera_s": round(camera_step, 5),
        "camera_step_over_physics": round(camera_step / physics, 2),
        "reset_with_camera_s": round(camera_reset, 4),
    }


def measure_export(batch: Path) -> dict:
    """WebDataset export of ``batch`` against a plain copy of the same files."""
    import shutil

    from scenegen.export.scene_shards import export_webdataset

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        description = export_webdataset(batch, Path(tmp) / "shards")
        export_s = time.perf_counter() - start
        size = sum(p.stat().st_size for p in (Path(tmp) / "shards").glob("*.tar"))
        start = time.perf_counter()
        shutil.copytree(batch, Path(tmp) / "copy")
        copy_s = time.perf_counter() - start
    scenes = description["counts"]["scenes"]
    return {
        "export_scenes_per_s": round(scenes / export_s, 2),
        "export_mb_per_s": round(size / 1e6 / export_s, 1),
        "export_over_copy": round(export_s / copy_s, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=Path, help="a stored batch (default: generate 6 scenes)")
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--camera-size", type=int, nargs=2, default=[128, 128], metavar=("W", "H"))
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/env_step.json"))
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        batch = args.batch
        if batch is None:
            batch = Path(tmp) / "batch"
            config = load_pipeline(Path("pipelines/procedural.yaml"), {"n": args.scenes, "seed": 0})
            run_batch(config, batch, workers=1, progress=False)
        scenes = batch_scenes(batch)[: args.scenes]
        result = measure(scenes, args.steps, tuple(args.camera_size))
        result |= measure_export(batch)
    result |= {"scenes": len(scenes), "machine": platform.processor() or platform.machine()}
    width = max(len(k) for k in result)
    for key, value in result.items():
        print(f"{key:{width}s}  {value}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {args.json}")


if __name__ == "__main__":
    main()
