"""What executing plans on a grid (``plan_grid``, manipulation/primitives.py ``PlanGrid``) changes in a
transfer run's outcomes, and what it saves: two out folders of the same version 2 runs (heads and
choosers from the cache), one evaluated with plans as planned, one on the grid.

    .venv/bin/python benchmarks/plan_grid.py runs/transfer_v2/pilot3 runs/transfer_v2/grid5 \
        [--condition head] [--json benchmarks/results/plan_grid.json]

Reports, over every (panel, run) episodes file both folders hold:
- outcomes: episodes whose success agrees, each folder's success rate and the grid's minus the exact
  plans' with a 95 % paired bootstrap interval (runs and layouts resampled), per arm and pooled, and
  each arm contrast (C - A+, ...) under both;
- sharing: of the pairs of runs on one layout that chose the same first primitive, how many executed
  the same first plan (one attempt, served to the other from the sequence store), in each folder;
  and from each folder's costs.jsonl the share of attempts served and the CPU-s per episode.
Run it on the validation side: the grid is chosen there and then declared.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scenegen.experiment.transfer_stats import difference, interval  # noqa: E402


def episodes(folder: Path, condition: str) -> dict[tuple[str, str], dict[str, dict]]:
    """(panel, run) -> layout -> episode record, for one condition."""
    out = {}
    for path in sorted((folder / "episodes").glob(f"*/*_{condition}.jsonl")):
        run = path.name[: -len(f"_{condition}.jsonl")]
        rows = [json.loads(line) for line in path.read_text().splitlines()]
        out[(path.parent.name, run)] = {r["layout"]: r for r in rows}
    return out


def grids(both: dict, runs: list[str], layouts: list[tuple[str, str]], which: int) -> np.ndarray:
    """(runs, layouts) success of folder ``which`` (0: exact, 1: grid)."""
    return np.array([[float(both[(p, run)][which][lay]["success"]) for p, lay in layouts] for run in runs])


def first_plans_shared(records: dict) -> dict:
    """Pairs of runs on one layout choosing the same first primitive; of them, same first plan."""
    by_layout = defaultdict(list)
    for (panel, _), rows in records.items():
        for layout, r in rows.items():
            by_layout[(panel, layout)].append(r)
    same_primitive = same_plan = 0
    for rows in by_layout.values():
        for a, b in itertools.combinations(rows, 2):
            if a["choices"][0] == b["choices"][0]:
                same_primitive += 1
                same_plan += a["plans"][0] == b["plans"][0]
    return {"same_first_primitive": same_primitive, "same_first_plan": same_plan}


def costs(folder: Path, condition: str) -> dict:
    rows = [json.loads(line) for line in (folder / "costs.jsonl").read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r.get("condition") == condition]
    attempts, episodes_n = sum(r["attempts"] for r in rows), sum(r["episodes"] for r in rows)
    return {
        "episodes": episodes_n,
        "attempts": attempts,
        "served": round(sum(r["shared"] for r in rows) / attempts, 4) if attempts else None,
        "cpu_s_per_episode": round(sum(sum(r["cpu_seconds"].values()) for r in rows) / episodes_n, 3)
        if episodes_n
        else None,
        "simulated_cpu_s_per_episode": round(sum(r["cpu_seconds"]["simulate"] for r in rows) / episodes_n, 3)
        if episodes_n
        else None,
    }


def compare(exact: Path, grid: Path, condition: str, replicates: int = 2000) -> dict:
    first, second = episodes(exact, condition), episodes(grid, condition)
    common = sorted(set(first) & set(second))
    if not common:
        raise SystemExit(f"{exact} and {grid}: no episodes file of condition {condition!r} in both")
    both = {k: (first[k], second[k]) for k in common}
    agree = total = 0
    for rows_exact, rows_grid in both.values():
        for layout, r in rows_exact.items():
            total += 1
            agree += r["success"] == rows_grid[layout]["success"]
    panels = sorted({p for p, _ in common})
    runs = sorted(run for run in {r for _, r in common} if all((p, run) in both for p in panels))
    arms = sorted({run.rsplit("_s", 1)[0] for run in runs})  # runs on every panel (one still going: not)
    layouts = [(p, lay) for p in panels for lay in sorted(first[(p, runs[0])])]
    report: dict = {
        "condition": condition,
        "files": len(common),
        "episodes": total,
        "same_outcome": agree,
        "same_outcome_share": round(agree / total, 4),
        "arms": {},
        "contrasts": {},
    }
    by_arm = {}
    for arm in arms:
        mine = [run for run in runs if run.rsplit("_s", 1)[0] == arm]
        g_exact, g_grid = grids(both, mine, layouts, 0), grids(both, mine, layouts, 1)
        by_arm[arm] = (g_exact, g_grid)
        report["arms"][arm] = {
            "exact": interval(g_exact, replicates, seed=0),
            "grid": interval(g_grid, replicates, seed=0),
            "grid - exact": difference(g_grid, g_exact, replicates, seed=1),
        }
    for a, b in itertools.permutations(arms, 2):
        if (a, b) in {("C", "A+"), ("D", "A+"), ("D", "C"), ("D", "E"), ("D", "B"), ("A+", "A")}:
            report["contrasts"][f"{a} - {b}"] = {
                "exact": difference(by_arm[a][0], by_arm[b][0], replicates, seed=2),
                "grid": difference(by_arm[a][1], by_arm[b][1], replicates, seed=2),
            }
    report["first_plans"] = {"exact": first_plans_shared(first), "grid": first_plans_shared(second)}
    report["costs"] = {"exact": costs(exact, condition), "grid": costs(grid, condition)}
    return report


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("exact", type=Path, help="out folder evaluated with plans as planned")
    parser.add_argument("grid", type=Path, help="out folder of the same runs evaluated on a plan grid")
    parser.add_argument("--condition", default="head", help="which condition's episodes (default head)")
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args()
    report = compare(args.exact, args.grid, args.condition)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")


if __name__ == "__main__":
    main()
