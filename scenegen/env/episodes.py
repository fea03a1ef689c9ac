"""The episode record: what one run of something acting in a :class:`SceneEnv` leaves behind.

An episode holds the scene it ran in, the observations at decision points (the moments a policy
chose: the first observation and one after each chosen action or primitive), every low-level action
with its reward, a trace of the simulation subsampled every ``trace_every`` control steps (robot
joints, end effector, fingers, the target's pose, contacts on the target), and the outcome.

On disk an episode is a folder: ``episode.json`` (metadata, decisions' choices, outcome) and
``arrays.npz`` (actions, rewards, the trace, each decision's observation arrays as
``decision<i>/<key>``), both written atomically; reading uses ``np.load(allow_pickle=False)``.
"""

from __future__ import annotations

import dataclasses
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenegen.store.batch import atomic_write

EPISODE_VERSION = 1
TRACE_KEYS = (
    "time",
    "robot_qpos",
    "eef_pos",
    "gripper_qpos",
    "target_pos",
    "target_quat",
    "target_contacts",
    "robot_target_contacts",
)


class EpisodeError(ValueError):
    """An episode folder that cannot be read; the message names the file."""


@dataclass
class Decision:
    """One decision point: the step index it came at, what the policy saw and what it chose."""

    step: int
    observation: dict[str, np.ndarray]
    choice: dict  # e.g. {"primitive": "top_grasp", "params": {...}} or {"action": [...]}


@dataclass
class Episode:
    """Everything about one episode. ``actions`` (T, A) float32, ``rewards`` (T,) float32; ``trace``
    arrays share their first axis (one row every ``trace_every`` control steps, and the last)."""

    episode_id: str
    scene: dict  # scene_id, source, origin, path (a stored scene) and target
    observation_kind: str  # "rgbd" (camera frames + proprioception) or "state"
    controller: str
    control_freq: float
    trace_every: int
    decisions: list[Decision] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    trace: dict[str, list] = field(default_factory=lambda: {k: [] for k in TRACE_KEYS})
    success: bool = False
    info: dict = field(default_factory=dict)

    @property
    def length(self) -> int:
        return len(self.actions)


class EpisodeRecorder:
    """Fills an :class:`Episode` while something acts in ``env`` (a SceneEnv after ``reset_to``)."""

    def __init__(self, env, episode_id: str, observation_kind: str = "rgbd", trace_every: int = 5):
        if observation_kind not in ("rgbd", "state"):
            raise ValueError(f"observation_kind {observation_kind!r}: choose 'rgbd' or 'state'")
        scene = env.scene
        self.env = env
        self.episode = Episode(
            episode_id=episode_id,
            scene={
                "scene_id": scene.scene_id,
                "source": scene.source,
                "origin": scene.origin,
                "path": str(scene.path) if scene.path else None,
                "target": scene.target,
            },
            observation_kind=observation_kind,
            controller=type(env.robots[0].composite_controller).__name__,
            control_freq=float(env.control_freq),
            trace_every=trace_every,
        )
        self._trace_now()

    def decide(self, observation: dict, choice: dict) -> None:
        """Record a decision point: the observation the policy used and its choice."""
        kept = {k: np.asarray(v) for k, v in observation.items()}
        self.episode.decisions.append(Decision(self.episode.length, kept, dict(choice)))

    def step(self, action) -> tuple[dict, float, bool]:
        """Step the environment with ``action`` and record it; returns (obs, reward, done)."""
        obs, reward, done, _ = self.env.step(np.asarray(action, dtype=np.float64))
        self.episode.actions.append(np.asarray(action, dtype=np.float32))
        self.episode.rewards.append(float(reward))
        if self.episode.length % self.episode.trace_every == 0:
            self._trace_now()
        return obs, float(reward), bool(done)

    def finish(self, success: bool, **info) -> Episode:
        """Close the record with the simulator-measured outcome."""
        if self.episode.length % self.episode.trace_every != 0:
            self._trace_now()
        self.episode.success = bool(success)
        self.episode.info.update(info)
        return self.episode

    def snapshot(self) -> Episode:
        """The episode so far as :meth:`finish` would close it (its trace ends now), leaving the
        record open: what a caller measures between two decisions."""
        trace = {k: list(v) for k, v in self.episode.trace.items()}
        if self.episode.length % self.episode.trace_every != 0:
            for k, v in self._trace_row().items():
                trace[k].append(v)
        return dataclasses.replace(self.episode, trace=trace, info=dict(self.episode.info))

    def _trace_now(self) -> None:
        for k, v in self._trace_row().items():
            self.episode.trace[k].append(v)

    def _trace_row(self) -> dict:
        env = self.env
        model, data = env.sim.model._model, env.sim.data._data
        robot = env.robots[0]
        target_pos, target_quat = env.target_pose()
        target_contacts = robot_contacts = 0
        for c in data.contact[: data.ncon]:
            bodies = (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2])
            if env.target_body_id in bodies:
                target_contacts += 1
                other = bodies[1] if bodies[0] == env.target_body_id else bodies[0]
                robot_contacts += model.body(other).name.startswith(("robot0_", "gripper0_"))
        return {
            "time": float(data.time),
            "robot_qpos": data.qpos[robot._ref_joint_pos_indexes].copy(),
            "eef_pos": data.site_xpos[robot.eef_site_id["right"]].copy(),
            "gripper_qpos": data.qpos[robot._ref_gripper_joint_pos_indexes["right"]].copy(),
            "target_pos": target_pos,
            "target_quat": target_quat,
            "target_contacts": target_contacts,
            "robot_target_contacts": robot_contacts,
        }


def write_episode(folder: Path, episode: Episode) -> Path:
    """Write ``episode`` into ``folder`` (created); arrays first, the JSON that names them last."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    arrays = {
        # an episode may hold no action (a learned perception that never saw the target)
        "actions": np.asarray(episode.actions, dtype=np.float32).reshape(episode.length, -1)
        if episode.length
        else np.zeros((0, 0), np.float32),
        "rewards": np.asarray(episode.rewards, dtype=np.float32),
    }
    arrays |= {f"trace/{k}": np.asarray(v) for k, v in episode.trace.items()}
    for i, decision in enumerate(episode.decisions):
        arrays |= {f"decision{i}/{k}": v for k, v in decision.observation.items()}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write(folder / "arrays.npz", buffer.getvalue())
    meta = {
        "episode_version": EPISODE_VERSION,
        "episode_id": episode.episode_id,
        "scene": episode.scene,
        "observation_kind": episode.observation_kind,
        "controller": episode.controller,
        "control_freq": episode.control_freq,
        "trace_every": episode.trace_every,
        "length": episode.length,
        "decisions": [
            {"step": d.step, "choice": d.choice, "keys": sorted(d.observation)} for d in episode.decisions
        ],
        "success": episode.success,
        "info": episode.info,
    }
    atomic_write(folder / "episode.json", json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return folder


def read_episode(folder: Path) -> Episode:
    """The episode written by :func:`write_episode` in ``folder``."""
    folder = Path(folder)
    try:
        meta = json.loads((folder / "episode.json").read_text())
        arrays = dict(np.load(folder / "arrays.npz", allow_pickle=False))
    except FileNotFoundError as exc:
        raise EpisodeError(f"{folder}: not an episode folder (missing {Path(exc.filename).name})") from None
    except (ValueError, OSError) as exc:
        raise EpisodeError(f"{folder}: unreadable episode ({str(exc).splitlines()[0]})") from None
    if meta.get("episode_version") != EPISODE_VERSION:
        raise EpisodeError(
            f"{folder / 'episode.json'}: episode_version {meta.get('episode_version')!r}, expected 1"
        )
    decisions = [
        Decision(d["step"], {k: arrays[f"decision{i}/{k}"] for k in d["keys"]}, d["choice"])
        for i, d in enumerate(meta["decisions"])
    ]
    return Episode(
        episode_id=meta["episode_id"],
        scene=meta["scene"],
        observation_kind=meta["observation_kind"],
        controller=meta["controller"],
        control_freq=meta["control_freq"],
        trace_every=meta["trace_every"],
        decisions=decisions,
        actions=list(arrays["actions"]),
        rewards=[float(r) for r in arrays["rewards"]],
        trace={k: list(arrays[f"trace/{k}"]) for k in TRACE_KEYS},
        success=meta["success"],
        info=meta["info"],
    )
