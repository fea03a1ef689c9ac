"""What the robot sees at a decision point, as a planner uses it (:class:`TargetView`).

Two observation kinds, never mixed: ``rgbd`` (:func:`observe`), what a real robot has: the frames are
rendered once, at the decision point, from every camera the environment observes, and give the
target's points (its instance mask and depth, back-projected) and the other instances' points (objects
and furniture; not the table, the arena or the robot). ``state`` (:func:`observe_state`), the
ablation: the same summary computed from the simulator's state, every vertex of the target's and the
other objects' meshes and of the furniture's boxes at their current poses, so a primitive's planner
sees the whole object, occluded or not. Both add the robot's own state.
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
KINDS = ("rgbd", "state")


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
    base, closing = _robot_state(env)
    return obs, TargetView(estimate, points, base, closing)


def _robot_state(env) -> tuple[tuple[float, float], tuple[float, float]]:
    base = env.sim.data._data.xpos[env.sim.model._model.body("robot0_base").id][:2]
    closing = grip_site(env)[1][:2, 0]  # the site's x axis: the fingers close along it
    closing = closing / max(np.linalg.norm(closing), 1e-9)
    return (float(base[0]), float(base[1])), (float(closing[0]), float(closing[1]))


def _body_points(model, data, body: int) -> np.ndarray:
    """World points of a body's visible geoms: mesh vertices, or a box's corners."""
    points = []
    for g in np.nonzero(model.geom_bodyid == body)[0]:
        if model.geom_group[g] not in (0, 1):
            continue  # collision parts (group 3) duplicate the visual mesh
        rot, pos = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        if model.geom_type[g] == 7:  # mjGEOM_MESH
            mesh = model.geom_dataid[g]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            local = model.mesh_vert[start : start + count]
        elif model.geom_type[g] == 6:  # mjGEOM_BOX
            half = model.geom_size[g]
            local = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        else:
            continue
        points.append(local @ rot.T + pos)
    return np.concatenate(points) if points else np.zeros((0, 3))


def observe_state(env) -> tuple[dict, TargetView]:
    """The ``state`` ablation: the view from the simulator's state (no rendering); its observation
    dict holds the target's pose, so an episode record says what the decision used."""
    model, data = env.sim.model._model, env.sim.data._data
    scene = env.scene
    target = _body_points(model, data, env.target_body_id)
    others = [
        _body_points(model, data, model.body(o.name).id) for o in scene.objects if o.name != scene.target
    ]
    others += [_body_points(model, data, model.body(f.name).id) for f in scene.furniture]
    estimate = estimate_target(target)
    base, closing = _robot_state(env)
    points = np.concatenate(others) if others else np.zeros((0, 3))
    position, quat = env.target_pose()
    return {"target_pos": position, "target_quat": quat}, TargetView(estimate, points, base, closing)


CATEGORIES = ("bottle", "bowl", "box", "can", "fork", "knife", "mug", "plate", "spoon")
TABLE_TOP, TABLE_HALF = 0.8, (0.4, 0.5)  # m: the table top's height and half extents (x, y)
STATE_SIZE = len(CATEGORIES) + 15


def state_features(env) -> np.ndarray:
    """The state-observation policy's input (``STATE_SIZE``,) float32, from the simulator's state: what
    a perfect perception system would summarise, so a policy on it separates data value from learning
    to see. Target category (one-hot); target position (x, y, height above the table); its up axis'
    z (1 upright, 0 lying); distance to the nearest table edge; furniture above it (count, lowest
    clearance); other objects within 10 and 20 cm and the nearest one's distance; the grip site
    relative to the target; the fingers' opening; total light (ambient + diffuse)."""
    model, data = env.sim.model._model, env.sim.data._data
    scene = env.scene
    category = next(o.category for o in scene.objects if o.name == scene.target)
    position, quat = env.target_pose()
    up = 1 - 2 * (quat[1] ** 2 + quat[2] ** 2)  # z of the body's z axis
    edge = min(TABLE_HALF[0] - abs(position[0]), TABLE_HALF[1] - abs(position[1]))
    above, clearance = 0, 1.0
    for furniture in scene.furniture:
        body = model.body(furniture.name).id
        for g in np.nonzero(model.geom_bodyid == body)[0]:
            centre, half = data.geom_xpos[g], model.geom_size[g]
            bottom = centre[2] - half[2]
            if np.linalg.norm(centre[:2] - position[:2]) < max(half[0], half[1]) and bottom > position[2]:
                above += 1
                clearance = min(clearance, bottom - position[2])
    others = [data.xpos[model.body(o.name).id] for o in scene.objects if o.name != scene.target]
    gaps = np.array([np.linalg.norm(p[:2] - position[:2]) for p in others]) if others else np.array([1.0])
    hand, _ = grip_site(env)
    robot = env.robots[0]
    fingers = data.qpos[robot._ref_gripper_joint_pos_indexes["right"]]
    light = sum(sum(lt.colour) * lt.intensity for lt in scene.lighting.lights) + sum(scene.lighting.ambient)
    values = [
        *(float(category == c) for c in CATEGORIES),
        position[0],
        position[1],
        position[2] - TABLE_TOP,
        up,
        edge,
        above,
        clearance,
        float((gaps < 0.1).sum()),
        float((gaps < 0.2).sum()),
        float(gaps.min()),
        *(hand - position),
        float(np.abs(fingers).sum()),
        light,
    ]
    return np.asarray(values, dtype=np.float32)
