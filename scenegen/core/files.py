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


def load_rows(path: Path, split: str | None = "train") -> list[dict]:
    """Rows (dicts) of a reference Parquet file, of one split (``train``, ``heldout``) or all (None)."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"split {split!r}: use one of {', '.join(SPLITS)}, or None for all rows")
    import pyarrow.parquet as pq

    rows = pq.read_table(path).to_pylist()
    return [row for row in rows if split is None or row["split"] == split]
