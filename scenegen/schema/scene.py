"""The values that pass between stages: proposals, check results, settled scene records.

Frames and units: positions are metres in the MuJoCo world frame (z up; the table top is at
``core.layout.TABLE_TOP_Z``, the robot base behind the table at negative x, facing +x);
orientations are wxyz quaternions as MuJoCo uses them; angles are radians.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_serializer, model_validator

from scenegen.schema.condition import Condition, vouch_for_objects

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # w, x, y, z

RejectionLabel = Literal[
    "out_of_workspace",
    "unsupported",
    "collision",
    "robot_overlap",
    "unreachable",
    "unstable",
    "fell_off",
    "sim_diverged",
    "condition_unmet",
    "unrealistic",
    "render_failed",
    "furniture_overhang",  # a furniture piece not wholly on the table (checks.furniture_on_table)
]
REJECTION_LABELS: tuple[str, ...] = RejectionLabel.__args__  # type: ignore[attr-defined]
Stage = Literal["propose", "check", "settle", "tag", "render", "store"]


class _Value(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class ObjectPlacement(_Value):
    """One object instance: which asset, where, how it rests.

    ``support`` names what it rests on (``table``, ``shelf``, ``bin``); ``resting_pose`` indexes
    the asset's stable resting poses; ``projection_distance`` is how far (metres) snapping moved
    the raw proposal onto that pose and support height (0 for the procedural proposer, which
    samples on the pose directly).
    """

    name: str
    asset: str
    category: str
    position: Vec3
    quat: Quat
    scale: float = 1.0
    support: str = "table"
    resting_pose: int = 0
    projection_distance: float = 0.0


class FurniturePlacement(_Value):
    """A fixed piece of furniture on the table: ``kind`` from ``core.layout.FURNITURE``, pose by yaw."""

    name: str
    kind: Literal["shelf", "bin"]
    position: Vec3  # centre of its footprint on the table top
    yaw: float = 0.0


class Light(_Value):
    """A spot light. Colour is 0-1 RGB; intensity scales it (diffuse = colour x intensity)."""

    position: Vec3
    direction: Vec3
    colour: Vec3 = (1.0, 1.0, 1.0)
    intensity: float = Field(0.6, ge=0.0, le=3.0)
    cast_shadow: bool = True


class Lighting(_Value):
    lights: tuple[Light, ...]
    ambient: Vec3 = (0.1, 0.1, 0.1)


class Camera(_Value):
    """A pinhole camera looking from ``position`` at ``lookat``; ``fovy``: vertical field of view (deg)."""

    name: str
    position: Vec3
    lookat: Vec3
    fovy: float = 45.0
    width: int = 640
    height: int = 480

    def intrinsics(self) -> dict[str, float]:
        """fx, fy, cx, cy in pixels, as MuJoCo renders (square pixels, principal point at the centre)."""
        import math

        f = 0.5 * self.height / math.tan(math.radians(self.fovy) / 2)
        return {"fx": f, "fy": f, "cx": self.width / 2, "cy": self.height / 2}


class RepairStep(_Value):
    """One repair on a scene's path: attempt ``attempt`` of its proposal index re-sampled (or, with
    ``method`` project, moved) ``resampled`` (object names, ``furniture``, ``lights``) of attempt
    ``parent``, which failed ``label`` at ``check`` (``detail`` as its rejection row says). Attempt 0
    is the first-pass proposal."""

    attempt: int = Field(ge=1)
    parent: int = Field(ge=0)
    label: RejectionLabel
    check: str
    detail: str = ""
    resampled: tuple[str, ...]
    # how: re-denoised (inpainting), or moved by the rejection's measured margin (propose/project.py);
    # left out of the row at its default (paths made before projections read as before)
    method: Literal["denoise", "project"] = "denoise"

    @model_serializer(mode="wrap")
    def _omit_default(self, handler):
        data = handler(self)
        if data.get("method") == "denoise":
            data.pop("method", None)
        return data


class SceneProposal(_Value):
    """What a proposer hands to the checks: one candidate scene. ``attempt`` > 0: a repair of the
    proposal ``index`` (propose/repair.py), reached by ``repairs`` (first repair first)."""

    index: int  # position in the batch's proposal stream; decides commit order
    seed: int  # the seed this proposal's own randomness came from
    condition: Condition
    target: str  # name of the target object instance
    objects: tuple[ObjectPlacement, ...]
    furniture: tuple[FurniturePlacement, ...]
    lighting: Lighting
    cameras: tuple[Camera, ...]
    attempt: int = Field(0, ge=0)
    repairs: tuple[RepairStep, ...] = ()

    @model_validator(mode="wrap")
    @classmethod
    def _own_categories(cls, data, handler):
        return vouch_for_objects(data, handler)  # its objects' categories are known targets


class CheckResult(_Value):
    """Outcome of one check. ``value`` and ``threshold`` are in the unit the check names."""

    stage: Stage
    check: str
    passed: bool
    label: RejectionLabel | None = None  # the rejection label when not passed
    value: float | None = None
    threshold: float | None = None
    detail: str = ""


class Rejection(_Value):
    """One row of a batch's rejection log. ``attempt``: which try of the proposal index (0 the first
    pass, k the k-th repair); ``repaired``: a repair of it followed, so the index's outcome is a later
    row or scene. Both are left out of the row at their defaults (logs without repairs read as
    before repairs existed)."""

    proposal_index: int
    stage: Stage
    label: RejectionLabel
    check: str
    value: float | None = None
    threshold: float | None = None
    detail: str = ""
    attempt: int = Field(0, ge=0)
    repaired: bool = False

    @model_serializer(mode="wrap")
    def _omit_defaults(self, handler):
        data = handler(self)
        if not data.get("attempt"):
            data.pop("attempt", None)
        if not data.get("repaired"):
            data.pop("repaired", None)
        return data

    @classmethod
    def from_check(cls, proposal_index: int, result: CheckResult, attempt: int = 0) -> Rejection:
        assert result.label is not None, "a passed check is not a rejection"
        return cls(
            proposal_index=proposal_index,
            stage=result.stage,
            label=result.label,
            check=result.check,
            value=result.value,
            threshold=result.threshold,
            detail=result.detail,
            attempt=attempt,
        )


class Contact(_Value):
    """A settled contact: ``a`` rests on or touches ``b``; ``distance`` is MuJoCo's signed distance (m)."""

    a: str
    b: str
    kind: Literal["rests_on", "touches"]
    distance: float


class SettledObject(ObjectPlacement):
    """An object after settling: the pose is the settled one; ``moved`` is the displacement (m)."""

    moved: float = 0.0
    rotated: float = 0.0  # radians between proposed and settled orientation


class TagValue(_Value):
    """One rare-case predicate measured on one scene (scenegen/tags/predicates.py)."""

    holds: bool
    value: float
    threshold: float
    unit: str


class SceneRecord(BaseModel):
    """scene.json: everything needed to understand and replay one stored scene.

    It holds no wall-clock data (timings go to the batch's timings.json), so the same recipe and seed
    give byte-identical files.
    """

    model_config = ConfigDict(extra="forbid")

    schema_version: Literal[1] = 1
    scene_id: str
    proposal_index: int
    seed: int
    condition: Condition
    generator: dict  # proposer kind and its settings
    target: str
    objects: tuple[SettledObject, ...]
    furniture: tuple[FurniturePlacement, ...]
    lighting: Lighting
    cameras: tuple[dict, ...]  # Camera fields + intrinsics + extrinsics (convention named)
    tags: dict[str, TagValue] = Field(default_factory=dict)  # measured on the settled scene
    predicate_version: str = ""  # scenegen.tags.predicates.PREDICATE_VERSION of the predicates used
    segmentation: dict[str, int] = Field(default_factory=dict)  # instance name -> id in *_seg.png
    render: dict | None = None  # render settings used (None: not rendered)
    contacts: tuple[Contact, ...]
    contact_options: dict  # MuJoCo options used while settling (also embedded in scene.xml)
    checks: tuple[CheckResult, ...]
    settle: dict  # sim time, steps, max speeds at the end
    provenance: dict  # scenegen version, package versions, pipeline hash, catalog hash
    files: dict[str, str] = Field(default_factory=dict)  # relative path -> sha256

    @model_validator(mode="wrap")
    @classmethod
    def _own_categories(cls, data, handler):
        return vouch_for_objects(data, handler)  # made with user catalogs: readable without them
