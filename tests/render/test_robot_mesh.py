"""The robot's meshes decimated for drawing (recipe key ``robot_mesh_detail``): fewer triangles, the
same picture within a measured tolerance, the simulated model untouched, recorded in scene.json."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml
from scenes import small_recipe

from scenegen.assets.catalog import load_catalog
from scenegen.cli import main
from scenegen.propose.procedural import ProceduralProposer
from scenegen.render.offscreen import ROBOT_BODY_PREFIXES, SceneRenderer, segmentation_ids
from scenegen.render.robot_mesh import decimated_copy, robot_visual_meshes
from scenegen.runner.config import load_pipeline
from scenegen.sim import world

DETAIL = 0.25
MESH_FIELDS = ("mesh_vert", "mesh_face", "mesh_normal", "mesh_vertnum", "mesh_facenum", "mesh_texcoordnum")


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):
    """A compiled procedural scene at its initial state, and its proposal."""
    recipe = small_recipe(tmp_path_factory.mktemp("recipe") / "r.yaml", size=(320, 240))
    config = load_pipeline(recipe, {})
    catalog = load_catalog()
    proposal = next(iter(ProceduralProposer(config.proposer, catalog).propose(config.condition, [0], 3)))
    spec = world.build_world(
        catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:], _ = world.initial_state(model, proposal.condition.robot_pose, proposal.objects)
    mujoco.mj_forward(model, data)
    return model, data, proposal


def robot_faces(model) -> int:
    return sum(int(model.mesh_facenum[i]) for i in robot_visual_meshes(model, ROBOT_BODY_PREFIXES))


def test_decimated_copy_draws_fewer_robot_triangles_and_leaves_the_model_alone(
    scene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    model, _, _ = scene
    monkeypatch.setenv("SCENEGEN_CACHE", str(tmp_path))  # the first copy decimates, the second reads
    before = {name: getattr(model, name).copy() for name in MESH_FIELDS}
    copy = decimated_copy(model, ROBOT_BODY_PREFIXES, DETAIL)
    assert robot_faces(model) > 100_000  # robosuite's Panda as shipped
    assert 0.15 < robot_faces(copy) / robot_faces(model) < 0.35
    robot = set(robot_visual_meshes(model, ROBOT_BODY_PREFIXES))
    others = [i for i in range(model.nmesh) if i not in robot]
    assert others and all(copy.mesh_facenum[i] == model.mesh_facenum[i] for i in others)
    for name in MESH_FIELDS:  # the simulated model is not touched
        assert np.array_equal(getattr(model, name), before[name]), name
    assert len(list((tmp_path / "robot_meshes").glob("*.npz"))) == 1
    again = decimated_copy(model, ROBOT_BODY_PREFIXES, DETAIL)
    for name in MESH_FIELDS:  # the same decimation every time, computed or cached
        assert np.array_equal(getattr(copy, name), getattr(again, name)), name
    with pytest.raises(ValueError, match="robot mesh detail"):
        decimated_copy(model, ROBOT_BODY_PREFIXES, 0.0)


def test_decimated_robot_changes_the_picture_only_slightly(scene):
    """Measured on this scene: the robot's pixels move at its silhouette, nothing else changes."""
    model, data, proposal = scene
    ids = segmentation_ids(model, [o.name for o in proposal.objects], [f.name for f in proposal.furniture])
    cams = [c.name for c in proposal.cameras]
    size = [(c.width, c.height) for c in proposal.cameras]
    renderer = SceneRenderer()
    try:
        full = renderer.render(model, data, cams, ids, size)
        light = renderer.render(model, data, cams, ids, size, robot_detail=DETAIL)
        full_again = renderer.render(model, data, cams, ids, size)
    finally:
        renderer.close()
    for a, b, c in zip(full, light, full_again, strict=True):
        assert np.array_equal(a.rgb, c.rgb), "the full-detail context was not restored"
        rgb = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(-1)
        assert rgb.any(), "the decimated robot drew the same pixels: nothing was decimated"
        robot = (a.seg == ids["robot"]) | (b.seg == ids["robot"])
        assert rgb.mean() < 2.0
        # Shading moves on the robot (normals of the welded, decimated surface); elsewhere only
        # its shadow's edge may: 1.5 % and 3.1 % of all pixels changed by more than 8, 0.1 % off
        # the robot, measured on this scene's two cameras.
        assert (rgb[~robot] > 8).sum() < 0.005 * rgb.size
        changed = a.seg != b.seg
        assert changed.mean() < 0.02
        assert np.all(robot[changed]), "segmentation changed away from the robot"


def test_recipe_key_is_recorded_and_absent_by_default(tmp_path: Path):
    recipe = small_recipe(tmp_path / "r.yaml", n=1)
    plain = load_pipeline(recipe, {})
    assert "robot_mesh_detail" not in plain.model_dump()  # earlier recipes hash as before
    raw = yaml.safe_load(recipe.read_text())
    raw["robot_mesh_detail"] = DETAIL
    (tmp_path / "light.yaml").write_text(yaml.safe_dump(raw))
    assert main(["generate", str(tmp_path / "light.yaml"), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    record = json.loads(next((tmp_path / "b").glob("scene_*/scene.json")).read_text())
    assert record["render"]["robot_mesh_detail"] == DETAIL
    raw["robot_mesh_detail"] = 1.5
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(raw))
    assert main(["generate", str(tmp_path / "bad.yaml"), "--out", str(tmp_path / "c"), "--quiet"]) == 2
    assert not (tmp_path / "c").exists()
