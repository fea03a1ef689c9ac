"""Pipeline recipes: the validated YAML files in pipelines/.

A recipe names the request (condition), the proposer and its distributions, and the thresholds of
every stage. Unknown keys, tasks, targets, tags or impossible values are errors that name the field.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_serializer, model_validator

from scenegen.assets.catalog import CatalogError, using_catalogs
from scenegen.check.geometry import CheckSettings
from scenegen.propose.base import impossible_request
from scenegen.propose.diffusion import DiffusionSettings
from scenegen.propose.procedural import ProceduralSettings
from scenegen.propose.targeted import TargetedSettings
from scenegen.schema.condition import Condition, parse_request
from scenegen.settle.physics import SettleSettings
from scenegen.tags.predicates import TagSettings

PROPOSER_SETTINGS: dict[str, type[BaseModel]] = {
    "procedural": ProceduralSettings,
    "targeted": TargetedSettings,
    "diffusion": DiffusionSettings,
}


class RealismFilter(BaseModel):
    """The per-scene ``unrealistic`` filter of a recipe (``realism:``): a settled scene whose
    typicality (scenegen.analysis.scene_score.SceneScorer) against the reference set's train split is
    below ``min_score`` is rejected as ``unrealistic``; the score is recorded in every scene's checks."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min_score: float = Field(0.01, ge=0.0, le=1.0)
    k: int = Field(5, ge=1, le=50)
    reference: str = "assets/reference/reference.parquet"  # relative paths: to the project root
    # ``whole``: every scene scored against the whole reference. ``per_tag``: a scene whose rare tags
    # the reference holds together in fewer than k layouts is judged per tag, each against the layouts
    # holding it (analysis/scene_score.py composition_scores); every other scene as ``whole``.
    compositions: Literal["whole", "per_tag"] = "whole"

    @model_serializer(mode="wrap")
    def _omit_whole(self, handler):
        data = handler(self)  # a recipe without the key dumps and hashes as before it existed
        if data.get("compositions") == "whole":
            del data["compositions"]
        return data


class ConfigError(ValueError):
    """A pipeline file is invalid; the message is one line naming the file and field."""


class PipelineConfig(BaseModel):
    """One pipeline recipe.

    Keys: ``name``; ``n`` accepted scenes wanted; ``seed``; ``max_proposals`` (give up after this
    many proposals, default 40 x n); ``max_tries`` (after this many tries, repairs included);
    ``condition`` (see :class:`Condition`); ``proposer``
    (``kind: procedural`` or ``kind: targeted`` and its settings, cameras included); ``checks``;
    ``settle``; ``tags``; ``realism`` (the per-scene ``unrealistic`` filter); ``render``;
    ``robot_mesh_detail`` (the robot's meshes decimated for drawing); ``floor`` (``plane``, the
    default, or ``box``: what objects on the floor rest on, sim/world.py ``FLOORS``); ``sensor``
    (``exact``, the default: the renderer's depth only; ``active_stereo`` or ``structured_light``: each
    camera's depth as that sensor returns it is stored too, ``<cam>_depth_<sensor>.png``;
    docs/sensor.md).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    n: int = Field(20, ge=1, le=1_000_000)
    seed: int = Field(0, ge=0, lt=2**63)
    max_proposals: int | None = Field(None, ge=1)
    condition: Condition = Condition()
    proposer: Annotated[
        ProceduralSettings | TargetedSettings | DiffusionSettings, Field(discriminator="kind")
    ] = ProceduralSettings()
    checks: CheckSettings = CheckSettings()
    settle: SettleSettings = SettleSettings()
    tags: TagSettings = TagSettings()
    realism: RealismFilter | None = None  # per-scene `unrealistic` filter; None: off
    render: bool = True  # RGB, depth and segmentation per camera (``--no-render`` turns it off)
    # Share of the robot's visual-mesh triangles drawn (quadric decimation, once per worker; the
    # simulated model is unchanged); None: the meshes as shipped. Recorded in scene.json `render`.
    robot_mesh_detail: float | None = Field(None, gt=0.0, le=1.0)
    # A depth sensor's frames stored beside the exact depth (render/sensor.py SENSORS; needs render).
    sensor: Literal["exact", "active_stereo", "structured_light"] = "exact"
    # User asset catalogs (``scenegen assets add``), each a catalog.yaml or its folder, relative to the
    # working directory; merged after the bundled one. Empty: the bundled catalog only.
    catalogs: tuple[str, ...] = ()
    # give up after this many tries: proposals and their repairs (None: only max_proposals caps)
    max_tries: int | None = Field(None, ge=1)
    # what objects on the floor rest on (sim/world.py FLOORS): robosuite's plane, or a box like the table
    floor: Literal["plane", "box"] = "plane"
    # rolling friction of the table's contacts (m, condim 6; sim/world.py); None: robosuite's table as is
    table_rolling_friction: float | None = Field(None, ge=0.0, le=0.05)

    @model_validator(mode="after")
    def _reachable_request(self):
        catalog = self.catalog()
        problem = impossible_request(
            self.condition, catalog, self.tags.overhang_cover, self.checks.furniture_on_table
        )
        if problem:
            raise ValueError(f"condition: {problem}")
        allowed = getattr(self.proposer, "assets", None)
        if allowed is not None and not any(catalog.get(a).category == self.condition.target for a in allowed):
            raise ValueError(
                f"proposer.assets: none is a {self.condition.target} (the target); add one, or drop the key"
            )
        if self.sensor != "exact" and not self.render:
            raise ValueError(f"sensor: {self.sensor} needs rendered frames (render: true); or sensor: exact")
        diffusion = self.proposer.kind == "diffusion"
        if diffusion and self.condition.target not in self.proposer.known_categories():
            raise ValueError(
                f"condition: generator {self.proposer.checkpoint} does not know the category "
                f"{self.condition.target!r}: use --proposer procedural, or retrain it on these catalogs "
                "(scenegen reference, scenegen train; docs/assets.md)"
            )
        return self

    def catalog(self):
        """The bundled catalog merged with the recipe's user ``catalogs`` (assets.catalog.Catalog)."""
        from scenegen.assets.catalog import load_catalogs

        return load_catalogs([Path(p) for p in self.catalogs])

    @model_serializer(mode="wrap")
    def _omit_unset_filter(self, handler):
        # A recipe without the realism filter dumps (and hashes) exactly as before the filter existed,
        # so the digests stamped into the reference set and earlier batches stay valid.
        data = handler(self)
        # the same for later keys
        for key in ("realism", "robot_mesh_detail", "max_tries", "table_rolling_friction"):
            if data.get(key, 0) is None:
                del data[key]
        if data.get("sensor") == "exact":
            del data["sensor"]
        if data.get("floor") == "plane":
            del data["floor"]
        if not data.get("catalogs", True):  # and for a recipe of the bundled catalog only
            del data["catalogs"]
        return data

    @property
    def supports(self) -> dict:
        """What objects rest on, as sim/world.py's build_world and contact_options take it."""
        return {"floor": self.floor, "table_rolling_friction": self.table_rolling_friction}

    @property
    def proposal_cap(self) -> int:
        return self.max_proposals or 40 * self.n

    def digest(self) -> str:
        """sha256 of the canonical JSON of the recipe (overrides included)."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()


def _fields_at(loc: tuple, proposer: type[BaseModel]) -> list[str]:
    """Field names of the (nested) model at ``loc`` of a recipe; ``proposer``: the settings model of
    the recipe's proposer kind."""
    model: type[BaseModel] = PipelineConfig
    for part in loc:
        if model is PipelineConfig and part == "proposer":
            model = proposer
            continue
        field = model.model_fields.get(part) if isinstance(part, str) else None
        annotation = getattr(field, "annotation", None)
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            break
        model = annotation
    return list(model.model_fields)


def _format_error(path: Path, exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = list(err["loc"])
    proposer: type[BaseModel] = ProceduralSettings
    if len(loc) >= 2 and loc[0] == "proposer" and loc[1] in PROPOSER_SETTINGS:
        proposer = PROPOSER_SETTINGS[loc.pop(1)]  # pydantic names the union member: drop it
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        import difflib

        valid = _fields_at(tuple(loc[:-1]), proposer)
        close = difflib.get_close_matches(str(loc[-1]), valid, n=2)
        shown = ", ".join(valid)
        if len(shown) > 150:  # an error line holds 300 characters: the first keys and the count
            fit = max(k for k in range(1, len(valid) + 1) if len(", ".join(valid[:k])) <= 120)
            shown = ", ".join(valid[:fit]) + f", ... ({len(valid)} keys)"
        hint = f"; did you mean {' or '.join(close)}?" if close else ""
        msg = f"unknown key{hint}; valid keys here: {shown} (docs/pipelines.md)"
    elif err["type"] in ("union_tag_invalid", "union_tag_not_found"):
        loc.append("kind")
        kind = err.get("ctx", {}).get("tag")
        msg = f"unknown proposer kind {kind!r}; valid: {', '.join(PROPOSER_SETTINGS)}"
    where = ".".join(str(p) for p in loc)
    more = f" (+{len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
    return f"{path}: {where + ': ' if where else ''}{msg}{more}"


def _check_overridden(path: Path, raw: dict, overrides: dict) -> None:
    """A recipe value that a command-line option replaces must still be valid: a wrong ``n:`` is a
    mistake in the file, not something ``--n`` may hide."""
    from pydantic import TypeAdapter

    for key in overrides.keys() & raw.keys():
        field = PipelineConfig.model_fields.get(key)
        if field is None:
            continue
        annotation = Annotated[(field.annotation, *field.metadata)] if field.metadata else field.annotation
        try:
            TypeAdapter(annotation).validate_python(raw[key])
        except ValidationError as exc:
            msg = exc.errors()[0]["msg"]
            option = "--" + key.replace("_", "-")
            where = f"{path}: {key}"
            raise ConfigError(f"{where}: {msg} (the recipe's own value, which {option} replaces)") from None


def load_pipeline(
    path: str | Path,
    overrides: dict | None = None,
    request: str | None = None,
    proposer: str | None = None,
) -> PipelineConfig:
    """Read, merge top-level ``overrides`` (e.g. n, seed) and validate a pipeline file.

    ``request``: free text (:func:`~scenegen.schema.condition.parse_request`) laid over the recipe's
    condition: the task, target and pose it names replace the recipe's, the tags it names are set.
    ``proposer``: another proposer kind, keeping the recipe's proposer settings that kind shares.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such pipeline file; bundled ones are in pipelines/")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        reason = f"not a UTF-8 text file (byte {exc.start}); a recipe is YAML text"
        raise ConfigError(f"{path}: {reason}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{path}:{line} not valid YAML: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{path}: a pipeline file must be a mapping of keys (name, n, seed, condition, ...)"
        )
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    _check_overridden(path, raw, overrides)
    raw.update(overrides)
    if request is not None:
        try:
            parsed = parse_request(request)
        except ValueError as exc:
            raise ConfigError(f"--request: {exc}") from None
        condition = dict(raw.get("condition") or {})
        condition["tags"] = {**(condition.get("tags") or {}), **parsed.pop("tags", {})}
        condition.update(parsed)
        raw["condition"] = condition
    if proposer is not None:
        settings = PROPOSER_SETTINGS.get(proposer)
        if settings is None:
            raise ConfigError(f"--proposer {proposer}: unknown kind; valid: {', '.join(PROPOSER_SETTINGS)}")
        shared = {k: v for k, v in (raw.get("proposer") or {}).items() if k in settings.model_fields}
        raw["proposer"] = {**shared, "kind": proposer}
    try:
        with using_catalogs(_catalog_paths(path, raw.get("catalogs"))):
            return PipelineConfig.model_validate(raw)
    except CatalogError as exc:
        raise ConfigError(f"{path}: catalogs: {exc}") from None
    except ConfigError:
        raise  # names the recipe already
    except ValidationError as exc:
        raise ConfigError(_blame_request(_format_error(path, exc), path, request)) from None
    except ValueError as exc:
        raise ConfigError(_blame_request(f"{path}: {exc}", path, request)) from None


def validate_config(raw: dict) -> PipelineConfig:
    """A recipe mapping (a stored pipeline.yaml, or a worker's copy) validated against its own
    ``catalogs``: the bundled catalog and the user catalogs it names."""
    catalogs = raw.get("catalogs") or []
    with using_catalogs([Path(c) for c in catalogs]):
        return PipelineConfig.model_validate(raw)


def _catalog_paths(path: Path, catalogs) -> list[Path]:
    """The ``catalogs`` key of a recipe as paths (ConfigError naming the key if it is not a list)."""
    if catalogs is None:
        return []
    if not isinstance(catalogs, list | tuple) or not all(isinstance(c, str) for c in catalogs):
        raise ConfigError(f"{path}: catalogs: a list of catalog files, e.g. [user_assets/catalog.yaml]")
    from scenegen.assets.catalog import is_bundled

    for c in catalogs:
        if is_bundled(Path(c)):
            raise ConfigError(
                f"{path}: catalogs: {c} is the bundled catalog, always in use; list only your own "
                "catalogs (e.g. [user_assets/catalog.yaml]), or leave catalogs out"
            )
    return [Path(c) for c in catalogs]


def _blame_request(message: str, path: Path, request: str | None) -> str:
    """A condition error after ``--request`` was laid over the recipe names the option too: the
    request may be what made the condition impossible."""
    if request is not None and message.startswith(f"{path}: condition"):
        return f"--request over {path}: " + message.removeprefix(f"{path}: ")
    return message
