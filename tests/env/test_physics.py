"""The control loop's physics settings (scenegen/env/physics.py): ``exact`` compiles today's model to
the byte, a larger timestep keeps the 20 Hz control rate, and ``hull`` makes each object meet the
table through its convex hull only, resting where its parts rest."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from scenegen.assets.catalog import load_catalog
from scenegen.core.files import load_rows
from scenegen.env.physics import PHYSICS, ControlPhysics, physics_named
from scenegen.env.scenes import reference_scene
from scenegen.paths import PROJECT_ROOT
from scenegen.sim import world

REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def scene():
    # a layout with a many-part object (a mug or a bowl: 32 and 54 coacd parts) on the table
    for row in load_rows(REFERENCE, "train"):
        s = reference_scene(row)
        if any(o.asset.startswith(("mug", "bowl")) for o in s.objects) and not s.furniture:
            return s
    raise AssertionError("no reference layout with a mug or bowl and no furniture")


def _model_bytes(model: mujoco.MjModel) -> bytes:
    buffer = np.zeros(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return buffer.tobytes()


def _spec(scene):
    catalog = load_catalog()
    return catalog, world.build_world(catalog, scene.objects, scene.furniture, scene.lighting, scene.cameras)


def test_exact_compiles_todays_model_to_the_byte(scene):
    catalog, today = _spec(scene)
    _, applied = _spec(scene)
    PHYSICS["exact"].apply(applied, catalog, scene.objects)
    assert _model_bytes(today.compile()) == _model_bytes(applied.compile())


def test_a_timestep_must_divide_the_control_period():
    assert ControlPhysics(timestep=0.005).substeps == 10
    assert ControlPhysics(timestep=1 / 300).substeps == 15
    with pytest.raises(ValueError, match="timestep 0.004: must divide the 50 ms control period"):
        ControlPhysics(timestep=0.004)
    with pytest.raises(ValueError, match="physics 'fast': unknown; choose from exact"):
        physics_named("fast")


def test_the_key_follows_every_field_not_the_order_of_changes():
    exact = PHYSICS["exact"]
    assert exact.key().startswith("exact-")
    a = exact.with_changes("x", timestep=0.005, table_contact="hull")
    b = exact.with_changes("x", table_contact="hull").with_changes("x", timestep=0.005)
    assert a.key() == b.key()
    assert a.key() != exact.with_changes("x", timestep=0.005).key()


def test_a_larger_timestep_keeps_the_control_rate(scene):
    from scenegen.env.robosuite_env import SceneEnv

    env = SceneEnv(scene, physics=ControlPhysics(name="dt5", timestep=0.005))
    try:
        env.reset_to(scene)
        t0 = env.sim.data._data.time
        for _ in range(4):
            env.step(np.zeros(7))
        assert env.sim.model._model.opt.timestep == 0.005
        assert env.sim.data._data.time - t0 == pytest.approx(4 * 0.05)
    finally:
        env.close()


@pytest.mark.parametrize("physics", ["exact", "dt5"])
def test_an_observation_is_the_state_at_the_end_of_its_control_step(scene, physics):
    """robosuite's observables sample on a clock the physics step advances; under a 5 ms step its
    sums fell short of 50 ms and observations lagged a step (0.047 rad, measured): they are the state
    now, and new arrays every step, under any physics."""
    from scenegen.env.robosuite_env import SceneEnv

    env = SceneEnv(scene, physics=physics, cameras=[], render_each_step=False)
    try:
        obs = env.reset_to(scene)
        model, data = env.sim.model._model, env.sim.data._data
        joints = [model.joint(f"robot0_joint{i}").qposadr[0] for i in range(1, 8)]
        rng = np.random.default_rng(0)
        for _ in range(5):
            before = obs["robot0_joint_pos"]
            obs, *_ = env.step(rng.uniform(-1, 1, 7))
            np.testing.assert_array_equal(obs["robot0_joint_pos"], data.qpos[joints])
            assert obs["robot0_joint_pos"] is not before
    finally:
        env.close()


def _table_contacts(env) -> tuple[set[str], set[str]]:
    """Names of the geoms touching the table: objects' parts, objects' hulls."""
    model, data = env.sim.model._model, env.sim.data._data
    table = model.geom("table_collision").id
    parts, hulls = set(), set()
    for c in data.contact[: data.ncon]:
        if table in (c.geom1, c.geom2):
            other = model.geom(c.geom2 if c.geom1 == table else c.geom1).name
            (hulls if other.endswith("_hull") else parts if "_part" in other else set()).add(other)
    return parts, hulls


def test_hull_objects_meet_the_table_through_their_hulls_and_rest_where_their_parts_rest(scene):
    from scenegen.env.robosuite_env import SceneEnv

    rest = {}
    for physics in (PHYSICS["exact"], ControlPhysics(name="hull", table_contact="hull")):
        env = SceneEnv(scene, physics=physics)
        try:
            env.reset_to(scene)
            for _ in range(20):  # 1 s, the arm held still
                env.step(np.zeros(7))
            parts, hulls = _table_contacts(env)
            model = env.sim.model._model
            if physics.table_contact == "hull":
                assert not parts and hulls  # the table meets hulls, never parts
                hull_geoms = [g for g in range(model.ngeom) if model.geom(g).name.endswith("_hull")]
                assert len(hull_geoms) == len(scene.objects)
                assert model.body_mass[model.body(f"{scene.objects[0].name}_hull_body").id] == 0
            else:
                assert parts and not hulls
            rest[physics.table_contact] = {
                o.name: env.sim.data._data.xpos[model.body(o.name).id].copy() for o in scene.objects
            }
        finally:
            env.close()
    for name, where in rest["parts"].items():
        assert np.linalg.norm(rest["hull"][name] - where) < 1e-3, name


def test_the_controller_tracks_the_same_motion_at_a_5_ms_timestep(scene):
    """robosuite's OSC gains are set for 2 ms steps: at 5 ms the same servo motions take the same
    control steps and the grip site stays within 2 mm of its 2 ms path (measured: 1.0 mm)."""
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.manipulation.motion import down_grasp, servo
    from scenegen.perception.robot_state import grip_site

    paths, steps = {}, {}
    for physics in (PHYSICS["exact"], ControlPhysics(name="dt5", timestep=0.005)):
        env = SceneEnv(scene, physics=physics)
        try:
            env.reset_to(scene)
            here, _ = grip_site(env)
            path = []

            def step(action, env=env, path=path):
                env.step(action)
                path.append(grip_site(env)[0].copy())

            moves = [(here + [0.1, 0.1, 0.1], down_grasp(np.array([1.0, 0.0]))), (here, None)]
            steps[physics.name] = [
                servo(env, goal, rot, max_steps=80, step=step).steps for goal, rot in moves
            ]
            paths[physics.name] = np.array(path)
        finally:
            env.close()
    assert steps["dt5"] == steps["exact"]
    assert np.abs(paths["dt5"] - paths["exact"]).max() < 0.002
