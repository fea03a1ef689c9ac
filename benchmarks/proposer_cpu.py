"""The proposer's own CPU: sampling, decoding and overlap separation per first-pass proposal, for the
code at a baseline commit and the code here, in the same invocation.

    .venv/bin/python benchmarks/proposer_cpu.py [--n 64] [--baseline bf81ff9 | --no-baseline]
        [--requests "retrieve the can clutter" ...]

Each configuration runs in a fresh process with one torch thread: the demo recipe's diffusion
proposer (``pipelines/demo.yaml``: w = 1, cost 0.1, 20 steps) proposes ``--n`` proposals per
request, and the CPU time (time.process_time) of the whole proposer call and of its ``separate``
calls is measured. The baseline is that commit's code extracted with `git archive` and run with the
same virtual environment, its own demo recipe's settings and the checkpoint of this checkout
(``--baseline-checkpoint``), twice: with numpy's
default BLAS threads (one per core: how the pipeline's coordinator ran it until the BLAS limit) and
with one (OPENBLAS_NUM_THREADS=1, as the pipeline runs the proposer now: runner/executors.py
``one_blas_thread``); this checkout with one. Proposals are compared too: how many are identical to
the baseline's, and the largest position difference (none are once the recipe or the checkpoint
changed). Prints a table and writes
benchmarks/results/proposer_cpu.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from baseline import ROOT, baseline_tree

CHECKPOINT = "assets/generator"
REQUESTS = (
    "retrieve the can clutter",
    "retrieve the mug toppled occluded low_light",
    "retrieve the spoon under_overhang clutter occluded",
    "retrieve the spoon",
)


def measure(code: str, requests: list[str], n: int, checkpoint: str = CHECKPOINT) -> dict:
    """Run in a child process whose sys.path starts with ``code``: CPU seconds per proposal."""
    sys.path.insert(0, code)
    import time

    import torch

    torch.set_num_threads(1)
    import scenegen.propose.diffusion as diffusion
    from scenegen.runner.config import load_pipeline

    spent = {"separate": 0.0}
    separate = diffusion.separate

    def timed_separate(*args, **kwargs):
        t0 = time.process_time()
        try:
            return separate(*args, **kwargs)
        finally:
            spent["separate"] += time.process_time() - t0

    diffusion.separate = timed_separate
    out = {}
    for request in requests:
        # the code's own demo recipe (its own settings); the checkpoint from this checkout
        config = load_pipeline(Path(code) / "pipelines" / "demo.yaml", request=request)
        settings = config.proposer.model_copy(update={"checkpoint": str(ROOT / checkpoint)})
        proposer = diffusion.DiffusionProposer(settings, config.catalog())
        proposer.propose(config.condition, range(8), 99)  # warm-up: model load, caches
        spent["separate"] = 0.0
        t0 = time.process_time()
        proposals = proposer.propose(config.condition, range(n), config.seed)
        total = time.process_time() - t0
        out[request] = {
            "proposals": n,
            "cpu_per_proposal": total / n,
            "separate_per_proposal": spent["separate"] / n,
            "positions": [[list(o.position) for o in p.objects] for p in proposals],
        }
    return out


def run(
    code: Path, requests: list[str], n: int, blas_threads: int | None = 1, checkpoint: str = CHECKPOINT
) -> dict:
    script = (
        f"import json, sys; sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); import proposer_cpu; "
        f"print(json.dumps(proposer_cpu.measure({str(code)!r}, {requests!r}, {n}, {checkpoint!r})))"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if blas_threads is not None:
        env["OPENBLAS_NUM_THREADS"] = str(blas_threads)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=code, env=env)
    if done.returncode:
        raise SystemExit(f"{code}: {done.stderr.strip().splitlines()[-1]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(a: list, b: list) -> tuple[int, float]:
    """(proposals identical in positions, largest position difference in m)."""
    same, worst = 0, 0.0
    for pa, pb in zip(a, b, strict=True):
        if len(pa) != len(pb):
            worst = float("inf")
            continue
        diff = max(
            (max(abs(x - y) for x, y in zip(u, v, strict=True)) for u, v in zip(pa, pb, strict=True)),
            default=0.0,
        )
        same += diff == 0.0
        worst = max(worst, diff)
    return same, worst


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=64, help="proposals per request (default 64)")
    parser.add_argument("--baseline", default="bf81ff9", help="commit to compare with (default bf81ff9)")
    parser.add_argument(
        "--baseline-checkpoint",
        default="assets/generator",
        help="the baseline's checkpoint in this checkout (default assets/generator)",
    )
    parser.add_argument("--no-baseline", action="store_true", help="measure this checkout only")
    parser.add_argument("--requests", nargs="+", default=list(REQUESTS), help="request texts")
    args = parser.parse_args(argv)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_baseline:
            code = baseline_tree(args.baseline, Path(tmp) / "code")
            ckpt = args.baseline_checkpoint
            results["baseline_default_blas"] = run(code, args.requests, args.n, None, ckpt)
            results["baseline"] = run(code, args.requests, args.n, 1, ckpt)
        results["current"] = run(ROOT, args.requests, args.n)
    print(f"proposer CPU per first-pass proposal (ms), {args.n} proposals per request, one thread")
    print(
        "| request | baseline, default BLAS threads | baseline | current | ratio | ratio to default BLAS "
        "| separate: baseline | current | identical | max diff (m) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for request in args.requests:
        cur = results["current"][request]
        base = results.get("baseline", {}).get(request)
        if base is None:
            print(
                f"| {request} | | | {1e3 * cur['cpu_per_proposal']:.1f} | | | | "
                f"{1e3 * cur['separate_per_proposal']:.1f} | | |"
            )
            continue
        same, worst = compare(base["positions"], cur["positions"])
        default = results["baseline_default_blas"][request]["cpu_per_proposal"]
        print(
            f"| {request} | {1e3 * default:.1f} | {1e3 * base['cpu_per_proposal']:.1f} | "
            f"{1e3 * cur['cpu_per_proposal']:.1f} | "
            f"{cur['cpu_per_proposal'] / base['cpu_per_proposal']:.2f} | "
            f"{cur['cpu_per_proposal'] / default:.2f} | "
            f"{1e3 * base['separate_per_proposal']:.1f} | {1e3 * cur['separate_per_proposal']:.1f} | "
            f"{same}/{args.n} | {worst:.2g} |"
        )
    out = ROOT / "benchmarks" / "results" / "proposer_cpu.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    for side in results.values():
        for row in side.values():
            row.pop("positions")
    out.write_text(json.dumps({"n": args.n, "baseline": args.baseline, **results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
