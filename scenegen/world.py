"""The one world builder: every stage that needs a MuJoCo model gets it here.

A world is robosuite's table arena and Panda (arm, gripper and mount built from robosuite's own model
classes, so body and joint names match a robosuite environment: ``robot0_*``, ``gripper0_*``), plus
furniture pieces as their own bodies, plus the scene's free objects, lights and cameras. The robot is
held at the requested initial pose by gravity compensation and position servos, so a stored scene
stays put when simulated passively.

Frame: MuJoCo world, metres. The table top is the plane z = ``TABLE_TOP_Z`` over the rectangle
|x| <= TABLE_SIZE[0]/2, |y| <= TABLE_SIZE[1]/2; the robot base sits behind it at negative x.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from scenegen.assets.catalog import Asset, Catalog
from scenegen.schema.scene import Camera, FurniturePlacement, Lighting, ObjectPlacement

TABLE_SIZE = (0.8, 1.0, 0.05)  # full x, y extents and thickness (m)
TABLE_TOP_Z = 0.8
TIMESTEP = 0.002
ROBOT_PREFIXES = ("robot0_", "gripper0_")
ARM_JOINTS = tuple(f"robot0_joint{i}" for i in range(1, 8))
ARM_ACTUATORS = tuple(f"robot0_torq_j{i}" for i in range(1, 8))
GRIPPER_OPEN = {"gripper0_finger_joint1": 0.04, "gripper0_finger_joint2": -0.04}
HOLD_KP, HOLD_DAMPRATIO = 400.0, 1.0  # position hold of the arm (N m / rad)
OBJECT_CONDIM = 4  # sliding + torsional friction: objects come to rest instead of spinning slowly
# Contact and solver options used while settling; embedded in scene.xml and recorded in scene.json.
CONTACT_OPTIONS = {
    "timestep": TIMESTEP,
    "integrator": "implicitfast",
    "cone": "elliptic",
    "impratio": 10.0,
    "object_condim": OBJECT_CONDIM,
    "torsional_friction": 0.005,
    "rolling_friction": 0.0001,
    "multiccd": True,
    # Contacts of object parts activate 0.5 mm before touching: without it, 50 g utensils 3 mm thick
    # kept chattering at ~3 cm/s on the table (measured) and never came to rest.
    "object_margin": 0.0005,
}

# Geom groups: visual geoms are in group 1 (rendered), collision parts of objects in group 3
# (hidden in renders). Furniture boxes are exact primitives, so one geom serves both.
VISUAL_GROUP, COLLISION_GROUP = 1, 3


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in a furniture body's frame: centre and half sizes (m)."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]


@dataclass(frozen=True)
class FurnitureKind:
    """Boxes of a furniture piece (its frame: origin at the centre of its footprint on the table) and
    the surface objects can rest on (height above the table top, half extents of its inner region)."""

    boxes: tuple[Box, ...]
    surface_height: float
    surface_half: tuple[float, float]
    rgba: tuple[float, float, float, float]


def _shelf() -> FurnitureKind:
    depth, width, height, t = 0.26, 0.42, 0.24, 0.02
    return FurnitureKind(
        boxes=(
            Box((0.0, -(width - t) / 2, (height - t) / 2), (depth / 2, t / 2, (height - t) / 2)),
            Box((0.0, (width - t) / 2, (height - t) / 2), (depth / 2, t / 2, (height - t) / 2)),
            Box((0.0, 0.0, height - t / 2), (depth / 2, width / 2, t / 2)),  # the overhanging board
        ),
        surface_height=height,
        surface_half=(depth / 2, width / 2),
        rgba=(0.55, 0.38, 0.22, 1.0),
    )


def _bin() -> FurnitureKind:
    lx, ly, h, t = 0.24, 0.30, 0.08, 0.01
    return FurnitureKind(
        boxes=(
            Box((0.0, 0.0, t / 2), (lx / 2, ly / 2, t / 2)),
            Box((-(lx - t) / 2, 0.0, h / 2), (t / 2, ly / 2, h / 2)),
            Box(((lx - t) / 2, 0.0, h / 2), (t / 2, ly / 2, h / 2)),
            Box((0.0, -(ly - t) / 2, h / 2), (lx / 2, t / 2, h / 2)),
            Box((0.0, (ly - t) / 2, h / 2), (lx / 2, t / 2, h / 2)),
        ),
        surface_height=t,
        surface_half=(lx / 2 - t, ly / 2 - t),
        rgba=(0.3, 0.35, 0.4, 1.0),
    )


FURNITURE: dict[str, FurnitureKind] = {"shelf": _shelf(), "bin": _bin()}


@dataclass(frozen=True)
class Surface:
    """A horizontal support surface in the world frame: height z, centre, half extents, yaw (rad)."""

    name: str
    z: float
    center: tuple[float, float]
    half: tuple[float, float]
    yaw: float = 0.0

    def local_xy(self, xy: Sequence[float]) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = xy[0] - self.center[0], xy[1] - self.center[1]
        return np.array([c * dx + s * dy, -s * dx + c * dy])

    def margin(self, xy: Sequence[float]) -> float:
        """Signed distance (m) from a point to the surface's boundary; positive inside."""
        local = np.abs(self.local_xy(xy))
        return float(min(self.half[0] - local[0], self.half[1] - local[1]))


# The floor strip beside the table (+y side) where an object may lie on the floor (``on_floor``).
FLOOR = Surface("floor", 0.0, (0.0, TABLE_SIZE[1] / 2 + 0.18), (0.35, 0.12))


def support_surfaces(
    furniture: Sequence[FurniturePlacement],
    objects: Sequence[ObjectPlacement] = (),
    catalog: Catalog | None = None,
) -> dict[str, Surface]:
    """Surfaces objects can rest on, keyed by name: ``table``, ``floor``, each furniture piece, and
    (given the catalog) the flat top of each object, under the object's name (stacking)."""
    surfaces = {
        "table": Surface("table", TABLE_TOP_Z, (0.0, 0.0), (TABLE_SIZE[0] / 2, TABLE_SIZE[1] / 2)),
        "floor": FLOOR,
    }
    for piece in furniture:
        kind = FURNITURE[piece.kind]
        surfaces[piece.name] = Surface(
            piece.name,
            TABLE_TOP_Z + kind.surface_height,
            (piece.position[0], piece.position[1]),
            kind.surface_half,
            piece.yaw,
        )
    if catalog is not None:
        for obj in objects:
            surfaces[obj.name] = object_top_surface(catalog, obj)
    return surfaces


def object_top_surface(catalog: Catalog, obj: ObjectPlacement, tolerance: float = 0.0015) -> Surface:
    """The top of an object as a support: its highest convex-part vertices (within ``tolerance``),
    bounded by a rectangle in the object's yaw frame. A pointed or round top gives a tiny region."""
    from scenegen.assets.catalog import convex_part_vertices
    from scenegen.check.geometry import quat_to_matrix

    rot = quat_to_matrix(obj.quat)
    pts = np.concatenate(convex_part_vertices(catalog.root, obj.asset)) * obj.scale @ rot.T
    top = pts[pts[:, 2] >= pts[:, 2].max() - tolerance]
    x_axis = rot[:, 0] if np.hypot(rot[0, 0], rot[1, 0]) > 1e-6 else rot[:, 1]
    yaw = math.atan2(x_axis[1], x_axis[0])
    c, s = math.cos(yaw), math.sin(yaw)
    local = top[:, :2] @ np.array([[c, -s], [s, c]])  # world offsets -> yaw frame
    lo, hi = local.min(axis=0), local.max(axis=0)
    mid = (lo + hi) / 2
    center = np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1]]) + obj.position[:2]
    return Surface(
        obj.name,
        float(obj.position[2] + pts[:, 2].max()),
        (float(center[0]), float(center[1])),
        (float((hi - lo)[0] / 2), float((hi - lo)[1] / 2)),
        yaw,
    )


def furniture_boxes(piece: FurniturePlacement) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """World-frame boxes of a furniture piece: (centre (3,), rotation (3, 3), half sizes (3,))."""
    rot = _yaw_matrix(piece.yaw)
    origin = np.array([piece.position[0], piece.position[1], TABLE_TOP_Z])
    return [
        (origin + rot @ np.array(box.center), rot, np.array(box.half)) for box in FURNITURE[piece.kind].boxes
    ]


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _quiet_robosuite() -> None:
    """Drop robosuite's import-time warnings (private macro file, optional robots, mink IK): they
    concern features scenegen does not use and would greet every user of the CLI."""
    import logging

    logging.getLogger("robosuite_logs").addFilter(lambda record: record.levelno >= logging.ERROR)


@functools.lru_cache(maxsize=1)
def _robosuite_xml() -> str:
    """Table arena + Panda with gripper and mount, as robosuite's own table tasks assemble them."""
    _quiet_robosuite()
    from robosuite.models import MujocoWorldBase
    from robosuite.models.arenas import TableArena
    from robosuite.models.bases import robot_base_factory
    from robosuite.models.grippers import gripper_factory
    from robosuite.models.robots import Panda

    world = MujocoWorldBase()
    robot = Panda()
    robot.add_gripper(gripper_factory("PandaGripper"))
    robot.add_base(robot_base_factory(robot.default_base))
    robot.set_base_xpos(robot.base_xpos_offset["table"](TABLE_SIZE[0]))
    world.merge(TableArena(table_full_size=TABLE_SIZE, table_offset=(0, 0, TABLE_TOP_Z)))
    world.merge(robot)
    return world.get_xml()


@functools.lru_cache(maxsize=1)
def _base_spec() -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_string(_robosuite_xml())
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = CONTACT_OPTIONS["impratio"]
    # Convex-convex collisions return a single contact point unless multiccd is on, and objects
    # resting on one point rock instead of settling.
    spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_MULTICCD
    for body in spec.bodies:
        if body.name.startswith(ROBOT_PREFIXES):
            body.gravcomp = 1.0
    for name in ARM_ACTUATORS:
        act = spec.actuator(name)
        torque_limit = tuple(act.ctrlrange)
        act.set_to_position(kp=HOLD_KP, dampratio=HOLD_DAMPRATIO)
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = torque_limit
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = spec.joint(act.target).range
    for light in list(spec.lights):  # the scene's own lighting replaces robosuite's
        spec.delete(light)
    for cam in list(spec.cameras):
        if not cam.name.startswith(ROBOT_PREFIXES):  # keep the wrist camera
            spec.delete(cam)
    return spec


def robot_spec() -> mujoco.MjSpec:
    """A fresh copy of the robot-and-table world with nothing else in it."""
    return _base_spec().copy()


def build_world(
    catalog: Catalog,
    objects: Sequence[ObjectPlacement],
    furniture: Sequence[FurniturePlacement] = (),
    lighting: Lighting | None = None,
    cameras: Sequence[Camera] = (),
) -> mujoco.MjSpec:
    """A spec of the full scene; objects are free bodies named as their placements, at their poses.

    Call :func:`initial_state` on the compiled model for the qpos/ctrl of the robot at its pose.
    """
    spec = robot_spec()
    for piece in furniture:
        _add_furniture(spec, piece)
    # Every catalog mesh is declared, used or not, in catalog order: all scenes of a catalog then share
    # one mesh table, so a renderer can keep one MjrContext for all of them (render.py).
    for asset in catalog.assets:
        _add_asset_meshes(spec, catalog, asset, {1.0})
    for asset in {obj.asset: catalog.get(obj.asset) for obj in objects}.values():
        _add_asset_meshes(spec, catalog, asset, {o.scale for o in objects if o.asset == asset.name} - {1.0})
    for obj in objects:
        _add_object(spec, catalog.get(obj.asset), obj)
    if lighting is not None:
        _add_lighting(spec, lighting)
    for cam in cameras:
        add_camera(spec, cam)
    return spec


def _add_furniture(spec: mujoco.MjSpec, piece: FurniturePlacement) -> None:
    kind = FURNITURE[piece.kind]
    body = spec.worldbody.add_body(
        name=piece.name,
        pos=[piece.position[0], piece.position[1], TABLE_TOP_Z],
        quat=[math.cos(piece.yaw / 2), 0, 0, math.sin(piece.yaw / 2)],
    )
    for i, box in enumerate(kind.boxes):
        body.add_geom(
            name=f"{piece.name}_box{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=box.center,
            size=box.half,
            rgba=kind.rgba,
            group=VISUAL_GROUP,
            friction=[0.8, 0.005, 0.0001],
        )


def _mesh_names(asset: Asset, scale: float) -> tuple[str, list[str]]:
    suffix = "" if scale == 1.0 else f"_s{scale:g}"
    parts = [f"{asset.name}{suffix}_part{i}" for i in range(len(asset.parts.files))]
    return f"{asset.name}{suffix}_visual", parts


def _add_asset_meshes(spec: mujoco.MjSpec, catalog: Catalog, asset: Asset, scales: set[float]) -> None:
    for scale in sorted(scales):
        visual, parts = _mesh_names(asset, scale)
        files = [asset.mesh, *asset.parts.files]
        for name, rel in zip([visual, *parts], files, strict=True):
            spec.add_mesh(name=name, file=str(catalog.path(rel)), scale=[scale] * 3)


def _add_object(spec: mujoco.MjSpec, asset: Asset, obj: ObjectPlacement) -> None:
    s = obj.scale
    body = spec.worldbody.add_body(name=obj.name, pos=obj.position, quat=obj.quat)
    body.add_freejoint(name=f"{obj.name}_joint")
    inertia = np.asarray(asset.inertia) * s**5
    body.explicitinertial = True
    body.mass = asset.mass * s**3
    body.ipos = [0, 0, 0]
    body.fullinertia = [
        inertia[0, 0],
        inertia[1, 1],
        inertia[2, 2],
        inertia[0, 1],
        inertia[0, 2],
        inertia[1, 2],
    ]
    visual, parts = _mesh_names(asset, s)
    body.add_geom(
        name=f"{obj.name}_visual",
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=visual,
        rgba=asset.rgba,
        group=VISUAL_GROUP,
        contype=0,
        conaffinity=0,
        mass=0,
    )
    for i, part in enumerate(parts):
        body.add_geom(
            name=f"{obj.name}_part{i}",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=part,
            group=COLLISION_GROUP,
            rgba=[0.5, 0.5, 0.5, 0.3],
            mass=0,
            condim=OBJECT_CONDIM,
            margin=CONTACT_OPTIONS["object_margin"],
            friction=[
                asset.friction,
                CONTACT_OPTIONS["torsional_friction"],
                CONTACT_OPTIONS["rolling_friction"],
            ],
        )


def _add_lighting(spec: mujoco.MjSpec, lighting: Lighting) -> None:
    spec.visual.headlight.ambient = list(lighting.ambient)
    spec.visual.headlight.diffuse = [0.0, 0.0, 0.0]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    for i, light in enumerate(lighting.lights):
        spec.worldbody.add_light(
            name=f"light{i}",
            pos=light.position,
            dir=light.direction,
            diffuse=[c * light.intensity for c in light.colour],
            specular=[0.2, 0.2, 0.2],
            castshadow=light.cast_shadow,
        )


def camera_rotation(cam: Camera) -> np.ndarray:
    """Camera-to-world rotation (3, 3), MuJoCo/OpenGL convention: x right, y up, looking along -z."""
    forward = np.asarray(cam.lookat, float) - np.asarray(cam.position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward], axis=1)


def add_camera(spec: mujoco.MjSpec, cam: Camera) -> None:
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, camera_rotation(cam).ravel())
    spec.worldbody.add_camera(name=cam.name, pos=cam.position, quat=quat, fovy=cam.fovy)


def initial_state(
    model: mujoco.MjModel, robot_pose: Sequence[float], objects: Sequence[ObjectPlacement]
) -> tuple[np.ndarray, np.ndarray]:
    """qpos and ctrl that put the robot at ``robot_pose`` (held, gripper open) and objects at their poses."""
    qpos = model.qpos0.copy()
    for name, q in zip(ARM_JOINTS, robot_pose, strict=True):
        qpos[model.joint(name).qposadr[0]] = q
    for name, q in GRIPPER_OPEN.items():
        qpos[model.joint(name).qposadr[0]] = q
    for obj in objects:
        adr = model.joint(f"{obj.name}_joint").qposadr[0]
        qpos[adr : adr + 3] = obj.position
        qpos[adr + 3 : adr + 7] = obj.quat
    ctrl = np.zeros(model.nu)
    for act, q in zip(ARM_ACTUATORS, robot_pose, strict=True):
        ctrl[model.actuator(act).id] = q
    for i in range(model.nu):  # gripper servos hold the fingers open
        target = model.actuator_trnid[i, 0]
        jname = model.joint(target).name
        if jname in GRIPPER_OPEN:
            ctrl[i] = GRIPPER_OPEN[jname]
    return qpos, ctrl
