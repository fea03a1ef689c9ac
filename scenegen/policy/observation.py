"""What the robot sees at a decision point, as a planner uses it (:class:`TargetView`).

The frames are rendered once, at the decision point, from every camera the environment observes: the
target's points (its instance mask and depth, back-projected) and the other instances' points (objects
and furniture; not the table, the arena or the robot), plus the robot's own state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen.policy.motion import grip_site
from scenegen.policy.perception import TargetEstimate, estimate_target, target_points


@dataclass(frozen=True)
class TargetView:
    """What a planner may use. ``target``: the target as seen; ``others``: (N, 3) world points of the
    other objects and furniture; ``robot_base``: (x, y) of the robot's base (it faces +x)."""

    target: TargetEstimate
    others: np.ndarray
    robot_base: tuple[float, float] = (-0.56, 0.0)
    hand_closing: tuple[float, float] = (0.0, 1.0)  # the fingers' closing axis now, (x, y) (proprioception)


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
