"""What a depth sensor does to the retrieval head's region step (issue 45's "next"; docs/transfer.md,
"Result"; issue 62 for the active stereo sensor): measured on frames, not in closed loop.

    MUJOCO_GL=egl .venv/bin/python benchmarks/depth_noise_regions.py [PER_PANEL] [SENSOR]   # ~1 min at 2

SENSOR: ``structured_light`` (default; results in depth_noise_regions.json) or ``active_stereo``
(depth_noise_regions_active_stereo.json).

For the first PER_PANEL (default 2) layouts of each rare panel of the version 2 panels' validation
side, at the first decision, per camera: the share of the table top that ``regions.foreground``
takes for an object, the candidate regions per frame (``regions.candidate_regions``) and the share
of the target's pixels inside any candidate region, for exact depth, the sensor's noisy depth, and
the noisy depth with its missing pixels filled from their nearest valid neighbour (then a 5 x 5
median). Writes benchmarks/results/depth_noise_regions.json; changes nothing in the package.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from scenegen.perception.retrieval import regions

RESULTS = Path(__file__).parent / "results" / "depth_noise_regions.json"
RARE = ("near_edge", "toppled", "occluded", "clutter", "stacked", "low_light")
TABLE_TOP_TOL = 0.001  # m: a table-top pixel's exact world point lies within this of the top
ABOVE_MM = (5, 8, 12)  # foreground thresholds tried on the filled, smoothed depth


FILL, MEDIAN5 = regions.DepthRule(fill=True), regions.DepthRule(median=5)  # the head's own mending


def frame_rows(scene, observations: dict, sensed: dict, cameras) -> list[dict]:
    """Per camera and depth variant (``observations``: exact frames, ``sensed``: the sensor's):
    table-top pixels counted foreground, regions, target pixels in a region (counts, pooled by the
    caller)."""
    from scenegen.perception.points import masked_points
    from scenegen.perception.retrieval import regions

    ids, rows = scene.segmentation, []
    for camera in scene.cameras:
        if camera.name not in cameras:
            continue
        exact = np.squeeze(observations[f"{camera.name}_depth"], -1).astype(np.float32)
        seg = np.squeeze(observations[f"{camera.name}_segmentation"], -1)
        robot, target = seg == ids["robot"], seg == scene.target_id
        noisy = np.squeeze(sensed[f"{camera.name}_depth"], -1).astype(np.float32)
        world = masked_points(exact, np.ones_like(exact, bool), camera).reshape(*exact.shape, 3)
        top = (
            (seg == ids["table"])
            & (np.abs(world[..., 2] - regions.TABLE_TOP) < TABLE_TOP_TOL)
            & (np.abs(world[..., 0]) <= regions.TABLE_HALF[0])
            & (np.abs(world[..., 1]) <= regions.TABLE_HALF[1])
        )
        mended = FILL.mend(noisy)
        variants = {
            "exact": exact,
            "noisy": noisy,
            "noisy, holes filled": mended,
            "noisy, holes filled, median 5": MEDIAN5.mend(mended),
        }
        rules = {name: {} for name in variants}
        smooth = MEDIAN5.mend(mended)
        for mm in ABOVE_MM:  # the foreground's height threshold, for a sensor whose depth is not exact
            variants[f"noisy, filled, median 5, above {mm} mm"] = smooth
            rules[f"noisy, filled, median 5, above {mm} mm"] = {"above": mm / 1000}
        for mm in ABOVE_MM:  # ... with the robot's mask widened and the table's plane fitted per frame
            name = f"noisy, filled, median 5, above {mm} mm, robot +4 px, table fitted"
            variants[name] = smooth
            rules[name] = {"above": mm / 1000, "robot_margin": 4, "table_fit": True}
        for name, depth in variants.items():
            keep, _ = regions.foreground(depth, robot, camera, **rules[name])
            found = regions.candidate_regions(depth, robot, camera, **rules[name])
            inside = np.any(found, axis=0) if found else np.zeros_like(keep)
            rows.append(
                {
                    "variant": name,
                    "table": int(top.sum()),
                    "table_foreground": int((keep & top).sum()),
                    "regions": len(found),
                    "target": int(target.sum()),
                    "target_in_region": int((inside & target).sum()),
                }
            )
    return rows


def main(per_panel: int, sensor: str = "structured_light") -> dict:
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.perception.observation import CAMERA_SIZE, CAMERAS
    from scenegen.policy.labels import HORIZON
    from scenegen.policy.panels_v2 import load_panels_v2, panel_id, panel_scenes
    from scenegen.render.sensor import SENSORS

    panels = load_panels_v2()
    chosen = {"validation": {p: panels["validation"][p][:per_panel] for p in RARE}}  # never the test side
    rows, env = [], None
    for scenes in panel_scenes(chosen, "validation").values():
        for scene in scenes:
            if env is None:
                env = SceneEnv(
                    scene, cameras=CAMERAS, camera_size=CAMERA_SIZE, render_each_step=False, horizon=HORIZON
                )
            env.reset_to(scene)
            observed = env.camera_observations(image=False)
            env.depth_sensor = (SENSORS[sensor], f"{panel_id(scene)}|regions")
            sensed = env.camera_observations()  # with the colour frame, as at a decision
            rows += frame_rows(scene, observed, sensed, CAMERAS)
    if env is not None:
        env.close()
    pooled = {}
    for variant in dict.fromkeys(r["variant"] for r in rows):
        mine = [r for r in rows if r["variant"] == variant]
        pooled[variant] = {
            "table_top_counted_foreground": round(
                sum(r["table_foreground"] for r in mine) / sum(r["table"] for r in mine), 4
            ),
            "regions_per_frame": round(float(np.mean([r["regions"] for r in mine])), 2),
            "target_pixels_in_a_region": round(
                sum(r["target_in_region"] for r in mine) / sum(r["target"] for r in mine), 4
            ),
        }
    frames = sum(r["variant"] == "exact" for r in rows)
    return {"sensor": sensor, "layouts": per_panel * len(RARE), "frames": frames, "pooled": pooled}


if __name__ == "__main__":
    sensor = sys.argv[2] if len(sys.argv) > 2 else "structured_light"
    result = main(int(sys.argv[1]) if len(sys.argv) > 1 else 2, sensor)
    if sensor != "structured_light":
        RESULTS = RESULTS.with_name(f"depth_noise_regions_{sensor}.json")
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=1) + "\n")
    for variant, figures in result["pooled"].items():
        print(f"{variant:32s} " + ", ".join(f"{k} {v}" for k, v in figures.items()))
    print(f"{result['layouts']} layouts, {result['frames']} frames -> {RESULTS}")
