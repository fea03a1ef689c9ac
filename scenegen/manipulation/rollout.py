"""One primitive, observed, planned and executed in a SceneEnv, its outcome measured by the simulator.
The observation is rendered once, at the decision point, before the primitive (observation.py)."""

from __future__ import annotations

from scenegen.manipulation.primitives import PRIMITIVES, PlanGrid, make_plan
from scenegen.manipulation.proposals import Candidate, execute
from scenegen.manipulation.task import RetrieveMonitor, RetrieveOutcome
from scenegen.perception.observation import KINDS, observe, observe_state


def run_primitive(
    env,
    name: str,
    recorder=None,
    observation_kind: str = "rgbd",
    episode: tuple[float, float] | None = None,
    perception=None,
    observed: tuple | None = None,
    look=None,
    images: bool | None = None,
    grid: PlanGrid | None = None,
) -> tuple[RetrieveOutcome, dict | None]:
    """Observe (``rgbd``, or the ``state`` ablation), plan ``name`` and execute it from the
    environment's current state; the outcome as the simulator measured it and the planned parameters
    (None when the target was not seen). ``episode``: (start time, the target's settled height) of
    the episode this attempt belongs to (default: it starts now), so that time, the limit and the
    lift count from the episode's start, not the attempt's. ``grid``: the resolution its plans (and a
    re-observation's) are executed at (None: as planned)."""
    if observation_kind not in KINDS:
        raise ValueError(f"observation_kind {observation_kind!r}: choose one of {', '.join(KINDS)}")
    if recorder is not None and recorder.episode.observation_kind != observation_kind:
        raise ValueError(
            f"observation_kind {observation_kind!r}: "
            f"the episode records {recorder.episode.observation_kind!r}"
        )
    start, settled_z = episode if episode is not None else (None, None)
    # the oracle's planner reads depth and masks: its colour pass is drawn only for a record
    image = (recorder is not None) if images is None else images
    monitor = RetrieveMonitor(env, start=start, settled_z=settled_z)
    if observed is not None:
        obs, view = observed
    else:
        obs, view = observe(env, perception, image) if observation_kind == "rgbd" else observe_state(env)
    if recorder is not None:
        recorder.decide(obs, {"primitive": name, "observation_kind": observation_kind})
    if view is None:
        monitor.outcome.events.append("target_not_seen")
        return monitor.outcome, None
    chosen = PRIMITIVES[name]
    params = make_plan(name, view, grid)

    step = _stepper(env, recorder, monitor)
    look = look or (lambda: observe(env, perception, image))
    chosen.execute(env, params, step=step, look=look, grid=grid)
    return monitor.outcome, params


def run_candidate(
    env, candidate: Candidate, recorder=None, episode: tuple[float, float] | None = None
) -> RetrieveOutcome:
    """Execute a proposal ``candidate`` from the environment's current state; its outcome as the
    simulator measured it. ``episode`` as for :func:`run_primitive`. A push or pull that does not
    lift the target ends without success: the next decision is a new observation and proposal."""
    start, settled_z = episode if episode is not None else (None, None)
    monitor = RetrieveMonitor(env, start=start, settled_z=settled_z)

    execute(env, candidate, step=_stepper(env, recorder, monitor))
    return monitor.outcome


def _stepper(env, recorder, monitor):
    """The function an attempt takes an action by: the recorder's step (or the environment's),
    then the task monitor's update."""

    def step(action):
        if recorder is not None:
            recorder.step(action)
        else:
            env.step(action)
        monitor.update()

    return step
