"""Physics settling and the passive stability test.

:func:`settle` steps a scene until every object is still (named velocity tolerances, a time cap) and
rejects it as ``sim_diverged``, ``fell_off`` (left its proposed support) or ``unstable`` (moved more
than a tolerance). It then runs :func:`passive_test`, the same function the acceptance tests run on a
re-loaded scene.xml, so that the stage and the acceptance cannot disagree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.schema.scene import CheckResult, Contact, SceneProposal

EE_BODY = "gripper0_eef"


class SettleSettings(BaseModel):
    """Tolerances of settling (metres, radians, seconds)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_time: float = 2.0  # simulated seconds before giving up on stillness
    min_time: float = 0.1
    still_linear: float = 0.005  # m/s: an object slower than this is still
    still_angular: float = 0.05  # rad/s
    still_steps: int = 25  # consecutive still steps that end settling
    max_move: float = 0.02  # an object moved further than this from its proposal is unstable
    max_rotate: float = 0.35  # rad
    support_drop: float = 0.02  # below its support surface by more than this: fell off
    diverged_speed: float = 5.0  # m/s: faster means the simulation blew up
    passive_time: float = 2.0  # the passive test (also the acceptance test)
    passive_move: float = 0.005  # max object displacement during the passive test
    passive_ee_move: float = 0.005  # max end-effector displacement during the passive test
    max_penetration: float = 0.001  # deepest contact allowed at the settled state


@dataclass
class SettleOutcome:
    checks: list[CheckResult]
    passed: bool
    qpos: np.ndarray
    ctrl: np.ndarray
    stats: dict = field(default_factory=dict)


def _result(check: str, passed: bool, label: str, value: float, threshold: float, detail: str = ""):
    return CheckResult(
        stage="settle",
        check=check,
        passed=passed,
        label=None if passed else label,
        value=round(float(value), 6) if math.isfinite(value) else value,
        threshold=threshold,
        detail=detail,
    )


def free_bodies(model: mujoco.MjModel) -> list[tuple[str, int]]:
    """(body name, qpos address) of every body with a free joint: the scene's objects."""
    out = []
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out.append((model.body(model.jnt_bodyid[j]).name, int(model.jnt_qposadr[j])))
    return out


def rotation_angle(q1, q2) -> float:
    """Angle (rad) between two orientations given as wxyz quaternions."""
    q1, q2 = np.asarray(q1, float), np.asarray(q2, float)
    dot = abs(float(np.dot(q1, q2)) / (np.linalg.norm(q1) * np.linalg.norm(q2)))
    return 2.0 * math.acos(min(1.0, dot))


def settle(
    model: mujoco.MjModel,
    proposal: SceneProposal,
    qpos0: np.ndarray,
    ctrl: np.ndarray,
    settings: SettleSettings,
    catalog: Catalog,
) -> SettleOutcome:
    """Step until still; check divergence, support and displacement; then run the passive test."""
    bodies = free_bodies(model)
    qpos, lin, stats = _step_until_still(model, qpos0, ctrl, settings, bodies)
    diverged = not math.isfinite(lin) or lin > settings.diverged_speed
    checks = [
        _result(
            "sim_diverged",
            not diverged,
            "sim_diverged",
            lin,
            settings.diverged_speed,
            "max object speed m/s",
        )
    ]
    if diverged:
        return SettleOutcome(checks, False, qpos, ctrl, stats)
    if not stats["still"]:
        checks.append(
            _result("still", False, "unstable", lin, settings.still_linear, "not still within max_time")
        )
        return SettleOutcome(checks, False, qpos, ctrl, stats)

    (worst_drop, drop_who), (worst_move, move_who), worst_rot = _displacements(
        proposal, catalog, bodies, qpos
    )
    checks.append(
        _result(
            "fell_off",
            worst_drop <= settings.support_drop,
            "fell_off",
            worst_drop,
            settings.support_drop,
            drop_who,
        )
    )
    if not checks[-1].passed:
        return SettleOutcome(checks, False, qpos, ctrl, stats)
    stable = worst_move <= settings.max_move and worst_rot <= settings.max_rotate
    checks.append(
        _result(
            "displacement",
            stable,
            "unstable",
            worst_move,
            settings.max_move,
            f"{move_who}; rot {worst_rot:.3f} rad",
        )
    )
    if not stable:
        return SettleOutcome(checks, False, qpos, ctrl, stats)
    passive = passive_test(model, qpos, ctrl, settings)
    checks.extend(passive)
    return SettleOutcome(checks, all(c.passed for c in passive), qpos, ctrl, stats)


def _step_until_still(
    model: mujoco.MjModel, qpos0: np.ndarray, ctrl: np.ndarray, settings: SettleSettings, bodies
) -> tuple[np.ndarray, float, dict]:
    """Step from ``qpos0`` until every free body is still (or diverges, or time runs out); returns the
    final qpos, the last max linear speed (inf when the state went non-finite) and the stats."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos0
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    dof = [model.jnt_dofadr[model.body(name).jntadr[0]] for name, _ in bodies]
    steps_max = int(round(settings.max_time / model.opt.timestep))
    steps_min = int(round(settings.min_time / model.opt.timestep))
    still, step = 0, 0
    lin = ang = 0.0
    for step in range(1, steps_max + 1):
        mujoco.mj_step(model, data)
        v = np.array([data.qvel[d : d + 6] for d in dof]) if dof else np.zeros((0, 6))
        if not np.isfinite(data.qpos).all() or not np.isfinite(v).all():
            lin = math.inf
            break
        lin = float(np.linalg.norm(v[:, :3], axis=1).max(initial=0.0))
        ang = float(np.linalg.norm(v[:, 3:], axis=1).max(initial=0.0))
        if lin > settings.diverged_speed:
            break
        still = still + 1 if (lin < settings.still_linear and ang < settings.still_angular) else 0
        if still >= settings.still_steps and step >= steps_min:
            break
    stats = {
        "sim_time": round(step * model.opt.timestep, 4),
        "steps": step,
        "still": still >= settings.still_steps,
        "final_linear_speed": round(lin, 6) if math.isfinite(lin) else None,
        "final_angular_speed": round(ang, 6),
    }
    return data.qpos.copy(), lin, stats


def _displacements(proposal: SceneProposal, catalog: Catalog, bodies, qpos: np.ndarray):
    """The worst drop off a support (m, who), the worst move (m, who) and the worst rotation (rad)
    of the proposal's objects at ``qpos``."""
    surfaces = layout.support_surfaces(proposal.furniture, proposal.objects, catalog)
    placements = {o.name: o for o in proposal.objects}
    worst_drop, drop_who, worst_move, move_who, worst_rot = -math.inf, "", 0.0, "", 0.0
    for name, adr in bodies:
        obj = placements[name]
        surface = surfaces[obj.support]
        pos, quat = qpos[adr : adr + 3], qpos[adr + 3 : adr + 7]
        # Fell off: its centre left the region of its support, or sank below the support's plane.
        drop = max(-surface.margin(pos[:2]), surface.z - pos[2])
        if drop > worst_drop:
            worst_drop, drop_who = drop, name
        move = float(np.linalg.norm(pos - np.asarray(obj.position)))
        rot = rotation_angle(quat, np.asarray(obj.quat))
        if move > worst_move:
            worst_move, move_who = move, name
        worst_rot = max(worst_rot, rot)
    return (worst_drop, drop_who), (worst_move, move_who), worst_rot


def passive_test(
    model: mujoco.MjModel, qpos: np.ndarray, ctrl: np.ndarray, settings: SettleSettings
) -> list[CheckResult]:
    """From (qpos, ctrl): deepest contact penetration, then ``passive_time`` s of simulation.

    Returns three results: ``penetration`` (m, deepest contact), ``passive_motion`` (m, largest
    object displacement) and ``ee_motion`` (m, end-effector displacement). Any failure is ``unstable``.
    This is the acceptance test of a stored scene: tests call it on a re-loaded scene.xml.
    """
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    # Contacts inside the 0.5 mm margin have a positive distance: no penetration is depth 0.
    depth = max((-data.contact[i].dist for i in range(data.ncon)), default=0.0)
    depth = max(depth, 0.0)
    bodies = free_bodies(model)
    start = {name: data.qpos[adr : adr + 3].copy() for name, adr in bodies}
    ee0 = data.body(EE_BODY).xpos.copy()
    for _ in range(int(round(settings.passive_time / model.opt.timestep))):
        mujoco.mj_step(model, data)
    moves = {name: float(np.linalg.norm(data.qpos[adr : adr + 3] - start[name])) for name, adr in bodies}
    worst = max(moves, key=moves.get) if moves else ""
    move = moves.get(worst, 0.0)
    if not np.isfinite(data.qpos).all():
        move = math.inf
    ee = float(np.linalg.norm(data.body(EE_BODY).xpos - ee0))
    return [
        _result(
            "penetration", depth <= settings.max_penetration, "unstable", depth, settings.max_penetration
        ),
        _result(
            "passive_motion",
            move <= settings.passive_move,
            "unstable",
            move,
            settings.passive_move,
            worst,
        ),
        _result("ee_motion", ee <= settings.passive_ee_move, "unstable", ee, settings.passive_ee_move),
    ]


def contact_configuration(model: mujoco.MjModel, qpos: np.ndarray, objects: Sequence[str]) -> list[Contact]:
    """Which object rests on or touches which body at ``qpos`` (one row per pair, deepest distance)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    names = set(objects)
    found: dict[tuple[str, str], list[tuple[str, float]]] = {}
    for i in range(data.ncon):
        c = data.contact[i]
        b1 = model.body(model.geom_bodyid[c.geom1]).name
        b2 = model.body(model.geom_bodyid[c.geom2]).name
        # The contact normal (frame row 0) points from geom1 to geom2.
        for a, b, up in ((b1, b2, -c.frame[2]), (b2, b1, c.frame[2])):
            if a in names and a != b:
                kind = "rests_on" if up > 0.7 else "touches"  # b pushes a upward
                found.setdefault((a, b), []).append((kind, float(c.dist)))
    contacts = []
    for (a, b), rows in sorted(found.items()):
        kind = "rests_on" if any(k == "rests_on" for k, _ in rows) else "touches"
        contacts.append(Contact(a=a, b=b, kind=kind, distance=round(min(d for _, d in rows), 6)))
    return contacts
