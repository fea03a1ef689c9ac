"""Version 2's report and manifest outcome (issue 45, point 6; docs/transfer.md): from ``metrics.json``
(``transfer_v2.metrics_v2``), the episodes and ``sources.json``, the artifact's ``report.md`` in the
order the issue asks (the positive control C - A+ first, the primary endpoint D - A+, the other
contrasts, D's share of C's gain; what was run: each condition's runs, so the configuration's cuts
show; per-seed rates, per-panel closed-loop rates and contrasts, the perturbations and the oracle
rows, the heads' table, the failure labels, generation CPU-s and CPU-s per point) and, when the
configuration names a manifest, its transfer outcome (version 2) with the artifact's sha256."""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path

from scenegen.core.files import folder_sha256
from scenegen.policy.panels import PANEL_TAGS
from scenegen.store.batch import atomic_write

POSITIVE_CONTROL, PRIMARY = "C - A+", "D - A+"
# episodes evaluated through another machine's parts, beside the artifact (docs/transfer.md)
OTHER_MACHINE = "first_machine"


def _fmt(x: dict | None) -> str:
    if not x:
        return "not run"
    return f"{x['mean']:+.3f} [{x['low']:+.3f}, {x['high']:+.3f}]"


def _rate(x: dict | None) -> str:
    return "-" if not x else f"{x['mean']:.3f} [{x['low']:.3f}, {x['high']:.3f}]"


def episodes_of(out: Path, condition: str) -> dict[str, list[dict]]:
    """Per arm, the episodes of ``condition`` on the rare panels (every run of the arm)."""
    arms: dict[str, list[dict]] = {}
    for path in sorted((Path(out) / "episodes").glob(f"*/*_{condition}.jsonl")):
        if path.parent.name == "common":
            continue
        arm = path.name[: -len(f"_{condition}.jsonl")].rsplit("_s", 1)[0]
        arms.setdefault(arm, []).extend(json.loads(line) for line in path.read_text().splitlines())
    return arms


def head_table(out: Path, arms: list[str]) -> dict[str, dict[str, float]]:
    """Offline side of the closed loop: per panel and arm, the share of episodes whose first decision's
    head overlapped the target (``hit_iou``), through the head, nominal."""
    table: dict[str, dict[str, float]] = {}
    for arm, rows in episodes_of(out, "head").items():
        by_panel: dict[str, list[bool]] = {}
        for r in rows:
            score = r["perception"][0] if r["perception"] else None
            if score is not None:
                by_panel.setdefault(r["panel"], []).append(bool(score["hit_iou"]))
        for panel, hits in by_panel.items():
            table.setdefault(panel, {})[arm] = round(sum(hits) / len(hits), 3)
    return {p: {a: table[p][a] for a in arms if a in table[p]} for p in sorted(table)}


def failure_table(out: Path, condition: str = "head") -> dict[str, dict[str, int]]:
    """Per arm, its failed rare-panel episodes by first failure label (``perception`` among them)."""
    return {
        arm: dict(Counter(r["failure"] for r in rows if not r["success"]).most_common())
        for arm, rows in episodes_of(out, condition).items()
    }


def cost_per_point(metrics: dict, sources: dict) -> dict[str, dict]:
    """Generation CPU-s of C (rejection sampling), D and E, and per percentage point each arm gained
    over A+ on the rare panels through the heads (None where it gained none)."""
    spent = sources.get("generation_cpu_s", {})
    contrasts = metrics.get("head", {}).get("contrasts", {}).get("rare", {})
    out = {}
    for arm in ("C", "D", "E"):
        if arm not in spent:
            continue
        cpu = spent[arm]["cpu_s"]
        gain = contrasts.get(f"{arm} - A+", {}).get("mean")
        points = None if gain is None else 100 * gain
        out[arm] = {"cpu_s": cpu, "points_over_a_plus": points}
        out[arm]["cpu_s_per_point"] = round(cpu / points, 1) if points and points > 0 else None
    return out


def machine_effect(out: Path, other: Path) -> dict[str, dict]:
    """What another machine's parts moved (docs/transfer.md "Restarted on committed parts"): per run
    file (arm, seed, sight, condition) on the rare panels that both folders evaluated, paired by
    (panel, layout): the episodes paired, the success rate here and there, and the share of paired
    episodes whose outcome agrees. Pooled per arm and sight (nominal conditions only) under ``arms``."""

    def outcomes(folder: Path) -> dict[str, dict[tuple, bool]]:
        runs: dict[str, dict[tuple, bool]] = {}
        for path in sorted((Path(folder) / "episodes").glob("*/*.jsonl")):
            if path.parent.name == "common":
                continue
            rows = (json.loads(line) for line in path.read_text().splitlines())
            runs.setdefault(path.stem, {}).update({(r["panel"], r["layout"]): r["success"] for r in rows})
        return runs

    here, there = outcomes(out), outcomes(other)
    per_run, pooled = {}, {}
    for name in sorted(here.keys() & there.keys()):
        pairs = [(here[name][k], there[name][k]) for k in here[name].keys() & there[name].keys()]
        if not pairs:
            continue
        per_run[name] = _paired(pairs)
        if "@" not in name:  # nominal: pool per arm and sight
            run, sight = name.rsplit("_", 1)
            pooled.setdefault(f"{run.rsplit('_s', 1)[0]} {sight}", []).extend(pairs)
    arms = {name: _paired(pairs) for name, pairs in sorted(pooled.items())}
    return {"runs": per_run, "arms": arms}


def _paired(pairs: list[tuple[bool, bool]]) -> dict:
    """Episodes paired, the success rate here and there, and the share of outcomes that agree."""
    n = len(pairs)
    return {
        "paired": n,
        "here": round(sum(x for x, _ in pairs) / n, 3),
        "there": round(sum(y for _, y in pairs) / n, 3),
        "agree": round(sum(x == y for x, y in pairs) / n, 3),
    }


def machine_lines(effect: dict) -> list[str]:
    """The report's section on another machine's parts (nothing when no run was evaluated on both)."""
    if not effect["arms"]:
        return []
    lines = [
        "## Another machine's parts (the first machine's heads and choosers, same data and seeds)",
        "",
        "Rare panels, nominal; paired by (panel, layout). Not part of any contrast: it measures what "
        "retraining the same arm on another processor moves.",
        "",
        "| arm, sight | paired episodes | rate here | rate there | outcomes agreeing |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {r['paired']} | {r['here']:.3f} | {r['there']:.3f} | {r['agree']:.3f} |"
        for name, r in effect["arms"].items()
    ]
    return lines + [""]


def report(metrics: dict, out: Path, sources: dict, other: Path | None = None) -> str:
    """The artifact's report.md; with ``other`` (episodes evaluated through another machine's parts),
    a last section comparing them."""
    head = metrics.get("head", {})
    rare = head.get("contrasts", {}).get("rare", {})
    lines = [
        f"# Transfer version 2 ({metrics['side']} side)",
        "",
        "Success in closed loop on the rare panels pooled, each run through its own retrieval head; 95 % "
        "hierarchical bootstrap intervals (seeds and layouts resampled, paired by layout).",
        "",
        f"- **Positive control C - A+: {_fmt(rare.get(POSITIVE_CONTROL))}**"
        + (
            ""
            if not rare.get(POSITIVE_CONTROL)
            else f" (excludes 0: {excludes_zero(rare[POSITIVE_CONTROL])})"
        ),
        f"- **Primary endpoint D - A+: {_fmt(rare.get(PRIMARY))}**",
    ]
    lines += [
        f"- {name}: {_fmt(value)}" for name, value in rare.items() if name not in (POSITIVE_CONTROL, PRIMARY)
    ]
    share, control = head.get("share"), rare.get(POSITIVE_CONTROL)
    if share and share["mean"] is not None and control and control["low"] > 0:
        lines.append(f"- D's share of the C - A+ gain: {_fmt(share)}")
    elif share:  # a ratio over a gain that may be 0 or negative says nothing
        lines.append("- D's share of the C - A+ gain: undefined (C - A+ is not above 0)")
    lines += ["", *scope_lines(metrics)]
    lines += [
        "",
        "## Per arm (rare panels pooled) and per seed",
        "",
        "| arm | rate | per seed |",
        "|---|---|---|",
    ]
    per_seed = head.get("per_seed", {}).get("rare", {})
    for arm, value in head.get("rates", {}).get("rare", {}).items():
        seeds = ", ".join(f"{v:.3f}" for n, v in per_seed.items() if n.rsplit("_s", 1)[0] == arm)
        lines.append(f"| {arm} | {_rate(value)} | {seeds} |")
    lines += ["", "## Per panel and condition", ""]
    conditions = [c for c in metrics if isinstance(metrics[c], dict) and "rates" in metrics[c]]
    for condition in conditions:
        rates = metrics[condition]["rates"]
        arms = sorted({a for group in rates.values() for a in group})
        lines += [
            f"### {condition}",
            "",
            "| panel | " + " | ".join(arms) + " |",
            "|---" * (len(arms) + 1) + "|",
        ]
        for group, by_arm in rates.items():
            lines.append(f"| {group} | " + " | ".join(_rate(by_arm.get(a)) for a in arms) + " |")
        lines.append("")
    contrasts = head.get("contrasts", {})
    names = list(contrasts.get("rare", {}))
    if names:
        lines += [
            "## Contrasts per panel (through the heads)",
            "",
            *contrast_table("panel", contrasts, names),
        ]
    lines += condition_contrast_lines(metrics, conditions)
    lines += ["## The heads, offline: first decision overlapping the target", ""]
    table = head_table(out, list(head.get("rates", {}).get("rare", {})))
    arms = sorted({a for row in table.values() for a in row})
    lines += ["| panel | " + " | ".join(arms) + " |", "|---" * (len(arms) + 1) + "|"]
    shown = lambda row, a: "-" if a not in row else f"{row[a]:.3f}"  # noqa: E731
    lines += [f"| {p} | " + " | ".join(shown(row, a) for a in arms) + " |" for p, row in table.items()]
    lines += ["", "## Failure labels (rare panels, through the heads)", ""]
    for arm, counts in failure_table(out).items():
        lines.append(f"- {arm}: " + (", ".join(f"{k} {v}" for k, v in counts.items()) or "none"))
    lines += ["", "## Generation CPU-s", ""]
    for arm, c in cost_per_point(metrics, sources).items():
        per = "no gain over A+" if c["cpu_s_per_point"] is None else f"{c['cpu_s_per_point']} CPU-s per point"
        lines.append(f"- {arm}: {c['cpu_s']} CPU-s; {per}")
    lines += ["", *cost_lines(out)]
    if other is not None:
        lines += [""] + machine_lines(machine_effect(out, other))
    return "\n".join(lines).rstrip("\n") + "\n"


def condition_contrast_lines(metrics: dict, conditions: list[str]) -> list[str]:
    """The contrasts on the rare panels pooled under every condition (through the heads, through true
    masks, each under its shifts): one row per condition, the contrasts its arms allow."""
    pooled = {c: metrics[c].get("contrasts", {}).get("rare", {}) for c in conditions}
    names = list(dict.fromkeys(n for by_name in pooled.values() for n in by_name))
    if not names:
        return []
    return [
        "## Contrasts per condition (rare panels pooled)",
        "",
        *contrast_table("condition", pooled, names),
    ]


def contrast_table(first: str, rows: dict[str, dict], names: list[str]) -> list[str]:
    """A markdown table: one row per key of ``rows`` (named by the column ``first``), the contrasts
    ``names`` in columns ("not run" where a row has none), and a blank line."""
    lines = [f"| {first} | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    lines += [
        f"| {row} | " + " | ".join(_fmt(by_name.get(n)) for n in names) + " |"
        for row, by_name in rows.items()
    ]
    return [*lines, ""]


def scope_lines(metrics: dict) -> list[str]:
    """What was run: each arm's training seeds, the panels with their layouts, the conditions and
    which arms and seeds each covers (the cuts of the configuration show here), and the rare tags
    with no panel run."""
    seeds: dict[str, list[int]] = {}
    for run in metrics.get("runs", []):
        seeds.setdefault(run["arm"], []).append(run["seed"])
    panels = metrics.get("panels", {})
    no_panel = [t for t in PANEL_TAGS if t not in panels]  # the test side's: under_overhang
    lines = [
        "## What was run",
        "",
        "- arms and training seeds: " + "; ".join(f"{a} {s}" for a, s in seeds.items()),
        "- panels (layouts): " + ", ".join(f"{p} {len(ids)}" for p, ids in panels.items()),
        *([f"- rare tags with no panel run, out of scope: {', '.join(no_panel)}"] if no_panel else []),
    ]
    for condition, block in metrics.items():
        if not (isinstance(block, dict) and "per_seed" in block):
            continue
        runs = sorted({n for group in block["per_seed"].values() for n in group})
        lines.append(f"- {condition}: {', '.join(runs)}")
    return lines


def cost_lines(out: Path) -> list[str]:
    """What the run spent (``transfer_ledger.totals`` over its costs.jsonl): training, and evaluation
    per condition class, wall and CPU hours, and the processors that evaluated."""
    from scenegen.experiment.transfer_ledger import totals

    spent = totals(out)
    lines = [
        "## What the run cost (costs.jsonl)",
        "",
        "Wall hours as measured, including any time the machine was shared; CPU hours of the evaluation "
        "jobs.",
        "",
        f"- heads: {spent['head']['n']} trained, {spent['head']['wall_h']} h of wall",
        f"- choosers: {spent['chooser']['n']} trained, {spent['chooser']['wall_h']} h of wall",
    ]
    for kind, c in spent["episodes"].items():
        if c["n"]:
            lines.append(
                f"- {c['n']:,} episodes {kind}: {c['wall_h']} h of wall, {c['cpu_h']} CPU-h "
                f"({c['cpu_s_per_episode']} CPU-s each; the sequence store served {c['served']:.0%} "
                "of the attempts)"
            )
    run = spent["all"]
    if run["attempts"]:
        lines.append(
            f"- in all: {run['wall_h']} h of wall, the evaluation {run['evaluation_cpu_h']} CPU-h; the store "
            f"served {run['served']:.0%} of {run['attempts']:,} attempts (the rest simulated)"
        )
    lines += [f"- evaluated on {cpu}: {n} episodes" for cpu, n in spent["processors"].items()]
    return lines


def excludes_zero(contrast: dict) -> bool:
    return contrast["low"] > 0 or contrast["high"] < 0


def finish_v2(config, metrics: dict, out: Path) -> dict:
    """report.md into the artifact, then its checksum and, with ``config.manifest``, the manifest's
    transfer outcome; returns the checksum and the endpoints. A folder ``first_machine`` beside the
    artifact (episodes through another machine's parts) adds the report's last section."""
    out = Path(out)
    sources = json.loads((out / "sources.json").read_text())
    other = out.parent / OTHER_MACHINE
    atomic_write(out / "report.md", report(metrics, out, sources, other if other.is_dir() else None).encode())
    checksum = folder_sha256(out)
    if config.manifest is not None:
        write_outcome_v2(Path(config.manifest), out, checksum, metrics, config)
    return {"artifact_sha256": checksum}


def write_outcome_v2(manifest_path: Path, out: Path, checksum: str, metrics: dict, config) -> None:
    """The manifest's transfer section, version 2: measured on a simulated panel, each arm's rates
    through its heads (rare pooled and common) and through true masks, the positive control, the
    primary endpoint, every contrast, and the artifact's location and checksum."""
    from scenegen.manifest.io import read_manifest, write_manifest
    from scenegen.manifest.schema import TransferOutcome

    manifest = read_manifest(manifest_path)
    head, oracle = metrics.get("head", {}), metrics.get("oracle", {})
    arms = {}
    for arm, rate in head.get("rates", {}).get("rare", {}).items():
        arms[arm] = {
            "seeds": sorted(
                int(n.rsplit("_s", 1)[1]) for n in head["per_seed"]["rare"] if n.rsplit("_s", 1)[0] == arm
            ),
            "rare": rate,
            "common": head["rates"].get("common", {}).get(arm),
            "oracle_rare": oracle.get("rates", {}).get("rare", {}).get(arm),
        }
    rare = head.get("contrasts", {}).get("rare", {})
    outcome = TransferOutcome(
        status="measured",
        panel="simulated",
        note="Version 2: each arm through its own retrieval head. Simulated stand-ins for real rare cases "
        f"(panel_origin: reference): the {metrics['side']} side of {config.panels}; never real. Full tables "
        "in the artifact's report.md.",
        metrics={
            "version": 2,
            "positive_control": {"contrast": POSITIVE_CONTROL, **(rare.get(POSITIVE_CONTROL) or {})},
            "primary": {
                "endpoint": "rare-panel success of D minus A+ through each run's own head",
                **(rare.get(PRIMARY) or {}),
            },
            "contrasts": rare,
            "arms": arms,
            "panels": {"file": str(config.panels), "side": metrics["side"], "panel_origin": "reference"},
            "plan_grid": metrics.get("plan_grid"),
        },
        artifact=Path(os.path.relpath(out.resolve(), manifest_path.resolve().parent)).as_posix(),
        artifact_sha256=checksum,
    )
    write_manifest(manifest_path, manifest.model_copy(update={"transfer": outcome}))
