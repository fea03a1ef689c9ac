"""Real scenes into the reference layout: a JSON file of measured scenes -> one Parquet row per scene.

The file format is documented in docs/real_data.md: a list of records, each a measured tabletop scene
(table, objects with poses in the MuJoCo world frame, optional furniture and lighting, the target and
the task). Every record is validated strictly (unknown keys, unknown assets or tasks, non-finite
numbers and a table that is not the simulated one are errors naming the record and the field), and
nothing is written unless every record passes.

Tags are recomputed, never copied: each scene is built as a MuJoCo world at its measured poses (no
settling: the poses are the measurement), its contacts are read at those poses, and the predicates of
scenegen/tags/predicates.py run with the main camera of the procedural proposer. Rows have the columns of
:func:`scenegen.data.reference.layout_row` plus ``origin`` (``real``) and ``id``, so real and reference
tables are read by the same code (coverage, evaluation).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import Counter
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    field_validator,
    model_validator,
)

from scenegen import __version__
from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.core import layout
from scenegen.schema.condition import ROBOT_POSES, TAGS, Condition, known_pose_name, known_task
from scenegen.schema.scene import (
    FurniturePlacement,
    Light,
    Lighting,
    ObjectPlacement,
    SceneRecord,
    SettledObject,
)
from scenegen.sim import world

TABLE_TOLERANCE = 0.01  # m: a record's table must match the simulated one this closely
QUAT_NORM_TOLERANCE = 0.01  # |norm - 1| allowed before a quaternion is refused (then normalised)
SUPPORT_GAP = 0.02  # m: an object whose lowest point is further above any surface has support "none"
ORIGIN = "real"

# Lighting assumed for a record without ``lighting``: a well-lit room, one ceiling lamp above the table
# centre and an ambient level above the low_light threshold, so that an assumption never makes a scene
# low_light (docs/real_data.md says so).
DEFAULT_LIGHTING = Lighting(
    lights=(Light(position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), intensity=0.6),),
    ambient=(0.3, 0.3, 0.3),
)


class ImportFormatError(ValueError):
    """A real-data file cannot be imported; the message is one line naming the record and field."""


# ------------------------------------------------------------------------------ the file format

Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]  # ints pass, strings/bools/NaN do not
Vec2 = tuple[Finite, Finite]
Vec3 = tuple[Finite, Finite, Finite]
Name = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=64)]


class _Input(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RealTable(_Input):
    """The table the scene was measured on: full ``size`` [x, y] (m) and ``top_z``, its top's height (m).

    scenegen simulates one table (``layout.TABLE_SIZE``, ``layout.TABLE_TOP_Z``); a record measured on
    another table is refused rather than rescaled, since every tag is measured against that table.
    """

    size: Vec2
    top_z: Finite

    @field_validator("size")
    @classmethod
    def _simulated_size(cls, size: tuple[float, float]) -> tuple[float, float]:
        want = layout.TABLE_SIZE[:2]
        if any(abs(a - b) > TABLE_TOLERANCE for a, b in zip(size, want, strict=True)):
            raise ValueError(
                f"{size[0]:g} x {size[1]:g} m does not match the simulated table {want[0]:g} x {want[1]:g} m "
                f"(tolerance {TABLE_TOLERANCE:g} m); scenes from another table cannot be imported"
            )
        return size

    @field_validator("top_z")
    @classmethod
    def _simulated_height(cls, top_z: float) -> float:
        if abs(top_z - layout.TABLE_TOP_Z) > TABLE_TOLERANCE:
            raise ValueError(
                f"{top_z:g} m does not match the simulated table top {layout.TABLE_TOP_Z:g} m "
                f"(tolerance {TABLE_TOLERANCE:g} m); scenes from another table cannot be imported"
            )
        return top_z


class RealObject(_Input):
    """A measured object: ``asset`` from the catalog, ``position`` (m) and wxyz ``quat`` of its body
    frame (the asset's centre-of-mass frame) in the MuJoCo world frame."""

    name: Name
    asset: str
    position: Vec3
    quat: tuple[Finite, Finite, Finite, Finite]

    @field_validator("asset")
    @classmethod
    def _known_asset(cls, asset: str) -> str:
        catalog = load_catalog()
        if asset not in catalog.by_name:
            raise ValueError(f"unknown asset {asset!r}; valid assets: {', '.join(sorted(catalog.by_name))}")
        return asset

    @field_validator("quat")
    @classmethod
    def _unit(cls, quat: tuple[float, ...]) -> tuple[float, ...]:
        norm = math.sqrt(sum(q * q for q in quat))
        if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
            raise ValueError(
                f"not a unit quaternion (norm {norm:.4g}); give [w, x, y, z] with norm 1 "
                f"(within {QUAT_NORM_TOLERANCE:g})"
            )
        return tuple(q / norm for q in quat)


class RealFurniture(_Input):
    """A shelf or bin on the table: ``position`` [x, y] (m) of its footprint centre, ``yaw`` (rad)."""

    kind: str
    position: Vec2
    yaw: Finite = 0.0
    name: Name | None = None  # default: the kind (with a number when a record has two of a kind)

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, kind: str) -> str:
        if kind not in layout.FURNITURE:
            raise ValueError(f"unknown furniture {kind!r}; valid kinds: {', '.join(layout.FURNITURE)}")
        return kind


class RealLight(_Input):
    """A spot light as in scene.json: position and direction (m, world frame), colour 0-1 RGB."""

    position: Vec3
    direction: Vec3
    colour: Vec3 = (1.0, 1.0, 1.0)
    intensity: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0.0, le=3.0)] = 0.6
    cast_shadow: bool = True


class RealLighting(_Input):
    """The measured lighting: spot lights and the ambient RGB (0-1)."""

    lights: list[RealLight] = Field(default_factory=list, max_length=8)
    ambient: Vec3 = (0.1, 0.1, 0.1)

    def lighting(self) -> Lighting:
        return Lighting(
            lights=tuple(Light(**light.model_dump()) for light in self.lights), ambient=self.ambient
        )


class RealRecord(_Input):
    """One measured scene (docs/real_data.md)."""

    id: Annotated[str, StringConstraints(min_length=1, max_length=200, pattern=r"^[^\n\r]+$")]
    task: str
    table: RealTable
    objects: list[RealObject] = Field(min_length=1, max_length=32)
    target: str
    furniture: list[RealFurniture] = Field(default_factory=list, max_length=8)
    lighting: RealLighting | None = None
    robot_pose: str | tuple[float, ...] = "home"  # a name of ROBOT_POSES or 7 Panda joint angles (rad)

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        return known_task(task)

    @field_validator("robot_pose", mode="before")
    @classmethod
    def _valid_pose(cls, pose):
        if isinstance(pose, str):
            return known_pose_name(pose)
        numbers = isinstance(pose, list) and all(
            isinstance(q, int | float) and not isinstance(q, bool) and math.isfinite(q) for q in pose
        )
        if not numbers or len(pose) != 7:
            raise ValueError(
                f"give a pose name ({', '.join(ROBOT_POSES)}) or a list of 7 finite joint angles"
            )
        try:
            Condition(robot_pose=tuple(pose))  # the Panda's joint limits
        except ValidationError as exc:
            raise ValueError(exc.errors()[0]["msg"].removeprefix("Value error, ")) from None
        return tuple(float(q) for q in pose)

    @model_validator(mode="after")
    def _names(self):
        names = [o.name for o in self.objects]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise _FieldError(("objects", i, "name"), f"duplicate object name {name!r}")
        if self.target not in names:
            raise _FieldError(
                ("target",), f"{self.target!r} is not an object of this record; objects: {names}"
            )
        for i, name in enumerate(self.furniture_names()):
            if name in names or name in self.furniture_names()[:i]:
                raise _FieldError(("furniture", i, "name"), f"name {name!r} is taken; give a unique name")
        return self

    def furniture_names(self) -> list[str]:
        kinds = Counter(f.kind for f in self.furniture)
        seen: Counter = Counter()
        out = []
        for f in self.furniture:
            seen[f.kind] += 1
            out.append(f.name or (f.kind if kinds[f.kind] == 1 else f"{f.kind}{seen[f.kind]}"))
        return out


class _FieldError(ValueError):
    """A cross-field error with the location of the field it is about (raised inside a validator)."""

    def __init__(self, loc: tuple, message: str):
        super().__init__(message)
        self.loc, self.message = loc, message


def _where(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(record)"


def _record_label(index: int, raw: Any) -> str:
    rid = raw.get("id") if isinstance(raw, dict) else None
    return f"record {index} (id {rid!r})" if isinstance(rid, str) else f"record {index}"


def _message(exc: ValidationError) -> str:
    err = exc.errors()[0]
    cause = (err.get("ctx") or {}).get("error")
    if isinstance(cause, _FieldError):
        return f"{_where(cause.loc)}: {cause.message}"
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "missing":
        msg = "required field missing (docs/real_data.md)"
    elif err["type"] == "extra_forbidden":
        msg = "unknown field (docs/real_data.md lists the fields)"
    elif err["type"] == "string_pattern_mismatch" and err["loc"][-1] == "name":
        msg = f"{err['input']!r}: a name starts with a letter and holds letters, digits and _ only"
    return f"{_where(err['loc'])}: {msg}"


def read_records(path: Path) -> list[RealRecord]:
    """Parse and validate every record of a real-data file; the first problem raises ImportFormatError."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise ImportFormatError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise ImportFormatError(f"{path}: not JSON (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ImportFormatError(
            f"{path}: not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    if not isinstance(raw, list):
        raise ImportFormatError(
            f"{path}: the top level must be a list of records (docs/real_data.md), got {type(raw).__name__}"
        )
    if not raw:
        raise ImportFormatError(f"{path}: no records; the list is empty")
    records: list[RealRecord] = []
    first_index: dict[str, int] = {}
    for i, item in enumerate(raw):
        label = _record_label(i, item)
        if not isinstance(item, dict):
            raise ImportFormatError(
                f"{path}: {label}: a record must be a JSON object (docs/real_data.md), "
                f"got {type(item).__name__}"
            )
        try:
            record = RealRecord.model_validate(item)
        except ValidationError as exc:
            raise ImportFormatError(_one_line(f"{path}: {label}: {_message(exc)}")) from None
        if record.id in first_index:
            raise ImportFormatError(f"{path}: {label}: id: duplicate of record {first_index[record.id]}")
        first_index[record.id] = i
        records.append(record)
    return records


def _one_line(message: str) -> str:
    return " ".join(message.split("\n"))


# ------------------------------------------------------------------------------- measurement


def _support(
    obj: ObjectPlacement, bottom: float, surfaces: dict[str, layout.Surface]
) -> tuple[str, layout.Surface | None]:
    """The highest surface at or just below the object's lowest point with the object's centre over it.

    Measured poses are noisy, so a surface up to 5 mm above the lowest point still counts, and the
    centre may overhang the surface region by up to 1 cm; nothing within ``SUPPORT_GAP`` gives "none".
    """
    best: tuple[str, layout.Surface | None] = ("none", None)
    for name, surface in surfaces.items():
        if name == obj.name or surface.z > bottom + 0.005 or bottom - surface.z > SUPPORT_GAP:
            continue
        if surface.margin(obj.position[:2]) < -0.01:
            continue
        if best[1] is None or surface.z > best[1].z:
            best = (name, surface)
    return best


def _placements(
    record: RealRecord, catalog: Catalog
) -> tuple[list[ObjectPlacement], list[FurniturePlacement]]:
    """Objects with their support and nearest resting pose, and furniture, as the pipeline names them."""
    from scenegen.assets.catalog import convex_part_vertices
    from scenegen.core.placement import snap_to_rest
    from scenegen.core.rotations import quat_to_matrix

    furniture = [
        FurniturePlacement(name=name, kind=f.kind, position=(f.position[0], f.position[1], 0.0), yaw=f.yaw)
        for name, f in zip(record.furniture_names(), record.furniture, strict=True)
    ]
    raw = [
        ObjectPlacement(
            name=o.name,
            asset=o.asset,
            category=catalog.get(o.asset).category,
            position=o.position,
            quat=o.quat,
        )
        for o in record.objects
    ]
    surfaces = layout.support_surfaces(furniture, raw, catalog)
    objects = []
    for obj in raw:
        asset = catalog.get(obj.asset)
        parts = np.concatenate(convex_part_vertices(catalog, obj.asset))
        bottom = float((parts @ quat_to_matrix(obj.quat).T)[:, 2].min() + obj.position[2])
        support, surface = _support(obj, bottom, surfaces)
        # Resting pose: the catalog pose nearest in orientation (yaw aside); the projection distance says
        # how far the measured pose is from lying exactly on it on its support (m).
        _, _, pose, distance = snap_to_rest(
            asset, obj.position, obj.quat, surface or layout.support_surfaces(())["table"]
        )
        objects.append(
            obj.model_copy(
                update={
                    "support": support,
                    "resting_pose": pose,
                    "projection_distance": distance if surface else 0.0,
                }
            )
        )
    return objects, furniture


def measure_record(record: RealRecord, index: int, catalog: Catalog, source: str = "") -> SceneRecord:
    """A scene record of one measured scene: world built at its poses, contacts and tags measured there."""
    import mujoco

    from scenegen.propose.procedural import DEFAULT_CAMERAS
    from scenegen.settle.physics import contact_configuration
    from scenegen.tags.predicates import PREDICATE_VERSION, TagContext, measure_tags

    objects, furniture = _placements(record, catalog)
    lighting = record.lighting.lighting() if record.lighting is not None else DEFAULT_LIGHTING
    camera = DEFAULT_CAMERAS[0]  # the main camera tags such as occluded are measured from
    condition = Condition(
        task=record.task,
        target=catalog.get(next(o.asset for o in record.objects if o.name == record.target)).category,
        robot_pose=record.robot_pose,
    )
    model = world.build_world(catalog, objects, furniture, lighting).compile()
    qpos, ctrl = world.initial_state(model, condition.robot_pose, objects)
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = qpos, ctrl
    mujoco.mj_forward(model, data)
    names = [o.name for o in objects]
    contacts = contact_configuration(model, qpos, names)
    context = TagContext.of_scene(
        model, data, catalog, record.target, objects, furniture, lighting, camera.position, contacts
    )
    tags = measure_tags(context)
    return SceneRecord(
        scene_id=f"real_{index:06d}",
        proposal_index=index,
        seed=0,
        condition=condition,
        generator={"kind": ORIGIN, "source": source, "id": record.id},
        target=record.target,
        objects=tuple(SettledObject(**o.model_dump()) for o in objects),
        furniture=tuple(furniture),
        lighting=lighting,
        cameras=(camera.model_dump(mode="json"),),
        tags=tags,
        predicate_version=PREDICATE_VERSION,
        contacts=tuple(contacts),
        contact_options=world.CONTACT_OPTIONS,
        checks=(),
        settle={"settled": False, "reason": "measured poses are used as given"},
        provenance={"scenegen": __version__, "catalog_sha256": catalog.sha256, "source": source},
    )


def real_row(record: RealRecord, scene: SceneRecord) -> dict:
    """A Parquet row: ``origin`` and ``id``, then the columns of ``reference.layout_row``."""
    from scenegen.data.reference import layout_row

    return {"origin": ORIGIN, "id": record.id, **layout_row(scene)}


def import_real(path: str | Path, out_parquet: str | Path) -> dict:
    """Validate every record of ``path``, measure each scene, and write ``out_parquet`` atomically.

    Raises :class:`ImportFormatError` (one line, naming the record and field) before anything is
    written when any record is malformed; an existing file at ``out_parquet`` is then left as it was.
    Returns stats: ``rows``, ``out``, ``tags`` (scenes holding each tag), ``unsupported`` (``id:object``
    of objects with no support surface within ``SUPPORT_GAP`` below them), ``seconds``.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from scenegen.data.reference import file_sha256
    from scenegen.tags.predicates import PREDICATE_VERSION

    start = time.perf_counter()
    path, out = Path(path), Path(out_parquet)
    records = read_records(path)
    catalog = load_catalog()
    spec = world.robot_spec()  # held: its bodies are views into it
    reserved = {body.name for body in spec.bodies}
    for i, record in enumerate(records):
        for field, names in (
            ("objects", [o.name for o in record.objects]),
            ("furniture", record.furniture_names()),
        ):
            for j, name in enumerate(names):
                if name in reserved:
                    raise ImportFormatError(
                        f"{path}: {_record_label(i, {'id': record.id})}: {field}[{j}].name: {name!r} is a "
                        "body of the simulated table or robot; rename it"
                    )
    rows, unsupported = [], []
    for i, record in enumerate(records):
        scene = measure_record(record, i, catalog, source=path.name)
        rows.append(real_row(record, scene))
        unsupported += [f"{record.id}:{o.name}" for o in scene.objects if o.support == "none"]
    metadata = {
        "scenegen.origin": ORIGIN,
        "scenegen.real": "measured scenes imported from a real-data file; tags recomputed at the given poses",
        "source_file": path.name,
        "source_sha256": file_sha256(path),
        "predicate_version": PREDICATE_VERSION,
        "catalog_sha256": catalog.sha256,
        "scenegen_version": __version__,
    }
    table = pa.Table.from_pylist(rows).replace_schema_metadata(metadata)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        pq.write_table(table, tmp, compression="zstd")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return {
        "rows": len(rows),
        "out": str(out),
        "tags": {t: sum(bool(r[f"tag_{t}"]) for r in rows) for t in TAGS},
        "unsupported": unsupported,
        "seconds": round(time.perf_counter() - start, 3),
    }
