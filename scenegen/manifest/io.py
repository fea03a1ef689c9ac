"""Reading, writing and merging manifests. Every write is atomic: a reader (or a run killed at any
point) sees the previous manifest or the new one, never a part of either."""

from __future__ import annotations

import os
from pathlib import Path

import yaml
from pydantic import ValidationError

from scenegen.manifest.schema import SCHEMA_VERSION, Manifest, Source
from scenegen.store.batch import atomic_write

HEADER = (
    f"# scenegen data manifest, schema v{SCHEMA_VERSION} (scenegen/manifest/schema.py; JSON Schema: "
    "docs/manifest.schema.json).\n# Counts and checksums are derived from the files; `scenegen audit` "
    "verifies them.\n"
)


class ManifestError(ValueError):
    """A manifest cannot be read or merged; the message is one line naming the file and the field."""


def _where(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def validation_problems(exc: ValidationError) -> list[tuple[str, str]]:
    """(field path, message) of every error of a pydantic ValidationError, e.g.
    ``("recipes[0].alpha", "Input should be greater than or equal to 0")``."""
    return [(_where(err["loc"]), err["msg"].removeprefix("Value error, ")) for err in exc.errors()]


def load_manifest_data(path: Path) -> dict:
    """The raw mapping of a manifest YAML file (safe_load); ManifestError when it is not one."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ManifestError(f"{path}: no such manifest") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        raise ManifestError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ManifestError(f"{path}: not a data manifest (a mapping with schema_version, kind, sources)")
    if data.get("schema_version") != SCHEMA_VERSION:
        raise ManifestError(
            f"{path}: schema_version {data.get('schema_version')!r}; this scenegen reads v{SCHEMA_VERSION} "
            "(regenerate batch manifests by rerunning their `scenegen generate` command)"
        )
    return data


def read_manifest(path: Path) -> Manifest:
    """A validated manifest; ManifestError (one line, naming the first bad field) otherwise."""
    data = load_manifest_data(path)
    try:
        return Manifest.model_validate(data)
    except ValidationError as exc:
        where, msg = validation_problems(exc)[0]
        raise ManifestError(f"{path}: {where}: {msg}") from None


def dump_manifest(manifest: Manifest) -> str:
    """The YAML text of a manifest: fields in schema order, readable in a diff."""
    body = yaml.safe_dump(
        manifest.model_dump(mode="json", exclude_none=True), sort_keys=False, width=100, allow_unicode=True
    )
    return HEADER + body


def write_manifest(path: Path, manifest: Manifest) -> None:
    """Write ``manifest`` to ``path`` atomically (a temporary file, fsync, rename)."""
    atomic_write(Path(path), dump_manifest(manifest))


def inside(path: Path, root: Path) -> bool:
    """Whether ``path`` (resolved) lies inside ``root`` (resolved)."""
    try:
        Path(path).resolve().relative_to(Path(root).resolve())
    except ValueError:
        return False
    return True


def add_source(project: Path, source: Source, replace: bool = False) -> Manifest:
    """Add ``source`` (its ``location`` already relative to the project manifest's folder) to the
    project manifest at ``project``, atomically. A source of the same name is an error unless
    ``replace``."""
    manifest = read_manifest(project)
    if manifest.kind != "project":
        raise ManifestError(f"{project}: a {manifest.kind} manifest; add sources to the project manifest")
    names = [s.name for s in manifest.sources]
    if source.name in names and not replace:
        raise ManifestError(
            f"{project}: sources[{names.index(source.name)}] is already named {source.name!r}; "
            "pass --name NEW to add it beside, or --replace to replace it"
        )
    sources = [s for s in manifest.sources if s.name != source.name] + [source]
    manifest = manifest.model_copy(update={"sources": sources})
    write_manifest(project, Manifest.model_validate(manifest.model_dump()))
    return manifest


def relocate(source: Source, batch: Path, project: Path, name: str | None = None) -> Source:
    """A batch manifest's source as the project manifest at ``project`` names it: ``location``
    relative to the project manifest's folder, which must hold the batch."""
    folder = Path(project).resolve().parent
    target = (Path(batch) / source.location).resolve()
    if not inside(target, folder):
        raise ManifestError(
            f"{batch}: lies outside {folder}; a manifest may only name data inside its folder "
            "(move the batch under it; a link out of the folder counts as outside)"
        )
    location = os.path.relpath(target, folder)
    return source.model_copy(update={"location": location, "name": name or source.name})
