"""The world builder: robosuite's table and Panda, furniture, free objects; the robot holds its pose."""

from __future__ import annotations

import functools

import mujoco
import numpy as np
import pytest
import scenes

from scenegen.assets.catalog import load_catalog
from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME
from scenegen.schema.condition import ROBOT_POSES
from scenegen.schema.scene import Camera, FurniturePlacement, Light, Lighting
from scenegen.sim import world

HOLD_TIME = 2.0  # s of passive simulation
EE_BODY = "gripper0_eef"


# These scenes never required the snap to keep the requested resting pose.
place = functools.partial(scenes.place, check_pose=False)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


@pytest.fixture(scope="module")
def scene(catalog):
    """A compiled world with a shelf, a bin and four objects (one of them scaled), and its initial state."""
    shelf = FurniturePlacement(name="shelf", kind="shelf", position=(*FURNITURE_HOME["shelf"], 0.0))
    bin_ = FurniturePlacement(name="bin", kind="bin", position=(*FURNITURE_HOME["bin"], 0.0), yaw=0.3)
    furniture = (shelf, bin_)
    objects = (
        place(catalog, "obj0_mug", "mug", 0.05, 0.0, pose=2),
        place(catalog, "obj1_small_box", "small_box", -0.05, -0.25),
        place(
            catalog,
            "obj2_soup_can",
            "soup_can",
            *FURNITURE_HOME["shelf"],
            support="shelf",
            furniture=furniture,
        ),
        place(catalog, "obj3_small_box", "small_box", 0.1, 0.3, scale=0.5),
    )
    lighting = Lighting(lights=(Light(position=(0.5, 0.5, 2.0), direction=(-0.2, -0.2, -1.0)),))
    camera = Camera(name="front", position=(1.25, 0.0, 1.45), lookat=(0.0, 0.0, 0.85))
    spec = world.build_world(catalog, objects, furniture, lighting, [camera])
    model = spec.compile()
    return model, objects, furniture


def test_world_compiles_with_robot_furniture_and_objects(scene):
    model, objects, furniture = scene
    bodies = {model.body(i).name for i in range(model.nbody)}
    for name in ["robot0_base", "robot0_link1", "robot0_link7", "robot0_right_hand", EE_BODY]:
        assert name in bodies
    for name in world.ARM_JOINTS:
        assert model.joint(name).type == mujoco.mjtJoint.mjJNT_HINGE
    for name in world.ARM_ACTUATORS:
        assert model.actuator(name).id >= 0
    for piece in furniture:
        assert piece.name in bodies
        n_boxes = len(layout.FURNITURE[piece.kind].boxes)
        assert [model.geom(f"{piece.name}_box{i}").bodyid[0] for i in range(n_boxes)] == [
            model.body(piece.name).id
        ] * n_boxes
    for obj in objects:
        assert obj.name in bodies
        joint = model.joint(f"{obj.name}_joint")
        assert joint.type == mujoco.mjtJoint.mjJNT_FREE and joint.bodyid[0] == model.body(obj.name).id
    assert model.body("table").id > 0
    assert model.nlight == 1
    assert model.camera("front").id >= 0


def test_robot_bodies_and_joints_are_prefixed_and_gravity_compensated(scene):
    model, objects, furniture = scene
    own = {o.name for o in objects} | {p.name for p in furniture}
    for j in range(model.njnt):
        name = model.joint(j).name
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            assert name.startswith(world.ROBOT_PREFIXES), name
    moving = [model.body(b).name for b in range(1, model.nbody) if model.body_dofnum[b] > 0]
    robot = [n for n in moving if n not in own]
    assert robot, "the robot has no moving bodies"
    for name in robot:
        assert name.startswith(world.ROBOT_PREFIXES), name
    # Every robot body (moving or welded to a moving one) is gravity-compensated, nothing else is.
    for b in range(model.nbody):
        prefixed = model.body(b).name.startswith(world.ROBOT_PREFIXES)
        assert model.body_gravcomp[b] == (1.0 if prefixed else 0.0), model.body(b).name


def test_object_mass_and_inertia_come_from_the_catalog(scene, catalog):
    model, objects, _ = scene
    for obj in objects:
        asset = catalog.get(obj.asset)
        body = model.body(obj.name)
        assert body.mass[0] == pytest.approx(asset.mass * obj.scale**3, rel=1e-6)
        # Principal moments: their sum is the trace of the catalog's inertia tensor, whatever the axes.
        assert body.inertia.sum() == pytest.approx(np.trace(asset.inertia) * obj.scale**5, rel=1e-4)
        assert body.ipos == pytest.approx(np.zeros(3), abs=1e-9)
        # Visual geoms do not collide; convex parts do.
        visual = model.geom(f"{obj.name}_visual")
        assert visual.contype[0] == 0 and visual.conaffinity[0] == 0
        assert all(model.geom(f"{obj.name}_part{i}").contype[0] for i in range(len(asset.parts.files)))


def test_initial_state_puts_robot_and_objects_at_their_poses(scene):
    model, objects, _ = scene
    pose = ROBOT_POSES["home"]
    qpos, ctrl = world.initial_state(model, pose, objects)
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = qpos, ctrl
    mujoco.mj_forward(model, data)
    arm = [data.joint(name).qpos[0] for name in world.ARM_JOINTS]
    assert arm == pytest.approx(pose, abs=1e-12)
    assert [data.actuator(name).ctrl[0] for name in world.ARM_ACTUATORS] == pytest.approx(pose)
    for obj in objects:
        assert data.body(obj.name).xpos == pytest.approx(obj.position, abs=1e-9)
        assert data.body(obj.name).xquat == pytest.approx(obj.quat, abs=1e-6)
    # The gripper hangs above the table in front of the base, fingers open.
    ee = data.body(EE_BODY).xpos
    assert -0.2 < ee[0] < 0.0 and abs(ee[1]) < 1e-6 and ee[2] > layout.TABLE_TOP_Z + 0.1
    for joint, q in world.GRIPPER_OPEN.items():
        assert data.joint(joint).qpos[0] == pytest.approx(q)


def _simulate(model, qpos, ctrl, seconds):
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = qpos, ctrl
    mujoco.mj_forward(model, data)
    ee0 = data.body(EE_BODY).xpos.copy()
    arm0 = np.array([data.joint(name).qpos[0] for name in world.ARM_JOINTS])
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
    arm = np.array([data.joint(name).qpos[0] for name in world.ARM_JOINTS])
    return float(np.linalg.norm(data.body(EE_BODY).xpos - ee0)), float(np.abs(arm - arm0).max())


@pytest.mark.parametrize("pose_name", sorted(ROBOT_POSES))
def test_robot_holds_its_pose_under_passive_simulation(scene, pose_name):
    model, objects, _ = scene
    qpos, ctrl = world.initial_state(model, ROBOT_POSES[pose_name], objects)
    ee_move, joint_move = _simulate(model, qpos, ctrl, HOLD_TIME)
    assert ee_move < 1e-4
    assert joint_move < 1e-4


def test_robot_without_its_hold_targets_moves(scene):
    # The hold is the servos' doing: with targets of zero (clipped to the joint ranges) the arm moves away.
    model, objects, _ = scene
    qpos, _ = world.initial_state(model, ROBOT_POSES["home"], objects)
    ee_move, joint_move = _simulate(model, qpos, np.zeros(model.nu), 0.5)
    assert ee_move > 0.01
    assert joint_move > 0.1


@pytest.mark.parametrize("pose_name", sorted(ROBOT_POSES))
def test_the_cores_shoulder_is_the_models_at_every_named_pose(pose_name):
    """core.layout.SHOULDER (the generator's cost uses it without MuJoCo) is robot0_link1's origin."""
    from scenegen.core.layout import SHOULDER

    model = world.robot_spec().compile()
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = world.initial_state(model, ROBOT_POSES[pose_name], [])
    mujoco.mj_forward(model, data)
    assert tuple(float(v) for v in data.body("robot0_link1").xpos) == SHOULDER
