"""``scenegen audit``: trust nothing in a manifest, verify everything against the files.

For each source: its location lies inside the manifest's folder and exists; counts are recounted
(scene directories, index rows, rejection-log rows and labels, table rows and splits); checksums are
recomputed along the chain (every file a scene.json lists, every scene.json against its index row,
the index, rejection log and recipe against the manifest, the root); the recipe file is present and
its digest matches; predicate versions agree (source, every scene, checkpoint, this scenegen);
checkpoint hashes match their files; the required realism checks are present, passing and computed
on the batch whose checksum they record. Then models, training recipes (sources exist, roles fit
their origins, alpha and effective shares recomputed) and the transfer section.

Every violation is collected (none stops the audit) with where it is and what is wrong.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pydantic import ValidationError

from scenegen.audit import IMAGE_SAMPLE
from scenegen.audit.files import audit_batch, audit_table
from scenegen.manifest.derive import effective_shares
from scenegen.manifest.io import ManifestError, inside, load_manifest_data, validation_problems
from scenegen.manifest.schema import REQUIRED_REALISM, CheckpointRef, Manifest, Source
from scenegen.paths import PROJECT_ROOT
from scenegen.store.batch import sha256_file

REFERENCE_ORIGINS = {"real": ("real", "reference"), "synthetic": ("synthetic",)}


@dataclass(frozen=True)
class Finding:
    """One violation or warning: ``where`` it is (a manifest path and, inside a source, a file),
    which ``check`` found it, and what is wrong."""

    where: str
    check: str
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message} [{self.check}]"


@dataclass
class AuditReport:
    """What an audit verified (``verified``: one line per entry), its violations and warnings."""

    manifest: str
    kind: str = ""
    verified: list[str] = field(default_factory=list)
    violations: list[Finding] = field(default_factory=list)
    warnings: list[Finding] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.violations

    def to_json(self) -> str:
        return json.dumps(
            {
                "manifest": self.manifest,
                "kind": self.kind,
                "ok": self.ok,
                "verified": self.verified,
                "violations": [asdict(v) for v in self.violations],
                "warnings": [asdict(w) for w in self.warnings],
            },
            indent=1,
        )

    def to_text(self) -> str:
        lines = [f"scenegen audit {self.manifest} ({self.kind or 'unreadable'} manifest)"]
        lines += [f"  ok  {line}" for line in self.verified]
        if self.warnings:
            lines.append(f"warnings ({len(self.warnings)}):")
            lines += [f"  {w}" for w in self.warnings]
        if self.violations:
            lines.append(f"violations ({len(self.violations)}):")
            lines += [f"  {v}" for v in self.violations]
        lines.append("PASSED" if self.ok else f"FAILED: {len(self.violations)} violation(s)")
        return "\n".join(lines)


class _Audit:
    def __init__(
        self, path: Path, workers: int = 1, backend=None, image_sample: int | None = IMAGE_SAMPLE, seed=0
    ):
        from scenegen.runner.executors import LOCAL

        self.path = Path(path)
        self.folder = self.path.resolve().parent
        self.report = AuditReport(str(path))
        self._hashes: dict[str, str] = {}
        # where a batch's per-scene checks run (audit/scenes.py), and how many scenes' images the
        # image check decodes (None: all), drawn by which seed
        self.workers, self.backend = workers, backend or LOCAL
        self.image_sample, self.sample_seed = image_sample, seed

    def file_sha256(self, path: Path) -> str:
        # every scene lists the batch's shared _assets/ files: hash each once per audit
        key = str(path.resolve())
        if key not in self._hashes:
            self._hashes[key] = sha256_file(path)
        return self._hashes[key]

    def violation(self, where: str, check: str, message: str) -> None:
        self.report.violations.append(Finding(where, check, message))

    def warning(self, where: str, check: str, message: str) -> None:
        self.report.warnings.append(Finding(where, check, message))

    # ------------------------------------------------------------------------ the manifest

    def run(self) -> AuditReport:
        try:
            data = load_manifest_data(self.path)
        except ManifestError as exc:
            self.violation("(manifest)", "schema", str(exc).removeprefix(f"{self.path}: "))
            return self.report
        try:
            manifest = Manifest.model_validate(data)
        except ValidationError as exc:
            for where, msg in validation_problems(exc):
                self.violation(where, "schema", msg)
            return self.report
        self.report.kind = manifest.kind
        from scenegen.tags.predicates import PREDICATE_VERSION

        self.predicate_version = PREDICATE_VERSION
        for i, source in enumerate(manifest.sources):
            self.source(f"sources[{i}] {source.name}", source)
        self.duplicates(manifest)
        for i, model in enumerate(manifest.models):
            where = f"models[{i}] {model.name}"
            ok = self.checkpoint(where, model.checkpoint)
            if model.recipe not in {r.name for r in manifest.recipes}:
                self.violation(
                    where, "recipe", f"recipe {model.recipe!r} is not among the manifest's recipes"
                )
            elif ok:
                self.report.verified.append(f"{where}: checkpoint {model.checkpoint.path} hashes match")
        for i, recipe in enumerate(manifest.recipes):
            self.recipe(f"recipes[{i}] {recipe.name}", recipe, manifest)
        transfer = manifest.transfer
        if transfer is not None:
            if transfer.recipe is not None and transfer.recipe not in {r.name for r in manifest.recipes}:
                self.violation("transfer", "recipe", f"recipe {transfer.recipe!r} is not in the manifest")
            elif transfer.artifact is None or self.artifact(transfer.artifact, transfer.artifact_sha256):
                self.report.verified.append(f"transfer: {transfer.status}, panel {transfer.panel}")
        return self.report

    def artifact(self, location: str, expected: str | None) -> bool:
        """The transfer experiment's artifact folder: inside the manifest's folder, and its files
        hash to the recorded checksum."""
        from scenegen.core.files import folder_sha256

        folder = self.folder / location
        if not inside(folder, self.folder) or not folder.is_dir():
            self.violation(
                "transfer", "artifact", f"artifact {location} is not a folder inside {self.folder}"
            )
            return False
        try:
            found = folder_sha256(folder)
        except ValueError as exc:
            self.violation("transfer", "artifact", str(exc))
            return False
        if found != expected:
            self.violation(
                "transfer",
                "artifact_sha256",
                f"the files of {location} hash to {found[:12]}, not {str(expected)[:12]}",
            )
            return False
        self.report.verified.append(f"transfer: artifact {location} hashes to its recorded checksum")
        return True

    # ------------------------------------------------------------------------ sources

    def source(self, where: str, source: Source) -> None:
        location = self.folder / source.location
        if not inside(location, self.folder):
            self.violation(where, "location", f"location {source.location} lies outside {self.folder}")
            return
        if not location.exists():
            self.violation(where, "location", f"location {source.location} does not exist")
            return
        before = len(self.report.violations)
        if source.predicate_version is not None and source.predicate_version != self.predicate_version:
            self.violation(
                where,
                "predicate_version",
                f"tags measured by predicates {source.predicate_version}, this scenegen's are "
                f"{self.predicate_version}: re-tag the source or audit with the scenegen that made it",
            )
        if source.generator is not None and source.generator.checkpoint is not None:
            self.checkpoint(f"{where}.generator", source.generator.checkpoint, source.predicate_version)
        try:
            if source.checksums.kind == "file":
                audit_table(self, where, source, location)
            else:
                audit_batch(self, where, source, location)
        except Exception as exc:  # noqa: BLE001 - whatever is malformed is a violation, never a traceback
            self.violation(where, "unreadable", f"{type(exc).__name__}: {exc}"[:300])
        self.realism(where, source)
        if len(self.report.violations) == before:
            self.report.verified.append(
                f"{where}: {source.origin}, {source.counts.scenes} samples recounted, checksums and "
                f"{len(source.realism)} realism check(s) verified"
            )

    def duplicates(self, manifest: Manifest) -> None:
        """The same data counted twice: two sources at one location, or with one checksum root."""
        seen: dict[str, str] = {}
        for i, source in enumerate(manifest.sources):
            keys = [str((self.folder / source.location).resolve())]
            keys.append(
                source.checksums.root if source.checksums.kind == "batch" else source.checksums.sha256
            )
            for key in keys:
                if key in seen:
                    self.violation(
                        f"sources[{i}] {source.name}",
                        "duplicate",
                        f"the same data as {seen[key]} (location or checksum): it would count twice",
                    )
                    break
                seen[key] = f"sources[{i}] {source.name}"

    # ------------------------------------------------------------------------ provenance

    def checkpoint(self, where: str, ref: CheckpointRef, predicate_version: str | None = None) -> bool:
        directory = Path(ref.path) if Path(ref.path).is_absolute() else PROJECT_ROOT / ref.path
        ok = True
        for name, sha in (("model.safetensors", ref.sha256), ("config.json", ref.config_sha256)):
            path = directory / name
            if not path.is_file():
                self.violation(f"{where}: {ref.path}/{name}", "provenance", "checkpoint file missing")
                ok = False
            elif sha256_file(path) != sha:
                self.violation(
                    f"{where}: {ref.path}/{name}", "provenance", "sha256 differs: not the checkpoint recorded"
                )
                ok = False
        if ok:
            try:
                stamped = json.loads((directory / "config.json").read_text()).get("predicate_version")
            except (ValueError, AttributeError):
                self.violation(f"{where}: {ref.path}/config.json", "provenance", "not a JSON mapping")
                return False
            for what, version in (
                ("the manifest's entry", ref.predicate_version),
                ("the source", predicate_version),
            ):
                if version is not None and stamped != version:
                    self.violation(
                        where,
                        "predicate_version",
                        f"checkpoint trained on tags of predicates {stamped}, {what} says {version}",
                    )
                    ok = False
        return ok

    def realism(self, where: str, source: Source) -> None:
        required = list(REQUIRED_REALISM) + (["image_stats"] if source.rendered else [])
        present = Counter(check.metric for check in source.realism)
        if source.origin == "synthetic":
            for metric in required:
                if not present[metric]:
                    self.violation(where, "realism", f"realism check {metric} is missing")
        root = source.checksums.root if source.checksums.kind == "batch" else source.checksums.sha256
        for i, check in enumerate(source.realism):
            at = f"{where}.realism[{i}] {check.metric}"
            if present[check.metric] > 1:
                self.violation(at, "realism", f"{check.metric} appears {present[check.metric]} times")
            if check.batch_sha256 != root:
                self.violation(
                    at,
                    "realism",
                    "computed on another batch (batch_sha256 is not this source's checksum root); "
                    "recompute it",
                )
            reference = PROJECT_ROOT / check.reference.source
            if not reference.is_file():
                self.violation(at, "realism", f"its reference {check.reference.source} is missing")
            elif self.file_sha256(reference) != check.reference.sha256:
                self.violation(
                    at, "realism", f"computed against another {check.reference.source}: recompute it"
                )
            if check.status == "failed":
                self.violation(
                    at,
                    "realism",
                    f"failed: {check.value:.4g} is not {check.comparison} {check.threshold:.4g}",
                )
            elif check.status == "insufficient":
                batch, why = check.samples.get("batch", 0), check.details.get("note", "")
                reason = (
                    why if batch >= check.min_samples else f"only {batch} samples (< {check.min_samples})"
                )
                self.warning(at, "realism", f"{reason}: recorded, not judged")

    # ------------------------------------------------------------------------ recipes

    def recipe(self, where: str, recipe, manifest: Manifest) -> None:
        sources = {s.name: s for s in manifest.sources}
        sizes = {}
        before = len(self.report.violations)
        for j, component in enumerate(recipe.components):
            at = f"{where}.components[{j}]"
            source = sources.get(component.source)
            if source is None:
                self.violation(at, "recipe", f"source {component.source!r} is not in the manifest")
                continue
            if source.origin not in REFERENCE_ORIGINS[component.role]:
                self.violation(
                    at,
                    "recipe",
                    f"a {source.origin} source cannot feed the {component.role} term of the loss",
                )
            if component.split is None:
                sizes[component.source] = source.counts.scenes
            elif source.counts.splits is None or component.split not in source.counts.splits:
                self.violation(at, "recipe", f"source {component.source!r} has no split {component.split!r}")
            else:
                sizes[component.source] = source.counts.splits[component.split]
        if len(self.report.violations) > before:
            return
        expected = effective_shares(recipe.alpha, recipe.components, sizes)
        if set(expected) != set(recipe.effective_shares) or any(
            abs(expected[k] - recipe.effective_shares[k]) > 1e-6 for k in expected
        ):
            self.violation(
                where,
                "recipe",
                f"effective_shares {recipe.effective_shares} do not follow from alpha: {expected}",
            )
        else:
            self.report.verified.append(f"{where}: alpha {recipe.alpha}, shares {expected}")


def audit(
    path: Path, workers: int = 1, backend=None, image_sample: int | None = IMAGE_SAMPLE, seed: int = 0
) -> AuditReport:
    """Audit the manifest at ``path`` against the files it describes; see the module docstring.
    ``workers`` and ``backend`` (runner/executors.py, default this process): where a batch's
    per-scene checks run; ``image_sample``: the scenes of a larger rendered batch, drawn by ``seed``,
    whose images are decoded for its image check (None: every scene's; every file's checksum is
    verified anyway)."""
    return _Audit(path, workers, backend, image_sample, seed).run()
