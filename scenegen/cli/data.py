"""Data commands: `reference`, `coverage`, `import-real`, `audit`, `manifest add`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenegen.cli.common import add_backend_arguments, backend_from, fail, first_line


def add_commands(sub) -> None:
    """The data subcommands."""
    _add_reference(sub)
    _add_coverage_and_import(sub)
    _add_audit_and_manifest(sub)
    _add_reference_images(sub)


def _add_reference(sub) -> None:
    ref = sub.add_parser(
        "reference",
        help="build the reference dataset (stand-in for real data) as Parquet",
        description="Procedural layouts through check, settle and tag (no rendering), one Parquet row per "
        "accepted layout with its request, layout, lighting and every tag's measurement; every fifth "
        "layout is held out. The bundled one: assets/reference/reference.parquet.",
    )
    ref.add_argument("pipeline", type=Path, nargs="?", default=Path("pipelines/reference.yaml"))
    ref.add_argument("--n", type=int, help="accepted layouts (overrides the recipe's n)")
    ref.add_argument("--seed", type=int, help="seed (overrides the recipe's seed)")
    ref.add_argument("--out", type=Path, default=Path("assets/reference/reference.parquet"))
    ref.add_argument(
        "--workers", type=int, default=1, help="processes (or Ray actors) for check/settle/tag (default 1)"
    )
    add_backend_arguments(ref)
    ref.add_argument("--quiet", action="store_true", help="no progress bar")
    ref.add_argument(
        "--manifest",
        type=Path,
        help="also register the table in this project manifest (origin reference), e.g. data_manifest.yaml",
    )
    ref.set_defaults(run=reference)


def _add_coverage_and_import(sub) -> None:
    from scenegen.data import CHART_NAME, SPARSE_COUNT  # not coverage.py: --help stays cheap

    cov = sub.add_parser(
        "coverage",
        help="(task x tag) histogram of a dataset, batch or manifest; marks sparse cells",
        description="Scenes per (task x tag) of a dataset, sparse cells marked, and a bar chart (PNG).",
    )
    cov.add_argument(
        "source", type=Path, help="reference/real Parquet table, batch directory, or manifest YAML"
    )
    cov.add_argument(
        "--out", type=Path, help=f"PNG bar chart to write (default: {CHART_NAME} next to SOURCE)"
    )
    cov.add_argument(
        "--sparse",
        type=int,
        default=SPARSE_COUNT,
        help=f"a cell with fewer scenes is sparse (default {SPARSE_COUNT}; so is one under 1%% of all)",
    )
    cov.set_defaults(run=coverage)

    imp = sub.add_parser(
        "import-real",
        help="import real scenes from the documented JSON format (docs/real_data.md); tags recomputed",
        description="Import measured real scenes (docs/real_data.md) into a Parquet table, tags "
        "recomputed at the measured poses.",
    )
    imp.add_argument("file", type=Path, help="JSON file of measured scenes (format: docs/real_data.md)")
    imp.add_argument("--out", type=Path, required=True, help="Parquet file to write (atomically)")
    imp.set_defaults(run=import_real)


def _add_audit_and_manifest(sub) -> None:
    from scenegen.audit import IMAGE_SAMPLE  # a number: --help stays cheap

    aud = sub.add_parser(
        "audit",
        help="verify a data manifest against its files (counts, checksums, provenance, realism)",
        description=(
            "Trust nothing in a manifest: recount files, recompute checksums, compare counts with batch "
            "indexes and rejection logs, check recipes and alpha, realism checks (present, passing, "
            "computed on the batch they name), predicate versions and checkpoint hashes. Exit 0 when "
            "everything holds, 1 with every violation named and located (an unreadable or invalid manifest "
            "included), 2 when the file does not exist."
        ),
    )
    aud.add_argument(
        "manifest",
        type=Path,
        nargs="?",
        default=Path("data_manifest.yaml"),
        help="a project manifest or a batch's manifest.yaml (default: data_manifest.yaml here)",
    )
    aud.add_argument("--json", action="store_true", help="the report as JSON on stdout")
    aud.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes (or Ray actors) checking a batch's scenes (default 1)",
    )
    add_backend_arguments(aud)
    aud.add_argument(
        "--image-sample",
        default=str(IMAGE_SAMPLE),
        metavar="N|all",
        help=f"a rendered batch of more than N scenes (default {IMAGE_SAMPLE}) has its image check judged "
        "on the images of N scenes drawn by --sample-seed (the rule is printed); 'all' decodes every "
        "image. Every file's checksum is verified whatever N is",
    )
    aud.add_argument("--sample-seed", type=int, default=0, help="seed of that sample (default 0)")
    aud.set_defaults(run=audit)

    man = sub.add_parser("manifest", help="add a batch to the project manifest (after auditing it)")
    man_sub = man.add_subparsers(dest="manifest_command", metavar="ACTION", required=True)
    add = man_sub.add_parser(
        "add",
        help="merge a batch's manifest.yaml into the project manifest, atomically",
        description=(
            "Audit BATCH/manifest.yaml, then add its source to the project manifest with its location "
            "relative to the project manifest's folder (which must hold the batch). Nothing is written "
            "when the batch fails its audit."
        ),
    )
    add.add_argument("batch", type=Path, help="batch directory written by `scenegen generate`")
    add.add_argument("--to", type=Path, default=Path("data_manifest.yaml"), help="project manifest")
    add.add_argument("--name", help="source name (default: the batch's recipe name)")
    add.add_argument("--replace", action="store_true", help="replace a source of the same name")
    add.set_defaults(run=manifest)
    refresh = man_sub.add_parser(
        "refresh",
        help="re-derive the project manifest's reference, model and recipe entries from the files",
        description=(
            "Re-derive data_manifest.yaml's entries for the reference set, the shipped checkpoint and its "
            "training recipe from the files, keep every other source, the datasheet and the transfer "
            "section, and re-export docs/manifest.schema.json."
        ),
    )
    refresh.add_argument("manifest", type=Path, nargs="?", default=Path("data_manifest.yaml"))
    refresh.set_defaults(run=manifest_refresh)


def _add_reference_images(sub) -> None:
    images = sub.add_parser(
        "reference-images",
        help="render the first N reference layouts; their image statistics are the image check's reference",
        description=(
            "Render the first N accepted layouts of the reference set exactly as its recipe makes them and "
            "write their image statistics (scenegen/analysis/image_stats.py) as JSON: the reference of the "
            "image_stats realism check. The bundled one: assets/reference/image_stats.json."
        ),
    )
    images.add_argument("--n", type=int, default=60, help="reference layouts to render (default 60)")
    images.add_argument("--out", type=Path, default=Path("assets/reference/image_stats.json"))
    images.add_argument("--workers", type=int, default=1, help="rendering processes (default 1)")
    images.add_argument("--recipe", type=Path, default=Path("pipelines/reference.yaml"))
    images.add_argument("--reference", type=Path, default=Path("assets/reference/reference.parquet"))
    images.add_argument("--images", type=Path, help="also write the RGB images here (PNG)")
    images.set_defaults(run=reference_images)


def reference(args: argparse.Namespace) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.runner.config import ConfigError, load_pipeline
    from scenegen.runner.executors import BackendError

    try:
        backend = backend_from(args)
        overrides = {"n": args.n, "seed": args.seed, "render": False, "sensor": "exact"}
        config = load_pipeline(args.pipeline, overrides)
    except (ConfigError, CatalogError, BackendError) as exc:
        return fail(str(exc))
    if args.workers < 1:
        return fail(f"--workers {args.workers}: must be at least 1")
    from scenegen.data.reference import build_reference, read_reference, tag_rates
    from scenegen.runner.executors import backend_session

    try:
        with backend_session(backend, args.workers):
            stats = build_reference(config, args.out, args.workers, not args.quiet, backend)
    except BackendError as exc:
        return fail(str(exc))
    table, _ = read_reference(args.out)
    print(f"{stats['rows']} layouts of {stats['proposals']} proposals -> {args.out}")
    print("tag rates: " + ", ".join(f"{t} {c} ({r:.1%})" for t, (c, r) in tag_rates(table).items()))
    if args.manifest:
        from scenegen.data.reference import reference_source
        from scenegen.manifest import ManifestError, add_source

        try:
            add_source(args.manifest, reference_source(args.out, args.manifest.parent), replace=True)
        except ManifestError as exc:
            return fail(str(exc))
        print(f"registered as source 'reference' in {args.manifest}")
    return 0


def coverage(args: argparse.Namespace) -> int:
    """``scenegen coverage``: print the table, write the chart; a one-line error and 2 on a bad source."""
    from scenegen.data.coverage import CoverageError, coverage_table, default_chart_path

    if args.sparse < 0:
        return fail(f"--sparse {args.sparse}: must be at least 0")
    chart = args.out or default_chart_path(args.source)
    try:
        table = coverage_table(args.source, sparse=args.sparse)
        out = table.bar_chart(chart)
    except CoverageError as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"{chart}: {first_line(exc)}")
    print(table.format_table())
    print(f"chart: {out}")
    return 0


def import_real(args: argparse.Namespace) -> int:
    """``scenegen import-real``: summary on stdout; a one-line error on stderr and 2 on a bad file."""
    from scenegen.data.importer import SUPPORT_GAP, ImportFormatError
    from scenegen.data.importer import import_real as run_import

    try:
        stats = run_import(args.file, args.out)
    except ImportFormatError as exc:
        return fail(str(exc))
    print(f"{stats['rows']} real scenes from {args.file} -> {stats['out']} ({stats['seconds']:.1f} s)")
    print("tags: " + ", ".join(f"{t} {c}" for t, c in stats["tags"].items()))
    if stats["unsupported"]:
        print(
            f"scenegen: warning: no support surface within {SUPPORT_GAP:g} m below: "
            + ", ".join(stats["unsupported"]),
            file=sys.stderr,
        )
    return 0


def audit(args: argparse.Namespace) -> int:
    from scenegen.audit.manifest import audit
    from scenegen.runner.executors import BackendError

    if not args.manifest.is_file():
        return fail(
            f"{args.manifest}: no such manifest (give a data_manifest.yaml or a batch's manifest.yaml)"
        )
    sample = None if args.image_sample == "all" else args.image_sample
    if sample is not None and not (sample.isdigit() and int(sample) >= 2):
        return fail(f"--image-sample {args.image_sample!r}: give a number of scenes, at least 2, or 'all'")
    if args.workers < 1:
        return fail("--workers must be at least 1")
    try:
        backend = backend_from(args)
    except (BackendError, ValueError) as exc:
        return fail(first_line(exc))
    sample = None if sample is None else int(sample)
    report = audit(args.manifest, args.workers, backend, sample, args.sample_seed)
    print(report.to_json() if args.json else report.to_text())
    return 0 if report.ok else 1


def manifest(args: argparse.Namespace) -> int:
    from scenegen.audit.manifest import audit
    from scenegen.manifest import ManifestError, add_source, read_manifest, relocate

    batch_manifest = args.batch / "manifest.yaml"
    if not batch_manifest.is_file():
        return fail(f"{batch_manifest}: missing; is {args.batch} a batch written by `scenegen generate`?")
    report = audit(batch_manifest)
    if not report.ok:
        more = len(report.violations) - 1
        return fail(
            f"{args.batch}: fails its audit, nothing was added: {report.violations[0]}"
            + (f" (+{more} more)" if more else "")
            + f"; see `scenegen audit {batch_manifest}`"
        )
    try:
        (source,) = read_manifest(batch_manifest).sources
        source = relocate(source, args.batch, args.to, args.name)
        add_source(args.to, source, replace=args.replace)
    except ManifestError as exc:
        return fail(str(exc))
    print(f"added source {source.name!r} ({source.counts.scenes} scenes, {source.location}) to {args.to}")
    return 0


def manifest_refresh(args: argparse.Namespace) -> int:
    from scenegen.data.project_manifest import refresh
    from scenegen.manifest import ManifestError

    try:
        path = refresh(args.manifest)
    except ManifestError as exc:
        return fail(f"{exc}; fix it first (nothing was written)")
    print(f"wrote {path} and docs/manifest.schema.json")
    return 0


def reference_images(args: argparse.Namespace) -> int:
    from scenegen.data.reference_images import build_reference_image_stats

    try:
        result = build_reference_image_stats(
            args.n, args.out, args.workers, args.recipe, args.reference, args.images
        )
    except ValueError as exc:
        return fail(str(exc))
    print(f"wrote {args.out}: {len(result['rows'])} rows of {result['n']} scenes in {result['seconds']} s")
    return 0
