"""`scenegen train` and `scenegen sweep`: the diffusion generator's training and its guidance sweep."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import add_device_argument, device_error, fail


def add_commands(sub) -> None:
    """The ``train`` and ``sweep`` subcommands."""
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
    tr.add_argument(
        "--lr-decay",
        type=float,
        help="last share of the steps over which the learning rate falls to 0 on a half cosine (default 0: "
        "constant)",
    )
    tr.add_argument(
        "--spread-bins",
        type=int,
        help="condition on the layout's spread, in this many equal-count bins of its mean pair distance "
        "(default 0: not; a recipe then draws it with proposer.draw_spread)",
    )
    tr.add_argument(
        "--rare-share", type=float, help="share of each batch drawn by rare-tag oversampling (default 0.25)"
    )
    tr.add_argument(
        "--tag-loss-weight",
        type=float,
        help="extra loss weight of a layout holding a rare tag: it counts 1 + this (default 0: plain MSE)",
    )
    tr.add_argument(
        "--light-loss-weight",
        type=float,
        help="loss weight of the scene token's lighting numbers, ambient and light slots (default 1)",
    )
    tr.add_argument("--d-model", type=int, help="transformer width (default 128)")
    tr.add_argument("--layers", type=int, help="transformer layers (default 4)")
    tr.add_argument("--seed", type=int, help="seed (default 0)")
    tr.add_argument("--split", choices=("train", "heldout", "all"), help="rows to train on (default train)")
    add_device_argument(tr)
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    tr.set_defaults(run=train)

    sw = sub.add_parser(
        "sweep",
        help="guidance sweep of the diffusion generator: adherence, acceptance, realism vs w",
        description="Closed-loop guidance sweep (propose, check, settle, tag; no rendering): the null "
        "condition, then for each w one request per rare tag ('retrieve the TARGET TAG', TARGET the "
        "category holding the tag most often in the held-out reference), cost guidance off and on. "
        "Writes OUT/sweep.md (table), OUT/sweep.png (plot) and OUT/sweep.json. Metrics: "
        "scenegen/experiment/sweep.py.",
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
    sw.set_defaults(run=sweep)


def train(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from scenegen.diffusion.train import TrainSettings, train

    overrides = {
        "steps": args.steps,
        "batch_size": args.batch_size,
        "lr_decay": args.lr_decay,
        "spread_bins": args.spread_bins,
        "rare_share": args.rare_share,
        "tag_loss_weight": args.tag_loss_weight,
        "light_loss_weight": args.light_loss_weight,
        "d_model": args.d_model,
        "layers": args.layers,
        "seed": args.seed,
        "split": args.split,
    }
    try:
        settings = TrainSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        err = exc.errors()[0]
        return fail(f"--{str(err['loc'][0]).replace('_', '-')}: {err['msg']}")
    if (problem := device_error(args)) is not None:
        return fail(problem)
    if not args.data.is_file():
        return fail(
            f"--data {args.data}: no such Parquet file (the bundled one: assets/reference/reference.parquet)"
        )
    try:
        config = train(args.data, args.out, settings, progress=not args.quiet, device=args.device)
    except ValueError as exc:
        return fail(str(exc))
    print(
        f"{config['step']} steps, loss {sum(config['losses'][-50:]) / len(config['losses'][-50:]):.4f} "
        f"(last 50), {config['cpu_seconds']:.1f} CPU-s -> {args.out}"
    )
    return 0


def sweep(args: argparse.Namespace) -> int:
    import torch

    from scenegen.assets.catalog import CatalogError
    from scenegen.experiment import sweep
    from scenegen.runner.config import ConfigError, load_pipeline
    from scenegen.schema.condition import RARE_TAGS

    if args.proposals < 1 or args.workers < 1:
        return fail("--proposals and --workers must be at least 1")
    unknown = sorted(set(args.tags or ()) - set(RARE_TAGS))
    if unknown:
        return fail(f"--tags {' '.join(unknown)}: not rare tags; valid: {', '.join(RARE_TAGS)}")
    if args.cost_weight < 0:
        return fail(f"--cost-weight {args.cost_weight}: must be >= 0")
    try:
        config = load_pipeline(args.pipeline, {"seed": args.seed, "render": False, "sensor": "exact"})
    except (ConfigError, CatalogError) as exc:
        return fail(str(exc))
    if config.proposer.kind != "diffusion":
        return fail(
            f"{args.pipeline}: proposer.kind is {config.proposer.kind}; the sweep needs kind: diffusion"
        )
    if not args.reference.is_file():
        return fail(f"--reference {args.reference}: no such Parquet file")
    from scenegen.analysis.realism import load_rows

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
