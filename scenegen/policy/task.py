"""The recovery task ``retrieve``: from a scene's settled state, lift the target at least 5 cm above its
settled height and hold it there for 1 s, within a time limit. Success, lift height, contacts and time
are measured by the simulator (:class:`RetrieveMonitor`), never inferred.

Targets on the floor are outside a table-top arm's reach: such scenes are infeasible for this task
(:func:`feasible`), not failures.
"""

from __future__ import annotations

from dataclasses import dataclass, field

LIFT_HEIGHT = 0.05  # m above the settled height
HOLD_TIME = 1.0  # s the lift must last
TIME_LIMIT = 30.0  # s of simulated time for one episode


def feasible(scene) -> bool:
    """Whether ``retrieve`` applies to ``scene`` (its target is not on the floor)."""
    return not scene.tags.get("on_floor", False)


@dataclass
class RetrieveOutcome:
    """What the simulator measured: ``success``; ``lift`` the largest height (m) of the target above
    its settled height; ``time`` simulated seconds; ``success_time`` when the hold completed."""

    success: bool = False
    lift: float = 0.0
    time: float = 0.0
    success_time: float | None = None
    robot_touched: bool = False
    events: list[str] = field(default_factory=list)


class RetrieveMonitor:
    """Watches a SceneEnv after ``reset_to``: call :meth:`update` after every control step."""

    def __init__(self, env, lift_height: float = LIFT_HEIGHT, hold_time: float = HOLD_TIME):
        self.env = env
        self.lift_height, self.hold_time = lift_height, hold_time
        self.settled_z = float(env.target_pose()[0][2])
        self.start = float(env.sim.data._data.time)
        self._lifted_since: float | None = None
        self.outcome = RetrieveOutcome()

    def update(self) -> RetrieveOutcome:
        env, out = self.env, self.outcome
        now = float(env.sim.data._data.time) - self.start
        lift = float(env.target_pose()[0][2]) - self.settled_z
        out.time, out.lift = now, max(out.lift, lift)
        out.robot_touched |= self._robot_touches_target()
        if lift >= self.lift_height:
            self._lifted_since = now if self._lifted_since is None else self._lifted_since
            if not out.success and now - self._lifted_since >= self.hold_time - 1e-9:
                out.success, out.success_time = True, now
        else:
            self._lifted_since = None
        return out

    def _robot_touches_target(self) -> bool:
        model, data = self.env.sim.model._model, self.env.sim.data._data
        target = self.env.target_body_id
        for c in data.contact[: data.ncon]:
            a, b = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
            if target in (a, b):
                other = model.body(b if a == target else a).name
                if other.startswith(("robot0_", "gripper0_")):
                    return True
        return False

    @property
    def timed_out(self) -> bool:
        return self.outcome.time >= TIME_LIMIT
