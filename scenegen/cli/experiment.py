"""`scenegen experiment transfer|verifier|panels|perception-gap`: the transfer experiment (docs/transfer.md),
the learned verifier's measurement, the version 2 panels and the perception gap."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from scenegen.cli.common import add_sensor_argument, fail, first_line, physics_from

STAGES = ("sources", "labels", "training")


def add_commands(sub) -> None:
    """The ``experiment`` command and its ``transfer`` subcommand."""
    ex = sub.add_parser(
        "experiment",
        help="experiments that measure what the generated data is worth (transfer)",
        description="Experiments over the whole pipeline. `scenegen experiment transfer` is the one the "
        "project exists for (docs/transfer.md).",
    )
    kinds = ex.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    tr = kinds.add_parser(
        "transfer",
        help="do generated rare-case scenes make a recovery policy succeed more often in closed loop?",
        description="Builds or reuses the labelled sources (reference sets A, A+, C; generated sets D "
        "(diffusion) and E (hand-targeted), labelled by every primitive into a shared, content-keyed "
        "label store), trains every arm and seed, evaluates each policy in closed loop on the committed "
        "rare and common panels (and the rare panel under a lighting shift), and writes OUT: "
        "config.yaml, sources.json, panels.json, episodes/*.jsonl (one record per episode, with its "
        "failure label), metrics.json (success with 95% hierarchical bootstrap intervals), report.md, "
        "transfer.png. The outcome and the artifact's checksum go into the manifest's transfer section "
        "(`scenegen audit` verifies it). Version 2 (`version: 2`, the default configuration "
        "pipelines/transfer.yaml; version 1's is pipelines/transfer_v1.yaml) trains per arm and seed its "
        "own retrieval head and a chooser through it, evaluates through the head and through true masks "
        "(nominal, dim light, depth noise) on one side of the version 2 panels, plans on the configured "
        "grid, and writes config.yaml, sources.json, costs.jsonl, episodes/PANEL/RUN_CONDITION.jsonl and "
        "metrics.json. Resumable: rerun the same command after a kill. Cost: docs/transfer.md, and "
        "--estimate.",
    )
    tr.add_argument(
        "config",
        type=Path,
        nargs="?",
        default=Path("pipelines/transfer.yaml"),
        help="configuration file (default pipelines/transfer.yaml)",
    )
    tr.add_argument("--out", type=Path, help="artifact folder (overrides the configuration's out)")
    tr.add_argument("--cache", type=Path, help="cache folder: batches, observations, checkpoints")
    tr.add_argument("--manifest", type=Path, help="manifest to write the outcome into")
    tr.add_argument("--no-manifest", action="store_true", help="write no manifest")
    tr.add_argument("--workers", type=int, help="processes for labelling, generation and evaluation")
    tr.add_argument("--stop-after", choices=STAGES, help="stop after this stage (to build caches in steps)")
    tr.add_argument(
        "--check",
        action="store_true",
        help="only validate the configuration and the files and recipes it names; writes nothing",
    )
    only = tr.add_mutually_exclusive_group()
    only.add_argument(
        "--estimate",
        type=Path,
        nargs="+",
        metavar="FOLDER",
        help="version 2: only project the configuration's wall time from the costs.jsonl that earlier "
        "runs wrote into these out folders (a pilot's); writes nothing",
    )
    only.add_argument(
        "--status",
        action="store_true",
        help="version 2: only say how far the run in the out folder has come (per arm: runs and "
        "episodes done; the hours left at the folder's measured rates) and the rates and contrasts "
        "of the arms already whole; writes nothing",
    )
    tr.add_argument("--quiet", action="store_true", help="no progress bars")
    tr.set_defaults(run=transfer)
    _add_panels(kinds)
    _add_verifier(kinds)


def _add_verifier(kinds) -> None:
    ve = kinds.add_parser(
        "verifier",
        help="collect the generator's labelled tries on the request suite's tuning half and train the "
        "learned verifier that guides sampling",
        description="Asks the generator (RECIPE's proposer) every request of the request suite's tuning "
        "half (never the held-out half), and each --bundled recipe its own request, keeping every try "
        "(first passes and repairs) encoded as tokens with what the checks, settling and predicates said "
        "(OUT/tries/NNN.npz, one per request: resumable); then fits the verifier, p(accepted) and "
        "p(tag holds) from noisy tokens, timestep and request, every fifth request's tries held out to "
        "measure it, and writes OUT/verifier (model.safetensors, config.json with the data's size, the "
        "CPU-s of collecting and training and the held-out accuracy). A recipe uses it with "
        "proposer.verifier (the folder), verifier_sha256 and verifier_weight (docs/generator.md).",
    )
    ve.add_argument("recipe", type=Path, help="the generator's recipe, e.g. pipelines/generator_v3.yaml")
    ve.add_argument("--out", type=Path, required=True, help="folder for the tries and the verifier")
    ve.add_argument("--count", type=int, default=30, help="requests of the tuning half (default 30)")
    ve.add_argument("--tries", type=int, default=150, help="tries per request at most (default 150)")
    ve.add_argument("--scenes", type=int, default=3, help="stop a request at this many scenes (default 3)")
    ve.add_argument("--bundled", type=Path, nargs="*", default=[], help="recipes asked their own request")
    ve.add_argument("--steps", type=int, default=3000, help="training steps (default 3000)")
    ve.add_argument("--collect-only", action="store_true", help="collect the tries, train nothing")
    ve.set_defaults(run=verifier)


def verifier(args: argparse.Namespace) -> int:
    from scenegen.core.files import CheckpointError, load_rows
    from scenegen.experiment import verifier_data
    from scenegen.paths import ASSETS_DIR
    from scenegen.runner.config import ConfigError, load_pipeline

    if min(args.count, args.tries, args.scenes, args.steps) < 1:
        return fail("--count, --tries, --scenes and --steps must be at least 1")
    try:
        for recipe in [args.recipe, *args.bundled]:
            if load_pipeline(recipe, {"n": 1}).proposer.kind != "diffusion":
                return fail(f"{recipe}: proposer.kind is not diffusion; the verifier guides the generator")
        rows = load_rows(ASSETS_DIR / "reference" / "reference.parquet", "train")
        requests = verifier_data.requests_for(rows, "tuning", args.count)
    except (ConfigError, CheckpointError, OSError, ValueError) as exc:
        return fail(first_line(exc))
    jobs = verifier_data.jobs(args.recipe, requests, args.bundled)
    verifier_data.collect_all(args.out, jobs, args.tries, args.scenes)
    if args.collect_only:
        return 0
    summary = verifier_data.train(args.out, args.recipe, args.steps)
    print(json.dumps(summary, indent=1))
    print(f"-> {args.out / 'verifier'}")
    return 0


def _add_panels(kinds) -> None:
    from scenegen.paths import ASSETS_DIR

    v2 = ASSETS_DIR / "panels" / "v2"  # as scenegen/policy/panels_v2.py names them (checked in its test)
    labels, layouts, out = v2 / "heldout_labels.parquet", v2 / "reference_seed1.parquet", v2 / "panels.json"
    pa = kinds.add_parser(
        "panels",
        help="draw the version 2 test and validation panels (unique-category, solvable layouts)",
        description="Labels, until some primitive succeeds, just the held-out layouts the version 2 panels "
        "need (the bundled table's held-out split, then the new-seed table; scenegen/policy/panels_v2.py "
        "says how pools are settled and drawn) and writes panels.json with the per-panel counts. "
        "Resumable: the label store keeps every row; rerun after a kill.",
    )
    pa.add_argument("--labels", type=Path, default=labels, help=f"label store (default {labels})")
    pa.add_argument("--new-layouts", type=Path, default=layouts, help=f"the new-seed table ({layouts})")
    pa.add_argument("--out", type=Path, default=out, help=f"panels file (default {out})")
    pa.add_argument("--workers", type=int, default=1, help="labelling processes (default 1)")
    pa.add_argument(
        "--no-label", action="store_true", help="draw from the labels the store holds; run nothing"
    )
    pa.add_argument("--quiet", action="store_true", help="no progress bars")
    pa.set_defaults(run=panels)
    _add_perception_gap(kinds, out)


def _add_perception_gap(kinds, panels_file: Path) -> None:
    from scenegen.paths import ASSETS_DIR
    from scenegen.perception.retrieval import DEFAULT_HEAD, SENSOR_HEAD

    gap = kinds.add_parser(
        "perception-gap",
        help="one policy on a version 2 panel through a retrieval head and through the oracle's masks",
        description="Runs the policy in closed loop on every layout of one side of the version 2 panels, "
        "first seeing through the retrieval head, then through the simulator's masks (the ceiling), on "
        "one sequence store keyed by the plans executed. Writes episodes_learned.jsonl, "
        "episodes_oracle.jsonl, summary.json and summary.md (success per panel with 95%% intervals, the "
        "gap, perception failures, the store's sharing rate and the CPU per episode). Resumable.",
    )
    gap.add_argument("--checkpoint", type=Path, default=ASSETS_DIR / "policy" / "baseline", help="policy")
    gap.add_argument(
        "--proposals",
        type=Path,
        metavar="MODEL",
        help="act by a proposal model instead (scenegen proposals train): candidates sampled from what "
        "the robot sees, the best by the model executed, proposed anew after each attempt",
    )
    gap.add_argument(
        "--candidates",
        type=int,
        nargs=4,
        metavar=("TOP", "SIDE", "PUSH", "PULL"),
        help="with --proposals: candidates proposed per decision, grasps from above, from the side, pushes, "
        "pulls (default 24 8 2 2)",
    )
    gap.add_argument(
        "--retrieval",
        type=Path,
        help=f"head (default {DEFAULT_HEAD.relative_to(ASSETS_DIR.parent)}; through --sensor active_stereo "
        f"{SENSOR_HEAD.relative_to(ASSETS_DIR.parent)}, trained through it)",
    )
    gap.add_argument("--panels", type=Path, default=panels_file, help=f"panels file (default {panels_file})")
    gap.add_argument(
        "--side",
        choices=("validation", "test"),
        default="validation",
        help="which panels (default validation: the only side a pilot may look at)",
    )
    gap.add_argument("--limit", type=int, help="only the first N layouts of each panel (a pilot)")
    gap.add_argument("--out", type=Path, required=True, help="folder for episodes and the summary")
    gap.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    gap.add_argument(
        "--perception-rules",
        type=int,
        choices=(1, 2),
        default=2,
        help="how a decision's mask is judged missed: 2 (default) the overlap rule (IoU >= 0.5 in every "
        "camera that sees the target, nothing where it does not); 1 the centre rule of issue 33's figures",
    )
    add_sensor_argument(gap, "the depth every decision reads, the oracle's too (default exact)")
    gap.add_argument(
        "--physics",
        metavar="NAME",
        help="what the episodes are simulated under (default: the default physics, dt5; the committed "
        "figures of docs/policy.md were made under exact)",
    )
    gap.add_argument("--quiet", action="store_true", help="no progress bars")
    gap.set_defaults(run=perception_gap)


def perception_gap(args: argparse.Namespace) -> int:
    from scenegen.core.files import CheckpointError
    from scenegen.experiment.perception_gap import markdown, run_gap
    from scenegen.manipulation.proposals import SamplerConfig
    from scenegen.perception.retrieval import default_head
    from scenegen.perception.retrieval.perceive import RetrievalPerception
    from scenegen.policy.network import PrimitivePolicy
    from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes

    if args.workers < 1 or (args.limit is not None and args.limit < 1):
        return fail("--workers and --limit must be at least 1")
    if args.candidates is not None and (
        args.proposals is None or min(args.candidates) < 0 or sum(args.candidates) < 1
    ):
        return fail("--candidates: four counts, none negative, at least one candidate, with --proposals")
    args.retrieval = args.retrieval or default_head(args.sensor)
    try:
        if args.proposals is not None:
            from scenegen.policy.proposal_model import ProposalModel

            ProposalModel.load(args.proposals)
        else:
            PrimitivePolicy.load(args.checkpoint)
        RetrievalPerception.load(args.retrieval)
        panel = panel_scenes(load_panels_v2(args.panels), args.side)
    except (CheckpointError, OSError, ValueError, KeyError) as exc:
        return fail(first_line(exc))
    if args.limit is not None:
        panel = {name: scenes[: args.limit] for name, scenes in panel.items()}
    try:
        physics = physics_from(args)
    except ValueError as exc:
        return fail(f"--physics {first_line(exc)}")
    summary = run_gap(
        args.checkpoint, args.retrieval, panel, args.out, args.workers, not args.quiet, args.perception_rules,
        args.sensor, physics, args.proposals, args.candidates and SamplerConfig(*args.candidates),
    )  # fmt: skip
    print(markdown(summary), end="")
    print(f"-> {args.out}")
    return 0


def panels(args: argparse.Namespace) -> int:
    from scenegen.env.scenes import SceneSourceError
    from scenegen.policy.labels import LabelError
    from scenegen.policy.panels_v2 import (
        REFERENCE,
        fill_pools,
        known_solvable,
        source_layouts,
        write_panels_v2,
    )

    if args.workers < 1:
        return fail("--workers must be at least 1")
    if not args.new_layouts.is_file():
        make = f"scenegen reference --n 5000 --seed 1 --out {args.new_layouts}"
        return fail(f"--new-layouts {args.new_layouts}: no such table; make it with `{make}`")
    sources = ((REFERENCE, "heldout"), (args.new_layouts, None))
    try:
        layouts = source_layouts(sources)
        if args.no_label:
            solvable = known_solvable(args.labels)
        else:
            solvable = fill_pools(layouts, args.labels, workers=args.workers, progress=not args.quiet)
    except (SceneSourceError, LabelError, OSError) as exc:
        return fail(first_line(exc))
    drawn = write_panels_v2(layouts, solvable, args.out, sources)
    print(json.dumps(drawn["counts"]))
    if drawn["short"]:
        print(f"short (no panel of their own): {', '.join(drawn['short'])}")
    print(f"-> {args.out}")
    return 0


def _v2_summary(metrics: dict) -> str:
    """Version 2's headline lines: per condition (sight, shift), each arm's rare-panel success and
    the contrasts."""
    lines = [f"transfer version 2, {metrics['side']} side"]
    for sight, block in metrics.items():
        if not (isinstance(block, dict) and "rare" in block.get("rates", {})):
            continue
        lines.append(f"{sight}: rare panels pooled")
        fmt = lambda c: f"{c['mean']:+.3f} [{c['low']:+.3f}, {c['high']:+.3f}]"  # noqa: E731
        for arm, c in block["rates"]["rare"].items():  # a rate, unsigned; a contrast, signed
            rate = f"{c['mean']:.3f} [{c['low']:.3f}, {c['high']:.3f}]"
            seeds = f"{c['seeds']} seed" + "s" * (c["seeds"] != 1)
            lines.append(f"  {arm}: {rate} ({seeds} x {c['scenes']} layouts)")
        for name, c in block["contrasts"]["rare"].items():
            lines.append(f"  {name}: {fmt(c)}")
    return "\n".join(lines)


def _estimate(config, folders: list[Path]) -> int:
    from scenegen.experiment.transfer_config import TransferConfigError
    from scenegen.experiment.transfer_cost import describe, project
    from scenegen.experiment.transfer_ledger import measured

    if getattr(config, "version", 1) != 2:
        raise TransferConfigError("--estimate: version 2 configurations only (version: 2)")
    rates = measured(folders)
    try:
        projection = project(config, rates)
    except ValueError as exc:
        raise TransferConfigError(f"--estimate: {exc}") from None
    print(describe(projection, rates))
    return 0


def _status(config) -> int:
    from scenegen.experiment.transfer_config import TransferConfigError
    from scenegen.experiment.transfer_cost import describe_status, status

    if getattr(config, "version", 1) != 2:
        raise TransferConfigError("--status: version 2 configurations only (version: 2)")
    state = status(config)
    print(describe_status(state))
    if state["metrics"] is not None:
        print(_v2_summary(state["metrics"]))
    return 0


def transfer(args: argparse.Namespace) -> int:
    from scenegen.experiment.transfer import TransferError, run_transfer
    from scenegen.experiment.transfer_config import (
        ARMS,
        TransferConfigError,
        check_inputs,
        load_transfer_config,
    )

    overrides = {"out": args.out, "cache": args.cache, "manifest": args.manifest, "workers": args.workers}
    try:
        config = load_transfer_config(
            args.config, {k: str(v) if isinstance(v, Path) else v for k, v in overrides.items()}
        )
        if args.no_manifest:
            config = config.model_copy(update={"manifest": None})
        try:
            check_inputs(config)  # before anything is written
        except TransferConfigError as exc:
            raise TransferConfigError(f"{args.config}: {exc}") from None
        if args.check:
            sweep = f", alpha sweep {list(config.alpha_sweep)}" if config.alpha_sweep else ""
            arms = ", ".join(getattr(config, "arms", ARMS)) + sweep
            if getattr(config, "version", 1) == 2:
                arms += f"; version 2, {config.side} panels, a head per arm and seed"
            print(
                f"{args.config}: valid. arms {arms}; {len(config.training.seeds)} training seeds, "
                f"{config.training.steps} steps; sizes A {config.sizes.a}, A+ {config.sizes.a_plus}, "
                f"extra {config.sizes.extra}; -> {config.out}"
            )
            return 0
        if args.estimate:
            return _estimate(config, args.estimate)
        if args.status:
            return _status(config)
        if getattr(config, "version", 1) == 2:
            from scenegen.experiment.transfer_v2 import run_transfer_v2

            metrics = run_transfer_v2(config, progress=not args.quiet, stop_after=args.stop_after)
        else:
            metrics = run_transfer(config, progress=not args.quiet, stop_after=args.stop_after)
    except (TransferConfigError, TransferError, FileNotFoundError) as exc:
        return fail(str(exc).splitlines()[0])
    if not metrics:
        print(f"stopped after {args.stop_after}; rerun without --stop-after to continue")
        return 0
    if metrics.get("version") == 2:
        print(_v2_summary(metrics))
        print(json.dumps({"artifact": str(config.out), "seconds": metrics["timings"]}))
        return 0
    print((Path(config.out) / "report.md").read_text())
    print(
        json.dumps(
            {
                "artifact": str(config.out),
                "artifact_sha256": metrics["artifact_sha256"],
                "seconds": metrics["timings"],
            }
        )
    )
    return 0
