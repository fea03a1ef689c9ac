"""What a version 2 run spent, read from the ``costs.jsonl`` that ``transfer_v2`` appends as it
works (issue 45; docs/transfer.md): wall seconds per trained head and chooser, and per evaluated
(run, panel, condition) its episodes, wall seconds, CPU per kind of job and the share of attempts
the sequence store served. :func:`totals` is a run's bill (report.md's "What the run cost");
:func:`measured` the rates ``transfer_cost`` projects a configuration with. A leaf: it reads files
and imports no stage, so the report and the projection both read it."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

CLASSES = ("head", "oracle", "head@shift", "oracle@shift")


def condition_class(condition: str) -> str:
    sight, _, shift = condition.partition("@")
    return f"{sight}@shift" if shift else sight


def cost_rows(folders) -> list[dict]:
    """Every row of the ``costs.jsonl`` of ``folders``."""
    rows = []
    for folder in folders:
        path = Path(folder) / "costs.jsonl"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no costs here; name the out folder of a version 2 run")
        for line in path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line torn by a kill (or being written): it counts nothing
    return rows


def _sums(rows: list[dict]) -> dict:
    """The sums both :func:`totals` and :func:`measured` read: per training stage the parts and
    their wall seconds (heads trained ``parallel`` at a time, transfer_v2.train_heads, count their
    wall over that), per condition class the episodes, wall and CPU seconds, attempts and attempts
    the sequence store served."""
    sums: dict = {"training": {}, "episodes": {}}  # a stage and a class are both called "head"
    for stage in ("head", "chooser"):
        mine = [r for r in rows if r.get("stage") == stage]
        sums["training"][stage] = {
            "n": len(mine),
            "wall_s": sum(r["wall_s"] / r.get("parallel", 1) for r in mine),
        }
    for kind in CLASSES:
        mine = [r for r in rows if "condition" in r and condition_class(r["condition"]) == kind]
        sums["episodes"][kind] = {
            "n": sum(r["episodes"] for r in mine),
            "wall_s": sum(r["wall_s"] for r in mine),
            "cpu_s": sum(sum(r["cpu_seconds"].values()) for r in mine),
            "attempts": sum(r["attempts"] for r in mine),
            "shared": sum(r["shared"] for r in mine),
        }
    return sums


def totals(folder) -> dict:
    """What a run spent, summed from its ``costs.jsonl``: heads and choosers trained (wall hours), per
    condition class the episodes evaluated, their wall and CPU hours, CPU-s per episode and the share
    of attempts the sequence store served, the whole run's wall and its evaluation's CPU hours, and
    the processors that evaluated (episodes each)."""
    rows = cost_rows([folder])
    sums = _sums(rows)
    hours = lambda seconds: round(seconds / 3600, 2)  # noqa: E731
    out: dict = {s: {"n": c["n"], "wall_h": hours(c["wall_s"])} for s, c in sums["training"].items()}
    out["episodes"] = {
        k: {
            "n": c["n"],
            "wall_h": hours(c["wall_s"]),
            "cpu_h": hours(c["cpu_s"]),
            "cpu_s_per_episode": round(c["cpu_s"] / c["n"], 2) if c["n"] else None,
            "served": round(c["shared"] / c["attempts"], 3) if c["attempts"] else None,
        }
        for k, c in sums["episodes"].items()
    }
    evaluation = {
        key: sum(c[key] for c in sums["episodes"].values()) for key in ("cpu_s", "attempts", "shared")
    }
    out["all"] = {
        "wall_h": hours(sum(c["wall_s"] for group in sums.values() for c in group.values())),
        "evaluation_cpu_h": hours(evaluation["cpu_s"]),
        "attempts": evaluation["attempts"],
        "served": round(evaluation["shared"] / evaluation["attempts"], 3) if evaluation["attempts"] else None,
    }
    processors: Counter = Counter()
    for r in rows:
        if "condition" in r:
            processors[r.get("cpu", "not recorded")] += r["episodes"]
    out["processors"] = dict(processors)
    return out


def measured(folders) -> dict:
    """Rates from the ``costs.jsonl`` of ``folders``: wall seconds per head (of the run's wall: a
    head's own over the number trained at once) and per chooser trained,
    and per class the wall and CPU seconds per episode and the share of attempts served."""
    sums = _sums(cost_rows(folders))
    out: dict = {"training": {}, "episodes": {}}
    for stage, c in sums["training"].items():
        if c["n"]:
            out["training"][stage] = {"wall_s": round(c["wall_s"] / c["n"], 1), "n": c["n"]}
    for kind, c in sums["episodes"].items():
        if c["n"]:
            out["episodes"][kind] = {
                "wall_s": round(c["wall_s"] / c["n"], 3),
                "cpu_s": round(c["cpu_s"] / c["n"], 3),
                "served": round(c["shared"] / c["attempts"], 4) if c["attempts"] else None,
                "n": c["n"],
            }
    return out
