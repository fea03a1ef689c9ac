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

example:
  scenegen generate pipelines/demo.yaml --n 20 --seed 0 --out runs/demo
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
    gen.add_argument("--out", type=Path, help="output directory, new or empty (default runs/<name>)")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _fail(message: str) -> int:
    print(f"scenegen: error: {message}", file=sys.stderr)
    return USAGE_ERROR


def _generate(args: argparse.Namespace) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.config import ConfigError, load_pipeline

    overrides = {"n": args.n, "seed": args.seed, "max_proposals": args.max_proposals}
    try:
        config = load_pipeline(args.pipeline, overrides)
    except (ConfigError, CatalogError) as exc:
        return _fail(str(exc))
    out = args.out or Path("runs") / config.name
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        return _fail(f"--out {out}: already exists and is not empty; choose a new directory")

    from scenegen.pipeline import run_batch

    summary = run_batch(config, out, progress=not args.quiet)
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


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return USAGE_ERROR
    if args.command == "generate":
        return _generate(args)
    return _fail(f"unknown command {args.command}")


if __name__ == "__main__":
    sys.exit(main())
