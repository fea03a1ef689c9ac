"""What the closed loop measures, kept so that it is measured once: the sequence store and the
observation store (``closed_loop.py`` runs the evaluation over them).

Given a scene, the physics is a function of the plans executed: :class:`PathStore` keeps each measured
primitive sequence keyed by the scene's sha256, the rules' version (``SEQUENCE_RULES``) and every
attempt's token (``decision_token``: the primitive, its version and a digest of its plan; ``+digest``
of the plan made at a re-observation inside push or pull): whether the last attempt succeeded (the hold
complete within the task's time limit, counted from the episode's start) and when, the simulated time
so far, the failure rules' physical features of the last attempt, the state after it (``qpos``) and,
for an attempt that looked again, the state and plan of that re-observation. Policies seeing through
any head (or the oracle) that execute the same plans share the outcome exactly; :func:`match` serves an
attempt with a re-observation once the policy's own plan at the stored re-observation state agrees.
:class:`ObservationStore` keeps decision points (the policy input, each primitive's plan token, what the
decision's mask was), keyed by the state, what the planners see through (``sight``) and the lighting
(:class:`Variant`). Both are appended as they are measured, so a killed evaluation continues where it
stopped.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.physics import ControlPhysics, physics_mark
from scenegen.env.scenes import EnvScene
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.proposals import ACTIONS, SAMPLER_VERSION, Candidate
from scenegen.store.batch import atomic_write, recover_jsonl


@dataclass(frozen=True)
class Variant:
    """What the cameras see: ``nominal``, a shift of the scene's lighting (every light's intensity
    and the ambient term scaled by ``light_scale``), and/or a depth ``sensor``'s errors (a name of
    ``render.sensor.SENSORS``; the noise drawn per decision point and camera, :meth:`sense`).
    Lighting changes only the colour frames (a head's predictions, and the policy's input); a sensor
    changes the depth every planner reads, the oracle's too. The store keys a sequence by the plans
    executed, so one PathStore serves every variant all the same."""

    name: str = "nominal"
    light_scale: float = 1.0
    sensor: str | None = None

    def sense(self, env, point: str) -> None:
        """Set ``env``'s depth to this variant's sensor at the decision point ``point`` (after a
        reset, which clears it; a no-op without a sensor)."""
        if self.sensor is not None:
            from scenegen.render.sensor import SENSORS

            if not point:
                raise ValueError(f"variant {self.name}: a sensor's noise needs the decision point")
            env.depth_sensor = (SENSORS[self.sensor], point)

    def apply(self, scene: EnvScene) -> EnvScene:
        if self.light_scale == 1.0:
            return scene
        lighting = scene.lighting
        lights = tuple(
            light.model_copy(update={"intensity": min(3.0, light.intensity * self.light_scale)})
            for light in lighting.lights
        )
        ambient = tuple(min(1.0, a * self.light_scale) for a in lighting.ambient)
        shifted = lighting.model_copy(update={"lights": lights, "ambient": ambient})
        return dataclasses.replace(scene, lighting=shifted)


NOMINAL = Variant()


# 2: success held to the time limit from the episode's start, features per attempt, other objects
# touched (version 1, assets/transfer/paths.jsonl: success per attempt, features over the episode);
# 3: keyed by the plans executed (decision and re-observation), not by what the planners saw
SEQUENCE_RULES = 3
PLAN_DIGITS = 9  # a plan's numbers in its key: 1e-9 m, far below what the controller resolves


def plan_digest(plan: dict | None) -> str:
    """A plan's parameters as a short digest (``unseen``: no plan, the target was not seen)."""
    if plan is None:
        return "unseen"

    def rounded(value):
        if isinstance(value, (list, tuple, np.ndarray)):
            return [rounded(v) for v in value]
        return round(float(value), PLAN_DIGITS) if isinstance(value, (float, np.floating)) else value

    text = json.dumps({k: rounded(v) for k, v in plan.items()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def decision_token(name: str, plan: dict | None, physics: ControlPhysics | None = None) -> str:
    """What an attempt executes as decided: the primitive, its version (and the physics it runs
    under, ``physics_mark``: nothing for ``exact``) and its plan."""
    mark = "" if physics is None else physics_mark(physics)
    return f"{name}@{PRIMITIVES[name].version}{mark}:{plan_digest(plan)}"


def candidate_token(candidate: Candidate, physics: ControlPhysics | None = None) -> str:
    """What a proposal decision executes: the action, its executor's and the sampler's versions
    (``grasp@1s2``), the physics mark and the candidate's parameters; a path key's token as
    :func:`decision_token` is, so proposal attempts live in the same store."""
    mark = "" if physics is None else physics_mark(physics)
    version = f"{ACTIONS[candidate.action].version}s{SAMPLER_VERSION}"
    return f"{candidate.action}@{version}{mark}:{plan_digest(candidate.params)}"


def path_key(sha: str, tokens: Sequence[str]) -> str:
    """A sequence's key: the scene, the rules and every attempt's token (its decision, and the plan
    made at a re-observation inside it, ``+digest``). The physics is a function of the scene and
    the plans executed, so any two policies, seeing through any heads, that execute the same plans
    share the outcome exactly."""
    return f"{sha}|rules{SEQUENCE_RULES}|" + "|".join(tokens)


def again_point(sha: str, tokens: Sequence[str], primitive: str, number: int) -> str:
    """The decision point of the ``number``-th re-observation inside ``primitive``, run after
    ``tokens``: what seeds a variant's sensor there (the decision's own is ``path_key``)."""
    return f"{path_key(sha, tokens)}|{primitive}|again{number}"


def sight(retrieval: Path | None, variant: Variant, rules: int | None = None) -> str:
    """What the planners see through: ``oracle`` (the simulator's masks: lighting cannot change a
    plan), or a retrieval head under ``variant``'s lighting, which its predictions, hence the plans,
    depend on, scored by the perception rules' version ``rules`` (default ``PERCEPTION_RULES``;
    perception/retrieval/evaluate.py). It keys observations, not sequences. A head is its whole
    folder's sha256 (an ``instances`` head holds two weight files); a head of issue 33's designs
    under version 1 keeps its key of then (model.safetensors alone), so figures made under it still
    read their stored observations."""
    if retrieval is None:
        return "oracle"
    from scenegen.core.files import folder_sha256, sha256_file
    from scenegen.perception.retrieval.evaluate import PERCEPTION_RULES

    rules = PERCEPTION_RULES if rules is None else rules
    if rules == 1 and not (Path(retrieval) / "separator.safetensors").exists():
        digest = sha256_file(Path(retrieval) / "model.safetensors")[:16]
        return f"retrieval:{digest}@{variant.name}:{variant.light_scale}"
    digest = folder_sha256(Path(retrieval))[:16]
    return f"retrieval:{digest}@{variant.name}:{variant.light_scale}|perception{rules}"


class PathStore:
    """Measured primitive sequences, appended to a JSONL file (a torn last line is dropped). Rows of
    earlier rules stay in the file and answer nothing."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.entries: dict[str, dict] = {}
        self.decisions: dict[tuple, list[dict]] = {}
        self.mismatches = 0  # a plan path measured twice with different outcomes (should stay 0)
        for row in recover_jsonl(self.path):
            self._index(row)

    def _index(self, row: dict) -> None:
        self.entries[row["key"]] = row
        if row.get("rules") == SEQUENCE_RULES:
            where = (row["scene_sha256"], tuple(row["tokens"][:-1]), row["decision"])
            self.decisions.setdefault(where, []).append(row)

    def get(self, sha: str, tokens: Sequence[str]) -> dict | None:
        return self.entries.get(path_key(sha, tokens))

    def candidates(self, sha: str, before: Sequence[str], decision: str) -> list[dict]:
        """The measured attempts that execute ``decision`` after the attempts ``before``: one, or
        several that differ in the plan made at the re-observation inside the primitive."""
        return self.decisions.get((sha, tuple(before), decision), [])

    def add(self, rows: Sequence[dict]) -> None:
        with open(self.path, "a") as sink:
            for row in rows:
                known = self.entries.get(row["key"])
                if known is not None:
                    same = (known["success"], known["time"]) == (row["success"], row["time"])
                    self.mismatches += not same
                    continue
                sink.write(json.dumps(row, sort_keys=True) + "\n")
                self._index(row)
            sink.flush()
            os.fsync(sink.fileno())


def match(store: PathStore, sha: str, before: Sequence[str], decision: str, regrasp: str | None):
    """The stored attempt a policy's decision leads to: the one without a re-observation, or the one
    whose re-observation plan is ``regrasp`` (the policy's own at the stored re-observation state)."""
    for row in store.candidates(sha, before, decision):
        if row["regrasp"] is None or row["regrasp"]["plan"] == regrasp:
            return row
    return None


class ObservationStore:
    """Policy inputs at decision points, one ``.npy`` per (state, sight, variant, input kind), and
    beside it a JSON of what the decision needs besides (each primitive's plan token, the head's
    score), written atomically."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    @staticmethod
    def key(sha: str, tokens: Sequence[str], variant: Variant, inputs: str, seen: str = "oracle") -> str:
        shown = f"{variant.name}:{variant.light_scale}"
        if variant.sensor is not None:
            from scenegen.perception.points import SENSED_POINTS
            from scenegen.render.sensor import SENSORS

            shown += f":{SENSORS[variant.sensor].key()}:points{SENSED_POINTS}"  # what reads its depth
        text = f"{path_key(sha, tokens)}|{seen}|{shown}|{inputs}"
        return hashlib.sha256(text.encode()).hexdigest()[:32]

    def get(self, key: str) -> np.ndarray | None:
        path = self.folder / f"{key}.npy"
        return np.load(path, allow_pickle=False) if path.exists() else None

    def meta(self, key: str) -> dict | None:
        path = self.folder / f"{key}.json"
        return json.loads(path.read_text()) if path.exists() else None

    def put(self, key: str, value: np.ndarray | None, meta: dict | None = None) -> None:
        import io

        if meta is not None:
            atomic_write(self.folder / f"{key}.json", json.dumps(meta, sort_keys=True).encode())
        if value is not None:
            buffer = io.BytesIO()
            np.save(buffer, value, allow_pickle=False)
            atomic_write(self.folder / f"{key}.npy", buffer.getvalue())


@dataclass
class Cost:
    """Where an evaluation's work went: attempts answered from the store (``shared``) or simulated,
    and the CPU seconds of each kind of job (measured in the process that ran it)."""

    attempts: int = 0
    shared: int = 0
    simulated: int = 0
    cpu: dict = dataclasses.field(
        default_factory=lambda: dict.fromkeys(("observe", "regrasp", "simulate"), 0.0)
    )

    def add(self, kind: str, seconds: float) -> None:
        self.cpu[kind] += seconds

    def summary(self, episodes: int) -> dict:
        total = sum(self.cpu.values())
        return {
            "episodes": episodes,
            "attempts": self.attempts,
            "shared": self.shared,
            "sharing_rate": round(self.shared / self.attempts, 4) if self.attempts else None,
            "sequences_simulated": self.simulated,
            "cpu_seconds": {k: round(v, 2) for k, v in self.cpu.items()},
            "cpu_per_episode": round(total / episodes, 3) if episodes else None,
        }
