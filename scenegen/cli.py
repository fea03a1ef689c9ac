"""Command line: ``scenegen generate`` and friends. ``scenegen --help`` lists the commands."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

USAGE_ERROR = 2

DESCRIPTION = """\
scenegen generates physically verified tabletop manipulation scenes for rare cases.

A pipeline recipe (pipelines/*.yaml) names the request (task, target, rare-case tags, robot pose)
and the distributions of the proposer. `generate` proposes scenes, rejects the infeasible ones
(workspace, support, collisions on convex parts, robot clearance, reachability, MuJoCo settling)
and stores each accepted scene as scene.json + scene.xml, with a log of every rejection and a
batch manifest.

Accepted scenes are rendered off-screen (RGB, depth in millimetres, instance segmentation per
camera; MUJOCO_GL=egl works on CPU machines through Mesa). A batch killed at any point resumes
exactly when the same command is run again; the output does not depend on --workers.

examples:
  scenegen generate pipelines/demo.yaml --n 20 --seed 0 --out runs/demo --workers 2
  scenegen show runs/demo            # contact sheet: runs/demo/contact_sheet.png
  scenegen audit runs/demo/manifest.yaml
  scenegen manifest add runs/demo    # into data_manifest.yaml, after auditing it
"""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scenegen", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    gen = sub.add_parser(
        "generate",
        help="generate a batch of verified scenes from a pipeline recipe",
        description="Generate a batch: propose, check, settle and store scenes until --n are accepted.",
    )
    gen.add_argument("pipeline", type=Path, help="pipeline YAML, e.g. pipelines/demo.yaml")
    gen.add_argument("--n", type=int, help="accepted scenes wanted (overrides the recipe's n)")
    gen.add_argument("--seed", type=int, help="batch seed (overrides the recipe's seed)")
    gen.add_argument("--max-proposals", type=int, help="give up after this many proposals (default 40 x n)")
    gen.add_argument(
        "--out",
        type=Path,
        help="output directory (default runs/<name>); the same command on a killed batch resumes it",
    )
    gen.add_argument(
        "--request",
        metavar="TEXT",
        help="the request, laid over the recipe's condition, e.g. \"retrieve the mug near edge, not "
        "clutter\" (tags named are required, 'not TAG' forbidden; docs/conditions.md)",
    )
    gen.add_argument(
        "--proposer",
        choices=("diffusion", "procedural", "targeted"),
        help="proposer kind instead of the recipe's (keeps its shared settings): diffusion = the trained "
        "generator (assets/generator); procedural = rejection sampling from the recipe's distributions; "
        "targeted = hand-written rules per required tag",
    )
    gen.add_argument("--workers", type=int, default=1, help="processes for check/settle/render (default 1)")
    gen.add_argument("--no-render", action="store_true", help="skip rendering (no GL needed)")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")

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
    ref.add_argument("--workers", type=int, default=1, help="processes for check/settle/tag (default 1)")
    ref.add_argument("--quiet", action="store_true", help="no progress bar")
    ref.add_argument(
        "--manifest",
        type=Path,
        help="also register the table in this project manifest (origin reference), e.g. data_manifest.yaml",
    )

    tr = sub.add_parser(
        "train",
        help="train the diffusion generator on a reference/real Parquet table (resumable)",
        description="Train the conditional diffusion denoiser (DDPM, v prediction, EMA) on the layouts of a "
        "Parquet table. OUT holds model.safetensors (EMA weights), config.json (settings, data sha256, "
        "predicate version, loss curve), train_state.safetensors and loss.png; the same command on a "
        "killed run resumes it from its last checkpoint.",
    )
    tr.add_argument("--data", type=Path, default=Path("assets/reference/reference.parquet"))
    tr.add_argument("--out", type=Path, default=Path("runs/checkpoint"), help="checkpoint directory")
    tr.add_argument("--steps", type=int, help="optimizer steps (default 6000)")
    tr.add_argument("--batch-size", type=int, help="layouts per step (default 128)")
    tr.add_argument("--d-model", type=int, help="transformer width (default 128)")
    tr.add_argument("--layers", type=int, help="transformer layers (default 4)")
    tr.add_argument("--seed", type=int, help="seed (default 0)")
    tr.add_argument("--split", choices=("train", "heldout", "all"), help="rows to train on (default train)")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")

    sw = sub.add_parser(
        "sweep",
        help="guidance sweep of the diffusion generator: adherence, acceptance, realism vs w",
        description="Closed-loop guidance sweep (propose, check, settle, tag; no rendering): the null "
        "condition, then for each w one request per rare tag ('retrieve the TARGET TAG', TARGET the "
        "category holding the tag most often in the held-out reference), cost guidance off and on. "
        "Writes OUT/sweep.md (table), OUT/sweep.png (plot) and OUT/sweep.json. Metrics: "
        "scenegen/diffusion/sweep.py.",
    )
    sw.add_argument(
        "pipeline",
        type=Path,
        nargs="?",
        default=Path("pipelines/demo.yaml"),
        help="recipe with a diffusion proposer",
    )
    sw.add_argument("--weights", type=float, nargs="+", help="guidance weights w (default 0 0.5 1 2 4)")
    sw.add_argument(
        "--cost-weight",
        type=float,
        default=0.1,
        help="cost guidance of the 'on' cells (default 0.1; 0: off only)",
    )
    sw.add_argument("--proposals", type=int, default=12, help="proposals per request and cell (default 12)")
    sw.add_argument("--tags", nargs="+", help="rare tags to request (default all)")
    sw.add_argument("--reference", type=Path, default=Path("assets/reference/reference.parquet"))
    sw.add_argument("--seed", type=int, help="seed (overrides the recipe's seed)")
    sw.add_argument("--out", type=Path, default=Path("runs/sweep"))
    sw.add_argument("--workers", type=int, default=1, help="processes for check/settle/tag (default 1)")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")

    from scenegen import coverage  # numpy only: cheap to import for --help

    cov = sub.add_parser(
        "coverage",
        help="(task x tag) histogram of a dataset, batch or manifest; marks sparse cells",
        description=coverage.__doc__.splitlines()[0],
    )
    coverage.add_arguments(cov)
    # The importer needs MuJoCo, which must not load before MUJOCO_GL is checked: its two arguments
    # are declared here.
    imp = sub.add_parser(
        "import-real",
        help="import real scenes from the documented JSON format (docs/real_data.md); tags recomputed",
        description="Import measured real scenes (docs/real_data.md) into a Parquet table, tags "
        "recomputed at the measured poses.",
    )
    imp.add_argument("file", type=Path, help="JSON file of measured scenes (format: docs/real_data.md)")
    imp.add_argument("--out", type=Path, required=True, help="Parquet file to write (atomically)")

    show = sub.add_parser(
        "show",
        help="write a contact sheet PNG of a batch",
        description="Contact sheet of a batch: RGB thumbnails labelled with scene id, target and tags.",
    )
    show.add_argument("batch", type=Path, help="batch directory written by `scenegen generate`")
    show.add_argument("--out", type=Path, help="PNG to write (default BATCH/contact_sheet.png)")
    show.add_argument("--camera", help="camera name (default: the first camera of each scene)")
    show.add_argument("--depth", action="store_true", help="add depth beside each RGB thumbnail")
    show.add_argument("--seg", action="store_true", help="add segmentation beside each RGB thumbnail")
    show.add_argument("--max", type=int, default=24, help="at most this many scenes (default 24)")
    show.add_argument("--columns", type=int, default=4, help="thumbnails per row (default 4)")
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
    return parser


def _fail(message: str) -> int:
    print(f"scenegen: error: {message}", file=sys.stderr)
    return USAGE_ERROR


def _generate(args: argparse.Namespace) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.config import ConfigError, load_pipeline

    overrides = {"n": args.n, "seed": args.seed, "max_proposals": args.max_proposals}
    if args.no_render:
        overrides["render"] = False
    if args.workers < 1:
        return _fail(f"--workers {args.workers}: must be at least 1")
    try:
        config = load_pipeline(args.pipeline, overrides, request=args.request, proposer=args.proposer)
    except (ConfigError, CatalogError) as exc:
        return _fail(str(exc))
    out = args.out or Path("runs") / config.name
    if config.render:
        from scenegen.render import gl_problem

        problem = gl_problem()
        if problem:
            return _fail(problem)

    from scenegen.pipeline import run_batch
    from scenegen.store import StoreError

    try:
        summary = run_batch(config, out, workers=args.workers, progress=not args.quiet)
    except StoreError as exc:
        return _fail(str(exc))
    rejected = sum(summary.rejections.values())
    print(
        f"{summary.accepted} scenes accepted of {summary.proposals} proposals "
        f"in {summary.wall:.1f} s -> {out}"
    )
    if rejected:
        print("rejections: " + ", ".join(f"{k} {v}" for k, v in summary.rejections.most_common()))
    print("stage seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in summary.seconds.items()))
    if summary.accepted < config.n:
        print(
            f"scenegen: warning: only {summary.accepted} of {config.n} scenes accepted before the "
            f"proposal cap ({config.proposal_cap}); raise --max-proposals or relax the recipe",
            file=sys.stderr,
        )
        return 1
    return 0


def _reference(args: argparse.Namespace) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.config import ConfigError, load_pipeline

    try:
        config = load_pipeline(args.pipeline, {"n": args.n, "seed": args.seed, "render": False})
    except (ConfigError, CatalogError) as exc:
        return _fail(str(exc))
    if args.workers < 1:
        return _fail(f"--workers {args.workers}: must be at least 1")
    from scenegen.reference import build_reference, read_reference, tag_rates

    stats = build_reference(config, args.out, workers=args.workers, progress=not args.quiet)
    table, _ = read_reference(args.out)
    print(f"{stats['rows']} layouts of {stats['proposals']} proposals -> {args.out}")
    print("tag rates: " + ", ".join(f"{t} {c} ({r:.1%})" for t, (c, r) in tag_rates(table).items()))
    if args.manifest:
        from scenegen.manifest import ManifestError, add_source
        from scenegen.reference import reference_source

        try:
            add_source(args.manifest, reference_source(args.out, args.manifest.parent), replace=True)
        except ManifestError as exc:
            return _fail(str(exc))
        print(f"registered as source 'reference' in {args.manifest}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from scenegen.diffusion.train import TrainSettings, train

    overrides = {
        "steps": args.steps,
        "batch_size": args.batch_size,
        "d_model": args.d_model,
        "layers": args.layers,
        "seed": args.seed,
        "split": args.split,
    }
    try:
        settings = TrainSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        err = exc.errors()[0]
        return _fail(f"--{str(err['loc'][0]).replace('_', '-')}: {err['msg']}")
    if not args.data.is_file():
        return _fail(
            f"--data {args.data}: no such Parquet file (the bundled one: assets/reference/reference.parquet)"
        )
    try:
        config = train(args.data, args.out, settings, progress=not args.quiet)
    except ValueError as exc:
        return _fail(str(exc))
    print(
        f"{config['step']} steps, loss {sum(config['losses'][-50:]) / len(config['losses'][-50:]):.4f} "
        f"(last 50), {config['cpu_seconds']:.1f} CPU-s -> {args.out}"
    )
    return 0


def _sweep(args: argparse.Namespace) -> int:
    import torch

    from scenegen.assets.catalog import CatalogError
    from scenegen.config import ConfigError, load_pipeline
    from scenegen.diffusion import sweep
    from scenegen.schema.condition import RARE_TAGS

    if args.proposals < 1 or args.workers < 1:
        return _fail("--proposals and --workers must be at least 1")
    unknown = sorted(set(args.tags or ()) - set(RARE_TAGS))
    if unknown:
        return _fail(f"--tags {' '.join(unknown)}: not rare tags; valid: {', '.join(RARE_TAGS)}")
    if args.cost_weight < 0:
        return _fail(f"--cost-weight {args.cost_weight}: must be >= 0")
    try:
        config = load_pipeline(args.pipeline, {"seed": args.seed, "render": False})
    except (ConfigError, CatalogError) as exc:
        return _fail(str(exc))
    if config.proposer.kind != "diffusion":
        return _fail(
            f"{args.pipeline}: proposer.kind is {config.proposer.kind}; the sweep needs kind: diffusion"
        )
    if not args.reference.is_file():
        return _fail(f"--reference {args.reference}: no such Parquet file")
    from scenegen.realism import load_rows

    torch.set_num_threads(1)  # the sampler's CPU time is one thread's, like each check/settle worker's
    heldout = load_rows(args.reference, "heldout")
    targets = sweep.best_targets(heldout, args.tags or RARE_TAGS)
    weights = args.weights if args.weights is not None else sweep.DEFAULT_WEIGHTS
    cells = sweep.make_cells(config.condition, targets, weights, args.cost_weight)
    results = sweep.run_sweep(config, cells, args.proposals, args.workers, progress=not args.quiet)
    rows = [sweep.summarize(r, heldout, config.seed) for r in results]
    meta = {
        "pipeline": str(args.pipeline),
        "checkpoint": config.proposer.checkpoint,
        "steps": config.proposer.steps,
        "seed": config.seed,
        "proposals_per_request": args.proposals,
        "targets": targets,
        "reference": str(args.reference),
    }
    sweep.write_report(args.out, rows, meta)
    print(sweep.table(rows))
    print("\naccepted / proposals (adherence) per request:\n")
    print(sweep.request_table(rows))
    print(f"-> {args.out}/sweep.md, sweep.png, sweep.json")
    return 0


def _show(args: argparse.Namespace) -> int:
    from scenegen.contact_sheet import SheetError, contact_sheet

    try:
        path = contact_sheet(
            args.batch,
            args.out,
            camera=args.camera,
            depth=args.depth,
            seg=args.seg,
            limit=args.max,
            columns=args.columns,
        )
    except SheetError as exc:
        return _fail(str(exc))
    print(path)
    return 0


# Values mujoco accepts for MUJOCO_GL on Linux (mujoco/gl_context.py); anything else fails at import.
_GL_BACKENDS = (
    "egl",
    "osmesa",
    "glfw",
    "glx",
    "enable",
    "enabled",
    "on",
    "true",
    "1",
    "disable",
    "disabled",
    "off",
    "false",
    "0",
    "",
)


def _audit(args: argparse.Namespace) -> int:
    from scenegen.manifest.audit import audit

    if not args.manifest.is_file():
        return _fail(
            f"{args.manifest}: no such manifest (give a data_manifest.yaml or a batch's manifest.yaml)"
        )
    report = audit(args.manifest)
    print(report.to_json() if args.json else report.to_text())
    return 0 if report.ok else 1


def _manifest(args: argparse.Namespace) -> int:
    from scenegen.manifest import ManifestError, add_source, read_manifest, relocate
    from scenegen.manifest.audit import audit

    batch_manifest = args.batch / "manifest.yaml"
    if not batch_manifest.is_file():
        return _fail(f"{batch_manifest}: missing; is {args.batch} a batch written by `scenegen generate`?")
    report = audit(batch_manifest)
    if not report.ok:
        print(report.to_text(), file=sys.stderr)
        return _fail(
            f"{args.batch}: fails its audit ({len(report.violations)} violations); nothing was added"
        )
    try:
        (source,) = read_manifest(batch_manifest).sources
        source = relocate(source, args.batch, args.to, args.name)
        add_source(args.to, source, replace=args.replace)
    except ManifestError as exc:
        return _fail(str(exc))
    print(f"added source {source.name!r} ({source.counts.scenes} scenes, {source.location}) to {args.to}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return USAGE_ERROR
    no_gl = args.command in ("train", "sweep", "audit", "manifest") or (
        args.command == "generate" and args.no_render
    )
    if no_gl and "mujoco" not in sys.modules:
        os.environ["MUJOCO_GL"] = "disable"  # no GL is touched: a broken GL set-up cannot get in the way
    backend = os.environ.get("MUJOCO_GL", "egl").lower().strip()
    if backend not in _GL_BACKENDS:
        return _fail(
            f"MUJOCO_GL={backend}: not a GL backend mujoco knows; use MUJOCO_GL=egl (or --no-render)"
        )
    try:
        import mujoco  # noqa: F401 - a GL backend that cannot load fails here
    except Exception as exc:  # noqa: BLE001
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return _fail(
            f"MUJOCO_GL={backend}: mujoco cannot load this GL backend ({reason}); "
            "use MUJOCO_GL=egl (or --no-render)"
        )
    if args.command == "generate":
        return _generate(args)
    if args.command == "show":
        return _show(args)
    if args.command == "reference":
        return _reference(args)
    if args.command == "train":
        return _train(args)
    if args.command == "sweep":
        return _sweep(args)
    if args.command == "audit":
        return _audit(args)
    if args.command == "manifest":
        return _manifest(args)
    if args.command == "coverage":
        from scenegen import coverage

        return coverage.run(args)
    if args.command == "import-real":
        from scenegen import importer

        return importer.run(args)
    return _fail(f"unknown command {args.command}")


if __name__ == "__main__":
    sys.exit(main())
