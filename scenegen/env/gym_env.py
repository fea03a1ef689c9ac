"""The gymnasium face of :class:`~scenegen.env.robosuite_env.SceneEnv`: a ``gymnasium.Env`` that
resets into scenes drawn from a list, uniformly or by a mixture recipe, seeded.

``reset(seed=..., options={"scene_index": i})`` resets into scene ``i`` (or into a drawn one when no
index is given) and returns ``(obs, info)``; ``info`` names the scene (``scene_id``, ``source``,
``origin``, ``scene_index``). ``step(action) -> (obs, reward, terminated, truncated, info)``:
``terminated`` when the task succeeds, ``truncated`` at the horizon. Observations are a dict of
robosuite's robot keys, the camera frames of the requested cameras and ``target_id``.
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium
import numpy as np
from gymnasium import spaces

from scenegen.env.mixture import MixtureRecipe, scene_weights
from scenegen.env.robosuite_env import SceneEnv
from scenegen.env.scenes import EnvScene

# The robot part of the observation space: robosuite key -> (size, bound): radians, metres, unit quaternion
ROBOT_KEYS = {
    "robot0_joint_pos": (7, 2 * np.pi),
    "robot0_eef_pos": (3, 5.0),
    "robot0_eef_quat": (4, 1.0),
    "robot0_gripper_qpos": (2, 0.1),
}
_MAX_DEPTH = 100.0  # m: bound of the depth space (0 = no return)


class SceneGymEnv(gymnasium.Env):
    """Resets into ``scenes`` (drawn by ``recipe``'s weights, or uniformly) and steps robosuite's
    Panda through its controller. Keyword arguments go to :class:`SceneEnv` (``controller_config``,
    ``cameras``, ``camera_size``, ``horizon``, ``catalog``)."""

    metadata = {"render_modes": []}

    def __init__(self, scenes: Sequence[EnvScene], recipe: MixtureRecipe | None = None, **env_kwargs):
        if not scenes:
            raise ValueError("scenes: empty; give at least one scene (scenegen.env.scenes.load_scenes)")
        self.scenes = list(scenes)
        self.weights = (
            scene_weights(recipe, self.scenes)
            if recipe is not None
            else np.full(len(self.scenes), 1.0 / len(self.scenes))
        )
        self.env = SceneEnv(self.scenes[0], **env_kwargs)
        low, high = self.env.action_spec
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self.observation_space = self._space()
        self.scene_index = 0

    def _space(self) -> spaces.Dict:
        fields = {key: spaces.Box(-b, b, (n,), np.float64) for key, (n, b) in ROBOT_KEYS.items()}
        width, height = self.env.camera_size
        for cam in self.env.cameras:
            fields[f"{cam}_image"] = spaces.Box(0, 255, (height, width, 3), np.uint8)
            fields[f"{cam}_depth"] = spaces.Box(0.0, _MAX_DEPTH, (height, width, 1), np.float32)
            fields[f"{cam}_segmentation"] = spaces.Box(0, 10_000, (height, width, 1), np.int32)
        fields["target_id"] = spaces.Box(0, 10_000, (1,), np.int32)
        return spaces.Dict(fields)

    def _obs(self, raw: dict) -> dict[str, np.ndarray]:
        return {key: np.asarray(raw[key], dtype=space.dtype) for key, space in self.observation_space.items()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if "scene_index" in options:
            index = int(options["scene_index"])
            if not 0 <= index < len(self.scenes):
                raise ValueError(f"options.scene_index {index}: must lie in [0, {len(self.scenes)})")
        else:
            index = self._draw()
        self.scene_index = index
        raw = self.env.reset_to(self.scenes[index])
        return self._obs(raw), self._info()

    def _draw(self) -> int:
        """A scene index drawn by the weights from the environment's seeded generator."""
        return int(self.np_random.choice(len(self.scenes), p=self.weights))

    def _info(self) -> dict:
        scene = self.scenes[self.scene_index]
        return {
            "scene_id": scene.scene_id,
            "source": scene.source,
            "origin": scene.origin,
            "scene_index": self.scene_index,
        }

    def step(self, action):
        raw, reward, done, _ = self.env.step(np.asarray(action, dtype=np.float64))
        terminated = bool(self.env._check_success())
        truncated = bool(done) and not terminated
        return self._obs(raw), float(reward), terminated, truncated, self._info()

    def close(self):
        self.env.close()
