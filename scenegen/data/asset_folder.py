"""``scenegen assets add DIR``: every mesh file of a folder imported into a user catalog.

What each file is (category, units or scale, mass, ...) comes from a sidecar (``--sidecar``: YAML, a
mapping of file name to its keys, or CSV with a ``file`` column and one column per key) over the
flags given for all. The costly half of each import (mesh repair, convex parts, drops) runs on
``workers`` processes; the coordinator lists the staged assets one at a time, in the files' order,
so the catalog is the same for any worker count and each listing is atomic as a single import's: a
run killed midway leaves a catalog of exactly the assets whose imports completed. A file whose
asset the catalog already holds from the same bytes is skipped as present, so rerunning a killed
command finishes it.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from scenegen.assets.catalog import CatalogError, catalog_file, load_catalog
from scenegen.core.files import OutsideRootError, confined, sha256_file
from scenegen.data.asset_import import ImportOptions, commit_asset, default_name, stage_asset
from scenegen.data.asset_meshes import FORMATS, UNITS, MeshImportError

Outcome = Literal["imported", "refused", "skipped"]


class SidecarError(ValueError):
    """A sidecar that cannot be read or names what the folder does not hold; one line."""


class SidecarRow(BaseModel):
    """What a sidecar may say about one file; a key left out takes the command's flag."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    category: str | None = None
    name: str | None = None
    units: Literal["mm", "cm", "m"] | None = None
    scale: float | None = None
    mass: float | None = None
    density: float | None = None
    friction: float | None = None
    up: Literal["z", "y"] | None = None
    texture: str | None = None
    collision: Literal["auto", "hull"] | None = None

    @field_validator("*", mode="before")
    @classmethod
    def _blank_is_unset(cls, value):
        if isinstance(value, bool):  # YAML's true/yes would otherwise pass as 1.0
            raise ValueError(f"{value!r} is not a value for this key")
        return None if isinstance(value, str) and not value.strip() else value  # an empty CSV cell


@dataclass(frozen=True)
class FolderRow:
    """One file's outcome: ``imported`` (``detail``: the import's notes), ``refused`` (``detail``
    says why) or ``skipped`` (its asset already listed from the same bytes)."""

    file: str
    outcome: Outcome
    asset: str = ""
    detail: str = ""


def mesh_files(folder: Path) -> list[Path]:
    """The mesh files at the top of ``folder`` (the formats ``assets add`` reads), sorted by name."""
    if not folder.is_dir():
        raise SidecarError(f"{folder}: not a folder")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FORMATS)
    if not files:
        raise SidecarError(f"{folder}: holds no mesh file ({', '.join(FORMATS)})")
    return files


def read_sidecar(path: Path, folder: Path) -> dict[str, SidecarRow]:
    """``path``'s rows by file name; each must name a mesh file of ``folder``."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # a spreadsheet's CSV may start with a BOM
    except (OSError, UnicodeDecodeError) as exc:
        raise SidecarError(f"--sidecar {path}: cannot be read ({exc.__class__.__name__})") from exc
    if Path(path).suffix.lower() == ".csv":
        rows = list(csv.DictReader(io.StringIO(text)))
        if rows and "file" not in rows[0]:
            raise SidecarError(f"--sidecar {path}: needs a `file` column (then category, mass, ...)")
        raw = {}
        for line, row in enumerate(rows, start=2):
            file = row.pop("file")
            if file in raw:
                raise SidecarError(f"--sidecar {path}: line {line} names {file!r} a second time")
            raw[file] = row
    else:
        try:
            raw = yaml.load(text, Loader=_UniqueKeys) or {}
        except yaml.MarkedYAMLError as exc:
            where = f"line {exc.problem_mark.line + 1}: " if exc.problem_mark else ""
            raise SidecarError(f"--sidecar {path}: not YAML ({where}{exc.problem})") from exc
        except yaml.YAMLError as exc:
            raise SidecarError(f"--sidecar {path}: not YAML ({exc.__class__.__name__})") from exc
        if not isinstance(raw, dict) or not all(isinstance(v, dict) for v in raw.values()):
            raise SidecarError(f"--sidecar {path}: must map each file name to its keys (category: ...)")
    present = {p.name for p in mesh_files(folder)}
    rows = {}
    for file, keys in raw.items():
        if str(file) not in present:
            raise SidecarError(f"--sidecar {path}: {file!r} is not a mesh file of {folder}")
        try:
            rows[str(file)] = SidecarRow(**keys)
        except (ValidationError, TypeError) as exc:
            raise SidecarError(f"--sidecar {path}: {file}: {_pydantic_line(exc)}") from exc
    return rows


def folder_options(
    folder: Path, flags: ImportOptions, sidecar: dict[str, SidecarRow]
) -> list[tuple[Path, ImportOptions | str]]:
    """Each mesh file with its import options (a sidecar row over the flags), or why it cannot be
    imported as given."""
    jobs: list[tuple[Path, ImportOptions | str]] = []
    for mesh in mesh_files(folder):
        row = sidecar.get(mesh.name, SidecarRow()).model_dump(exclude_none=True)
        if "texture" in row:
            try:
                row["texture"] = confined(folder / row["texture"], folder, "the sidecar's texture")
            except OutsideRootError as exc:
                jobs.append((mesh, str(exc)))
                continue
        if "units" in row or "scale" in row:  # a row's size replaces the flags' size
            row = {"units": None, "scale": None, **row}
        if "mass" in row or "density" in row:
            row = {"mass": None, "density": None, **row}
        options = replace(flags, **row)
        if not options.category:
            jobs.append((mesh, "no category: give --category or a sidecar row with one"))
        elif options.units is not None and options.scale is not None:
            jobs.append((mesh, "units and scale both given: give one"))
        else:
            jobs.append((mesh, options))
    return jobs


def import_meshes(
    jobs: Sequence[tuple[Path, ImportOptions | str]],
    catalog: Path,
    workers: int = 1,
    on_row: Callable[[FolderRow], None] | None = None,
) -> list[FolderRow]:
    """Import each (mesh, options) job into ``catalog``: stage on ``workers`` processes, list in the
    jobs' order. A job whose options are a string is refused with it; one whose asset the catalog
    holds from the same file bytes is skipped. ``on_row`` sees each row as it is decided."""
    from scenegen.runner.executors import ordered_map

    target = catalog_file(catalog)
    rows: list[FolderRow] = []
    staged_jobs = []
    for mesh, options in jobs:
        early = _decided_early(mesh, options, target)
        if early is None:
            staged_jobs.append((mesh, options, target))
        rows.append(early)
    staged = ordered_map(_stage_job, list(staged_jobs), workers)
    pending = iter(staged_jobs)
    try:
        for i, row in enumerate(rows):
            if row is None:
                rows[i] = row = _commit(next(pending)[0], next(staged), target)
            if on_row is not None:
                on_row(row)
    finally:
        staged.close()  # stops the workers
    return rows


def _decided_early(mesh: Path, options: ImportOptions | str, target: Path) -> FolderRow | None:
    """The row of a job that needs no import: refused as given, or skipped as present."""
    if isinstance(options, str):
        return FolderRow(mesh.name, "refused", detail=options)
    name = options.name or default_name(mesh)
    if target.is_file():
        listed = load_catalog(target).by_name.get(name)
        if listed is not None and listed.source and listed.source.sha256 == sha256_file(mesh):
            changed = _changed(listed, options)
            if changed:  # a sidecar or flag fixed since: a skip would keep the old values
                return FolderRow(
                    mesh.name,
                    "refused",
                    name,
                    f"{name} is in {target} from these bytes with another {', '.join(changed)}; remove it "
                    "from the catalog or give another name",
                )
            return FolderRow(mesh.name, "skipped", name, f"already in {target}")
    return None


def _changed(listed, options: ImportOptions) -> list[str]:
    """What ``options`` set otherwise than the listed asset was imported with."""
    changed = []
    if listed.category != options.category:
        changed.append("category")
    if abs(listed.source.scale - float(options.scale or UNITS[options.units or "m"])) > 1e-12:
        changed.append("units or scale")
    if listed.source.up != options.up:
        changed.append("up axis")
    if options.mass is not None and abs(listed.mass - options.mass) > 1e-4 * options.mass:  # density rounds
        changed.append("mass")
    if options.density is not None and abs(listed.density - options.density) > 1e-3:
        changed.append("density")
    return changed


def _stage_job(job: tuple[Path, ImportOptions, Path]):
    """A worker's half: the staged asset, or the one-line reason it was refused."""
    mesh, options, target = job
    try:
        return stage_asset(mesh, options, target, log=_silent)
    except (MeshImportError, CatalogError, OSError, ValueError) as exc:
        return str(exc).strip()


def _commit(mesh: Path, staged, target: Path) -> FolderRow:
    if isinstance(staged, str):
        return FolderRow(mesh.name, "refused", detail=staged)
    try:
        result = commit_asset(staged, target)
    except (CatalogError, OSError) as exc:
        return FolderRow(mesh.name, "refused", staged.name, str(exc).strip())
    notes = "; ".join(result.notes)
    return FolderRow(mesh.name, "imported", result.asset.name, notes)


class _UniqueKeys(yaml.SafeLoader):
    """safe_load's loader, refusing a mapping that names a key twice (safe_load keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"{key!r} named a second time", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _pydantic_line(exc: Exception) -> str:
    if isinstance(exc, ValidationError):
        error = exc.errors()[0]
        return f"{'.'.join(str(p) for p in error['loc'])}: {error['msg']}"
    return str(exc)


def _silent(*_args, **_kwargs) -> None:
    """Workers print nothing: the coordinator's table says what each did."""
