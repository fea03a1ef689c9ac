"""Reading and hashing the project's files: the sha256 of a file, and the rows of a layout table
(the reference set's Parquet format, also that of imported real data). Standard library and pyarrow."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

SPLITS = ("train", "heldout")
SCENE_ID = re.compile(r"^scene_\d{6}$")  # a stored scene's folder name in its batch


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def folder_sha256(folder: Path) -> str:
    """One sha256 over every file under ``folder``: each file's relative path and sha256, sorted
    (temporary ``.tmp`` files left out). Symlinks are refused: a folder checksum covers its own files."""
    folder = Path(folder)
    lines = []
    for path in sorted(p for p in folder.rglob("*") if not p.name.endswith(".tmp")):
        if path.is_symlink():
            raise ValueError(f"{path}: a symlink; an artifact folder holds its own files")
        if path.is_file():
            lines.append(f"{path.relative_to(folder).as_posix()} {sha256_file(path)}")
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def load_rows(path: Path, split: str | None = "train") -> list[dict]:
    """Rows (dicts) of a reference Parquet file, of one split (``train``, ``heldout``) or all (None)."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"split {split!r}: use one of {', '.join(SPLITS)}, or None for all rows")
    import pyarrow.parquet as pq

    rows = pq.read_table(path).to_pylist()
    return [row for row in rows if split is None or row["split"] == split]


class CheckpointError(ValueError):
    """A checkpoint folder is missing, unreadable or not of the expected kind (one line)."""


def read_checkpoint_config(folder: Path, kind: str, remedy: str) -> dict:
    """The ``config.json`` object of a checkpoint folder (config.json + model.safetensors), after
    checking both files are there; CheckpointError naming the file otherwise. ``kind``: what the
    folder should hold (e.g. "generator"); ``remedy``: what the user can do (e.g. "retrain it")."""
    import json

    folder = Path(folder)
    if not folder.is_dir():
        raise CheckpointError(
            f"{folder}: not a {kind} checkpoint: no such folder (config.json + model.safetensors)"
        )
    config_path = folder / "config.json"
    for path in (config_path, folder / "model.safetensors"):
        if not path.is_file():
            raise CheckpointError(
                f"{path}: missing, so not a {kind} checkpoint (config.json + model.safetensors)"
            )
    try:
        config = json.loads(config_path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise CheckpointError(f"{config_path}: not UTF-8 JSON (byte {exc.start}); {remedy}") from None
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{config_path}: not readable JSON ({_first_line(exc)}); {remedy}") from None
    if not isinstance(config, dict):
        found = type(config).__name__
        raise CheckpointError(f"{config_path}: a JSON object expected, found {found}; {remedy}")
    return config


def checkpoint_error(path: Path, exc: BaseException, remedy: str) -> CheckpointError:
    """The one-line error for a checkpoint whose contents do not load (``exc``: why)."""
    why = f"{type(exc).__name__}: {_first_line(exc)[:120]}"
    return CheckpointError(f"{path}: does not load ({why}); {remedy}")


def names_field(config: dict, key: str, folder: Path, what: str) -> list[str]:
    """A checkpoint config's non-empty list of names under ``key``; CheckpointError otherwise."""
    value = config.get(key)
    if not (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
        raise CheckpointError(f"{Path(folder) / 'config.json'}: {key}: a list of {what} names expected")
    return value


def int_field(config: dict, key: str, folder: Path, low: int, high: int) -> int:
    """A checkpoint config's integer under ``key`` in [low, high]; CheckpointError otherwise."""
    value = config.get(key)
    if not (isinstance(value, int) and low <= value <= high):
        raise CheckpointError(
            f"{Path(folder) / 'config.json'}: {key}: an integer from {low} to {high} expected"
        )
    return value


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class OutsideRootError(ValueError):
    """A path read from a data file leads out of that file's root (``..``, an absolute path, a symlink)."""


def confined(path: Path, root: Path, what: str = "it") -> Path:
    """``path`` when it lies inside ``root`` once both are resolved (symlinks followed); otherwise
    OutsideRootError naming the path: data files may name only files under their own root."""
    path, root = Path(path), Path(root)
    try:
        path.resolve().relative_to(root.resolve())
    except ValueError:
        raise OutsideRootError(
            f"{path}: {what} lies outside {root} ('..', absolute or a symlink); refused"
        ) from None
    return path
