"""What the robot sees at a decision point, as a planner uses it (:class:`TargetView`).

Two observation kinds, never mixed: ``rgbd`` (:func:`observe`), what a real robot has: the frames are
rendered once, at the decision point, from every camera the environment observes, and give the
target's points (its mask and depth, back-projected) and the other objects' points. Where the
target's mask comes from is the ``perception``: a learned one (the retrieval head,
``perception/retrieval/perceive.py``: frames and the requested category in, the target's pixels
out), for which nothing here reads a segmentation, the other objects being the depth points above
the table that are neither the robot's own pixels nor the predicted target's; or, given none, the
oracle: the simulator's instance masks (the target's, and the other instances': objects and
furniture; not the table, the arena or the robot), which sets each panel's ceiling. ``state``
(:func:`observe_state`), the ablation: the same summary computed from the simulator's state, every
vertex of the target's and the other objects' meshes and of the furniture's boxes at their current
poses, so a primitive's planner sees the whole object, occluded or not. Both add the robot's own
state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen.perception.points import TargetEstimate, estimate_target, inliers, masked_points
from scenegen.perception.robot_state import grip_site


@dataclass(frozen=True)
class TargetView:
    """What a planner may use. ``target``: the target as seen; ``others``: (N, 3) world points of the
    other objects and furniture; ``robot_base``: (x, y) of the robot's base (it faces +x)."""

    target: TargetEstimate
    others: np.ndarray
    robot_base: tuple[float, float] = (-0.56, 0.0)
    hand_closing: tuple[float, float] = (0.0, 1.0)  # the fingers' closing axis now, (x, y) (proprioception)
    target_points: np.ndarray | None = (
        None  # (M, 3) the target's visible world points (what ``target`` sums up)
    )


CAMERAS = ("front", "side")  # what the planners observe
CAMERA_SIZE = (320, 240)  # px: a 3 cm spoon covers enough pixels to be seen from the default cameras
BACKGROUND = ("arena", "table", "robot")
KINDS = ("rgbd", "state")


def observe(env, perception=None, image: bool = True) -> tuple[dict, TargetView | None]:
    """The camera observation now and what a planner sees in it (None: the target is not seen).
    ``perception``: a learned target finder (``target_masks(obs, cameras, category, parameters)``:
    the frames, the cameras' poses and intrinsics, which a robot knows, and the requested category,
    the environment's ``requested_category``, set with the task at reset), or None for the oracle's
    instance masks. With one, the observation holds no segmentation: per camera the
    image, depth, the robot's own pixels (``<cam>_robot_mask``) and the predicted target
    (``<cam>_predicted_target``). ``image=False`` (the oracle only, whose planner reads depth and
    masks): no ``<cam>_image`` in the observation, its colour pass not drawn."""
    if perception is not None:
        return _observe_learned(env, perception)
    obs = env.camera_observations(image=image)
    scene = env.scene
    cameras = {c.name: c for c in scene.cameras}
    background = {scene.segmentation[name] for name in BACKGROUND}
    robust = sensed(env)
    target, others = [], []
    for name in env.cameras:
        depth, seg = obs[f"{name}_depth"], np.squeeze(obs[f"{name}_segmentation"])
        target.append(masked_points(depth, seg == scene.target_id, cameras[name], robust))
        for instance in set(np.unique(seg)) - background - {0, scene.target_id}:
            others.append(masked_points(depth, seg == instance, cameras[name], robust))
    points = np.concatenate(others) if others else np.zeros((0, 3))
    return obs, _view(env, np.concatenate(target), points[points[:, 2] > _floor(robust)], robust)


def sensed(env) -> bool:
    """Whether ``env``'s depth comes from a sensor (read by the robust rule: perception/points.py)."""
    return getattr(env, "depth_sensor", None) is not None


def _floor(robust: bool) -> float:
    """Points at or below this height are not objects: the table's (a sensor's depth: its noise)."""
    return TABLE_TOP + (SENSOR_ABOVE_TABLE if robust else -np.inf)


def _view(env, seen: np.ndarray, others: np.ndarray, robust: bool) -> TargetView | None:
    if robust:  # a sensed target: its points under the table and far from the rest are errors
        seen = inliers(seen[seen[:, 2] > TABLE_TOP - SENSOR_BELOW_TABLE])
    estimate = estimate_target(seen, robust)
    if estimate is None:
        return None
    base, closing = _robot_state(env)
    return TargetView(estimate, others, base, closing, seen)


TABLE_MARGIN = 0.05  # m beyond the table's edges where points still count (an overhanging object)
ABOVE_TABLE = 0.0015  # m: points lower than this above the table top are the table (a fork lies 3 mm high)
SENSOR_ABOVE_TABLE = 0.015  # m: the same through a sensor, above its noise (3.5-7 mm at 1.4 m)
SENSOR_BELOW_TABLE = 0.02  # m: a sensed target point lower than this under the table top is an error


def _observe_learned(env, perception) -> tuple[dict, TargetView | None]:
    frames = env.camera_observations(segmentation=False)
    # only what a robot has: the observation is built from named keys, never passed through whole
    kept = ("image", "depth", "robot_mask")
    obs = {f"{name}_{kind}": frames[f"{name}_{kind}"] for name in env.cameras for kind in kept}
    scene = env.scene
    cameras = {c.name: c for c in scene.cameras}
    masks = perception.target_masks(obs, env.cameras, env.requested_category, scene.cameras)
    robust = sensed(env)
    above = SENSOR_ABOVE_TABLE if robust else ABOVE_TABLE
    target, others = [], []
    for name in env.cameras:
        depth, robot = obs[f"{name}_depth"], np.squeeze(obs[f"{name}_robot_mask"], -1)
        mask = masks[name]
        obs[f"{name}_predicted_target"] = mask[..., None]
        target.append(masked_points(depth, mask, cameras[name], robust))
        rest = masked_points(depth, ~mask & ~robot, cameras[name])
        on_table = (
            (rest[:, 2] > TABLE_TOP + above)
            & (np.abs(rest[:, 0]) <= TABLE_HALF[0] + TABLE_MARGIN)
            & (np.abs(rest[:, 1]) <= TABLE_HALF[1] + TABLE_MARGIN)
        )
        others.append(rest[on_table])
    return obs, _view(env, np.concatenate(target), np.concatenate(others), robust)


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
    view = TargetView(estimate, points, base, closing, target)
    return {"target_pos": position, "target_quat": quat}, view


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
    if category not in CATEGORIES:  # a user catalog's: no one-hot column, so no state to give
        raise ValueError(
            f"target category {category!r}: the state features know {', '.join(CATEGORIES)} (the "
            "bundled catalog's) and cannot describe a target of a user category"
        )
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
