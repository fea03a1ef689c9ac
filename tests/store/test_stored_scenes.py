"""Acceptance of a stored batch, checked by re-loading its files with plain MuJoCo calls.

Nothing here trusts the numbers the pipeline recorded (scene.json ``checks``, ``settle``) or calls
``scenegen.settle.physics.passive_test``: every property is measured again on the stored scene.xml.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from scenegen import paths
from scenegen.core import layout
from scenegen.manifest import read_manifest
from scenegen.schema.condition import PANDA_JOINT_LIMITS
from scenegen.schema.scene import REJECTION_LABELS, FurniturePlacement
from scenegen.sim import world

REPO_ROOT = Path(__file__).resolve().parents[2]
N_SCENES = 6  # the demo_batch fixture asks for 6 accepted scenes
EE_BODY = "gripper0_eef"
KEYFRAME = "settled"
MAX_PENETRATION = 1e-3  # m, deepest contact at the keyframe
PASSIVE_SECONDS = 2.0
MAX_OBJECT_MOVE = 5e-3  # m, during the passive simulation
MAX_EE_MOVE = 5e-3  # m, strictly less
MAX_FLOAT = 3e-3  # m, lowest collision point above its support surface
POSE_TOL = 1e-6  # keyframe qpos vs scene.json settled pose
ASSET_DIR = "../_assets/"


# ---------------------------------------------------------------- helpers


def scene_dirs(batch: Path) -> list[Path]:
    return sorted(d for d in batch.iterdir() if d.is_dir() and d.name.startswith("scene_"))


def read_record(scene: Path) -> dict:
    return json.loads((scene / "scene.json").read_text())


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def free_joint_bodies(model: mujoco.MjModel) -> dict[str, int]:
    """body name -> qpos address of its free joint."""
    out = {}
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out[model.body(model.jnt_bodyid[j]).name] = int(model.jnt_qposadr[j])
    return out


def contact_label(model: mujoco.MjModel, contact) -> str:
    return (
        f"{model.geom(contact.geom1).name or contact.geom1}/{model.geom(contact.geom2).name or contact.geom2}"
    )


def at_keyframe(model: mujoco.MjModel) -> mujoco.MjData:
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return data


def lowest_point_over(
    model: mujoco.MjModel, data: mujoco.MjData, body: str, surface: layout.Surface
) -> float:
    """Lowest world z of a body's collision meshes (group 3 mesh geoms) over its support's region.

    Vertices outside the surface's region (an object overhanging the table edge or a shelf board)
    may hang below the surface plane and are not counted.
    """
    body_id = model.body(body).id
    lowest = np.inf
    n = 0
    for g in range(model.ngeom):
        if (
            model.geom_bodyid[g] != body_id
            or model.geom_group[g] != world.COLLISION_GROUP
            or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH
        ):
            continue
        n += 1
        mesh = model.geom_dataid[g]
        start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        verts = model.mesh_vert[start : start + count]
        world_verts = verts @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        over = [v[2] for v in world_verts if surface.margin(v[:2]) >= 0.0]
        lowest = min(lowest, *over) if over else lowest
    assert n > 0, f"{body}: no collision mesh geoms in group {world.COLLISION_GROUP}"
    return float(lowest)


@pytest.fixture(scope="module")
def scenes(
    demo_batch: Path, tmp_path_factory: pytest.TempPathFactory
) -> list[tuple[Path, dict, mujoco.MjModel]]:
    """(scene dir, scene.json, model) of every stored scene, loaded from an unrelated working dir."""
    elsewhere = tmp_path_factory.mktemp("unrelated_cwd")
    out = []
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(elsewhere)
        for scene in scene_dirs(demo_batch):
            out.append((scene, read_record(scene), mujoco.MjModel.from_xml_path(str(scene / "scene.xml"))))
    return out


# ---------------------------------------------------------------- layout


def test_batch_has_the_requested_scenes_and_no_leftovers(demo_batch: Path):
    dirs = scene_dirs(demo_batch)
    assert len(dirs) == N_SCENES
    for d in dirs:
        images = [f"{cam}_{kind}.png" for cam in ("front", "side") for kind in ("depth", "rgb", "seg")]
        assert sorted(p.name for p in d.iterdir()) == sorted([*images, "scene.json", "scene.xml"]), d
        record = read_record(d)
        assert d.name == record["scene_id"] == f"scene_{record['proposal_index']:06d}"
    top = {p.name for p in demo_batch.iterdir()}
    expected = {
        "_assets",
        "index.jsonl",
        "rejections.jsonl",
        "manifest.yaml",
        "pipeline.yaml",
        "timings.json",
    }
    assert top == expected | {d.name for d in dirs}, "temporary or unexpected files left in the batch"


# ---------------------------------------------------------------- acceptance (physics, re-measured)


@pytest.mark.parametrize("i", range(N_SCENES))
def test_scene_loads_elsewhere_and_stays_at_rest(
    demo_batch: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, i: int
):
    scene = scene_dirs(demo_batch)[i]
    xml_path = (scene / "scene.xml").resolve()
    elsewhere = tmp_path / "unrelated"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)

    model = mujoco.MjModel.from_xml_path(str(xml_path))
    assert model.nkey >= 1 and model.key(0).name == KEYFRAME
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    np.testing.assert_array_equal(data.ctrl, model.key_ctrl[0])
    mujoco.mj_forward(model, data)

    depths = {contact_label(model, data.contact[k]): -data.contact[k].dist for k in range(data.ncon)}
    deepest = max(depths, key=depths.get, default=None)
    assert deepest is None or depths[deepest] <= MAX_PENETRATION, (
        f"{scene.name}: contact {deepest} penetrates {depths[deepest] * 1e3:.3f} mm"
    )

    bodies = free_joint_bodies(model)
    assert bodies, "no free objects in the scene"
    start = {name: data.qpos[adr : adr + 3].copy() for name, adr in bodies.items()}
    ee_start = data.body(EE_BODY).xpos.copy()
    ctrl = data.ctrl.copy()
    steps = int(round(PASSIVE_SECONDS / model.opt.timestep))
    for _ in range(steps):
        mujoco.mj_step(model, data)
    assert data.time == pytest.approx(PASSIVE_SECONDS)
    np.testing.assert_array_equal(data.ctrl, ctrl)
    assert np.isfinite(data.qpos).all(), f"{scene.name}: simulation diverged"

    moves = {
        name: float(np.linalg.norm(data.qpos[adr : adr + 3] - start[name])) for name, adr in bodies.items()
    }
    worst = max(moves, key=moves.get)
    assert moves[worst] <= MAX_OBJECT_MOVE, f"{scene.name}: {worst} moved {moves[worst] * 1e3:.3f} mm"
    ee_move = float(np.linalg.norm(data.body(EE_BODY).xpos - ee_start))
    assert ee_move < MAX_EE_MOVE, f"{scene.name}: end effector moved {ee_move * 1e3:.3f} mm"


def test_objects_rest_on_their_support(scenes):
    """Over its support's region, no object floats more than 3 mm above (or sinks 1 mm into) it."""
    problems = []
    for scene, record, model in scenes:
        data = at_keyframe(model)
        surfaces = layout.support_surfaces([FurniturePlacement(**f) for f in record["furniture"]])
        for obj in record["objects"]:
            assert obj["support"] in surfaces, f"{scene.name}: {obj['name']} on unknown support"
            surface = surfaces[obj["support"]]
            gap = lowest_point_over(model, data, obj["name"], surface) - surface.z
            if not -MAX_PENETRATION <= gap <= MAX_FLOAT:
                problems.append(f"{scene.name}: {obj['name']} is {gap * 1e3:+.2f} mm from {obj['support']}")
    assert not problems, "\n".join(problems)


def test_contact_options_are_embedded(scenes):
    for scene, record, model in scenes:
        options = record["contact_options"]
        assert model.opt.timestep == pytest.approx(options["timestep"]), scene.name
        assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST, scene.name
        assert options["integrator"] == "implicitfast"
        assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC, scene.name
        assert options["cone"] == "elliptic"
        assert model.opt.impratio == pytest.approx(options["impratio"]), scene.name
        assert bool(model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_MULTICCD) == options["multiccd"]


# ---------------------------------------------------------------- XML vs scene.json


def test_xml_bodies_match_scene_json(scenes):
    for scene, record, model in scenes:
        names = {o["name"] for o in record["objects"]}
        assert record["target"] in names
        assert set(free_joint_bodies(model)) == names, scene.name
        root = ET.parse(scene / "scene.xml").getroot()
        xml_free = {b.get("name") for b in root.iter("body") if b.find("freejoint") is not None}
        xml_free |= {
            b.get("name") for b in root.iter("body") for j in b.findall("joint") if j.get("type") == "free"
        }
        assert xml_free == names, scene.name
        for piece in record["furniture"]:
            assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, piece["name"]) >= 0, (
                f"{scene.name}: furniture {piece['name']} missing from scene.xml"
            )


def test_keyframe_holds_the_settled_poses(scenes):
    mismatches = []
    for scene, record, model in scenes:
        assert model.key(0).name == KEYFRAME
        bodies = free_joint_bodies(model)
        key = model.key_qpos[0]
        for obj in record["objects"]:
            adr = bodies[obj["name"]]
            for what, stored, expected in (
                ("position", key[adr : adr + 3], obj["position"]),
                ("quat", key[adr + 3 : adr + 7], obj["quat"]),
            ):
                err = float(np.max(np.abs(np.asarray(stored) - np.asarray(expected))))
                if err > POSE_TOL:
                    mismatches.append(
                        f"{scene.name} {obj['name']} {what}: keyframe {list(stored)} vs scene.json "
                        f"{expected} (max error {err:.2e})"
                    )
    assert not mismatches, "\n".join(mismatches)


def test_keyframe_ctrl_holds_the_requested_robot_pose(scenes):
    for scene, record, model in scenes:
        pose = record["condition"]["robot_pose"]
        assert len(pose) == len(world.ARM_ACTUATORS)
        for act, q, (lo, hi) in zip(world.ARM_ACTUATORS, pose, PANDA_JOINT_LIMITS, strict=True):
            assert lo <= q <= hi
            assert model.key_ctrl[0][model.actuator(act).id] == pytest.approx(q, abs=1e-5), (scene.name, act)
        for joint, q in world.GRIPPER_OPEN.items():
            adr = model.joint(joint).qposadr[0]
            assert model.key_qpos[0][adr] == pytest.approx(q, abs=2e-3), (scene.name, joint)


# ---------------------------------------------------------------- files and assets


def test_xml_references_assets_only_inside_the_batch(scenes, demo_batch: Path):
    forbidden = {
        str(REPO_ROOT),
        str(paths.PROJECT_ROOT),
        str(paths.ASSETS_DIR),
        str(demo_batch),
        str(demo_batch.resolve()),
        sys.prefix,
        "site-packages",
    }
    for scene, record, _ in scenes:
        text = (scene / "scene.xml").read_text()
        for needle in forbidden:
            assert needle not in text, f"{scene.name}: scene.xml contains {needle!r}"
        root = ET.fromstring(text)
        compiler = root.find("compiler")
        assert compiler is not None
        assert compiler.get("meshdir") == ASSET_DIR and compiler.get("texturedir") == ASSET_DIR
        referenced = set()
        for element in root.iter():
            name = element.get("file")
            if name is None:
                continue
            assert element.tag in ("mesh", "texture", "hfield", "skin"), f"{scene.name}: <{element.tag} file>"
            assert "/" not in name and "\\" not in name and not Path(name).is_absolute(), name
            assert (scene / ASSET_DIR / name).is_file(), f"{scene.name}: {name} missing from _assets"
            referenced.add(ASSET_DIR + name)
        listed = {k for k in record["files"] if k.startswith(ASSET_DIR)}
        assert referenced == listed, f"{scene.name}: files in scene.json differ from those scene.xml uses"


def test_file_hashes_match_the_files_on_disk(demo_batch: Path):
    for scene in scene_dirs(demo_batch):
        files = read_record(scene)["files"]
        assert "scene.xml" in files
        for rel, digest in files.items():
            path = scene / rel
            assert path.resolve().is_relative_to(demo_batch.resolve()), rel
            assert path.is_file(), f"{scene.name}: {rel} missing"
            assert sha256(path) == digest, f"{scene.name}: sha256 of {rel} does not match scene.json"


def test_batch_is_relocatable(demo_batch: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A moved copy of a scene loads, and reads its meshes from the copy's own _assets/."""
    scene = scene_dirs(demo_batch)[0]
    copy = tmp_path / "moved" / "batch"
    shutil.copytree(demo_batch / "_assets", copy / "_assets")
    shutil.copytree(scene, copy / scene.name)
    monkeypatch.chdir(tmp_path)
    xml = copy / scene.name / "scene.xml"
    model = mujoco.MjModel.from_xml_path(str(xml))
    assert set(free_joint_bodies(model)) == {o["name"] for o in read_record(scene)["objects"]}
    shutil.rmtree(copy / "_assets")
    with pytest.raises(ValueError):
        mujoco.MjModel.from_xml_path(str(xml))


# ---------------------------------------------------------------- index, rejections, manifest


def test_index_has_one_row_per_scene(demo_batch: Path):
    rows = read_jsonl(demo_batch / "index.jsonl")
    dirs = scene_dirs(demo_batch)
    assert len(rows) == len(dirs) == N_SCENES
    assert [r["scene_id"] for r in rows] == [d.name for d in dirs]
    indices = [r["proposal_index"] for r in rows]
    assert indices == sorted(indices) and len(set(indices)) == len(indices), indices
    for row in rows:
        scene = demo_batch / row["scene_id"]
        record = read_record(scene)
        assert row["scene_json_sha256"] == sha256(scene / "scene.json"), row["scene_id"]
        assert row["proposal_index"] == record["proposal_index"]
        assert row["target"] == record["target"]
        assert row["n_objects"] == len(record["objects"])


def test_rejections_and_acceptances_partition_the_proposals(demo_batch: Path):
    accepted = [r["proposal_index"] for r in read_jsonl(demo_batch / "index.jsonl")]
    rejections = read_jsonl(demo_batch / "rejections.jsonl")
    rejected = [r["proposal_index"] for r in rejections]
    assert len(set(rejected)) == len(rejected), "a proposal is rejected twice"
    assert not set(rejected) & set(accepted), set(rejected) & set(accepted)
    everything = set(rejected) | set(accepted)
    assert everything == set(range(max(everything) + 1)), "proposal indices are not contiguous from 0"
    assert max(everything) == max(accepted), "proposals continued after the last accepted scene"
    for row in rejections:
        assert row["label"] in REJECTION_LABELS, row
    timings = json.loads((demo_batch / "timings.json").read_text())
    assert timings["proposals_this_run"] == len(everything)


def test_manifest_counts_equal_the_files(demo_batch: Path):
    manifest = read_manifest(demo_batch / "manifest.yaml")
    assert manifest.kind == "batch" and len(manifest.sources) == 1
    source = manifest.sources[0]
    scenes = [d for d in scene_dirs(demo_batch) if (d / "scene.json").is_file()]
    rejections = read_jsonl(demo_batch / "rejections.jsonl")
    assert source.counts.scenes == len(scenes) == N_SCENES
    assert source.counts.rejected == len(rejections)
    assert source.counts.proposals == len(scenes) + len(rejections)
    assert source.rejections_by_label == dict(Counter(r["label"] for r in rejections))
    assert source.origin == "synthetic" and source.seed_panel.seed == 0
    pipeline = yaml.safe_load((demo_batch / "pipeline.yaml").read_text())
    assert pipeline["n"] == N_SCENES and pipeline["seed"] == 0
    for scene in scenes:
        assert read_record(scene)["provenance"]["pipeline_sha256"] == source.pipeline.sha256
