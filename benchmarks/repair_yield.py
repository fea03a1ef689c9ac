"""Multi-tag requests with repairs: accepted scenes, tries (first-pass proposals + repairs) per
accepted scene and the proposer's own CPU, for the code at a baseline commit and this checkout
without and with repairs (``--repairs``), in the same invocation.

    .venv/bin/python benchmarks/repair_yield.py [--n 20] [--baseline-n 10] [--baseline bf81ff9]
        [--repairs 4] [--width 1] [--max-proposals 200]
        [--requests "retrieve the mug toppled occluded low_light" ...]

Each run is `scenegen generate pipelines/demo.yaml --request R --no-render --workers 1` in a fresh
process (one process, so the coordinator's ``propose`` seconds in timings.json are the proposer's
own time on one core, sampling + decoding + separating + repairing, and the checkpoint's loading,
~1.7 s, at the first); the baseline runs from that commit's code (`git archive`) with its own recipe
and checkpoint, this checkout with the demo recipe plus the v2 cost terms (``soft_occluded``,
``arm_clearance``), without repairs and with ``proposer.repairs`` / ``repair_width``. A run stops
at ``--max-proposals`` first-pass proposals if it has not its n scenes by then (a rare request).
CPU-s: the child process's user + system time. Prints a table and writes benchmarks/results/repair_yield.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proposer_cpu import ROOT, extract  # noqa: E402

REQUESTS = (
    "retrieve the mug toppled occluded low_light",
    "retrieve the spoon under_overhang clutter occluded",
    "retrieve the box on_floor toppled low_light",
)


def generate(code: Path, recipe: Path, request: str, n: int, out: Path, cap: int) -> dict:
    """One batch in a child process; its counts, the proposer's seconds and the child's CPU-s."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(recipe), "--request", request]
    cmd += ["--n", str(n), "--max-proposals", str(cap), "--no-render", "--workers", "1", "--quiet"]
    cmd += ["--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(code), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 1):
        raise SystemExit(f"{request}: {done.stderr.strip().splitlines()[-1]}")
    rows = [json.loads(line) for line in (out / "rejections.jsonl").read_text().splitlines()]
    accepted = len((out / "index.jsonl").read_text().splitlines())
    first = accepted + sum(1 for r in rows if not r.get("repaired"))
    tries = accepted + len(rows)
    propose = json.loads((out / "timings.json").read_text())["stages"]["propose"]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "accepted": accepted,
        "first_pass": first,
        "tries": tries,
        "tries_per_accepted": tries / accepted if accepted else None,
        "propose_s": propose,
        "propose_s_per_first_pass": propose / max(first, 1),
        "propose_s_per_accepted": propose / accepted if accepted else None,
        "cpu_s": cpu,
        "cpu_s_per_accepted": cpu / accepted if accepted else None,
    }


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20, help="accepted scenes per request with repairs")
    parser.add_argument("--baseline-n", type=int, default=10, help="accepted scenes per request, baseline")
    parser.add_argument("--baseline", default="bf81ff9", help="commit without repairs (default bf81ff9)")
    parser.add_argument("--repairs", type=int, default=4, help="repairs per proposal (default 4)")
    parser.add_argument("--width", type=int, default=1, help="repairs per expansion (default 1: a chain)")
    parser.add_argument("--max-proposals", type=int, default=200, help="first-pass proposals per run at most")
    parser.add_argument("--repair-labels", nargs="+", help="repair only these rejection labels (default all)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the baseline commit's runs")
    parser.add_argument("--requests", nargs="+", default=list(REQUESTS), help="request texts")
    args = parser.parse_args(argv)
    raw = yaml.safe_load((ROOT / "pipelines" / "demo.yaml").read_text())
    raw["proposer"].update(soft_occluded=True, arm_clearance=True)  # generator v2's cost terms
    plain = dict(raw, proposer=dict(raw["proposer"]))
    raw["proposer"].update(repairs=args.repairs, repair_width=args.width)
    if args.repair_labels:
        raw["proposer"]["repair_labels"] = list(args.repair_labels)
    sides = ("no_repairs", "repairs") if args.no_baseline else ("baseline", "no_repairs", "repairs")
    results: dict = {side: {} for side in sides}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        recipe, no_repairs = tmp / "repairs.yaml", tmp / "no_repairs.yaml"
        recipe.write_text(yaml.safe_dump(raw, sort_keys=False))
        no_repairs.write_text(yaml.safe_dump(plain, sort_keys=False))
        code = tmp if args.no_baseline else extract(args.baseline, tmp)
        for k, request in enumerate(args.requests):
            cap = args.max_proposals
            base_recipe = code / "pipelines" / "demo.yaml"
            runs = {
                "baseline": (code, base_recipe, args.baseline_n),
                "no_repairs": (ROOT, no_repairs, args.n),
                "repairs": (ROOT, recipe, args.n),
            }
            for side, (where, what, n) in ((k, v) for k, v in runs.items() if k in sides):
                results[side][request] = generate(where, what, request, n, tmp / f"{side}{k}", cap)
            print(request, json.dumps({s: results[s][request] for s in sides}), flush=True)
    labels = ", ".join(args.repair_labels or ["all"])
    print(
        f"\nrepairs {args.repairs} ({labels}), width {args.width}; baseline {args.baseline}; one process each"
    )
    print(
        "| request | run | accepted / tries (first pass) | tries per accepted | proposer ms per first-pass "
        "proposal | proposer CPU-s per accepted | CPU-s per accepted |"
    )
    print("|---" * 7 + "|")
    for request in args.requests:
        for side in sides:
            r = results[side][request]
            per = [_fmt(r[k], f) for k, f in (("tries_per_accepted", 1), ("propose_s_per_accepted", 2))]
            print(
                f"| {request} | {side} | {r['accepted']} / {r['tries']} ({r['first_pass']}) | {per[0]} | "
                f"{1e3 * r['propose_s_per_first_pass']:.0f} | {per[1]} | {_fmt(r['cpu_s_per_accepted'], 1)} |"
            )
    out = ROOT / "benchmarks" / "results" / "repair_yield.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), **results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
