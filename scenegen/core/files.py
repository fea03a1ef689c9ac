"""Reading and hashing the project's files: the sha256 of a file, and the rows of a layout table
(the reference set's Parquet format, also that of imported real data). Standard library and pyarrow."""

from __future__ import annotations

import hashlib
from pathlib import Path

SPLITS = ("train", "heldout")


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
