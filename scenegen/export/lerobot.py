"""Export episodes (``scenegen.env.episodes``) as a LeRobot dataset, format v3.0, through lerobot's own
writer (``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize``).

lerobot is optional: install it with ``make install-exporters`` (lerobot 0.4.4 beside the project's
pins, see constraints/exporters.txt); without it :func:`export_lerobot` raises :class:`ExporterMissing`.

The mapping: one LeRobot episode per project episode, one LeRobot frame per DECISION. A decision is the
only moment at which an episode holds a complete observation (camera frames and proprioception, what the
policy saw); the per-step record has actions and rewards but no observations, and the trace has no
images and only every ``trace_every``-th step. Holding or interpolating observations to fill every
control step would make up data, so the exporter does not. Each frame holds:

- ``observation.state`` (9,) float32: the arm's 7 joint positions and the 2 finger joints at the decision
  step, from the decision's observation (``robot0_joint_pos``, ``robot0_gripper_qpos``); where those keys
  are missing, from the trace row at that step (``robot_qpos``, ``gripper_qpos``; the same quantities),
  and an error where the step has no trace row either.
- ``observation.images.<cam>`` (H, W, 3) uint8 image features: the decision's ``<cam>_image`` frames,
  for every camera that all exported decisions carry (depth and segmentation are not exported).
- ``action`` (A,) float32: the low-level action applied right after the observation (``actions[step]``),
  bit-equal to the recorded one. When a decision spans several control steps (a primitive), only its
  first action is the frame's action; ``decision.num_steps`` says how many steps it spanned.
- ``next.reward`` (1,) float32: the rewards of the decision's control steps, summed.
- ``next.done`` (1,) bool: true on the episode's last frame. ``next.success`` (1,) bool: the episode's
  simulator-measured success on its last frame, false before (the record holds only the final outcome).
- ``decision.step`` (1,) int64: the control step of the decision (its time is step / control_freq);
  ``decision.num_steps`` (1,) int64: the control steps until the next decision (or the episode's end).

LeRobot puts frame ``i`` at ``timestamp = i / fps``. ``fps=None`` takes control_freq / k when all
decisions of all episodes are evenly k control steps apart (k = 1 for a policy that decides every step:
then the dataset is the ordinary per-step one); otherwise pass ``fps`` (the frame clock: what
``delta_timestamps`` count in), and read the true time from ``decision.step``. A decision at the
episode's end (step == length: an observation no action followed) has no action and is left out
(counted as ``dropped_decisions``).

Per-episode metadata: the task string is ``scene <scene_id> from <source>, target <target>`` (episodes of
one scene share a task index), and ``meta/scenegen_episodes.jsonl`` holds one JSON line per LeRobot
episode (``episode_index``, ``episode_id``, the folder, the scene record, ``success``, ``info``, the
controller, control frequency, length and the decisions' steps and choices); LeRobot ignores that file.

The dataset is written into a temporary folder beside ``out`` and renamed into place at the end, so
``out`` is either absent or complete; an existing ``out`` is an error.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
import types
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

import numpy as np

from scenegen.env.episodes import Episode, read_episode

INSTALL_HINT = "make install-exporters"
FORMAT_VERSION = "v3.0"
EXPORT_FILE = "meta/scenegen_export.json"  # source episodes and their checksums, counts
SIDECAR = "meta/scenegen_episodes.jsonl"
STATE_KEYS = (("robot0_joint_pos", "robot_qpos"), ("robot0_gripper_qpos", "gripper_qpos"))


class ExporterMissing(RuntimeError):
    """The optional packages of an exporter are not installed; the message says how to install them."""


def _import_torchvision() -> None:
    """Import torchvision, beside torch's CPU build if need be.

    PyPI's torchvision is built against CUDA torch: beside torch 2.13.0+cpu its compiled operators are
    not registered and ``torchvision._meta_registrations`` fails at import ("operator torchvision::nms
    does not exist"). lerobot's dataset code only needs torchvision's pure-Python parts (transforms.v2),
    so an empty stand-in for that one module lets it load (shared/PITFALLS.md, "Installing").
    """
    try:
        import torchvision  # noqa: F401
    except RuntimeError as exc:
        if "does not exist" not in str(exc):
            raise
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        sys.modules["torchvision._meta_registrations"] = types.ModuleType("torchvision._meta_registrations")
        import torchvision  # noqa: F401


def _import_lerobot():
    """lerobot's LeRobotDataset class and lerobot's version; ExporterMissing when it can't be had."""
    try:
        import lerobot  # noqa: F401  (first, so that a hidden lerobot fails even when submodules are loaded)

        _import_torchvision()
        from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset
    except ImportError as exc:
        raise ExporterMissing(
            f"the LeRobot exporter needs lerobot 0.4.4 and its dataset packages ({exc}): run `{INSTALL_HINT}`"
        ) from None
    version = metadata.version("lerobot")
    if CODEBASE_VERSION != FORMAT_VERSION:
        raise ExporterMissing(
            f"lerobot {version} writes dataset format {CODEBASE_VERSION}, the exporter writes "
            f"{FORMAT_VERSION} with lerobot 0.4.4: run `{INSTALL_HINT}`"
        )
    return LeRobotDataset, version


def lerobot_version() -> str:
    """The installed lerobot's version, once its dataset writer imports (else ExporterMissing)."""
    return _import_lerobot()[1]


def _exported_decisions(episode: Episode) -> list:
    """The decisions that an action followed (step < length), in step order."""
    return sorted((d for d in episode.decisions if d.step < episode.length), key=lambda d: d.step)


def _cameras(episode: Episode) -> dict[str, tuple[int, ...]]:
    """Camera name -> image shape, for the cameras that every exported decision of ``episode`` carries."""
    decisions = _exported_decisions(episode)
    if not decisions:
        return {}
    names = set.intersection(
        *({k[: -len("_image")] for k in d.observation if k.endswith("_image")} for d in decisions)
    )
    shapes = {}
    for cam in sorted(names):
        found = {tuple(d.observation[f"{cam}_image"].shape) for d in decisions}
        if len(found) != 1:
            raise ValueError(f"episode {episode.episode_id}: camera {cam!r} frames of several sizes {found}")
        shapes[cam] = found.pop()
    return shapes


def _state(episode: Episode, decision) -> np.ndarray:
    parts = []
    for obs_key, trace_key in STATE_KEYS:
        if obs_key in decision.observation:
            parts.append(np.asarray(decision.observation[obs_key]).ravel())
        elif decision.step % episode.trace_every == 0:
            parts.append(np.asarray(episode.trace[trace_key][decision.step // episode.trace_every]).ravel())
        else:
            raise ValueError(
                f"episode {episode.episode_id}: the decision at step {decision.step} has no {obs_key} "
                f"and the trace no row at that step (trace_every {episode.trace_every})"
            )
    return np.concatenate(parts).astype(np.float32)


def _frame_clock(episodes: Sequence[Episode], fps: int | None) -> int:
    if fps is not None:
        if int(fps) != fps or fps <= 0:
            raise ValueError(f"fps {fps!r}: a positive integer")
        return int(fps)
    freqs = {float(e.control_freq) for e in episodes}
    steps = [[d.step for d in _exported_decisions(e)] for e in episodes]
    gaps = {b - a for st in steps for a, b in zip(st, st[1:], strict=False)}
    if len(freqs) == 1 and len(gaps) <= 1:
        freq, k = freqs.pop(), (gaps.pop() if gaps else 1)
        if k > 0 and (freq / k).is_integer():
            return int(freq / k)
    raise ValueError(
        f"the decisions are not evenly spaced at an integer rate (control_freq {sorted(freqs)}, "
        f"steps between decisions {sorted(gaps)}): pass fps (LeRobot's frame clock)"
    )


def _features(episodes: Sequence[Episode], cameras: dict[str, tuple[int, ...]]) -> dict:
    action_dims = {np.asarray(e.actions).reshape(e.length, -1).shape[1] for e in episodes if e.length}
    if len(action_dims) != 1:
        raise ValueError(f"the episodes' actions have several sizes {sorted(action_dims)}")
    dim = action_dims.pop()
    state_dim = len(_state(episodes[0], _exported_decisions(episodes[0])[0]))
    features = {
        "observation.state": {
            "dtype": "float32",
            "shape": (state_dim,),
            "names": [f"joint_{i}" for i in range(state_dim - 2)] + ["finger_0", "finger_1"],
        },
        "action": {
            "dtype": "float32",
            "shape": (dim,),
            "names": [
                f"action_{i}" for i in range(dim)
            ],  # the controller's own order (OSC_POSE: xyz, rxyz, grip)
        },
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "decision.step": {"dtype": "int64", "shape": (1,), "names": None},
        "decision.num_steps": {"dtype": "int64", "shape": (1,), "names": None},
    }
    for cam, shape in cameras.items():
        features[f"observation.images.{cam}"] = {
            "dtype": "image",
            "shape": shape,
            "names": ["height", "width", "channels"],
        }
    return features


def task_string(episode: Episode) -> str:
    """The LeRobot task of ``episode``: its scene, source and target."""
    scene = episode.scene
    return f"scene {scene.get('scene_id')} from {scene.get('source')}, target {scene.get('target')}"


def _frames(episode: Episode, cameras: dict[str, tuple[int, ...]]):
    actions = np.asarray(episode.actions, dtype=np.float32).reshape(episode.length, -1)
    rewards = np.asarray(episode.rewards, dtype=np.float32)
    decisions = _exported_decisions(episode)
    task = task_string(episode)
    for i, decision in enumerate(decisions):
        end = decisions[i + 1].step if i + 1 < len(decisions) else episode.length
        last = i + 1 == len(decisions)
        frame = {
            "observation.state": _state(episode, decision),
            "action": actions[decision.step].copy(),
            "next.reward": np.array([rewards[decision.step : end].sum()], dtype=np.float32),
            "next.done": np.array([last]),
            "next.success": np.array([last and bool(episode.success)]),
            "decision.step": np.array([decision.step], dtype=np.int64),
            "decision.num_steps": np.array([end - decision.step], dtype=np.int64),
            "task": task,
        }
        for cam in cameras:
            frame[f"observation.images.{cam}"] = np.asarray(
                decision.observation[f"{cam}_image"], dtype=np.uint8
            )
        yield frame


def _sidecar_line(index: int, folder: Path, episode: Episode) -> str:
    record = {
        "episode_index": index,
        "episode_id": episode.episode_id,
        "folder": str(folder),
        "scene": episode.scene,
        "success": bool(episode.success),
        "info": episode.info,
        "observation_kind": episode.observation_kind,
        "controller": episode.controller,
        "control_freq": episode.control_freq,
        "trace_every": episode.trace_every,
        "length": episode.length,
        "decisions": [{"step": d.step, "choice": d.choice} for d in _exported_decisions(episode)],
        "dropped_decisions": len(episode.decisions) - len(_exported_decisions(episode)),
    }
    return json.dumps(record, sort_keys=True, default=str) + "\n"


def _remove_empty_dirs(root: Path) -> None:
    for folder, _, _ in sorted(os.walk(root), key=lambda w: -len(w[0])):
        if Path(folder) != root and not os.listdir(folder):
            os.rmdir(folder)


def _description(folders: Sequence[Path], written: dict, version: str) -> dict:
    """What ``meta/scenegen_export.json`` holds: the export's format, counts and its sources' checksums."""
    from scenegen import __version__
    from scenegen.core.files import sha256_file

    return {
        "format": "lerobot",
        "format_version": written["codebase_version"],
        "lerobot": version,
        "scenegen": __version__,
        "counts": {"episodes": written["total_episodes"], "frames": written["total_frames"]},
        "source": [
            {
                "folder": str(Path(f).resolve()),
                "episode.json": sha256_file(Path(f) / "episode.json"),
                "arrays.npz": sha256_file(Path(f) / "arrays.npz"),
            }
            for f in folders
        ],
    }


def export_lerobot(
    episode_folders: Sequence[Path],
    out: Path,
    repo_id: str = "scenegen/episodes",
    fps: int | None = None,
) -> dict:
    """Write the episodes in ``episode_folders`` as one LeRobot dataset (format v3.0) at ``out``.

    One LeRobot episode per folder, one frame per decision (see the module's docstring). Returns
    ``{"episodes", "frames", "dropped_decisions", "fps", "path", "lerobot_version", "format_version",
    "seconds"}``. Raises ExporterMissing without lerobot, FileExistsError when ``out`` exists,
    ValueError for episodes that do not fit one dataset (different cameras, action sizes, no decision).
    """
    started = time.perf_counter()
    LeRobotDataset, version = _import_lerobot()
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists: the exporter writes a new dataset only")
    folders = [Path(f) for f in episode_folders]
    if not folders:
        raise ValueError("no episode folders to export")
    episodes = [read_episode(f) for f in folders]
    for folder, episode in zip(folders, episodes, strict=True):
        if not _exported_decisions(episode):
            raise ValueError(f"{folder}: episode {episode.episode_id} has no decision followed by an action")
    cameras = _cameras(episodes[0])
    for folder, episode in zip(folders[1:], episodes[1:], strict=True):
        if _cameras(episode) != cameras:
            raise ValueError(
                f"{folder}: cameras {_cameras(episode)} differ from the first episode's {cameras}"
            )
    clock = _frame_clock(episodes, fps)
    features = _features(episodes, cameras)

    out.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    root = scratch / "dataset"
    try:
        from lerobot.utils.utils import SuppressProgressBars

        with SuppressProgressBars():
            dataset = LeRobotDataset.create(
                repo_id,
                fps=clock,
                features=features,
                root=root,
                robot_type="panda",
                use_videos=False,
                video_backend="pyav",  # never decodes here (no video features); avoids torchcodec's probe
            )
            for episode in episodes:
                for frame in _frames(episode, cameras):
                    dataset.add_frame(frame)
                dataset.save_episode()
            dataset.finalize()
        lines = [_sidecar_line(i, f, e) for i, (f, e) in enumerate(zip(folders, episodes, strict=True))]
        (root / SIDECAR).write_text("".join(lines))
        _remove_empty_dirs(root)  # lerobot leaves the emptied images/ staging folders behind
        written = json.loads((root / "meta" / "info.json").read_text())
        (root / EXPORT_FILE).write_text(json.dumps(_description(folders, written, version), indent=1) + "\n")
        os.rename(root, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return {
        "episodes": written["total_episodes"],
        "frames": written["total_frames"],
        "dropped_decisions": sum(len(e.decisions) - len(_exported_decisions(e)) for e in episodes),
        "fps": clock,
        "path": str(out),
        "lerobot_version": version,
        "format_version": written["codebase_version"],
        "seconds": round(time.perf_counter() - started, 3),
    }
