"""The retrieval head's learning curves (issue 43): quality against the number of annotated training
scenes, a natural-rate set against a rare-rich one of the same size, per rare tag.

Training sets come from the reference table's training split in the order of the transfer
experiment's :func:`~scenegen.experiment.transfer_sources.choose_reference_sets` (seed 20): the
**natural** set of size N is its A+ of size N (the first N layouts of the seeded shuffle); the
**rare-rich** set is its C: the first ``a = round(0.6 N)`` of them plus ``N - a`` layouts holding the
version 2 panel tags (not under_overhang, which has no panel), shared evenly over the tags, taken
after the first N. Both are drawn scene by scene with equal weight: C's extra layouts are more real
data, not a synthetic source.

The **curve set** scores them: the rare unique-category layouts of the seed-1 reference table
(assets/panels/v2/reference_seed1.parquet, which nothing trains on) that are on no panel, test or
validation; the validation panel is scored beside it. Nothing here reads a test panel's outcome.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.core.files import load_rows
from scenegen.env.scenes import EnvScene, reference_scene, unique_category
from scenegen.experiment.transfer_sources import choose_reference_sets
from scenegen.manipulation.task import feasible
from scenegen.paths import ASSETS_DIR
from scenegen.policy.panels import panel_id, panel_ids
from scenegen.policy.panels_v2 import NEW_LAYOUTS, panel_tags

REFERENCE = ASSETS_DIR / "reference" / "reference.parquet"
SEED = 20  # the transfer experiment's shuffle (pipelines/transfer.yaml)
SIZES = (30, 100, 300, 1000)
RARE_SHARE = 0.4  # of a rare-rich set: layouts chosen for a panel tag


def training_sets(n: int, reference: Path = REFERENCE, seed: int = SEED) -> dict[str, list[EnvScene]]:
    """The ``natural`` and ``rare_rich`` training scenes of size ``n`` (see the module docstring)."""
    train = load_rows(reference, "train")
    a = round((1 - RARE_SHARE) * n)
    sets = choose_reference_sets(train, a, n, n - a, seed, panel_tags())
    by_index = {r["index"]: r for r in train}
    natural = [reference_scene(by_index[i], "natural") for i in (*sets.a, *sets.a_plus_extra)]
    rare = [reference_scene(by_index[i], "rare") for i in sets.c_extra]
    return {"natural": natural, "rare_rich": natural[:a] + rare}


def curve_set(table: Path = NEW_LAYOUTS) -> list[EnvScene]:
    """The rare unique-category layouts of ``table`` on no version 2 panel (either side)."""
    taken = panel_ids()
    tags = panel_tags()
    scenes = [reference_scene(r, Path(table).stem) for r in load_rows(table, None)]
    return [
        s
        for s in scenes
        if feasible(s)
        and unique_category(s)
        and any(s.tags.get(t) for t in tags)
        and panel_id(s) not in taken
    ]


# ------------------------------------------------------------------------------------------- runs
DESIGNS = ("instances", "candidates")
SETS = ("natural", "rare_rich")
SEEDS = (0, 1, 2)
PANEL = "validation"  # the validation panel, scored beside the curve set


@dataclass(frozen=True)
class CurveJob:
    """One head of the curves: a design trained on one set of one size with one seed."""

    design: str
    set_name: str
    n: int
    seed: int

    @property
    def name(self) -> str:
        return f"{self.design}/{self.set_name}_{self.n}_s{self.seed}"


def curve_jobs(
    sizes: Sequence[int] = SIZES, seeds: Sequence[int] = SEEDS, designs: Sequence[str] = DESIGNS
) -> list[CurveJob]:
    """Every head of the curves, largest sizes first (they take longest)."""
    return [
        CurveJob(d, s, n, seed)
        for n in sorted(sizes, reverse=True)
        for d in designs
        for s in SETS
        for seed in seeds
    ]


def scoring_scenes() -> dict[str, list[EnvScene]]:
    """The layouts every head is scored on: the curve set and the validation panel."""
    from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes

    panel = panel_scenes(load_panels_v2(), PANEL)
    return {"curve": curve_set(), PANEL: list({panel_id(s): s for ss in panel.values() for s in ss}.values())}


def train_head(
    job: CurveJob,
    scenes: Sequence[EnvScene],
    out: Path,
    cache: Path,
    steps: dict | None = None,
    recipe=None,
    described: dict | None = None,
    sensor: str = "exact",
) -> dict:
    """Train ``job``'s head on ``scenes`` (frames from ``cache``) into ``out``, as the transfer
    experiment's arms train theirs: the design's defaults (``steps``: ``classifier`` and
    ``separator`` step counts instead, for a tiny run), every scene drawn with equal weight (or by
    ``recipe``, a MixtureRecipe: a transfer arm's). ``described``: what config.json records of the
    training set (default: the job and the scenes' layout ids). ``sensor``: the frames' depth
    (render.sensor); through a sensor the head is trained under that sensor's depth rule
    (``regions.rule_name_for``)."""
    from scenegen.assets.catalog import load_catalog
    from scenegen.perception.retrieval.frames import scene_frames
    from scenegen.perception.retrieval.regions import DEPTH_RULES, rule_name_for

    categories = list(load_catalog().categories)
    frames = list(scene_frames(scenes, cache, sensor=sensor))
    described = described or {"curve_job": job.name, "scenes": [panel_id(s) for s in scenes]}
    mixture = {} if recipe is None else {"recipe": recipe}
    steps = steps or {}
    classifier = {"steps": steps["classifier"]} if "classifier" in steps else {}
    if job.design == "instances":
        from scenegen.perception.retrieval.candidates import train_instances

        separator = {"separator_steps": steps["separator"]} if "separator" in steps else {}
        if sensor != "exact":  # exact's calls stay as they were
            separator["rule"] = DEPTH_RULES[rule_name_for(sensor)]
        return train_instances(
            scenes,
            frames,
            categories,
            out,
            seed=job.seed,
            description=described,
            **classifier,
            **separator,
            **mixture,
        )
    from scenegen.perception.retrieval.candidates import train_classifier

    return train_classifier(
        scenes, frames, categories, out, seed=job.seed, description=described, **classifier, **mixture
    )


def score_head(
    checkpoint: Path, scored: dict[str, list[EnvScene]], cache: Path, sensor: str = "exact"
) -> list[dict]:
    """One row per scored layout: its set, ``panel_id``, tags, overlap hit and centre hit; frames
    through ``sensor``."""
    from scenegen.perception.retrieval.evaluate import scene_metrics
    from scenegen.perception.retrieval.frames import scene_frames
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    predict = RetrievalPerception.load(checkpoint).predict
    rows = []
    for name, scenes in scored.items():
        for scene, frames in zip(scenes, scene_frames(scenes, cache, sensor=sensor), strict=True):
            m = scene_metrics(predict, scene, frames)
            rows.append(
                {
                    "set": name,
                    "layout": panel_id(scene),
                    "tags": m["tags"],
                    "hit_iou": m["hit_iou"],
                    "hit": m["hit"],
                }
            )
    return rows


def run_job(
    job: CurveJob,
    folder: Path,
    cache: Path,
    scored: dict | None = None,
    steps: dict | None = None,
    sensor: str = "exact",
) -> dict:
    """Train and score one head (skipped where its ``scores.jsonl`` exists: resumable); its record.
    ``scored``: the layouts to score on (default :func:`scoring_scenes`); ``steps``: see
    :func:`train_head`; ``sensor``: the frames' depth at training and scoring (a separate
    ``folder`` per sensor)."""
    import json

    import torch

    from scenegen.store.batch import atomic_write

    torch.set_num_threads(1)  # CPU seconds are the budget; the same bytes on any machine
    out = Path(folder) / job.name
    done = out / "scores.jsonl"
    if not done.exists():
        summary = train_head(job, training_sets(job.n)[job.set_name], out, cache, steps, sensor=sensor)
        rows = score_head(out, scored or scoring_scenes(), cache, sensor)
        record = {
            "job": job.name,
            "training_cpu_s": summary["cpu_seconds"],
            "candidates": summary["candidates"],
        }
        atomic_write(out / "record.json", json.dumps(record) + "\n")
        atomic_write(done, "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
    record = json.loads((out / "record.json").read_text())
    return record | {"rows": [json.loads(line) for line in done.read_text().splitlines()]}


# -------------------------------------------------------------------------------------- results
REPLICATES = 2000


def _grid(records: Sequence[dict], scored: str, tag: str, value: str = "hit_iou") -> np.ndarray:
    """(seeds, layouts) ``value`` (overlap hits) of one (design, set, size)'s models on the layouts of
    ``scored`` holding ``tag`` (``all``: every one), layouts in one order for every model (paired)."""
    rows = [[r for r in rec["rows"] if r["set"] == scored] for rec in records]
    keep = [i for i, r in enumerate(rows[0]) if tag == "all" or tag in r["tags"]]
    for other in rows[1:]:
        if [r["layout"] for r in other] != [r["layout"] for r in rows[0]]:
            raise ValueError("heads scored on different layouts: rerun their scoring")
    return np.array([[float(r[i][value]) for i in keep] for r in rows])


def _layouts(records: Sequence[dict], scored: str) -> list[str]:
    return [r["layout"] for r in records[0]["rows"] if r["set"] == scored]


def curve_results(
    records: Sequence[dict],
    replicates: int = REPLICATES,
    scored_sets: Sequence[str] = ("curve", PANEL),
    designs: Sequence[str] = DESIGNS,
    value: str = "hit_iou",
) -> dict:
    """Per scored set, design, tag and size: the natural and rare-rich sets' rates of ``value``
    (overlap hits) and the rare-rich set's lead, each with its 95 % bootstrap interval over seeds and
    layouts (the lead paired by layout); and the mean training CPU-seconds per design and size. A
    record's ``job`` is ``design/set_n_seed``; its rows name the scored set, layout and tags."""
    from scenegen.experiment.transfer_stats import difference, interval
    from scenegen.policy.panels_v2 import panel_tags

    by = {}
    for rec in records:
        design, rest = rec["job"].split("/")
        set_name, n, _ = rest.rsplit("_", 2)
        by.setdefault((design, set_name, int(n)), []).append(rec)
    designs = sorted({k[0] for k in by}, key=list(designs).index)
    sizes = sorted({k[2] for k in by})
    out: dict = {"sizes": sizes, "cpu_seconds": {}, "scored": {}}
    for design in designs:
        out["cpu_seconds"][design] = {
            n: round(
                float(np.mean([r["training_cpu_s"] for s in SETS for r in by.get((design, s, n), [])])), 1
            )
            for n in sizes
        }
    for scored in scored_sets:
        tags = ["all", *panel_tags()] + (["nominal"] if scored == PANEL else [])
        table = out["scored"][scored] = {}
        for design in designs:
            for tag in tags:
                for n in sizes:
                    if not all((design, s, n) in by for s in SETS):
                        continue
                    if _layouts(by[(design, SETS[0], n)], scored) != _layouts(
                        by[(design, SETS[1], n)], scored
                    ):
                        raise ValueError(
                            f"{design} {n}: the two sets' heads were scored on different layouts"
                        )
                    natural, rare = (_grid(by[(design, s, n)], scored, tag, value) for s in SETS)
                    if natural.shape[1] == 0:  # no scored layout holds the tag
                        continue
                    table.setdefault(design, {}).setdefault(tag, {})[n] = {
                        "natural": interval(natural, replicates, seed=n),
                        "rare_rich": interval(rare, replicates, seed=n + 1),
                        "lead": difference(rare, natural, replicates, seed=n + 2),
                    }
    return out


def leads(results: dict, scored: str = "curve", margin: float = 0.02) -> dict[str, dict[str, list[int]]]:
    """Per design and tag, the sizes where the rare-rich set leads beyond its interval (the lead's
    lower end above 0), and whether the design is flat (a lead under ``margin`` at every size on
    every rare tag)."""
    out = {}
    for design, tags in results["scored"][scored].items():
        rare = {t: v for t, v in tags.items() if t not in ("all", "nominal")}
        out[design] = {t: [n for n, c in v.items() if c["lead"]["low"] > 0] for t, v in rare.items()}
        out[design]["flat"] = all(c["lead"]["mean"] < margin for v in rare.values() for c in v.values())
    return out


def curve_table(results: dict, scored: str = "curve") -> str:
    """The curves as a markdown table: per design, tag and size, natural and rare-rich overlap hit
    rates with intervals and the lead."""
    lines = [
        "| design | tag | layouts | N | natural | rare-rich | lead (points) |",
        "|---|---|---|---|---|---|---|",
    ]
    fmt = lambda c: f"{c['mean']:.3f} [{c['low']:.3f}, {c['high']:.3f}]"  # noqa: E731
    for design, tags in results["scored"][scored].items():
        for tag, sizes in tags.items():
            for n, c in sizes.items():
                lead = c["lead"]
                lines.append(
                    f"| {design} | {tag} | {c['natural']['scenes']} | {n} | {fmt(c['natural'])} | "
                    f"{fmt(c['rare_rich'])} | {100 * lead['mean']:+.1f} [{100 * lead['low']:+.1f}, "
                    f"{100 * lead['high']:+.1f}] |"
                )
    return "\n".join(lines) + "\n"


_STYLE = {  # (design, set) -> BGR colour; instances solid, candidates thin
    ("instances", "natural"): (200, 120, 40),
    ("instances", "rare_rich"): (40, 40, 200),
    ("candidates", "natural"): (230, 190, 150),
    ("candidates", "rare_rich"): (150, 150, 240),
}


def plot_curves(
    results: dict,
    scored: str = "curve",
    size: tuple[int, int] = (1400, 720),
    title: str = "retrieval head: scene hit at IoU >= 0.5",
    styles: dict | None = None,
) -> bytes:
    """Small multiples, one per tag: the rate (``title``) against training scenes (log scale), a line
    per design and set with its 95 % interval; ``styles``: (design, set) -> BGR colour, the first
    design drawn thick. PNG bytes."""
    import math

    import cv2

    tags = list(next(iter(results["scored"][scored].values())))
    sizes = results["sizes"]
    w, h = size
    image = np.full((h, w, 3), 255, np.uint8)
    cols = 4
    pw, ph = (w - 80) // cols - 50, (h - 120) // 2 - 60
    text = lambda s, xy, scale=0.45, colour=(0, 0, 0), thick=1: cv2.putText(  # noqa: E731
        image, s, xy, 0, scale, colour, thick, cv2.LINE_AA
    )
    styles = styles or _STYLE
    first = next(iter(styles))[0]
    text(f"{title} against training scenes ({scored} set)", (20, 26), 0.6)
    legend = 20
    for (design, set_name), colour in styles.items():
        if design in results["scored"][scored]:
            text(f"{design} {set_name.replace('_', '-')}", (legend, 52), 0.5, colour, 2)
            legend += 240
    span = math.log(sizes[-1] / sizes[0]) or 1.0
    for i, tag in enumerate(tags):
        left, top = 70 + (i % cols) * (pw + 50), 100 + (i // cols) * (ph + 70)
        cv2.rectangle(image, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
        text(tag, (left, top - 8), 0.5)
        y_of = lambda v, top=top: int(top + ph - min(max(v, 0.0), 1.0) * ph)  # noqa: E731
        x_of = lambda n, left=left: int(left + 15 + (pw - 30) * math.log(n / sizes[0]) / span)  # noqa: E731
        for k in range(5):
            y = y_of(k / 4)
            cv2.line(image, (left, y), (left + pw, y), (225, 225, 225), 1)
            text(f"{k / 4:.2f}", (left - 38, y + 4), 0.38)
        for n in sizes:
            text(str(n), (x_of(n) - 10, top + ph + 16), 0.38)
        for (design, set_name), colour in styles.items():
            cells = results["scored"][scored].get(design, {}).get(tag)
            if not cells:
                continue
            thick = 2 if design == first else 1
            pts = [(x_of(n), y_of(cells[n][set_name]["mean"])) for n in sizes if n in cells]
            for a, b in zip(pts, pts[1:], strict=False):
                cv2.line(image, a, b, colour, thick, cv2.LINE_AA)
            for n in sizes:
                if n in cells:
                    c = cells[n][set_name]
                    x = x_of(n) + (3 if set_name == "rare_rich" else -3)
                    cv2.line(image, (x, y_of(c["low"])), (x, y_of(c["high"])), colour, 1)
                    cv2.circle(image, (x, y_of(c["mean"])), 3, colour, -1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()
