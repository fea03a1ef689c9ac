"""The transfer experiment's results: metrics with intervals (metrics.json), the report (report.md),
the plot (transfer.png: success per arm on both panels, per tag on the rare panel, the alpha curve),
the artifact's checksum and the manifest's transfer outcome."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from scenegen.core.files import folder_sha256
from scenegen.experiment.transfer_config import ARMS, TransferConfig
from scenegen.experiment.transfer_stats import difference, interval, success_grid
from scenegen.policy.failures import LABELS
from scenegen.store.batch import atomic_write

PRIMARY = ("D", "A+")  # the primary endpoint: rare-panel success of D minus A+ at the default alpha


def read_episodes(out: Path) -> list[dict]:
    records = []
    for path in sorted((out / "episodes").glob("*.jsonl")):
        records += [json.loads(line) for line in path.read_text().splitlines() if line]
    return records


def compute_metrics(config: TransferConfig, all_runs: list[dict], panels: dict, records: list[dict]) -> dict:
    """Every figure of the report (see docs/transfer_v1.md, 'Statistics')."""
    boot, seed = config.bootstrap, config.seed
    episodes: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        episodes.setdefault((r["panel"], r["variant"]), []).append(r)
    ids = {name: [s.scene_id for s in group] for name, group in panels.items()}

    def grid(arm_runs, panel, variant="nominal", scene_ids=None):
        return success_grid(
            episodes[(panel, variant)], [r["name"] for r in arm_runs], scene_ids or ids[panel]
        )

    def select(arm, alpha=config.alpha, inputs="rgbd", seeds=None):
        chosen = [r for r in all_runs if r["arm"] == arm and r["alpha"] == alpha and r["inputs"] == inputs]
        return [r for r in chosen if seeds is None or r["seed"] in seeds]

    by_tag = {t: [s.scene_id for s in panels["rare"] if s.tags.get(t)] for t in config.tags}
    arms = {}
    for arm in ARMS:
        chosen = select(arm)
        names = {r["name"] for r in chosen}
        failures = {}
        for panel in ("rare", "common"):
            failed = [r for r in episodes[(panel, "nominal")] if r["policy"] in names and not r["success"]]
            counts = Counter(r["failure"] for r in failed)
            counts["out_of_time"] = sum(bool(r.get("out_of_time")) for r in failed)
            failures[panel] = dict(counts)
        arms[arm] = {
            "alpha": config.alpha if arm not in ("A", "A+") else 0.0,
            "seeds": [r["seed"] for r in chosen],
            "rare": interval(grid(chosen, "rare"), boot, seed),
            "common": interval(grid(chosen, "common"), boot, seed),
            "per_tag": {
                t: interval(grid(chosen, "rare", scene_ids=s), boot, seed) for t, s in by_tag.items() if s
            },
            "failures": failures,
        }
    metrics = {
        "primary": {
            "endpoint": "rare-panel success of D minus A+ at the default alpha",
            **difference(grid(select("D"), "rare"), grid(select("A+"), "rare"), boot, seed),
        },
        "arms": arms,
        "exploratory": {},
        "panels": {name: len(group) for name, group in ids.items()},
        "panels_file": str(config.panels),
        "default_alpha": config.alpha,
    }
    explore = metrics["exploratory"]
    for other in ("A", "B", "C", "E"):
        explore[f"D - {other} (rare)"] = difference(
            grid(select("D"), "rare"), grid(select(other), "rare"), boot, seed
        )
    for other in ("A+", "A"):
        explore[f"D - {other} (common)"] = difference(
            grid(select("D"), "common"), grid(select(other), "common"), boot, seed
        )
    first = config.training.seeds[:1]
    metrics["alpha_sweep"] = {
        f"{alpha:g}": {
            panel: interval(grid(select("D", alpha, seeds=first), panel), boot, seed)
            for panel in ("rare", "common")
        }
        for alpha in config.alpha_sweep
    }
    if config.state_ablation:
        metrics["state_ablation"] = {
            arm: {
                panel: interval(grid(select(arm, inputs="state"), panel), boot, seed)
                for panel in ("rare", "common")
            }
            for arm in config.state_ablation
        }
    perturbation = config.perturbation
    if perturbation is not None:
        shifted = {
            arm: interval(grid(select(arm), "rare", perturbation.name), boot, seed)
            for arm in perturbation.arms
        }
        metrics["perturbation"] = {
            "name": perturbation.name,
            "light_scale": perturbation.light_scale,
            "rare": shifted,
        }
    return metrics


def cost_lines(metrics: dict, sources: dict) -> dict:
    """Generation CPU-s of C, D and E and CPU-s per rare-panel percentage point gained over A."""
    base = metrics["arms"]["A"]["rare"]["mean"]
    out = {}
    for arm in ("C", "D", "E"):
        cpu = sources["generation_cpu_s"][arm]["cpu_s"]
        gain = 100 * (metrics["arms"][arm]["rare"]["mean"] - base)
        out[arm] = {
            "cpu_s": cpu,
            "points_over_A": round(gain, 2),
            "cpu_s_per_point": round(cpu / gain, 1) if gain > 0 else None,
        }
    return out


def _fmt(x: dict) -> str:
    return f"{x['mean']:.3f} [{x['low']:.3f}, {x['high']:.3f}]"


def report(config: TransferConfig, metrics: dict) -> str:
    arms = metrics["arms"]
    p = metrics["primary"]
    lines = [
        f"# Transfer experiment: {config.name}",
        "",
        f"Primary endpoint ({p['endpoint']}): **{p['mean']:+.3f}** [{p['low']:+.3f}, {p['high']:+.3f}] "
        f"(95 % hierarchical bootstrap over {p['seeds']} seeds and {p['scenes']} rare-panel scenes).",
        "",
        "| arm | alpha | seeds | rare panel | common panel | generation CPU-s | CPU-s per point over A |",
        "|---|---|---|---|---|---|---|",
    ]
    for arm, m in arms.items():
        cost = metrics["cost"].get(arm, {})
        lines.append(
            f"| {arm} | {m['alpha']:g} | {len(m['seeds'])} | {_fmt(m['rare'])} | {_fmt(m['common'])} "
            f"| {cost.get('cpu_s', '-')} | {cost.get('cpu_s_per_point') or '-'} |"
        )
    shared = metrics["cost"].get("evaluation")
    if shared:
        lines += [
            "",
            f"Evaluation: {shared['episodes']} episodes; evaluated one policy at a time they would execute "
            f"{shared['primitive_executions_unshared']} primitives, the shared store holds "
            f"{shared['sequences_in_store']} measured sequences.",
        ]
    tags = list(next(iter(arms.values()))["per_tag"])
    lines += [
        "",
        "Rare panel per tag (descriptive):",
        "",
        "| arm | " + " | ".join(tags) + " |",
        "|---" * (len(tags) + 1) + "|",
    ]
    for arm, m in arms.items():
        lines.append(f"| {arm} | " + " | ".join(f"{m['per_tag'][t]['mean']:.2f}" for t in tags) + " |")
    lines += ["", "Exploratory differences:", ""]
    lines += [
        f"- {name}: {d['mean']:+.3f} [{d['low']:+.3f}, {d['high']:+.3f}]"
        for name, d in metrics["exploratory"].items()
    ]
    lines += ["", "Alpha sweep (D, one seed):", "", "| alpha | rare | common |", "|---|---|---|"]
    lines += [f"| {a} | {_fmt(v['rare'])} | {_fmt(v['common'])} |" for a, v in metrics["alpha_sweep"].items()]
    if "state_ablation" in metrics:
        lines += [
            "",
            "State-observation ablation (policy input: state features):",
            "",
            "| arm | rare | common |",
            "|---|---|---|",
        ]
        lines += [
            f"| {a} | {_fmt(v['rare'])} | {_fmt(v['common'])} |" for a, v in metrics["state_ablation"].items()
        ]
    if "perturbation" in metrics:
        pert = metrics["perturbation"]
        lines += ["", f"Rare panel under {pert['name']} (lights x {pert['light_scale']}):", ""]
        lines += [f"- {a}: {_fmt(v)} (nominal {_fmt(arms[a]['rare'])})" for a, v in pert["rare"].items()]
    lines += [
        "",
        "Failure labels (failed episodes, all seeds): the first attempt's cause; out_of_time beside it:",
        "",
        "| arm | panel | " + " | ".join(_LABELS) + " |",
        "|---" * (len(_LABELS) + 2) + "|",
    ]
    for arm, m in arms.items():
        for panel, counts in m["failures"].items():
            lines.append(f"| {arm} | {panel} | " + " | ".join(str(counts.get(k, 0)) for k in _LABELS) + " |")
    return "\n".join(lines) + "\n"


_LABELS = (*LABELS, "out_of_time")  # the first attempt's cause; the time-limit flag beside it
_COLOURS = [(180, 120, 40), (40, 40, 200), (60, 160, 60), (30, 140, 220), (160, 60, 160), (120, 120, 120)]


def plot(metrics: dict, size=(1200, 760)) -> bytes:
    """Three panels: success per arm (rare, common) with intervals; per tag (rare); D's alpha curve."""
    import cv2

    w, h = size
    image = np.full((h, w, 3), 255, np.uint8)
    arms = metrics["arms"]

    def frame(left, top, pw, ph, title):
        cv2.rectangle(image, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
        cv2.putText(image, title, (left, top - 8), 0, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        for k in range(5):
            y = int(top + ph - k / 4 * ph)
            cv2.line(image, (left, y), (left + pw, y), (225, 225, 225), 1)
            cv2.putText(image, f"{k / 4:.2f}", (left - 40, y + 4), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        return lambda v: int(top + ph - min(max(v, 0), 1) * ph)

    def bar(x, width, value, y_of, colour, whisker=None):
        cv2.rectangle(image, (x, y_of(value)), (x + width, y_of(0)), colour, -1)
        if whisker:
            cx = x + width // 2
            cv2.line(image, (cx, y_of(whisker[0])), (cx, y_of(whisker[1])), (0, 0, 0), 1)

    left, top, pw, ph = 60, 50, 500, 290
    y_of = frame(left, top, pw, ph, "success per arm: rare (dark), common (light) panel, 95% intervals")
    step = pw // len(arms)
    for i, (arm, m) in enumerate(arms.items()):
        x = left + i * step + 10
        for j, (panel, shade) in enumerate((("rare", 1.0), ("common", 0.55))):
            colour = tuple(int(255 - (255 - c) * shade) for c in _COLOURS[i % len(_COLOURS)])
            bar(
                x + j * (step // 2 - 5),
                step // 2 - 10,
                m[panel]["mean"],
                y_of,
                colour,
                (m[panel]["low"], m[panel]["high"]),
            )
        cv2.putText(image, arm, (x + step // 4, top + ph + 18), 0, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    left2 = 640
    y_of = frame(left2, top, pw, ph, "D's alpha sweep (one seed): rare (dark), common (light)")
    sweep = metrics["alpha_sweep"]
    for panel, shade in (("rare", 1.0), ("common", 0.55)):
        colour = tuple(int(255 - (255 - c) * shade) for c in _COLOURS[4])
        pts = [
            (left2 + 30 + k * (pw - 60) // max(len(sweep) - 1, 1), y_of(v[panel]["mean"]))
            for k, v in enumerate(sweep.values())
        ]
        for a, b in zip(pts, pts[1:], strict=False):
            cv2.line(image, a, b, colour, 2, cv2.LINE_AA)
        for pt in pts:
            cv2.circle(image, pt, 4, colour, -1, cv2.LINE_AA)
    for k, alpha in enumerate(sweep):
        cv2.putText(
            image,
            alpha,
            (left2 + 22 + k * (pw - 60) // max(len(sweep) - 1, 1), top + ph + 18),
            0,
            0.45,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    top3 = 420
    tags = list(next(iter(arms.values()))["per_tag"])
    y_of = frame(60, top3, w - 100, 290, "rare panel per tag (descriptive), one bar per arm:")
    for i, arm in enumerate(arms):  # the legend: each arm's name in its colour
        colour = _COLOURS[i % len(_COLOURS)]
        cv2.putText(image, arm, (470 + 45 * i, top3 - 8), 0, 0.55, colour, 2, cv2.LINE_AA)
    group = (w - 100) // max(len(tags), 1)
    width = max((group - 20) // len(arms), 2)
    for t, tag in enumerate(tags):
        for i, m in enumerate(arms.values()):
            bar(
                60 + t * group + 10 + i * width,
                width - 2,
                m["per_tag"][tag]["mean"],
                y_of,
                _COLOURS[i % len(_COLOURS)],
            )
        cv2.putText(image, tag, (60 + t * group + 10, top3 + 308), 0, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


def finish(
    config: TransferConfig, all_runs: list[dict], panels: dict, sources: dict, timings: dict, sequences: int
) -> dict:
    """metrics.json, report.md, transfer.png and panels.json in the artifact folder; the manifest's
    transfer outcome (when the configuration names a manifest). Returns the metrics. ``sequences``:
    the primitive sequences the shared store holds for the evaluation."""
    out = Path(config.out)
    records = read_episodes(out)
    metrics = compute_metrics(config, all_runs, panels, records)
    metrics["cost"] = cost_lines(metrics, sources)
    metrics["cost"]["evaluation"] = {  # what sharing saved: executions a per-policy evaluation runs
        "episodes": len(records),
        "primitive_executions_unshared": sum(len(r["choices"]) for r in records),
        "sequences_in_store": sequences,
    }
    metrics["runs"] = all_runs
    used = {name: [s.scene_id for s in group] for name, group in panels.items()}
    atomic_write(
        out / "panels.json",
        (json.dumps({"panels": str(config.panels), "scenes": used}, indent=1) + "\n").encode(),
    )
    atomic_write(out / "metrics.json", (json.dumps(metrics, indent=1, sort_keys=True) + "\n").encode())
    atomic_write(out / "report.md", report(config, metrics).encode())
    atomic_write(out / "transfer.png", plot(metrics))
    checksum = folder_sha256(out)
    if config.manifest is not None:
        write_outcome(Path(config.manifest), out, checksum, metrics)
    return metrics | {"artifact_sha256": checksum, "timings": timings}


def write_outcome(manifest_path: Path, out: Path, checksum: str, metrics: dict) -> None:
    """The manifest's transfer section: measured, on a simulated panel, with every arm's rates and
    intervals, its mixture recipe and the artifact's location and checksum."""
    import os

    from scenegen.manifest.io import read_manifest, write_manifest
    from scenegen.manifest.schema import TransferOutcome

    manifest = read_manifest(manifest_path)
    first = {}  # each arm's first run at the default alpha: its mixture recipe
    for r in metrics["runs"]:
        if r["inputs"] == "rgbd":
            first.setdefault((r["arm"], r["alpha"]), r)
    arms = {}
    for arm, m in metrics["arms"].items():
        run = first[(arm, metrics["default_alpha"])]
        arms[arm] = {
            "alpha": m["alpha"],
            "seeds": m["seeds"],
            "rare": m["rare"],
            "common": m["common"],
            "recipe": run["recipe"],
            "effective_shares": run["effective_shares"],
        }
    outcome = TransferOutcome(
        status="measured",
        panel="simulated",
        note="Simulated stand-ins for real rare cases (panel_origin: reference): held-out reference layouts "
        f"committed in {metrics['panels_file']}; never real. Full tables in the artifact's report.md.",
        metrics={
            "primary": metrics["primary"],
            "arms": arms,
            "panels": metrics["panels"] | {"file": metrics["panels_file"], "panel_origin": "reference"},
        },
        artifact=Path(os.path.relpath(out.resolve(), manifest_path.resolve().parent)).as_posix(),
        artifact_sha256=checksum,
    )
    write_manifest(manifest_path, manifest.model_copy(update={"transfer": outcome}))
