"""Requests nobody tuned for (issue 46, point 1): each request of one half of the drawn suite
(scenegen/experiment/request_suite.py: a target, 2-3 required tags the data shows for it, sometimes one
forbidden, a pose jittered from home or ready), asked of every proposer under the same recipe, caps
and seed, in this process one after the other.

    .venv/bin/python benchmarks/request_suite.py [--half tuning] [--count 30] [--scenes 3] [--cap 300]
        [--proposers diffusion procedural targeted] [--recipe pipelines/demo.yaml] [--limit N]
        [--also RECIPE ...] [--list]

Halves (scenegen/experiment/request_suite.py HALVES): ``tuning`` and ``heldout`` draw "retrieve"
requests (issues 46, 54), ``tuning-v4``, ``heldout-v4`` and ``heldout-v4b`` every task (issue 64).
``--list`` prints a half's requests and asks nothing.

The recipe (default the demo recipe, its realism check on) gives every proposer its settings; the
procedural and targeted proposers take the settings they share with it. ``--also``: more recipes
whose own proposer (e.g. the diffusion proposer with other settings) is asked the same requests in
the same run, each a column named ``KIND[recipe name]``. A try is every candidate
that reached check or settle, repairs included (the batch's proposals: accepted plus every logged
rejection); the cap is the batch's max_proposals. Per request and proposer: scenes accepted, tries
and CPU-s per accepted scene (None when none), the rejection labels, filled (all ``--scenes``) or
not, and a refusal (the recipe refused the request as impossible before any try, with its reason).
Per proposer: median and 90th percentile of tries and CPU-s per accepted scene over the requests
(a request left unfilled counts its tries over max(accepted, 1), so an empty one is not dropped),
and how many were filled and refused. A held-out half is for the final report only: it runs with
--final, never to choose a setting. CPU is process + children user + system time,
BLAS and OpenMP at one thread. Prints a table, saves JSON; each row is also appended to
JSON's ``.rows.jsonl`` as it is measured, and a rerun of the same command asks only what is missing.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "LP_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scenegen.core.files import load_rows  # noqa: E402
from scenegen.experiment.request_suite import HALVES, Request, suite  # noqa: E402
from scenegen.experiment.transfer_sources import cpu_seconds  # noqa: E402
from scenegen.runner.config import ConfigError, load_pipeline  # noqa: E402
from scenegen.runner.pipeline import run_batch  # noqa: E402

PROPOSER_KINDS = ("diffusion", "procedural", "targeted")


def ask(recipe: Path, request: Request, proposer: str | None, scenes: int, cap: int, seed: int) -> dict:
    """One request of one proposer (``proposer`` swapped in, or the recipe's own with None): a batch
    in a temporary folder, or the recipe's refusal."""
    condition = request.condition().model_dump(mode="json", exclude={"text"})
    overrides = {"n": scenes, "seed": seed, "max_proposals": cap, "max_tries": cap, "render": False}
    overrides["condition"] = condition
    try:
        config = load_pipeline(recipe, overrides, None, proposer)
    except ConfigError as exc:
        return {"refused": str(exc), "accepted": 0, "tries": 0, "cpu_s": 0.0, "filled": False}
    with tempfile.TemporaryDirectory() as tmp:
        start = cpu_seconds()
        summary = run_batch(config, Path(tmp) / "batch", workers=1, progress=False)
        cpu = cpu_seconds() - start
    accepted = summary.accepted
    return {
        "refused": None,
        "accepted": accepted,
        "filled": accepted >= scenes,
        "tries": summary.proposals,
        "cpu_s": round(cpu, 2),
        "tries_per_scene": round(summary.proposals / max(accepted, 1), 2),
        "cpu_s_per_scene": round(cpu / max(accepted, 1), 2),
        "rejections": dict(summary.rejections.most_common()),
    }


def summarise(rows: list[dict]) -> dict:
    """Median and 90th percentile of tries and CPU-s per accepted scene over the requests asked (not
    refused), how many were filled, refused and left empty."""
    asked = [r for r in rows if r["refused"] is None]
    out = {"requests": len(rows), "refused": len(rows) - len(asked)}
    out["filled"] = sum(r["filled"] for r in asked)
    out["empty"] = sum(r["accepted"] == 0 for r in asked)
    for key in ("tries_per_scene", "cpu_s_per_scene"):
        values = [r[key] for r in asked]
        out[key] = (
            {"median": round(float(np.median(values)), 2), "p90": round(float(np.percentile(values, 90)), 2)}
            if values
            else None
        )
    return out


def columns(proposers, recipe: Path, also=()) -> dict[str, tuple[Path, str | None]]:
    """The suite's columns: each proposer kind under ``recipe``, then each recipe of ``also`` with
    its own proposer, as ``KIND[name]``: name -> (recipe, proposer kind to swap in or None)."""
    out: dict[str, tuple[Path, str | None]] = {p: (recipe, p) for p in proposers}
    for path in also:
        raw = yaml.safe_load(Path(path).read_text())
        out[f"{raw['proposer']['kind']}[{raw['name']}]"] = (Path(path), None)
    return out


def run_suite(
    requests: list[Request],
    proposers,
    recipe: Path,
    scenes: int,
    cap: int,
    seed: int,
    log=print,
    also=(),
    rows_file: Path | None = None,
) -> dict:
    """Every request asked of every column (:func:`columns`); per column its rows and their summary.
    The diffusion checkpoint is loaded (and torch set up) once first, outside every timed batch.
    ``rows_file``: each row is appended there as it is measured, and rows found there (same column,
    recipe bytes, request, scenes, cap and seed) are not asked again: a killed run resumes."""
    table = columns(proposers, recipe, also)
    done = {}
    if rows_file is not None and rows_file.exists():
        for line in rows_file.read_text().splitlines():
            row = json.loads(line)
            done[row["key"]] = row["row"]
    if requests and any((kind or "diffusion") == "diffusion" for _, kind in table.values()):
        from scenegen.assets.catalog import load_catalog
        from scenegen.propose.base import PROPOSERS

        config = load_pipeline(recipe, {"n": 1}, None, "diffusion")
        PROPOSERS["diffusion"](config.proposer, load_catalog()).propose(requests[0].condition(), [0], seed)
    results: dict = {name: {"recipe": str(path), "rows": []} for name, (path, _) in table.items()}
    # a row is the recipe's as it was: an edited recipe (its bytes, the checkpoint's sha256 among them)
    # asks again
    digests = {name: hashlib.sha256(path.read_bytes()).hexdigest()[:16] for name, (path, _) in table.items()}
    for number, request in enumerate(requests):
        for name, (path, kind) in table.items():
            key = json.dumps([name, digests[name], request.text, list(request.robot_pose), scenes, cap, seed])
            row = done.get(key)
            if row is None:
                row = {"request": request.as_dict(), **ask(path, request, kind, scenes, cap, seed)}
                if rows_file is not None:
                    with rows_file.open("a") as f:
                        f.write(json.dumps({"key": key, "row": row}) + "\n")
            results[name]["rows"].append(row)
            shown = row["refused"] or f"{row['accepted']} scenes, {row['tries']} tries, {row['cpu_s']} CPU-s"
            log(f"[{number + 1}/{len(requests)}] {name:10s} {request.text}: {shown}")
    for name in table:
        results[name]["summary"] = summarise(results[name]["rows"])
    return results


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--half", choices=tuple(HALVES), default="tuning")
    parser.add_argument("--final", action="store_true", help="required with a held-out half: the report")
    parser.add_argument("--list", action="store_true", help="print the half's requests; ask nothing")
    parser.add_argument("--count", type=int, default=30, help="requests in the half (default 30)")
    parser.add_argument("--limit", type=int, help="ask only the first N requests (a quick look)")
    parser.add_argument("--scenes", type=int, default=3, help="scenes asked per request (default 3)")
    parser.add_argument("--cap", type=int, default=300, help="tries allowed per request (default 300)")
    parser.add_argument("--proposers", nargs="*", choices=PROPOSER_KINDS, default=list(PROPOSER_KINDS))
    parser.add_argument("--recipe", type=Path, default=ROOT / "pipelines" / "demo.yaml")
    parser.add_argument(
        "--also", type=Path, nargs="+", default=[], help="more recipes, each asked with its own proposer"
    )
    parser.add_argument("--reference", type=Path, default=ROOT / "assets" / "reference" / "reference.parquet")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="default benchmarks/results/request_suite_HALF.json")
    args = parser.parse_args()
    requests = suite(load_rows(args.reference, "train"), args.half, args.count)[: args.limit]
    if args.list:
        for number, request in enumerate(requests):
            print(f"{number + 1:3d}. {request.text}  (pose {request.pose_name} jittered)")
        return
    if args.half.startswith("heldout") and not args.final:
        parser.error(f"--half {args.half} is run once, for the final report: add --final")
    import torch

    torch.set_num_threads(1)
    target = args.json or ROOT / "benchmarks" / "results" / f"request_suite_{args.half}.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    rows_file = target.with_suffix(".rows.jsonl")  # measured rows as they come: a rerun resumes
    results = run_suite(
        requests,
        args.proposers,
        args.recipe,
        args.scenes,
        args.cap,
        args.seed,
        also=args.also,
        rows_file=rows_file,
    )
    print(f"\n{args.half} half, {len(requests)} requests, {args.scenes} scenes each, cap {args.cap} tries")
    print("| proposer | filled | empty | refused | tries/scene median | p90 | CPU-s/scene median | p90 |")
    print("|---|---|---|---|---|---|---|---|")
    for proposer, block in results.items():
        s = block["summary"]
        t, c = s["tries_per_scene"] or {}, s["cpu_s_per_scene"] or {}
        print(
            f"| {proposer} | {s['filled']} | {s['empty']} | {s['refused']} | {t.get('median')} | "
            f"{t.get('p90')} | {c.get('median')} | {c.get('p90')} |"
        )
    meta = {
        "half": args.half,
        "count": len(requests),
        "scenes": args.scenes,
        "cap": args.cap,
        "seed": args.seed,
    }
    meta |= {"recipe": str(args.recipe), "machine": platform.machine(), "python": platform.python_version()}
    target.write_text(json.dumps({"settings": meta, "proposers": results}, indent=1) + "\n")
    print(f"saved {target}")


if __name__ == "__main__":
    main()
