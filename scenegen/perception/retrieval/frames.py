"""The decision-point frames of scenes, rendered once and cached by content.

A scene's frames are what the planner observes at its first decision (``observation.CAMERAS`` at
``observation.CAMERA_SIZE``, from the scene's settled state, under its own lights): RGB, depth and
the instance segmentation. Reference layouts have no stored images, so they are rendered here; every
render is cached as one compressed ``.npz`` per scene in a cache folder, keyed by the scene's content
(``scene_sha256``), the cameras, the size, the depth sensor and ``FRAMES_VERSION``, so a second
training run, another arm or another machine's copy of the cache never renders a scene twice.

The depth is the renderer's (``sensor`` exact) or a depth sensor's (``render.sensor.SENSORS``:
``active_stereo``, ``structured_light``; docs/sensor.md), drawn at the decision point
``<scene sha256>|frames`` so the same scene gives the same frame in any process.

The segmentation is kept for training labels and scoring only: nothing at decision time reads it
(docs/policy.md).
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.perception.observation import CAMERA_SIZE, CAMERAS
from scenegen.store.batch import atomic_write

FRAMES_VERSION = 1  # bump when what a frame holds changes (renderer settings, cameras' meaning)


@dataclass(frozen=True)
class Frames:
    """One scene's frames: ``rgb`` (K, H, W, 3) uint8, ``depth`` (K, H, W) float32 metres along
    the optical axis (0: no return), ``seg`` (K, H, W) int32 instance ids as in the scene's
    ``segmentation``; K = len(``cameras``)."""

    cameras: tuple[str, ...]
    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray


def frames_key(
    scene: EnvScene,
    cameras: Sequence[str] = CAMERAS,
    size: tuple[int, int] = CAMERA_SIZE,
    sensor: str = "exact",
) -> str:
    """The cache key of ``scene``'s frames (hex, 32 characters) through ``sensor``."""
    text = f"{scene_sha256(scene)}|{','.join(cameras)}|{size[0]}x{size[1]}|frames{FRAMES_VERSION}"
    if sensor != "exact":  # exact's keys are as they were before sensors
        from scenegen.render.sensor import SENSORS

        text += f"|{SENSORS[sensor].key()}"
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def sensor_point(scene: EnvScene) -> str:
    """The decision point a scene's cached frames are sensed at (seeds the sensor's noise)."""
    return f"{scene_sha256(scene)}|frames"


class FrameCache:
    """``<folder>/<key[:2]>/<key>.npz``, written atomically (depth as uint16 millimetres)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def path(self, key: str) -> Path:
        return self.folder / key[:2] / f"{key}.npz"

    def get(self, key: str) -> Frames | None:
        path = self.path(key)
        if not path.exists():
            return None
        with np.load(path, allow_pickle=False) as z:
            cameras = tuple(str(c) for c in z["cameras"])
            depth = z["depth_mm"].astype(np.float32) / 1000.0
            return Frames(cameras, z["rgb"], depth, z["seg"].astype(np.int32))

    def put(self, key: str, frames: Frames) -> None:
        buffer = io.BytesIO()
        depth_mm = np.clip(np.round(frames.depth * 1000.0), 0, 65535).astype(np.uint16)
        np.savez_compressed(
            buffer,
            cameras=np.asarray(frames.cameras),
            rgb=frames.rgb,
            depth_mm=depth_mm,
            seg=frames.seg.astype(np.int16),
        )
        self.path(key).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path(key), buffer.getvalue())


def frames_of(obs: dict, cameras: Sequence[str] = CAMERAS) -> Frames:
    """The frames of an environment's camera observation dict (``<cam>_image`` etc.)."""
    return Frames(
        tuple(cameras),
        np.stack([obs[f"{c}_image"] for c in cameras]),
        np.stack([np.squeeze(obs[f"{c}_depth"], -1) for c in cameras]).astype(np.float32),
        np.stack([np.squeeze(obs[f"{c}_segmentation"], -1) for c in cameras]).astype(np.int32),
    )


# ------------------------------------------------------------------------------------------- workers
def _init_worker() -> None:
    from scenegen.env.robosuite_env import init_worker

    init_worker()


def _render(job: tuple[EnvScene, str]) -> Frames:
    """The settled state's frames of a scene in this process's environment, through a sensor."""
    from scenegen.env.robosuite_env import worker_env

    scene, sensor = job
    env = worker_env(scene, cameras=CAMERAS, camera_size=CAMERA_SIZE, render_each_step=False)
    env.reset_to(scene)
    if sensor != "exact":
        from scenegen.render.sensor import SENSORS

        env.depth_sensor = (SENSORS[sensor], sensor_point(scene))  # cleared by the next reset
    return frames_of(env.camera_observations())


def render_missing(
    scenes: Sequence[EnvScene], cache: Path, workers: int = 1, progress: bool = False, sensor: str = "exact"
) -> int:
    """Render the frames of the ``scenes`` that ``cache`` does not hold yet through ``sensor`` (by
    ``workers`` processes) and add them to it; how many were rendered. Nothing is read back."""
    from tqdm import tqdm

    from scenegen.runner.executors import ordered_map

    store = FrameCache(cache)
    missing = {}
    for scene in scenes:
        key = frames_key(scene, sensor=sensor)
        if not store.path(key).exists():
            missing.setdefault(key, scene)
    if missing:
        jobs = [(scene, sensor) for scene in missing.values()]
        rendered = ordered_map(_render, jobs, workers, _init_worker, ())
        bar = tqdm(rendered, total=len(missing), desc="rendering frames", disable=not progress)
        for key, frames in zip(missing, bar, strict=True):
            store.put(key, frames)
        if workers <= 1:
            from scenegen.env.robosuite_env import close_worker_envs

            close_worker_envs()  # made again on demand
    return len(missing)


def scene_frames(
    scenes: Sequence[EnvScene], cache: Path, workers: int = 1, progress: bool = False, sensor: str = "exact"
) -> Iterator[Frames]:
    """The frames of every scene through ``sensor``, in order: from ``cache``, or rendered by
    ``workers`` processes and added to it."""
    render_missing(scenes, cache, workers, progress, sensor)
    store = FrameCache(cache)
    for scene in scenes:
        yield store.get(frames_key(scene, sensor=sensor))
