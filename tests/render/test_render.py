"""Rendered images of stored scenes, checked against MuJoCo itself: files, segmentation, depth, lighting.

Nothing here trusts scenegen's own image bookkeeping: segmentation ids and depths are recomputed by
casting rays (``mujoco.mj_ray``) through pixel centres of the stored scene.xml at its keyframe, and
lighting is checked by re-rendering the stored model with its lights changed. The no-GL error paths
run in fresh interpreters, since MUJOCO_GL is read when mujoco is first imported.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import mujoco
import numpy as np
import pytest
from scenes import SMALL, small_recipe
from scipy import ndimage

from scenegen.cli import main
from scenegen.render.offscreen import SceneRenderer, encode_png
from scenegen.schema.scene import Camera
from scenegen.sim import world

REPO_ROOT = Path(__file__).resolve().parents[2]
DEMO = REPO_ROOT / "pipelines" / "procedural.yaml"
IMAGE_KINDS = ("rgb", "depth", "seg")
ROBOT_BODY_PREFIXES = ("robot0_", "gripper0_", "fixed_mount0_")  # robosuite's Panda, gripper and mount
DEPTH_TOL_MM = 5.0
MAX_RERENDER_RGB = 1e-4  # share of RGB pixels a re-render of scene.xml may change
MAX_SEG_MISMATCH = 0.002  # share of pixels whose id differs from the ray cast through their centre
USAGE_ERROR = 2
PREFIX = "scenegen: error: "


# ---------------------------------------------------------------- helpers


def scene_dirs(batch: Path) -> list[Path]:
    return sorted(d for d in batch.iterdir() if d.is_dir() and d.name.startswith("scene_"))


def read_record(scene: Path) -> dict:
    return json.loads((scene / "scene.json").read_text())


def read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, f"{path}: missing or unreadable"
    return image


def read_rgb(path: Path) -> np.ndarray:
    return read_image(path)[..., ::-1]  # OpenCV reads BGR


@functools.cache
def _stored_model(xml: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(xml)  # ~1.3 s each (robosuite's meshes): load once


def load_at_keyframe(scene: Path) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A private copy of the stored model (tests may change it) and its data at keyframe 0."""
    model = copy.deepcopy(_stored_model(str(scene / "scene.xml")))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return model, data


def geom_instances(model: mujoco.MjModel, ids: dict[str, int]) -> np.ndarray:
    """Instance id each geom should show as, from scene.json's names alone (-1: none).

    Bodies named in ``segmentation`` (table, furniture, objects) carry their own id, robot bodies the
    robot's, the world body's geoms (floor, walls) the arena's.
    """
    out = np.full(model.ngeom, -1, dtype=np.int64)
    for g in range(model.ngeom):
        body = int(model.geom_bodyid[g])
        name = model.body(body).name
        if name in ids:
            out[g] = ids[name]
        elif name.startswith(ROBOT_BODY_PREFIXES):
            out[g] = ids["robot"]
        elif body == 0:
            out[g] = ids["arena"]
    return out


def visible_groups(record: dict) -> np.ndarray:
    groups = np.zeros(mujoco.mjNGROUP, dtype=np.uint8)
    groups[record["render"]["visible_geom_groups"]] = 1
    return groups


def cast_pixels(
    model: mujoco.MjModel, data: mujoco.MjData, cam: dict, groups: np.ndarray, vs, us
) -> tuple[np.ndarray, np.ndarray]:
    """(geom id, depth in mm along the optical axis) of rays through the centres of pixels (v, u).

    The ray leaves the camera's position along its -z axis tilted by the pixel's offset from the
    principal point (x right, y up in the camera frame, image rows counted from the top).
    """
    k = cam["intrinsics"]
    cam_id = model.camera(cam["name"]).id
    origin = data.cam_xpos[cam_id].copy()
    rot = data.cam_xmat[cam_id].reshape(3, 3)
    geoms = np.full(len(vs), -1, dtype=np.int32)
    depth = np.zeros(len(vs))
    hit = np.zeros(1, dtype=np.int32)
    for i, (v, u) in enumerate(zip(vs, us, strict=True)):
        d_cam = np.array([(u + 0.5 - k["cx"]) / k["fx"], -(v + 0.5 - k["cy"]) / k["fy"], -1.0])
        norm = float(np.linalg.norm(d_cam))
        dist = mujoco.mj_ray(model, data, origin, rot @ d_cam / norm, groups, 1, -1, hit)
        if dist >= 0:
            geoms[i] = hit[0]
            depth[i] = dist / norm * 1000.0  # cos(angle to the optical axis) = 1 / |d_cam|
    return geoms, depth


def interior(mask: np.ndarray, size: int = 5) -> np.ndarray:
    """Pixels of a mask whose whole size x size neighbourhood is in the mask (away from edges)."""
    return ndimage.binary_erosion(mask, np.ones((size, size), bool), border_value=0)


def mean_front_rgb(scene: Path) -> float:
    return float(read_image(scene / "front_rgb.png").mean())


def camera_size(record: dict, name: str) -> tuple[int, int]:
    cam = next(c for c in record["cameras"] if c["name"] == name)
    return cam["width"], cam["height"]


def render_all(renderer: SceneRenderer, model, data, record: dict):
    names = [c["name"] for c in record["cameras"]]
    sizes = [(c["width"], c["height"]) for c in record["cameras"]]
    return dict(zip(names, renderer.render(model, data, names, record["segmentation"], sizes), strict=True))


def assert_one_line_error(result: subprocess.CompletedProcess, needles: list[str]) -> str:
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == USAGE_ERROR, (result.returncode, result.stderr)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{result.stderr}"
    assert lines[0].startswith(PREFIX), lines[0]
    missing = [n for n in needles if n not in lines[0]]
    assert not missing, f"error line lacks {missing}: {lines[0]}"
    return lines[0]


def cli_subprocess(args: list[str], gl: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MUJOCO_GL"] = gl
    return subprocess.run(
        [sys.executable, "-m", "scenegen.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=300,
    )


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def small_batch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 scenes of the demo recipe with 160x120 cameras, where a pixel spans ~1 cm on the table."""
    root = tmp_path_factory.mktemp("small_render")
    recipe = small_recipe(root / "small.yaml", n=3)
    out = root / "batch"
    assert main(["generate", str(recipe), "--seed", "0", "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(params=["demo_640x480", "small_160x120"])
def batch(request: pytest.FixtureRequest) -> Path:
    name = "demo_batch" if request.param.startswith("demo") else "small_batch"
    return request.getfixturevalue(name)


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer()
    yield r
    r.close()


# ---------------------------------------------------------------- files


def test_every_camera_has_rgb_depth_and_seg_pngs(batch: Path):
    scenes = scene_dirs(batch)
    assert scenes
    for scene in scenes:
        record = read_record(scene)
        assert [c["name"] for c in record["cameras"]] == ["front", "side"]
        for cam in record["cameras"]:
            assert cam["images"] == {k: f"{cam['name']}_{k}.png" for k in IMAGE_KINDS}
            shape = (cam["height"], cam["width"])
            rgb = read_image(scene / cam["images"]["rgb"])
            assert rgb.dtype == np.uint8 and rgb.shape == (*shape, 3), (scene.name, cam["name"], rgb.shape)
            for kind in ("depth", "seg"):
                image = read_image(scene / cam["images"][kind])
                assert image.dtype == np.uint16, (scene.name, cam["name"], kind, image.dtype)
                assert image.shape == shape, (scene.name, cam["name"], kind, image.shape)
            assert rgb.std() > 5, f"{scene.name} {cam['name']}: rgb is (nearly) uniform"


def test_camera_pose_and_intrinsics_match_scene_json(batch: Path):
    for scene in scene_dirs(batch):
        record = read_record(scene)
        model, data = load_at_keyframe(scene)
        for cam in record["cameras"]:
            cam_id = model.camera(cam["name"]).id
            assert model.cam_fovy[cam_id] == pytest.approx(cam["fovy"])
            k = cam["intrinsics"]
            f = 0.5 * cam["height"] / math.tan(math.radians(cam["fovy"]) / 2)
            assert k["fx"] == pytest.approx(f, abs=1e-5) and k["fy"] == pytest.approx(f, abs=1e-5)
            assert (k["cx"], k["cy"]) == (cam["width"] / 2, cam["height"] / 2)
            extr = cam["extrinsics"]
            np.testing.assert_allclose(data.cam_xpos[cam_id], extr["position"], atol=1e-5)
            np.testing.assert_allclose(data.cam_xmat[cam_id].reshape(3, 3), extr["rotation"], atol=1e-5)


# ---------------------------------------------------------------- segmentation


def test_segmentation_ids_name_the_scene_instances(batch: Path):
    for scene in scene_dirs(batch):
        record = read_record(scene)
        ids = record["segmentation"]
        names = ["arena", "table", "robot"]
        names += [f["name"] for f in record["furniture"]] + [o["name"] for o in record["objects"]]
        assert sorted(ids) == sorted(names), scene.name
        assert sorted(ids.values()) == list(range(1, len(ids) + 1)), f"{scene.name}: ids not 1..N: {ids}"
        for cam in record["cameras"]:
            seen = set(np.unique(read_image(scene / cam["images"]["seg"])).tolist())
            assert seen <= set(ids.values()) | {0}, f"{scene.name} {cam['name']}: unknown ids {seen}"


def test_front_camera_sees_table_robot_and_furniture(batch: Path):
    for scene in scene_dirs(batch):
        record = read_record(scene)
        ids = record["segmentation"]
        seg = read_image(scene / "front_seg.png")
        for name in ["table", "robot", *(f["name"] for f in record["furniture"])]:
            pixels = int((seg == ids[name]).sum())
            assert pixels >= 50, f"{scene.name}: {name} (id {ids[name]}) covers {pixels} px of front"


def test_segmentation_matches_ray_casts_through_pixel_centres(batch: Path):
    """Every pixel's id is the instance of the geom that a ray through its centre hits first.

    At 640x480 every 4th pixel in each direction is cast (19,200 rays per camera). Instances hit by
    a few rays (visible objects) must be present in the image, and ids of cast pixels must be hit.
    """
    for scene in scene_dirs(batch):
        record = read_record(scene)
        ids = record["segmentation"]
        names = {v: k for k, v in ids.items()}
        model, data = load_at_keyframe(scene)
        instance = geom_instances(model, ids)
        groups = visible_groups(record)
        for cam in record["cameras"]:
            seg = read_image(scene / cam["images"]["seg"])
            step = max(1, cam["width"] // SMALL[0])
            vs, us = np.mgrid[0 : cam["height"] : step, 0 : cam["width"] : step]
            vs, us = vs.ravel(), us.ravel()
            geoms, _ = cast_pixels(model, data, cam, groups, vs, us)
            expected = np.where(geoms >= 0, instance[np.maximum(geoms, 0)], 0)
            unnamed = sorted({model.geom(g).name for g in geoms[(geoms >= 0) & (expected < 0)]})
            assert not unnamed, f"{scene.name} {cam['name']}: visible geoms of no instance: {unnamed}"
            stored = seg[vs, us].astype(np.int64)
            wrong = float((stored != expected).mean())
            assert wrong <= MAX_SEG_MISMATCH, (
                f"{scene.name} {cam['name']}: {wrong:.2%} of pixels differ from the ray cast"
            )
            hits = {int(i): int((expected == i).sum()) for i in np.unique(expected) if i > 0}
            in_image = set(np.unique(seg).tolist()) - {0}
            missing = [names[i] for i, n in hits.items() if n >= 3 and i not in in_image]
            assert not missing, f"{scene.name} {cam['name']}: visible but absent from seg: {missing}"
            phantom = [names[int(i)] for i in np.unique(stored) if i > 0 and int(i) not in hits]
            assert not phantom, f"{scene.name} {cam['name']}: in seg but hit by no ray: {phantom}"


def test_objects_absent_from_every_image_are_really_hidden(batch: Path):
    """An object absent from every seg image is really hidden: no ray through a pixel centre hits it."""
    for scene in scene_dirs(batch):
        record = read_record(scene)
        ids = record["segmentation"]
        present = set()
        for cam in record["cameras"]:
            present |= set(np.unique(read_image(scene / cam["images"]["seg"])).tolist())
        absent = [o["name"] for o in record["objects"] if ids[o["name"]] not in present]
        if not absent:
            continue
        model, data = load_at_keyframe(scene)
        instance = geom_instances(model, ids)
        groups = visible_groups(record)
        for cam in record["cameras"]:
            vs, us = np.mgrid[0 : cam["height"], 0 : cam["width"]]
            geoms, _ = cast_pixels(model, data, cam, groups, vs.ravel(), us.ravel())
            hit = {int(instance[g]) for g in geoms if g >= 0}
            seen = [name for name in absent if ids[name] in hit]
            assert not seen, f"{scene.name} {cam['name']}: {seen} hit by rays but absent from seg"


# ---------------------------------------------------------------- depth


def test_depth_is_zero_exactly_where_nothing_is_segmented(batch: Path):
    for scene in scene_dirs(batch):
        for cam in read_record(scene)["cameras"]:
            depth = read_image(scene / cam["images"]["depth"])
            seg = read_image(scene / cam["images"]["seg"])
            assert not depth[seg == 0].any(), f"{scene.name} {cam['name']}: depth where seg is 0"
            assert depth[seg > 0].all(), f"{scene.name} {cam['name']}: depth 0 on a segmented pixel"


def test_depth_matches_ray_casts_through_pixel_centres(batch: Path):
    """Stored depth (mm) of pixels inside each instance's mask equals the ray-cast depth within 5 mm.

    Pixels 2+ px away from the mask's edge are used (up to 10 per instance and camera); the ray goes
    through the pixel centre (u + 0.5, v + 0.5) as the intrinsics (cx = W/2, cy = H/2) imply.
    """
    problems, checked = [], 0
    for scene in scene_dirs(batch):
        record = read_record(scene)
        names = {v: k for k, v in record["segmentation"].items()}
        model, data = load_at_keyframe(scene)
        instance = geom_instances(model, record["segmentation"])
        groups = visible_groups(record)
        for cam in record["cameras"]:
            depth = read_image(scene / cam["images"]["depth"]).astype(np.float64)
            seg = read_image(scene / cam["images"]["seg"])
            for i in np.unique(seg):
                if i == 0:
                    continue
                vs, us = np.nonzero(interior(seg == i))
                if len(vs) == 0:
                    continue
                pick = np.unique(np.linspace(0, len(vs) - 1, min(len(vs), 10)).astype(int))
                geoms, expected = cast_pixels(model, data, cam, groups, vs[pick], us[pick])
                for v, u, g, exp in zip(vs[pick], us[pick], geoms, expected, strict=True):
                    checked += 1
                    hit = names.get(int(instance[g]), "nothing") if g >= 0 else "nothing"
                    err = depth[v, u] - exp
                    if hit != names[int(i)] or abs(err) > DEPTH_TOL_MM:
                        problems.append(
                            f"{scene.name} {cam['name']} ({u},{v}) {names[int(i)]}: stored "
                            f"{depth[v, u]:.0f} mm, ray {exp:.1f} mm on {hit} (error {err:+.1f} mm)"
                        )
    assert checked >= 100, f"only {checked} pixels checked"
    assert not problems, f"{len(problems)} of {checked} pixels:\n" + "\n".join(problems[:25])


def test_background_has_depth_zero(demo_batch: Path, renderer: SceneRenderer):
    """A camera looking over the arena's wall at the sky: no return is segmented 0 and has depth 0."""
    scene = scene_dirs(demo_batch)[0]
    record = read_record(scene)
    model, data = load_at_keyframe(scene)
    cam_id = model.camera("front").id
    # Looking along +x (camera x right = -y, y up = +z, z back = -x), just under the 3 m wall's top.
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).ravel())
    model.cam_pos[cam_id], model.cam_quat[cam_id] = (0.0, 0.0, 2.9), quat
    mujoco.mj_forward(model, data)
    frames = renderer.render(model, data, ["front"], record["segmentation"], [SMALL])[0]
    sky = frames.seg == 0
    assert 0.1 < sky.mean() < 0.9, f"expected sky and wall, got {sky.mean():.0%} background"
    assert not frames.depth[sky].any(), "background pixels have a depth"
    assert (frames.depth[~sky] > 0).all()
    assert sky[0].all() and not sky[-1].any(), "sky should be above the wall"


# ---------------------------------------------------------------- lighting


def test_model_lights_are_the_scene_json_lights(demo_batch: Path):
    for scene in scene_dirs(demo_batch):
        lighting = read_record(scene)["lighting"]
        model, _ = load_at_keyframe(scene)
        assert model.nlight == len(lighting["lights"]) >= 1, scene.name
        np.testing.assert_allclose(model.vis.headlight.ambient, lighting["ambient"], atol=1e-6)
        np.testing.assert_array_equal(model.vis.headlight.diffuse, 0.0)
        for i, light in enumerate(lighting["lights"]):
            diffuse = np.multiply(light["colour"], light["intensity"])
            np.testing.assert_allclose(model.light_diffuse[i], diffuse, atol=1e-5, err_msg=scene.name)
            np.testing.assert_allclose(model.light_pos[i], light["position"], atol=1e-5, err_msg=scene.name)
            np.testing.assert_allclose(model.light_dir[i], light["direction"], atol=1e-5, err_msg=scene.name)
            assert bool(model.light_castshadow[i]) == light["cast_shadow"], scene.name


def test_lighting_varies_between_scenes(demo_batch: Path):
    means = {scene.name: mean_front_rgb(scene) for scene in scene_dirs(demo_batch)}
    spread = max(means.values()) - min(means.values())
    assert spread > 5.0, f"mean front intensity hardly varies across scenes: {means}"


def front_mean(renderer: SceneRenderer, model, data, record: dict) -> float:
    size = [camera_size(record, "front")]
    frames = renderer.render(model, data, ["front"], record["segmentation"], size)
    return float(frames[0].rgb.mean())


def test_scene_lights_light_the_image(demo_batch: Path, renderer: SceneRenderer):
    """Re-rendered with its lights' diffuse set to 0 a scene is darker; with ambient 0 too, black."""
    for scene in scene_dirs(demo_batch)[:3]:
        record = read_record(scene)
        model, data = load_at_keyframe(scene)
        lit = front_mean(renderer, model, data, record)
        assert lit == pytest.approx(mean_front_rgb(scene), abs=1.0), scene.name
        model.light_diffuse[:] = 0.0
        unlit = front_mean(renderer, model, data, record)
        assert unlit < lit - 5.0, f"{scene.name}: lights off {unlit:.1f} vs on {lit:.1f}"
        model.light_specular[:] = 0.0
        model.vis.headlight.ambient[:] = 0.0
        dark = front_mean(renderer, model, data, record)
        assert dark < 1.0, f"{scene.name}: {dark:.1f} mean grey with every scene light off"


# ---------------------------------------------------------------- determinism of rendering


def test_rendering_in_one_process_is_deterministic(demo_batch: Path, renderer: SceneRenderer):
    """Scene A, scene B, scene A again through one renderer: A's PNG bytes do not change."""
    first, second = scene_dirs(demo_batch)[:2]
    model_a, data_a = load_at_keyframe(first)
    model_b, data_b = load_at_keyframe(second)
    rec_a, rec_b = read_record(first), read_record(second)

    def pngs(frames) -> dict[str, bytes]:
        return {
            name: encode_png(f.rgb) + encode_png(f.seg.astype(np.uint16)) + f.depth.tobytes()
            for name, f in frames.items()
        }

    a1 = pngs(render_all(renderer, model_a, data_a, rec_a))
    render_all(renderer, model_b, data_b, rec_b)
    assert pngs(render_all(renderer, model_a, data_a, rec_a)) == a1


def compare_with_stored(scene: Path, name: str, frames) -> str | None:
    """None if a re-render matches the stored images, else what differs.

    Exact bytes are not required: MjSpec.to_xml() writes robosuite's own bodies with 6 significant
    digits (robot0_right_hand's quat moves by 1e-7, the arena's corner walls by 9e-8), which may flip
    a few edge pixels. Allowed: 0.01% of RGB pixels, no seg pixel, depth within 1 mm on 0.1% of pixels.
    """
    rgb_diff = (frames.rgb != read_rgb(scene / f"{name}_rgb.png")).any(axis=-1)
    seg_diff = frames.seg != read_image(scene / f"{name}_seg.png")
    depth = np.round(frames.depth * 1000).astype(np.int64)
    d_err = np.abs(depth - read_image(scene / f"{name}_depth.png").astype(np.int64))
    if rgb_diff.mean() > MAX_RERENDER_RGB or seg_diff.any() or d_err.max() > 1 or (d_err > 0).mean() > 1e-3:
        return (
            f"{scene.name} {name}: {rgb_diff.sum()} rgb, {seg_diff.sum()} seg, {(d_err > 0).sum()} depth "
            f"pixels differ (depth by up to {d_err.max()} mm)"
        )
    return None


def test_rerendering_a_stored_scene_reproduces_its_images(demo_batch: Path, renderer: SceneRenderer):
    """scene.xml at keyframe 0, rendered again here, gives the stored images (see compare_with_stored)."""
    problems = []
    for scene in scene_dirs(demo_batch):
        record = read_record(scene)
        model, data = load_at_keyframe(scene)
        for name, frames in render_all(renderer, model, data, record).items():
            problems.append(compare_with_stored(scene, name, frames))
    problems = [p for p in problems if p]
    assert not problems, "\n".join(problems)


def test_rerendering_with_exact_camera_and_light_parameters_reproduces_images(
    demo_batch: Path, renderer: SceneRenderer
):
    """The renderer itself is deterministic across processes: with the cameras and lights of scene.json
    at full precision (scene.xml keeps 6 significant digits of them), the stored images come back."""
    problems = []
    for scene in scene_dirs(demo_batch):
        record = read_record(scene)
        model, data = load_at_keyframe(scene)
        for cam in record["cameras"]:
            spec = Camera(**{k: cam[k] for k in ("name", "position", "lookat", "fovy", "width", "height")})
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, world.camera_rotation(spec).ravel())
            cam_id = model.camera(cam["name"]).id
            model.cam_pos[cam_id], model.cam_quat[cam_id] = spec.position, quat
        for i, light in enumerate(record["lighting"]["lights"]):
            model.light_pos[i] = light["position"]
            model.light_dir[i] = light["direction"]
            model.light_diffuse[i] = [c * light["intensity"] for c in light["colour"]]
        mujoco.mj_forward(model, data)
        for name, frames in render_all(renderer, model, data, record).items():
            problems.append(compare_with_stored(scene, name, frames))
    problems = [p for p in problems if p]
    assert not problems, "\n".join(problems)


# ---------------------------------------------------------------- no GL


def test_unknown_gl_backend_is_a_one_line_usage_error(tmp_path: Path):
    out = tmp_path / "X"
    result = cli_subprocess(["generate", str(DEMO), "--n", "1", "--out", str(out)], "bogus", tmp_path)
    assert_one_line_error(result, ["MUJOCO_GL"])
    assert result.stdout == ""
    assert not out.exists(), f"{out} was created"


@pytest.fixture(scope="module")
def no_render_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, Path]:
    root = tmp_path_factory.mktemp("no_render")
    recipe = small_recipe(root / "small.yaml", n=1)
    out = root / "batch"
    args = ["generate", str(recipe), "--n", "1", "--out", str(out), "--no-render", "--quiet"]
    return cli_subprocess(args, "bogus", root), out


def test_no_render_needs_no_gl(no_render_run):
    result, out = no_render_run
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    scenes = scene_dirs(out)
    assert len(scenes) == 1
    for scene in scenes:
        assert sorted(p.name for p in scene.iterdir()) == ["scene.json", "scene.xml"], scene.name
        record = read_record(scene)
        assert record["render"] is None and record["segmentation"] == {}
        assert not [f for f in record["files"] if f.endswith(".png") and not f.startswith("../")]


def test_no_render_scene_json_names_no_missing_images(no_render_run):
    """scene.json of a --no-render batch must not point at image files that were never written."""
    _, out = no_render_run
    for scene in scene_dirs(out):
        for cam in read_record(scene)["cameras"]:
            missing = [f for f in cam.get("images", {}).values() if not (scene / f).is_file()]
            assert not missing, f"{scene.name} camera {cam['name']} lists images never written: {missing}"


@pytest.mark.parametrize("gl", ["osmesa", "glfw"])
def test_unusable_gl_backend_is_a_one_line_error_or_works(tmp_path: Path, gl: str):
    """MUJOCO_GL=osmesa (no libOSMesa here) or glfw (no display): exit 2 with one line naming
    MUJOCO_GL and nothing written, or, where the backend does work, a rendered batch; never a traceback."""
    recipe = small_recipe(tmp_path / "small.yaml", n=1)
    out = tmp_path / "X"
    result = cli_subprocess(["generate", str(recipe), "--n", "1", "--out", str(out), "--quiet"], gl, tmp_path)
    assert "Traceback" not in result.stderr, result.stderr
    if result.returncode == 0:
        scenes = scene_dirs(out)
        assert len(scenes) == 1 and (scenes[0] / "front_rgb.png").is_file()
    else:
        assert_one_line_error(result, ["MUJOCO_GL"])
        assert not out.exists(), f"{out} was created"
