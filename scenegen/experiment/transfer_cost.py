"""What a version 2 configuration will cost, projected from what earlier runs measured (issue 45,
point 5; ``scenegen experiment transfer CONFIG --estimate FOLDER...``; docs/transfer.md).

The work of a configuration is counted, not guessed: its runs (each a head and a chooser to train)
and, per condition class (through the head or true masks, nominal or shifted), the episodes its
panels x runs x conditions hold (:func:`planned`). The measured side is the rates an earlier run's
``costs.jsonl`` holds (``transfer_ledger.measured``). :func:`project` multiplies the two; a class never
measured takes the nominal head's rate (said in the output). :func:`status` says how far a run that
goes on across sessions has come (``--status``): what each arm has evaluated, what is left at the
out folder's own rates, and the contrasts whose arms are whole (the figures the finished run will
report: each contrast reads its two arms' episodes alone)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from scenegen.experiment.transfer_config import TransferConfigV2
from scenegen.experiment.transfer_ledger import CLASSES, condition_class, measured


def planned(config: TransferConfigV2) -> dict:
    """The configuration's work: ``runs`` (heads and choosers to train) and ``episodes`` per class."""
    from scenegen.experiment.transfer_v2 import conditions, panels_v2, runs_v2

    runs, sizes = runs_v2(config), {p: len(s) for p, s in panels_v2(config).items()}
    episodes: Counter = Counter()
    for run in runs:
        for panel, n in sizes.items():
            for condition, _ in conditions(config, run, panel):
                episodes[condition_class(condition)] += n
    return {"runs": len(runs), "panels": sizes, "episodes": {c: episodes[c] for c in CLASSES}}


def project(config: TransferConfigV2, rates: dict) -> dict:
    """Hours of wall time for ``config`` at the measured ``rates`` (:func:`measured`)."""
    work = planned(config)
    training = rates["training"]
    per_run = sum(training.get(s, {}).get("wall_s", 0.0) for s in ("head", "chooser"))
    base = rates["episodes"].get("head")
    if base is None:
        raise ValueError("the costs measured hold no nominal episode through a head; run a pilot first")
    hours, assumed = {"training": work["runs"] * per_run / 3600}, []
    busy = {"training": hours["training"]}  # episodes at their CPU-s over the workers: no waiting
    for kind, n in work["episodes"].items():
        rate = rates["episodes"].get(kind)
        if rate is None and n:
            assumed.append(kind)
        hours[kind] = n * (rate or base)["wall_s"] / 3600
        busy[kind] = n * (rate or base)["cpu_s"] / config.workers / 3600
    return {
        "work": work,
        "hours": {k: round(v, 2) for k, v in hours.items()},
        "total_hours": round(sum(hours.values()), 2),
        "total_hours_at_cpu": round(sum(busy.values()), 2),
        "assumed_like_head": assumed,
    }


def describe(projection: dict, rates: dict) -> str:
    """The projection as lines a person reads."""
    work, hours = projection["work"], projection["hours"]
    lines = [f"{work['runs']} runs (a head and a chooser each): {hours['training']:.2f} h"]
    for kind in CLASSES:
        rate = rates["episodes"].get(kind)
        served = f", {rate['served']:.0%} of attempts served" if rate and rate["served"] is not None else ""
        measured_at = f"{rate['wall_s']:.2f} s wall each{served}" if rate else "not measured: as head"
        lines.append(f"{work['episodes'][kind]} episodes {kind}: {hours[kind]:.2f} h ({measured_at})")
    lines.append(f"total: {projection['total_hours']:.2f} h of wall time at the measured wall rates")
    lines.append(
        f"       {projection['total_hours_at_cpu']:.2f} h with the episodes' CPU-s spread over the "
        "workers (no waiting: the floor where the measuring machine was shared)"
    )
    return "\n".join(lines)


# where a configuration keeps things, not what it runs: they may differ between machines
STORAGE_KEYS = ("cache", "label_store", "path_store", "batches", "out")


def check_folder(config: TransferConfigV2) -> None:
    """Refuse (TransferError, one line) an out folder that holds no run, or another configuration's
    run (its config.yaml differs in what is run; storage keys aside): file names do not say which
    side or sizes their episodes came from."""
    import yaml

    from scenegen.experiment.transfer import TransferError
    from scenegen.experiment.transfer_v2 import resolved_config

    held = Path(config.out) / "config.yaml"
    if not held.is_file():
        raise TransferError(f"{config.out}: no run here yet (no config.yaml); start it without --status")
    mine, theirs = yaml.safe_load(resolved_config(config)), yaml.safe_load(held.read_text()) or {}
    keys = sorted({k for k in (*mine, *theirs) if k not in STORAGE_KEYS and mine.get(k) != theirs.get(k)})
    if keys:
        raise TransferError(
            f"{config.out}: holds another configuration's run (config.yaml differs in {', '.join(keys)}); "
            "name the configuration it ran"
        )


def status(config: TransferConfigV2) -> dict:
    """Where the run of ``config`` stands, read from its out folder (writes nothing; refuses a
    folder of another configuration, :func:`check_folder`): per arm its runs evaluated whole and its
    episodes done of planned (an episodes file is written whole, so one that exists is done), the
    episodes left per condition class and the hours their evaluation takes at the folder's own
    measured rates (a class not measured there at the nominal head's: ``assumed_like_head``), and
    ``metrics_v2`` over the arms whose every file is there: a contrast reads its two arms' episodes
    alone, with a bootstrap seed set by its panel group, so these are the finished run's figures."""
    from scenegen.experiment.transfer_v2 import conditions, episodes_file, metrics_v2, panels_v2, runs_v2

    check_folder(config)
    out, panels = Path(config.out), panels_v2(config)
    arms: dict = {arm: {"runs": 0, "whole": 0, "episodes": 0, "done": 0} for arm in config.arms}
    left: Counter = Counter()
    for run in runs_v2(config):
        row, complete = arms[run["arm"]], True
        for panel, scenes in panels.items():
            for condition, _ in conditions(config, run, panel):
                row["episodes"] += len(scenes)
                if episodes_file(out, panel, run["name"], condition).is_file():
                    row["done"] += len(scenes)
                else:
                    complete = False
                    left[condition_class(condition)] += len(scenes)
        row["runs"] += 1
        row["whole"] += complete
    rates = measured([out]) if (out / "costs.jsonl").is_file() else {"episodes": {}}
    base = rates["episodes"].get("head")
    hours: dict | None = {"wall": 0.0, "cpu": 0.0}
    assumed = sorted(kind for kind in left if kind not in rates["episodes"])
    for kind, n in left.items():
        rate = rates["episodes"].get(kind, base)
        if rate is None:
            hours = None
            break
        hours["wall"] += n * rate["wall_s"] / 3600
        hours["cpu"] += n * rate["cpu_s"] / config.workers / 3600
    whole = [arm for arm, row in arms.items() if row["runs"] == row["whole"]]
    metrics = None
    if whole:
        part = config.model_copy(update={"arms": tuple(whole)})
        metrics = metrics_v2(part, runs_v2(part), panels, out)
    return {
        "out": str(out),
        "arms": arms,
        "left": dict(left),
        "hours_left": hours,
        "assumed_like_head": assumed,
        "whole_arms": whole,
        "metrics": metrics,
    }


def describe_status(state: dict) -> str:
    """:func:`status` as lines a person reads."""
    arms = state["arms"]
    done, planned_ = sum(r["done"] for r in arms.values()), sum(r["episodes"] for r in arms.values())
    share = f"{int(1000 * done / planned_) / 10:.1f} %"  # rounded down: 100 % only when all is in
    lines = [f"{state['out']}: {done:,} of {planned_:,} episodes evaluated ({share})"]
    for arm, row in arms.items():
        lines.append(
            f"  {arm}: {row['whole']} of {row['runs']} runs whole, "
            f"{row['done']:,} of {row['episodes']:,} episodes"
        )
    hours, left = state["hours_left"], sum(state["left"].values())
    if not left:
        lines.append(
            "every episode is in: rerun the command to write metrics.json, the report and the outcome"
        )
    elif hours is None:
        lines.append(f"evaluation left: {left:,} episodes (no rate measured yet in this folder)")
    else:
        assumed = state["assumed_like_head"]
        lines.append(
            f"evaluation left: {left:,} episodes, about {hours['wall']:.1f} h of wall at this folder's "
            f"measured rates ({hours['cpu']:.1f} h with its CPU-s spread over the workers)"
            + (f"; {', '.join(assumed)} not measured here: at the head's rate" if assumed else "")
        )
    if state["metrics"] is None:
        lines.append("no arm is whole yet: no contrast to show")
    else:
        lines.append(f"whole arms: {', '.join(state['whole_arms'])} (their figures are final: below)")
    return "\n".join(lines)
