"""Scenes an environment can reset into: a stored scene (scene.json of a batch) or a reference layout
(a row of the reference Parquet table), as one value, :class:`EnvScene`.

Both carry the settled state: objects at their settled poses, the robot at the scene's initial pose
(the stored scene's arm was held there while it settled). A reference row has no cameras: it gets the
procedural proposer's default cameras, the ones the reference renders used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from scenegen.core.files import load_rows
from scenegen.propose.procedural import DEFAULT_CAMERAS
from scenegen.render.offscreen import segmentation_ids
from scenegen.schema.scene import (
    Camera,
    FurniturePlacement,
    Light,
    Lighting,
    ObjectPlacement,
    SceneRecord,
)
from scenegen.store.batch import StoreError, scene_dirs


class SceneSourceError(ValueError):
    """A scene source that cannot be read (missing file, wrong format); the message names it."""


@dataclass(frozen=True)
class EnvScene:
    """One scene to reset into. Poses in the MuJoCo world frame (metres, wxyz quaternions).

    ``scene_id`` is unique within its source; ``origin`` is ``synthetic`` (a generated batch) or
    ``reference`` (a reference layout); ``tags`` says which rare-case tags hold on the settled scene.
    """

    scene_id: str
    origin: str
    source: str
    target: str
    objects: tuple[ObjectPlacement, ...]
    furniture: tuple[FurniturePlacement, ...]
    lighting: Lighting
    cameras: tuple[Camera, ...]
    robot_pose: tuple[float, ...]
    tags: dict[str, bool] = field(default_factory=dict)
    path: Path | None = None  # the scene directory of a stored scene
    catalogs: tuple[str, ...] = ()  # the user catalogs its assets come from (scene.json provenance)
    floor: str = "plane"  # what the floor was when it settled (sim/world.py FLOORS; scene.json's)
    table_rolling_friction: float | None = None  # the table's when it settled (scene.json's)

    @property
    def segmentation(self) -> dict[str, int]:
        """Instance ids of the segmentation images, as in scene.json."""
        return segmentation_ids(None, [o.name for o in self.objects], [f.name for f in self.furniture])

    @property
    def target_id(self) -> int:
        return self.segmentation[self.target]


def stored_scene(scene_dir: Path, source: str | None = None) -> EnvScene:
    """The settled scene of a stored scene directory (its scene.json)."""
    scene_dir = Path(scene_dir)
    try:
        record = SceneRecord.model_validate_json((scene_dir / "scene.json").read_text())
    except FileNotFoundError as exc:
        raise SceneSourceError(f"{scene_dir}: no scene.json (is it a scene directory of a batch?)") from exc
    except ValueError as exc:
        first = str(exc).splitlines()[0]
        raise SceneSourceError(f"{scene_dir / 'scene.json'}: not a scene record ({first})") from exc
    cameras = tuple(
        Camera(**{k: cam[k] for k in ("name", "position", "lookat", "fovy", "width", "height")})
        for cam in record.cameras
    )
    objects = tuple(ObjectPlacement(**o.model_dump(exclude={"moved", "rotated"})) for o in record.objects)
    catalogs = _user_catalogs(scene_dir, record.provenance.get("catalogs") or [])
    return EnvScene(
        scene_id=record.scene_id,
        origin="synthetic",
        source=source or scene_dir.parent.name,
        target=record.target,
        objects=objects,
        furniture=record.furniture,
        lighting=record.lighting,
        cameras=cameras,
        robot_pose=tuple(record.condition.robot_pose),
        tags={name: value.holds for name, value in record.tags.items()},
        path=scene_dir,
        catalogs=catalogs,
        floor=record.contact_options.get("floor", "plane"),
        table_rolling_friction=record.contact_options.get("table_rolling_friction"),
    )


def _user_catalogs(scene_dir: Path, recorded: list) -> tuple[str, ...]:
    """The user catalogs (paths) a stored scene was made with, each checked against the sha256 it
    recorded (SceneSourceError naming the catalog if missing or changed since)."""
    from scenegen.assets.catalog import CatalogError, load_catalog

    paths = []
    for entry in recorded[1:]:  # the first is the bundled catalog
        try:
            catalog = load_catalog(Path(entry["path"]))
        except CatalogError as exc:
            raise SceneSourceError(
                f"{scene_dir}: made with the user catalog {entry['path']}: {exc}"
            ) from None
        if catalog.sha256 != entry["sha256"]:
            raise SceneSourceError(
                f"{scene_dir}: its user catalog {entry['path']} changed since it was made; "
                "restore that catalog, or generate the scene again"
            )
        paths.append(entry["path"])
    return tuple(paths)


def batch_scenes(batch: Path, source: str | None = None) -> list[EnvScene]:
    """Every accepted scene of a stored batch, in index order."""
    batch = Path(batch)
    try:
        folders = scene_dirs(batch)
    except StoreError as exc:
        raise SceneSourceError(str(exc)) from None
    return [stored_scene(folder, source or batch.name) for _, folder in folders]


def reference_scene(row: dict, source: str = "reference") -> EnvScene:
    """A reference layout (one row of the reference Parquet table) as a scene, with default cameras."""
    ambient = float(row["ambient"])
    lighting = Lighting(
        ambient=(ambient, ambient, ambient),
        lights=tuple(
            Light(
                position=tuple(light["position"]),
                direction=tuple(light["direction"]),
                colour=tuple(light["colour"]),
                intensity=light["intensity"],
                cast_shadow=light["cast_shadow"],
            )
            for light in row["lights"]
        ),
    )
    furniture = tuple(
        # named by kind, as the procedural proposer names them (one piece of each kind at most)
        FurniturePlacement(name=f["kind"], kind=f["kind"], position=(f["x"], f["y"], 0.0), yaw=f["yaw"])
        for f in row["furniture"]
    )
    objects = tuple(
        ObjectPlacement(
            name=o["name"],
            asset=o["asset"],
            category=o["category"],
            support=o["support"],
            resting_pose=o["resting_pose"],
            position=tuple(o["position"]),
            quat=tuple(o["quat"]),
        )
        for o in row["objects"]
    )
    return EnvScene(
        scene_id=f"{row.get('origin', 'reference')}_{row['index']:06d}",
        origin="reference",
        source=source,
        target=row["target"],
        objects=objects,
        furniture=furniture,
        lighting=lighting,
        cameras=DEFAULT_CAMERAS,
        robot_pose=tuple(row["robot_pose"]),
        tags={k[4:]: bool(v) for k, v in row.items() if k.startswith("tag_")},
    )


def table_scenes(path: Path, split: str | None = "train", source: str | None = None) -> list[EnvScene]:
    """The layouts of a reference (or imported real) Parquet table as scenes; ``split`` as in
    :data:`scenegen.core.files.SPLITS` (None: every row)."""
    path = Path(path)
    try:
        rows = load_rows(path, split)
    except (OSError, ValueError) as exc:
        raise SceneSourceError(f"{path}: {str(exc).splitlines()[0]}") from exc
    return [reference_scene(r, source or path.stem) for r in rows]


def load_scenes(source: Path | str, split: str | None = "train") -> list[EnvScene]:
    """Scenes of a batch directory, a scene directory or a Parquet table, by what ``source`` is."""
    source = Path(source)
    if source.suffix == ".parquet":
        return table_scenes(source, split)
    if (source / "scene.json").is_file():
        return [stored_scene(source)]
    return batch_scenes(source)


def source_scenes(
    manifest: Path, names: Sequence[str] | None = None, split: str | None = "train"
) -> list[EnvScene]:
    """The scenes of a manifest's sources (all of them, or those named), each labelled with its
    source name; a source's location must lie inside the manifest's folder. ``split`` applies to
    table sources (reference, real)."""
    from scenegen.manifest import read_manifest
    from scenegen.manifest.io import inside

    manifest = Path(manifest)
    sources = {s.name: s for s in read_manifest(manifest).sources}
    unknown = [n for n in names or () if n not in sources]
    if unknown:
        raise SceneSourceError(f"{manifest}: no source named {unknown}; it has {sorted(sources)}")
    scenes: list[EnvScene] = []
    for name in names or list(sources):
        source = sources[name]
        location = manifest.parent / source.location
        if not inside(location, manifest.parent):
            raise SceneSourceError(f"{manifest}: sources.{name}.location lies outside the manifest's folder")
        if source.origin == "synthetic":
            scenes += batch_scenes(location, name)
        else:
            scenes += [
                dataclasses.replace(s, origin=source.origin) for s in table_scenes(location, split, name)
            ]
    return scenes


def proposal_scene(proposal, scene_id: str = "proposal", source: str = "hand-built") -> EnvScene:
    """A scene of a proposal's placements as they are (not settled: place objects at rest, e.g. with
    ``core.placement.snap_to_rest``); cameras default to the procedural proposer's."""
    return EnvScene(
        scene_id=scene_id,
        origin="synthetic",
        source=source,
        target=proposal.target,
        objects=tuple(proposal.objects),
        furniture=tuple(proposal.furniture),
        lighting=proposal.lighting,
        cameras=tuple(proposal.cameras) or DEFAULT_CAMERAS,
        robot_pose=tuple(proposal.condition.robot_pose),
    )


def scene_sha256(scene: EnvScene) -> str:
    """A stored scene's scene.json sha256; a reference layout's, of its description as JSON."""
    if scene.path is not None:
        return hashlib.sha256((scene.path / "scene.json").read_bytes()).hexdigest()
    described = {
        "objects": [o.model_dump(mode="json") for o in scene.objects],
        "furniture": [f.model_dump(mode="json") for f in scene.furniture],
        "lighting": scene.lighting.model_dump(mode="json"),
        "cameras": [c.model_dump(mode="json") for c in scene.cameras],
        "robot_pose": list(scene.robot_pose),
        "target": scene.target,
    }
    return hashlib.sha256(json.dumps(described, sort_keys=True).encode()).hexdigest()


def target_category(scene: EnvScene) -> str:
    """The category of the scene's target object (``can``, ``mug``, ...)."""
    return next(o.category for o in scene.objects if o.name == scene.target)


def unique_category(scene: EnvScene) -> bool:
    """Whether the scene holds one object of its target's category (else "retrieve the mug" is
    ambiguous: the panels of issue 33 hold only such scenes)."""
    category = target_category(scene)
    return sum(o.category == category for o in scene.objects) == 1
