"""Hand-built scene helpers shared by the tests: snapped object placements, bare proposals, small recipes.

A plain module, not a conftest: test modules import it as ``from scenes import ...`` (pytest's default
"prepend" import mode puts tests/ on sys.path when it loads tests/conftest.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.core.placement import quat_mul, snap_to_rest, yaw_quat
from scenegen.paths import PROJECT_ROOT
from scenegen.propose.procedural import DEFAULT_CAMERAS
from scenegen.schema.condition import Condition
from scenegen.schema.scene import Camera, FurniturePlacement, Lighting, ObjectPlacement, SceneProposal

DEMO = Path(__file__).resolve().parents[1] / "pipelines" / "procedural.yaml"
SMALL = (160, 120)  # width, height of the cameras of small_recipe


REFERENCE = Path(__file__).resolve().parents[1] / "pipelines" / "reference.yaml"


def benchmark(name: str):
    """The script ``benchmarks/<name>.py`` loaded as a module (the benchmarks are scripts, not a
    package), so that a test can call its functions."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"{name}_bench", PROJECT_ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def stored_scenes(batch: Path) -> list[Path]:
    """The scene directories of a stored batch, in order."""
    return sorted(p for p in batch.glob("scene_*") if p.is_dir())


def generate_request(out: Path, request: str, proposer: str, n: int = 1, max_proposals: int = 40) -> int:
    """``scenegen generate`` of the reference recipe for a free-text request, unrendered, seed 3."""
    from scenegen.cli import main

    argv = ["generate", str(REFERENCE), "--request", request, "--proposer", proposer, "--n", str(n)]
    argv += ["--max-proposals", str(max_proposals), "--seed", "3", "--out", str(out)]
    return main(argv + ["--no-render", "--quiet"])


def place(
    catalog: Catalog,
    name: str,
    asset: str,
    x: float,
    y: float,
    *,
    pose: int = 0,
    yaw: float = 0.0,
    lift: float = 0.0,
    scale: float = 1.0,
    support: str = "table",
    furniture: Sequence[FurniturePlacement] = (),
    below: Sequence[ObjectPlacement] = (),
    check_pose: bool = True,
) -> ObjectPlacement:
    """An object snapped onto resting pose ``pose`` of ``support`` at (x, y) with yaw ``yaw``, raised by
    ``lift`` metres.

    ``below`` lists placed objects whose tops are supports (stacking: ``support`` is then one's name).
    With ``check_pose`` the snap must keep resting pose ``pose``.
    """
    a = catalog.get(asset)
    surface = layout.support_surfaces(furniture, below, catalog)[support]
    raw_quat = quat_mul(yaw_quat(yaw), np.asarray(a.resting_poses[pose].quat))
    position, quat, index, _ = snap_to_rest(a, (x, y, 0.0), raw_quat, surface, scale)
    if check_pose:
        assert index == pose
    return ObjectPlacement(
        name=name,
        asset=asset,
        category=a.category,
        position=(position[0], position[1], position[2] + lift),
        quat=quat,
        scale=scale,
        support=support,
        resting_pose=index,
    )


def proposal(
    objects: Sequence[ObjectPlacement],
    furniture: Sequence[FurniturePlacement] = (),
    target: str | None = None,
    *,
    lighting: Lighting | None = None,
    cameras: Sequence[Camera] = (),
) -> SceneProposal:
    """A proposal of ``objects`` for the first one's category; ``target`` defaults to the first object,
    ``lighting`` to no lights at all."""
    return SceneProposal(
        index=0,
        seed=0,
        condition=Condition(target=objects[0].category),
        target=target or objects[0].name,
        objects=tuple(objects),
        furniture=tuple(furniture),
        lighting=Lighting(lights=()) if lighting is None else lighting,
        cameras=tuple(cameras),
    )


def small_recipe(
    path: Path,
    size: tuple[int, int] = SMALL,
    *,
    n: int | None = None,
    n_objects: list[int] | None = None,
) -> Path:
    """pipelines/procedural.yaml with two small cameras (front, side) at the default poses, written to
    ``path``.

    ``n`` (scenes) and ``n_objects`` (the proposer's range) replace the recipe's when given.
    """
    recipe = yaml.safe_load(DEMO.read_text())
    if n is not None:
        recipe["n"] = n
    recipe["proposer"]["cameras"] = [
        {
            "name": cam.name,
            "position": list(cam.position),
            "lookat": list(cam.lookat),
            "width": size[0],
            "height": size[1],
        }
        for cam in DEFAULT_CAMERAS
    ]
    if n_objects is not None:
        recipe["proposer"]["n_objects"] = n_objects
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return path


def project_with(batch: Path, root: Path) -> Path:
    """A project folder ``root`` holding a copy of ``batch`` (its shared meshes hard-linked, never
    written) added to the folder's own data_manifest.yaml (the project's datasheet, a pending
    transfer section: the folder holds no transfer artifact; no other sources); returns the manifest's
    path. The copy is ``root``/batch."""
    from scenegen.cli import main

    copy_batch(batch, root / "batch")
    path = empty_project_manifest(root / "data_manifest.yaml")
    code = main(["manifest", "add", str(root / "batch"), "--to", str(path)])
    assert code == 0, f"scenegen manifest add exited {code}"
    return path


def empty_project_manifest(path: Path) -> Path:
    """The project's data_manifest.yaml without sources, models and recipes, its transfer section
    pending, written at ``path``: a project that batches can be added to."""
    from scenegen.data.project_manifest import TRANSFER

    manifest = yaml.safe_load((PROJECT_ROOT / "data_manifest.yaml").read_text())
    manifest = {k: v for k, v in manifest.items() if k not in ("models", "recipes")} | {"sources": []}
    manifest["transfer"] = TRANSFER.model_dump(mode="json", exclude_none=True)
    path.write_text(yaml.safe_dump(manifest, sort_keys=False))
    return path


def copy_batch(batch: Path, to: Path) -> Path:
    """A copy of ``batch`` at ``to`` whose shared meshes are hard links (never to be written)."""
    import os
    import shutil

    shutil.copytree(batch, to, ignore=shutil.ignore_patterns("_assets"))
    shutil.copytree(batch / "_assets", to / "_assets", copy_function=os.link)
    return to


def resimulated(scene_xml: Path, seconds: float = 2.0) -> tuple[float, float]:
    """Re-load a stored scene.xml with plain MuJoCo calls (from wherever the caller stands), reset it to
    its ``settled`` keyframe and simulate it passively: (deepest contact penetration at the keyframe,
    largest displacement of a free object after ``seconds``), both in metres."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("settled").id)
    mujoco.mj_forward(model, data)
    deepest = max((-data.contact[k].dist for k in range(data.ncon)), default=0.0)
    free = [
        model.jnt_qposadr[j] for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
    ]
    start = {adr: data.qpos[adr : adr + 3].copy() for adr in free}
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
    moved = max((float(np.linalg.norm(data.qpos[a : a + 3] - p)) for a, p in start.items()), default=0.0)
    return float(deepest), moved
