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

import mujoco
import numpy as np

from scenegen.assets.catalog import Asset, Catalog
from scenegen.core import rotations
from scenegen.core.layout import FURNITURE, TABLE_SIZE, TABLE_TOP_Z
from scenegen.schema.scene import Camera, FurniturePlacement, Lighting, ObjectPlacement

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

# What objects on the floor rest on. ``plane``: robosuite's floor plane (every scene before issue 64,
# the reference set's included). ``box``: a box whose top is the floor, as the table is a box, and the
# plane seen but not touched: on the plane a teaspoon alone still turned at 0.155 rad/s after 2 s, a
# knife at 0.199 (still_angular is 0.05), where on the table's box the same poses turn at 0-0.02
# (docs/generator.md). Recorded in scene.json's ``contact_options`` as ``floor`` when ``box``.
FLOORS = ("plane", "box")
FLOOR_BOX = "floor_support"
FLOOR_BOX_HALF = (3.0, 3.0, 0.05)  # m: the plane's extent, 10 cm thick, its top at z = 0
# Rolling friction of the floor box (its contacts take condim 6): a knife standing on its edge touches a
# box at two points, a line it kept rolling about (8 of 8 targeted "toppled on floor" knives still
# turned at 0.02-0.07 rad/s after 2 s, the still limit 0.05); with 0.005 m all 8 rest, with 0.001 m 4
# (docs/generator.md). Recorded as ``floor_rolling_friction`` beside ``floor``.
FLOOR_ROLLING_FRICTION = 0.005
# The table's rolling friction is a recipe's choice (``table_rolling_friction``; None: robosuite's table
# as it is, condim 3). On robosuite's table 4 of 12 knives (4 resting poses x 3 places) still turned at
# 0.08-0.21 rad/s after 2 s; with 0.005 m and condim 6, 12 of 12 rest (under 0.008; docs/generator.md).


def contact_options(floor: str = "plane", table_rolling_friction: float | None = None) -> dict:
    """``CONTACT_OPTIONS`` as a scene records them: ``floor`` only when it is not the plane and
    ``table_rolling_friction`` only when set, so a scene made without them records exactly what it did
    before they were choices."""
    options = dict(CONTACT_OPTIONS)
    if floor != "plane":
        options |= {"floor": floor, "floor_rolling_friction": FLOOR_ROLLING_FRICTION}
    if table_rolling_friction is not None:
        options["table_rolling_friction"] = table_rolling_friction
    return options


def _box_floor(spec: mujoco.MjSpec) -> None:
    """The floor as a box (``FLOORS``): the plane keeps its look and loses its contacts."""
    plane = spec.geom("floor")
    plane.contype = plane.conaffinity = 0
    table = spec.geom("table_collision")
    spec.worldbody.add_geom(
        name=FLOOR_BOX,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0, 0, -FLOOR_BOX_HALF[2]],
        size=FLOOR_BOX_HALF,
        group=0,  # a collision geom, hidden like the table's
        friction=[table.friction[0], table.friction[1], FLOOR_ROLLING_FRICTION],
        condim=6,
        rgba=[0.5, 0.5, 0.5, 1],
    )


def _rolling_table(spec: mujoco.MjSpec, rolling: float) -> None:
    """The table's contacts with rolling friction ``rolling`` (m) and condim 6, as the floor box's."""
    table = spec.geom("table_collision")
    table.friction = [table.friction[0], table.friction[1], rolling]
    table.condim = 6


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


def robot_world_spec(robosuite_xml: str, hold: bool = True) -> mujoco.MjSpec:
    """The robot-and-table world of a robosuite model XML with scenegen's solver options.

    ``hold``: the arm's torque motors become position servos with gravity compensation on every
    robot body, so a stored scene keeps its pose under passive simulation (settling, stored
    scenes). Without it the robot keeps robosuite's torque actuators and no compensation, as
    robosuite's controllers expect (scenegen/env/).
    """
    spec = mujoco.MjSpec.from_string(robosuite_xml)
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = CONTACT_OPTIONS["impratio"]
    # Convex-convex collisions return a single contact point unless multiccd is on, and objects
    # resting on one point rock instead of settling.
    spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_MULTICCD
    if hold:
        _hold_robot(spec)
    for light in list(spec.lights):  # the scene's own lighting replaces robosuite's
        spec.delete(light)
    for cam in list(spec.cameras):
        if not cam.name.startswith(ROBOT_PREFIXES):  # keep the wrist camera
            spec.delete(cam)
    return spec


def _hold_robot(spec: mujoco.MjSpec) -> None:
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


@functools.lru_cache(maxsize=1)
def _base_spec() -> mujoco.MjSpec:
    return robot_world_spec(_robosuite_xml(), hold=True)


def robot_spec() -> mujoco.MjSpec:
    """A fresh copy of the robot-and-table world with nothing else in it (robot held)."""
    return _base_spec().copy()


def build_world(
    catalog: Catalog,
    objects: Sequence[ObjectPlacement],
    furniture: Sequence[FurniturePlacement] = (),
    lighting: Lighting | None = None,
    cameras: Sequence[Camera] = (),
    base: mujoco.MjSpec | None = None,
    floor: str = "plane",
    table_rolling_friction: float | None = None,
) -> mujoco.MjSpec:
    """A spec of the full scene; objects are free bodies named as their placements, at their poses.

    ``base``: the robot-and-table world to furnish (default: :func:`robot_spec`, the held robot;
    it is modified in place). ``floor``: what the floor is (``FLOORS``); ``table_rolling_friction``: the
    table's rolling friction (m; None: robosuite's table as it is). Call :func:`initial_state`
    on the compiled model for the qpos/ctrl of the held robot at its pose.
    """
    if floor not in FLOORS:
        raise ValueError(f"floor {floor!r}: one of {', '.join(FLOORS)}")
    spec = robot_spec() if base is None else base
    if floor == "box":
        _box_floor(spec)
    if table_rolling_friction is not None:
        _rolling_table(spec, table_rolling_friction)
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
            spec.add_mesh(name=name, file=str(asset.file(rel)), scale=[scale] * 3)
    if asset.texture and not any(m.name == f"{asset.name}_material" for m in spec.materials):
        # A 2D texture mapped with the visual mesh's texture coordinates (an imported asset's).
        spec.add_texture(
            name=f"{asset.name}_texture",
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            file=str(asset.file(asset.texture)),
        )
        material = spec.add_material(name=f"{asset.name}_material")
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{asset.name}_texture"


def _add_object(spec: mujoco.MjSpec, asset: Asset, obj: ObjectPlacement) -> None:
    s = obj.scale
    body = spec.worldbody.add_body(name=obj.name, pos=obj.position, quat=obj.quat)
    body.add_freejoint(name=f"{obj.name}_joint")
    set_inertial(body, asset.mass * s**3, np.asarray(asset.inertia) * s**5)
    visual, parts = _mesh_names(asset, s)
    body.add_geom(
        name=f"{obj.name}_visual",
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=visual,
        rgba=[1.0, 1.0, 1.0, 1.0] if asset.texture else asset.rgba,  # a texture is drawn unshaded by rgba
        material=f"{asset.name}_material" if asset.texture else "",
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
            **object_contact(asset.friction),
        )


def set_inertial(body, mass: float, inertia) -> None:
    """Give ``body`` an explicit mass (kg) and inertia tensor (3, 3; kg m^2 about its origin, the
    centre of mass): the mesh geoms carry none (shared/PITFALLS.md)."""
    inertia = np.asarray(inertia)
    body.explicitinertial = True
    body.mass = mass
    body.ipos = [0, 0, 0]
    body.fullinertia = [
        inertia[0, 0],
        inertia[1, 1],
        inertia[2, 2],
        inertia[0, 1],
        inertia[0, 2],
        inertia[1, 2],
    ]


def object_contact(friction: float) -> dict:
    """The contact attributes of an object's collision geoms (``CONTACT_OPTIONS``), as add_geom keywords."""
    return {
        "condim": OBJECT_CONDIM,
        "margin": CONTACT_OPTIONS["object_margin"],
        "friction": [friction, CONTACT_OPTIONS["torsional_friction"], CONTACT_OPTIONS["rolling_friction"]],
    }


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
    return rotations.camera_rotation(cam.position, cam.lookat)


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
