"""What seeing for itself costs the policy: one policy in closed loop on a version 2 panel, through a
retrieval head and through the oracle's masks (``scenegen experiment perception-gap``).

Both settings run on one sequence store (sequences.PathStore, keyed by the plans executed), the
head first, then the oracle, each with its own :class:`~scenegen.experiment.closed_loop.Cost`: how
many attempts the store answered and the CPU seconds of each kind of job. The gap between the two
success rates is the most any data can add to a policy that sees through this head (docs/policy.md).
Writes ``episodes_<setting>.jsonl``, ``summary.json`` and ``summary.md``; resumable (the store and the
observation cache keep what was measured).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from scenegen.env.physics import DEFAULT_PHYSICS, physics_named
from scenegen.experiment.closed_loop import Cost, Workers, evaluate_policies
from scenegen.experiment.sequences import NOMINAL, ObservationStore, PathStore, Variant
from scenegen.experiment.transfer_stats import episodes_block
from scenegen.store.batch import atomic_write


def summarise(records: list[dict], panels: dict[str, list[str]]) -> dict:
    """Success with a 95 % Wilson interval, perception failures and failure labels, per panel and
    over all of them (an episode counts once per panel that holds its layout)."""
    by_id = {}
    for r in records:
        by_id.setdefault(r["panel_id"], r)
    out = {"all": episodes_block(list(by_id.values()))}
    for name, ids in panels.items():
        out[name] = episodes_block([by_id[i] for i in ids if i in by_id])
    return out


def run_gap(
    checkpoint: Path,
    retrieval: Path,
    panel: dict[str, list],
    out: Path,
    workers: int = 1,
    progress: bool = True,
    rules: int | None = None,
    sensor: str = "exact",
    physics: str = DEFAULT_PHYSICS,
    proposals: Path | None = None,
    candidates=None,
) -> dict:
    """Evaluate the policy at ``checkpoint`` on ``panel`` (panel name -> EnvScenes, each with its
    ``panel_id``) through ``retrieval`` and through the oracle, the head's decisions scored by the
    perception rules' version ``rules`` (default: the current one), every depth frame through
    ``sensor`` (exact: the renderer's), simulated under ``physics``; write and return the summary.
    ``proposals``: a proposal model's folder acts instead of the policy (issue 63: sampled candidates
    ranked by the model, ``proposal_loop.evaluate_proposals``), ``candidates`` of them per decision (a
    SamplerConfig; default ``proposal_loop.DECISIONS``')."""
    from tqdm import tqdm

    from scenegen.core.files import folder_sha256
    from scenegen.perception.retrieval.evaluate import PERCEPTION_RULES
    from scenegen.policy.network import PrimitivePolicy
    from scenegen.policy.panels_v2 import panel_id

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    policy = PrimitivePolicy.load(checkpoint) if proposals is None else None
    if proposals is not None:
        from scenegen.experiment.proposal_loop import DECISIONS, evaluate_proposals

        decisions = DECISIONS if candidates is None else dataclasses.replace(DECISIONS, sampler=candidates)
    scenes = list({panel_id(s): s for ss in panel.values() for s in ss}.values())
    ids = {name: [panel_id(s) for s in ss] for name, ss in panel.items()}
    store = PathStore(out / "paths.jsonl")
    observations = ObservationStore(out / "observations")
    summary = {
        "checkpoint": str(checkpoint),
        "retrieval": str(retrieval),
        "retrieval_sha256": folder_sha256(Path(retrieval)),  # the head: its whole folder
        "perception_rules": PERCEPTION_RULES if rules is None else rules,
        "layouts": len(scenes),
        **({"sensor": sensor} if sensor != "exact" else {}),
        **(
            {
                "proposals": str(proposals),
                "proposals_sha256": folder_sha256(Path(proposals)),
                "candidates": dataclasses.asdict(decisions.sampler),
            }  # fmt: skip
            if proposals
            else {}
        ),
        "physics": physics_named(physics).key(),
        "settings": {},
    }
    variant = NOMINAL if sensor == "exact" else Variant(f"sensor_{sensor}", 1.0, sensor)
    with Workers(workers, physics) as pool:
        for setting, head in (("learned", retrieval), ("oracle", None)):
            cost = Cost()
            began = time.monotonic()
            with tqdm(desc=setting, unit=" jobs", disable=not progress) as bar:
                if proposals is not None:
                    tick = lambda _, bar=bar: bar.update()  # noqa: E731
                    records = evaluate_proposals(proposals, scenes, store, observations, pool, head, variant,
                                                 decisions, cost=cost, progress=tick)  # fmt: skip
                else:
                    records = evaluate_policies(
                        {"policy": policy},
                        scenes,
                        store,
                        observations,
                        variant,
                        pool,
                        lambda _, bar=bar: bar.update(),
                        head,
                        cost,
                        summary["perception_rules"],
                    )
            for scene, record in zip(scenes, records, strict=True):
                record["panel_id"] = panel_id(scene)
            lines = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records)
            atomic_write(out / f"episodes_{setting}.jsonl", lines.encode())
            summary["settings"][setting] = {
                "success": summarise(records, ids),
                "cost": cost.summary(len(records)),
                "wall_seconds": round(time.monotonic() - began, 1),
            }
    summary["store_mismatches"] = store.mismatches
    atomic_write(out / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())
    atomic_write(out / "summary.md", markdown(summary).encode())
    return summary


def markdown(summary: dict) -> str:
    """Per panel: success through the head and through the oracle, the gap, perception failures."""
    learned, oracle = (summary["settings"][s]["success"] for s in ("learned", "oracle"))
    lines = [
        "| panel | episodes | learned | oracle | gap (points) | perception failures (learned) "
        "| first decision hit (centre) | first decision hit (IoU >= 0.5) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in learned:
        a, b = learned[name], oracle[name]
        if not a["episodes"]:
            continue
        gap = 100 * (b["success"] - a["success"])
        lines.append(
            f"| {name} | {a['episodes']} | {a['success']:.3f} | {b['success']:.3f} | {gap:+.1f} | "
            f"{a['perception_failures']} | {a['first_decision_hit']} | {a.get('first_decision_hit_iou')} |"
        )
    lines.append("")
    for setting, block in summary["settings"].items():
        cost = block["cost"]
        lines.append(
            f"{setting}: {cost['episodes']} episodes, {cost['attempts']} attempts, {cost['shared']} from the "
            f"store (sharing rate {cost['sharing_rate']}), {cost['sequences_simulated']} simulated, "
            f"{cost['cpu_per_episode']} CPU-s per episode ({cost['cpu_seconds']})"
        )
    return "\n".join(lines) + "\n"
