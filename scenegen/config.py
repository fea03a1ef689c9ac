"""Pipeline recipes: the validated YAML files in pipelines/.

A recipe names the request (condition), the proposer and its distributions, and the thresholds of
every stage. Unknown keys, tasks, targets, tags or impossible values are errors that name the field.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from scenegen.check.geometry import CheckSettings
from scenegen.propose.procedural import ProceduralSettings
from scenegen.schema.condition import Condition
from scenegen.settle import SettleSettings
from scenegen.tags import TagSettings


class ConfigError(ValueError):
    """A pipeline file is invalid; the message is one line naming the file and field."""


class PipelineConfig(BaseModel):
    """One pipeline recipe.

    Keys: ``name``; ``n`` accepted scenes wanted; ``seed``; ``max_proposals`` (give up after this
    many proposals, default 40 x n); ``condition`` (see :class:`Condition`); ``proposer``
    (``kind: procedural`` and its settings, cameras included); ``checks``; ``settle``; ``render``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    n: int = Field(20, ge=1, le=1_000_000)
    seed: int = Field(0, ge=0, lt=2**63)
    max_proposals: int | None = Field(None, ge=1)
    condition: Condition = Condition()
    proposer: ProceduralSettings = ProceduralSettings()
    checks: CheckSettings = CheckSettings()
    settle: SettleSettings = SettleSettings()
    tags: TagSettings = TagSettings()
    render: bool = True  # RGB, depth and segmentation per camera (``--no-render`` turns it off)

    @property
    def proposal_cap(self) -> int:
        return self.max_proposals or 40 * self.n

    def digest(self) -> str:
        """sha256 of the canonical JSON of the recipe (overrides included)."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()


def _fields_at(model: type[BaseModel], loc: tuple) -> list[str]:
    """Field names of the (nested) model at ``loc`` of a recipe."""
    for part in loc:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        annotation = getattr(field, "annotation", None)
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            break
        model = annotation
    return list(model.model_fields)


def _format_error(path: Path, exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        valid = ", ".join(_fields_at(PipelineConfig, err["loc"][:-1]))
        msg = f"unknown key; valid keys here: {valid} (docs/pipelines.md)"
    more = f" (+{len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
    return f"{path}: {where}: {msg}{more}"


def load_pipeline(path: str | Path, overrides: dict | None = None) -> PipelineConfig:
    """Read, merge top-level ``overrides`` (e.g. n, seed) and validate a pipeline file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such pipeline file; bundled ones are in pipelines/")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{path}:{line} not valid YAML: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{path}: a pipeline file must be a mapping of keys (name, n, seed, condition, ...)"
        )
    raw.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return PipelineConfig(**raw)
    except ValidationError as exc:
        raise ConfigError(_format_error(path, exc)) from None
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None
