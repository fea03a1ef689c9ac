"""One primitive, observed, planned and executed in a SceneEnv, its outcome measured by the simulator.

The observation is rendered once, at the decision point (before the primitive), from every camera the
environment observes: the target's points (its instance mask and depth, back-projected) and the other
instances' points (objects and furniture; not the table, the arena or the robot).
"""

from __future__ import annotations

import numpy as np

from scenegen.policy.motion import grip_site
from scenegen.policy.perception import estimate_target, target_points
from scenegen.policy.primitives import PRIMITIVES, TargetView
from scenegen.policy.task import RetrieveMonitor, RetrieveOutcome

BACKGROUND = ("arena", "table", "robot")


def observe(env) -> tuple[dict, TargetView | None]:
    """The camera observation now and what a planner sees in it (None: the target is not seen)."""
    obs = env.camera_observations()
    scene = env.scene
    cameras = {c.name: c for c in scene.cameras}
    background = {scene.segmentation[name] for name in BACKGROUND}
    target, others = [], []
    for name in env.cameras:
        depth, seg = obs[f"{name}_depth"], obs[f"{name}_segmentation"]
        target.append(target_points(depth, seg, scene.target_id, cameras[name]))
        for instance in set(np.unique(seg)) - background - {0, scene.target_id}:
            others.append(target_points(depth, seg, int(instance), cameras[name]))
    estimate = estimate_target(np.concatenate(target))
    if estimate is None:
        return obs, None
    points = np.concatenate(others) if others else np.zeros((0, 3))
    base = env.sim.data._data.xpos[env.sim.model._model.body("robot0_base").id][:2]
    closing = grip_site(env)[1][:2, 0]  # the site's x axis: the fingers close along it
    closing = closing / max(np.linalg.norm(closing), 1e-9)
    return obs, TargetView(
        estimate, points, (float(base[0]), float(base[1])), (float(closing[0]), float(closing[1]))
    )


def run_primitive(env, name: str, recorder=None) -> tuple[RetrieveOutcome, dict | None]:
    """Observe, plan ``name`` and execute it from the environment's current state; the outcome as
    the simulator measured it and the planned parameters (None when the target was not seen)."""
    monitor = RetrieveMonitor(env)
    obs, view = observe(env)
    if recorder is not None:
        recorder.decide(obs, {"primitive": name})
    if view is None:
        monitor.outcome.events.append("target_not_seen")
        return monitor.outcome, None
    chosen = PRIMITIVES[name]
    params = chosen.plan(view)

    def step(action):
        if recorder is not None:
            recorder.step(action)
        else:
            env.step(action)
        monitor.update()

    chosen.execute(env, params, step=step)
    return monitor.outcome, params
