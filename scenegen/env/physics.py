"""The physics of the control loop: solver, timestep and collision geometry of a :class:`SceneEnv`.

Labelling and the closed loop simulate thousands of primitive executions; their cost is the physics
(``mj_step1`` + ``mj_step2``, most of it the collision narrow phase between the objects' coacd parts
and the table) and the controller run at every physics substep. A :class:`ControlPhysics` names what
the environment's model is compiled with, so that cheaper settings can be screened and compared with
today's by their outcomes (``benchmarks/physics_screen.py``, docs/policy.md "Cheaper physics").

It applies to the environment's own model only (``SceneEnv._initialize_sim``): generation's settling,
stored scene.xml files and their sha256 keep ``sim.world.CONTACT_OPTIONS``. The default, ``exact``,
changes nothing: every field equals what ``world.robot_world_spec`` and MuJoCo's defaults give, so
its model, and every outcome, are bit-identical to the environment before this module existed
(tests/env/test_physics.py).

The levers:

- ``timestep`` (s): the physics step; the control rate stays 20 Hz, so it must divide 50 ms into a
  whole number of substeps (the controller still runs at every substep, as robosuite's does).
- ``solver``, ``iterations``, ``ls_iterations``, ``tolerance``: MuJoCo's constraint solver.
- ``cone``, ``impratio``: the friction cone (elliptic, as settling uses, or pyramidal).
- ``ccd_iterations``, ``ccd_tolerance``, ``multiccd``: MuJoCo's convex collision.
- ``table_contact``: ``parts`` (every coacd part of an object meets the table, as in settling) or
  ``hull`` (each object meets the table through one geom, the convex hull of its parts; the parts
  still meet everything else). A flat table top touches an object only on its convex hull, so the
  contact is the same where the object rests inside the top; at the top's edge a hull bridges the
  object's concavities.
- ``object_margin`` (m): the distance at which the objects' contacts activate (settling: 0.5 mm).
"""

from __future__ import annotations

import hashlib
import json
from functools import cache
from typing import Literal

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from scenegen.sim import world

CONTROL_PERIOD = 0.05  # s: one action per 50 ms (robosuite_env.CONTROL_FREQ = 20 Hz)
TABLE_GEOM = "table_collision"  # robosuite's table arena: one box is the table's only collision geom
# contype/conaffinity bits: bit 0 is everything's default; bit 1 joins an object's hull and the table
_HULL_BIT = 2
_SOLVERS = {
    "newton": mujoco.mjtSolver.mjSOL_NEWTON,
    "cg": mujoco.mjtSolver.mjSOL_CG,
    "pgs": mujoco.mjtSolver.mjSOL_PGS,
}
_CONES = {"elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC, "pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL}


class ControlPhysics(BaseModel):
    """What a :class:`~scenegen.env.robosuite_env.SceneEnv`'s model is compiled with (module doc).
    ``name`` identifies it in stores and figures; :meth:`key` adds a digest of every field."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "exact"
    timestep: float = Field(world.TIMESTEP, gt=0, le=CONTROL_PERIOD)
    solver: Literal["newton", "cg", "pgs"] = "newton"
    iterations: int = Field(100, ge=1)
    ls_iterations: int = Field(50, ge=1)
    tolerance: float = Field(1e-8, ge=0)
    cone: Literal["elliptic", "pyramidal"] = "elliptic"
    impratio: float = Field(world.CONTACT_OPTIONS["impratio"], ge=1)
    ccd_iterations: int = Field(35, ge=1)
    ccd_tolerance: float = Field(1e-6, gt=0)
    multiccd: bool = world.CONTACT_OPTIONS["multiccd"]
    table_contact: Literal["parts", "hull"] = "parts"
    object_margin: float = Field(world.CONTACT_OPTIONS["object_margin"], ge=0)

    @model_validator(mode="after")
    def _whole_substeps(self) -> ControlPhysics:
        n = CONTROL_PERIOD / self.timestep
        # robosuite steps int(period / timestep) times: the quotient must not fall below a whole
        if abs(n - round(n)) > 1e-9 or int(n) != round(n):
            raise ValueError(
                f"timestep {self.timestep}: must divide the 50 ms control period into whole substeps "
                "(e.g. 0.002, 0.0025, 1/300, 1/240, 0.005)"
            )
        return self

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return round(CONTROL_PERIOD / self.timestep)

    def key(self) -> str:
        """``name`` and a digest of every field: what stores made under this physics are keyed by."""
        fields = json.dumps(self.model_dump(mode="json", exclude={"name"}), sort_keys=True)
        return f"{self.name}-{hashlib.sha256(fields.encode()).hexdigest()[:10]}"

    def with_changes(self, name: str, **changes) -> ControlPhysics:
        """This physics with ``changes`` (validated), called ``name``."""
        return ControlPhysics.model_validate({**self.model_dump(), **changes, "name": name})

    # ------------------------------------------------------------------ the model
    def apply(self, spec: mujoco.MjSpec, catalog, objects) -> None:
        """Set this physics on ``spec``, a scene built by ``world.build_world`` with ``objects``
        (placements whose assets ``catalog`` holds), before it is compiled."""
        opt = spec.option
        opt.timestep = self.timestep
        opt.solver = _SOLVERS[self.solver]
        opt.iterations, opt.ls_iterations, opt.tolerance = self.iterations, self.ls_iterations, self.tolerance
        opt.cone = _CONES[self.cone]
        opt.impratio = self.impratio
        opt.ccd_iterations, opt.ccd_tolerance = self.ccd_iterations, self.ccd_tolerance
        if self.multiccd:
            opt.enableflags |= mujoco.mjtEnableBit.mjENBL_MULTICCD
        else:
            opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_MULTICCD)
        if self.object_margin != world.CONTACT_OPTIONS["object_margin"]:
            for obj in objects:
                for i in range(len(catalog.get(obj.asset).parts.files)):
                    spec.geom(f"{obj.name}_part{i}").margin = self.object_margin
        if self.table_contact == "hull":
            _table_through_hulls(spec, catalog, objects, self.object_margin)


def _table_through_hulls(spec: mujoco.MjSpec, catalog, objects, margin: float) -> None:
    """Each object meets the table through the convex hull of its parts, not the parts themselves.

    Contact filtering is MuJoCo's: two geoms collide when (contype1 & conaffinity2) or (contype2 &
    conaffinity1). The table keeps bit 0 in both (robot, furniture and floor as before) and takes
    bit 1 in its affinity; an object's parts stop meeting the table by an explicit exclusion of the
    pair (object body, table body), which would exclude a hull on the same body too: so the hull sits
    on a child body of the object (rigidly attached, no joint, no mass), whose contype is bit 1 only
    and affinity none, so it meets the table and nothing else."""
    spec.geom(TABLE_GEOM).conaffinity |= _HULL_BIT
    table_body = _body_of(spec, TABLE_GEOM)
    # every catalog asset's hull is declared, used or not, as build_world declares every mesh: scenes
    # then share one mesh table, and a renderer its one upload (render/offscreen.py)
    scales = [(asset, 1.0) for asset in catalog.assets]
    scales += [
        (catalog.get(a), s) for a, s in sorted({(o.asset, o.scale) for o in objects if o.scale != 1.0})
    ]
    for asset, scale in scales:
        points = _hull_points(tuple(str(asset.file(f)) for f in asset.parts.files)) * scale
        spec.add_mesh(name=_hull_mesh(asset.name, scale), uservert=points.ravel().tolist())
    for obj in objects:
        asset = catalog.get(obj.asset)
        holder = spec.body(obj.name).add_body(name=f"{obj.name}_hull_body")
        holder.add_geom(
            name=f"{obj.name}_hull",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=_hull_mesh(asset.name, obj.scale),
            group=world.COLLISION_GROUP,
            contype=_HULL_BIT,
            conaffinity=0,
            mass=0,
            **{**world.object_contact(asset.friction), "margin": margin},
        )
        spec.add_exclude(bodyname1=obj.name, bodyname2=table_body)


def _hull_mesh(asset: str, scale: float) -> str:
    return f"{asset}_hull" if scale == 1.0 else f"{asset}_s{scale:g}_hull"


def _body_of(spec: mujoco.MjSpec, geom: str) -> str:
    for body in spec.bodies:
        if any(g.name == geom for g in body.geoms):
            return body.name
    raise KeyError(f"no body holds geom {geom}")


@cache
def _hull_points(files: tuple[str, ...]) -> np.ndarray:
    """Every vertex of an asset's convex parts (N, 3), metres in the object's frame: MuJoCo takes a
    collision mesh's convex hull, so a mesh of these points collides as the parts' hull."""
    import trimesh

    return np.concatenate([trimesh.load(f, force="mesh", process=False).vertices for f in files])


PHYSICS: dict[str, ControlPhysics] = {"exact": ControlPhysics()}
# the screen's cheapest setting that kept outcomes (docs/policy.md "Cheaper physics"): a 5 ms step, 10
# substeps per control step; on 600 further layouts every primitive within 0.7 points of exact's rate
PHYSICS["dt5"] = PHYSICS["exact"].with_changes("dt5", timestep=0.005)
# What labelling, SceneEnv and the closed loop simulate under unless told otherwise (issue 61). The
# stores made under exact (assets/policy/labels, the transfer versions 1 and 2, the version 2 panels)
# keep it, by name.
DEFAULT_PHYSICS = "dt5"
EXACT_KEY = PHYSICS["exact"].key()  # what a store's row made before the physics was a setting was made under


def physics_mark(physics: ControlPhysics) -> str:
    """What a stored sequence's or observation's key adds for ``physics``: nothing for ``exact`` (the
    stores made before the physics was a setting keep serving it), else ``~`` and its key."""
    return "" if physics.key() == EXACT_KEY else f"~{physics.key()}"


def physics_named(name: str | ControlPhysics) -> ControlPhysics:
    """The registered physics called ``name`` (a :class:`ControlPhysics` passes through)."""
    if isinstance(name, ControlPhysics):
        return name
    if name not in PHYSICS:
        raise ValueError(f"physics {name!r}: unknown; choose from {', '.join(PHYSICS)}")
    return PHYSICS[name]
