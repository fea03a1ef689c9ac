"""The data manifest: schema (schema.py), entries derived from files (derive.py), atomic reading,
writing and merging (io.py) and the batch realism checks (realism_checks.py); ``scenegen audit``
verifies it (scenegen/audit/). docs/manifest.md describes the ledger; docs/manifest.schema.json is
its JSON Schema."""

from scenegen.manifest.io import (
    ManifestError,
    add_source,
    dump_manifest,
    read_manifest,
    relocate,
    write_manifest,
)
from scenegen.manifest.schema import (
    SCHEMA_VERSION,
    Counts,
    Manifest,
    RealismCheck,
    Source,
    TrainingRecipe,
)

__all__ = [
    "SCHEMA_VERSION",
    "Counts",
    "Manifest",
    "ManifestError",
    "RealismCheck",
    "Source",
    "TrainingRecipe",
    "add_source",
    "dump_manifest",
    "read_manifest",
    "relocate",
    "write_manifest",
]
