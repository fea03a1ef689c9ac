"""One primitive, observed, planned and executed in a SceneEnv, its outcome measured by the simulator.
The observation is rendered once, at the decision point, before the primitive (observation.py)."""

from __future__ import annotations

from scenegen.policy.observation import KINDS, observe, observe_state
from scenegen.policy.primitives import PRIMITIVES
from scenegen.policy.task import RetrieveMonitor, RetrieveOutcome


def run_primitive(
    env, name: str, recorder=None, observation_kind: str = "rgbd"
) -> tuple[RetrieveOutcome, dict | None]:
    """Observe (``rgbd``, or the ``state`` ablation), plan ``name`` and execute it from the
    environment's current state; the outcome as the simulator measured it and the planned parameters
    (None when the target was not seen)."""
    if observation_kind not in KINDS:
        raise ValueError(f"observation_kind {observation_kind!r}: choose one of {', '.join(KINDS)}")
    if recorder is not None and recorder.episode.observation_kind != observation_kind:
        raise ValueError(
            f"observation_kind {observation_kind!r}: "
            f"the episode records {recorder.episode.observation_kind!r}"
        )
    monitor = RetrieveMonitor(env)
    obs, view = observe(env) if observation_kind == "rgbd" else observe_state(env)
    if recorder is not None:
        recorder.decide(obs, {"primitive": name, "observation_kind": observation_kind})
    if view is None:
        monitor.outcome.events.append("target_not_seen")
        return monitor.outcome, None
    chosen = PRIMITIVES[name]
    params = chosen.plan(view)

    def step(action):
        if recorder is not None:
            recorder.step(action)
        else:
            env.step(action)
        monitor.update()

    chosen.execute(env, params, step=step)
    return monitor.outcome, params
