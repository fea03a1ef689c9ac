"""The guidance sweep: the diffusion proposer in the closed loop (propose, check, build, settle, tag)
for the null condition and for each guidance weight w, with cost guidance off and on.

Cells: ``null`` (the model's own distribution; the null condition, no tag required; with and
without the cost's feasibility terms; as many proposals as a guided cell) and, for each w
and cost weight, one request per rare tag, "TASK the TARGET TAG", with TARGET the category under
which the held-out reference holds that tag most often. Every cell proposes the same indices with
the same seed, so cells differ by their settings, not by their noise (common random numbers).

Per cell (pooled over its requests):

- ``pass_rate``: share of proposals that pass check and settle (accepted + condition_unmet);
- ``adherence``: share of those whose settled scene holds the request (accepted / passed);
- ``rejections``: share of proposals per rejection label;
- ``c2st`` / ``mmd_p``: two-sample tests of the accepted layouts against held-out reference layouts
  with the same tags (per request, as many held-out layouts holding its tag as it has accepted
  scenes, drawn without replacement; the null cell against all held-out layouts);
- ``diversity``: mean pairwise distance of the accepted layouts' standardised features over that of
  the matched reference layouts (1 = as spread out as the reference);
- ``projection_m``: mean distance decoding and separating moved an object (m);
- ``proposals_per_s``: proposals per CPU-second of the proposer (sampling, decoding and separating;
  this process, one thread);
- ``cpu_s_per_proposal``: sampler + check + build + settle + tag seconds per proposal.

The check and settle stages run in a pool of ``workers`` (the pipeline's own), the sampler here.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenegen.schema.condition import RARE_TAGS, Condition

DEFAULT_WEIGHTS = (0.0, 0.5, 1.0, 2.0, 4.0)


@dataclass(frozen=True)
class Cell:
    """One column of the sweep: a guidance setting and its requests."""

    name: str
    guidance: float | None  # None: the null condition
    cost_weight: float
    requests: tuple[Condition, ...]
    size: int = 1  # proposals per request: this many times the sweep's --proposals


@dataclass
class CellResult:
    cell: Cell
    proposals: int = 0
    accepted: list = field(default_factory=list)  # (request index, SceneRecord)
    rejections: Counter = field(default_factory=Counter)
    per_request: list[Counter] = field(default_factory=list)  # per request: proposals, accepted, labels
    projection: list[float] = field(default_factory=list)
    sample_seconds: float = 0.0
    stage_seconds: float = 0.0


def best_targets(heldout: Sequence[dict], tags: Sequence[str]) -> dict[str, str]:
    """Per tag, the target category under which the held-out layouts hold it most often (ties: name)."""
    out = {}
    for tag in tags:
        counts: Counter = Counter()
        totals: Counter = Counter()
        for row in heldout:
            totals[row["target_category"]] += 1
            counts[row["target_category"]] += bool(row[f"tag_{tag}"])
        out[tag] = max(sorted(totals), key=lambda c: counts[c] / totals[c])
    return out


def make_cells(
    base: Condition,
    targets: dict[str, str],
    weights: Sequence[float],
    cost_weight: float,
) -> list[Cell]:
    """The null cells, then per w one cell with cost guidance off and (if ``cost_weight`` > 0) one on."""
    requests = tuple(
        base.model_copy(update={"target": target, "tags": {tag: "required"}, "text": None})
        for tag, target in targets.items()
    )
    null = (base.model_copy(update={"tags": {}, "text": None}),)
    size = len(requests)  # as many null proposals as a guided cell has
    cells = [Cell("null", None, 0.0, null, size)]
    if cost_weight > 0:
        cells.append(Cell("null +cost", None, cost_weight, null, size))
    for w in weights:
        cells.append(Cell(f"w={w:g}", w, 0.0, requests))
        if cost_weight > 0:
            cells.append(Cell(f"w={w:g} +cost", w, cost_weight, requests))
    return cells


def run_sweep(
    config,
    cells: Sequence[Cell],
    proposals: int,
    workers: int = 1,
    progress: bool = True,
) -> list[CellResult]:
    """Run every cell's requests for ``proposals`` proposal indices each through check, settle, tag.

    ``config``: a pipeline config with a diffusion proposer (its checkpoint, steps, separation); the
    cells set guidance, cost weight and unconditional sampling."""
    from tqdm import tqdm

    from scenegen.assets.catalog import load_catalog
    from scenegen.check.geometry import arm_discs
    from scenegen.propose.diffusion import DiffusionProposer
    from scenegen.runner.executors import ordered_outcomes

    catalog = load_catalog()
    base = config.model_copy(update={"render": False})
    results = [CellResult(cell, per_request=[Counter() for _ in cell.requests]) for cell in cells]
    owner: deque = deque()  # (cell index, request index) of each proposal in flight, in order

    def stream() -> Iterator:
        for c, cell in enumerate(cells):
            settings = config.proposer.model_copy(
                update={
                    "guidance": cell.guidance or 0.0,
                    "cost_weight": cell.cost_weight,
                    "unconditional": cell.guidance is None,
                }
            )
            proposer = DiffusionProposer(settings, catalog, arm=arm_discs)  # as make_proposer gives it
            if c == 0:
                proposer.decoded(cell.requests[0], 0, config.seed)  # warm-up, not timed: lazy torch set-up
            for r, request in enumerate(cell.requests):
                for index in range(proposals * cell.size):
                    t0 = time.process_time()
                    decoded = proposer.decoded(request, index, config.seed)
                    results[c].sample_seconds += time.process_time() - t0
                    results[c].projection.extend(decoded.projection)
                    owner.append((c, r))
                    yield decoded.proposal

    total = sum(len(cell.requests) * cell.size for cell in cells) * proposals
    bar = tqdm(total=total, desc="sweep", unit="proposal", disable=not progress, dynamic_ncols=True)
    outcomes = ordered_outcomes(stream(), base, workers, export=False)
    try:
        for outcome in outcomes:
            c, r = owner.popleft()
            result = results[c]
            result.proposals += 1
            result.per_request[r]["proposals"] += 1
            result.stage_seconds += sum(outcome.seconds.values())
            if outcome.record is not None:
                result.accepted.append((r, outcome.record))
                result.per_request[r]["accepted"] += 1
            else:
                result.rejections[outcome.rejection.label] += 1
                result.per_request[r][outcome.rejection.label] += 1
            bar.set_postfix_str(cells[c].name, refresh=False)
            bar.update(1)
    finally:
        outcomes.close()
        bar.close()
    return results


def _request_row(request: Condition, counts: Counter) -> dict:
    """Pass rate and adherence of one request of a cell."""
    n = max(counts["proposals"], 1)
    passed = counts["accepted"] + counts["condition_unmet"]
    return {
        "request": " ".join([request.task, request.target, *request.required()]),
        "proposals": counts["proposals"],
        "accepted": counts["accepted"],
        "pass_rate": passed / n,
        "adherence": counts["accepted"] / passed if passed else None,
    }


def _diversity(features: np.ndarray, scale: np.ndarray) -> float:
    x = features / scale
    d = np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1))
    return float(d[np.triu_indices(len(x), k=1)].mean())


def summarize(result: CellResult, heldout: Sequence[dict], seed: int) -> dict:
    """The sweep's metrics of one cell (see the module docstring)."""
    from scenegen.analysis.realism import c2st, feature_matrix, mmd, record_row

    cell = result.cell
    passed = len(result.accepted) + result.rejections.get("condition_unmet", 0)
    n = max(result.proposals, 1)
    row = {
        "cell": cell.name,
        "guidance": cell.guidance,
        "cost_weight": cell.cost_weight,
        "proposals": result.proposals,
        "accepted": len(result.accepted),
        "pass_rate": passed / n,
        "adherence": len(result.accepted) / passed if passed else None,
        "rejections": {k: v / n for k, v in result.rejections.most_common()},
        "projection_m": float(np.mean(result.projection)) if result.projection else None,
        "proposals_per_s": result.proposals / result.sample_seconds if result.sample_seconds else None,
        "cpu_s_per_proposal": (result.sample_seconds + result.stage_seconds) / n,
        "c2st": None,
        "c2st_ci": None,
        "mmd_p": None,
        "diversity": None,
        "compared": 0,
        "requests": [
            _request_row(request, counts)
            for request, counts in zip(cell.requests, result.per_request, strict=True)
        ],
    }
    if cell.guidance is None:
        rows = [record_row(rec) for _, rec in result.accepted]
        reference = list(heldout)
        row["tag_rates"] = {
            tag: sum(rec.tags[tag].holds for _, rec in result.accepted) / max(len(rows), 1)
            for tag in RARE_TAGS
        }
        row["reference_rates"] = {
            tag: sum(bool(r[f"tag_{tag}"]) for r in heldout) / max(len(heldout), 1) for tag in RARE_TAGS
        }
    else:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
        rows, reference = [], []
        for r, request in enumerate(cell.requests):
            mine = [record_row(rec) for i, rec in result.accepted if i == r]
            required = request.required()
            pool = [h for h in heldout if all(h[f"tag_{t}"] for t in required)]
            k = min(len(mine), len(pool))
            rows += mine[:k]
            reference += [pool[i] for i in rng.choice(len(pool), size=k, replace=False)]
    if len(rows) >= 10 and len(reference) >= 10:
        a, b = feature_matrix(rows), feature_matrix(reference)
        test = c2st(a, b, seed=seed)
        scale = np.where(b.std(axis=0) > 1e-12, b.std(axis=0), 1.0)
        row.update(
            c2st=test.accuracy,
            c2st_ci=list(test.ci),
            mmd_p=mmd(a, b, seed=seed).p_value,
            diversity=_diversity(a, scale) / _diversity(b[: len(a)] if len(b) > len(a) else b, scale),
            compared=len(rows),
        )
    return row


# ------------------------------------------------------------------------------- report


def _fmt(value, spec: str = ".2f") -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def request_table(rows: Sequence[dict]) -> str:
    """Per request: accepted / proposals (adherence) in each guided cell, as a Markdown table."""
    guided = [r for r in rows if r["guidance"] is not None]
    if not guided:
        return ""
    lines = ["| request | " + " | ".join(r["cell"] for r in guided) + " |", "|---" * (1 + len(guided)) + "|"]
    for i, first in enumerate(guided[0]["requests"]):
        cells = [r["requests"][i] for r in guided]
        lines.append(
            f"| {first['request']} | "
            + " | ".join(f"{c['accepted']}/{c['proposals']} ({_fmt(c['adherence'], '.0%')})" for c in cells)
            + " |"
        )
    return "\n".join(lines)


def table(rows: Sequence[dict]) -> str:
    """The sweep as a Markdown table."""
    head = (
        "| cell | proposals | pass check+settle | adherence | accepted | C2ST (n) | MMD p | diversity "
        "| projection (mm) | proposals/s | CPU-s/proposal | rejections |"
    )
    lines = [head, "|---" * 12 + "|"]
    for r in rows:
        mix = ", ".join(f"{k} {v:.0%}" for k, v in r["rejections"].items()) or "-"
        c2 = f"{_fmt(r['c2st'])} ({r['compared']})" if r["c2st"] is not None else "-"
        projection_mm = None if r["projection_m"] is None else r["projection_m"] * 1000
        lines.append(
            f"| {r['cell']} | {r['proposals']} | {r['pass_rate']:.0%} | {_fmt(r['adherence'], '.0%')} "
            f"| {r['accepted']} | {c2} | {_fmt(r['mmd_p'])} | {_fmt(r['diversity'])} "
            f"| {_fmt(projection_mm, '.1f')} | {_fmt(r['proposals_per_s'], '.1f')} "
            f"| {r['cpu_s_per_proposal']:.2f} | {mix} |"
        )
    return "\n".join(lines)


_COLOURS = {"off": (200, 90, 30), "on": (40, 140, 40), "null": (120, 120, 120)}  # BGR


def plot(rows: Sequence[dict], size: tuple[int, int] = (1000, 700)) -> bytes:
    """Four panels against w (pass rate, adherence, C2ST, proposals/s), cost guidance off and on,
    the null condition (with cost, if swept) as a dashed grey line. PNG bytes."""
    import cv2

    panels = (  # title, key, y range (None: from the data), draw the null condition
        ("pass check + settle", "pass_rate", (0.0, 1.0), True),
        ("adherence after settling", "adherence", (0.0, 1.0), False),
        ("C2ST vs held-out (0.5 = indistinguishable)", "c2st", (0.4, 1.0), True),
        ("proposals per second (sample, decode, separate)", "proposals_per_s", None, True),
    )
    w, h = size
    image = np.full((h, w, 3), 255, np.uint8)
    null = next((r for r in rows if r["guidance"] is None and r["cost_weight"] > 0), None) or next(
        (r for r in rows if r["guidance"] is None), None
    )
    guided = [r for r in rows if r["guidance"] is not None]
    weights = sorted({r["guidance"] for r in guided}) or [0.0]
    cv2.putText(image, "guidance sweep: w on the x axis", (20, 24), 0, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    legend = (("cost off", "off"), ("cost on", "on"), ("null condition", "null"))
    for i, (text, key) in enumerate(legend):
        x = w - 420 + i * 140
        cv2.line(image, (x, 18), (x + 24, 18), _COLOURS[key], 2)
        cv2.putText(image, text, (x + 30, 23), 0, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    pw, ph = (w - 150) // 2, (h - 140) // 2
    for p, (title, key, limits, with_null) in enumerate(panels):
        left, top = 60 + (p % 2) * (pw + 80), 60 + (p // 2) * (ph + 60)
        values = [r[key] for r in rows if r[key] is not None]
        lo, hi = limits or (0.0, max(values + [1.0]) * 1.1)
        cv2.rectangle(image, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
        cv2.putText(image, title, (left, top - 8), 0, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        for k in range(5):
            v = lo + (hi - lo) * k / 4
            y = int(top + ph - (v - lo) / (hi - lo) * ph)
            cv2.line(image, (left, y), (left + pw, y), (225, 225, 225), 1)
            cv2.putText(image, f"{v:.2g}", (left - 42, y + 4), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)

        def px(x_value: float, value: float, left=left, top=top, lo=lo, hi=hi) -> tuple[int, int]:
            span = (weights[-1] - weights[0]) or 1.0
            x = left + 15 + (x_value - weights[0]) / span * (pw - 30)
            y = top + ph - (min(max(value, lo), hi) - lo) / (hi - lo) * ph
            return int(x), int(y)

        for wv in weights:
            x, _ = px(wv, lo)
            cv2.putText(image, f"{wv:g}", (x - 8, top + ph + 16), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        if with_null and null is not None and null[key] is not None:
            _, y = px(weights[0], null[key])
            for x in range(left, left + pw, 12):
                cv2.line(image, (x, y), (min(x + 6, left + pw), y), _COLOURS["null"], 1)
        for mode in ("off", "on"):
            pts = [
                px(r["guidance"], r[key])
                for r in sorted(guided, key=lambda r: r["guidance"])
                if r[key] is not None and (r["cost_weight"] > 0) == (mode == "on")
            ]
            for a, b in zip(pts, pts[1:], strict=False):
                cv2.line(image, a, b, _COLOURS[mode], 2, cv2.LINE_AA)
            for pt in pts:
                cv2.circle(image, pt, 4, _COLOURS[mode], -1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


def write_report(out: Path, rows: Sequence[dict], meta: dict) -> None:
    """sweep.json, sweep.md and sweep.png in ``out`` (each written atomically)."""
    from scenegen.store.batch import atomic_write

    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "sweep.json", json.dumps({**meta, "cells": list(rows)}, indent=1) + "\n")
    atomic_write(
        out / "sweep.md",
        table(rows) + "\n\naccepted / proposals (adherence) per request:\n\n" + request_table(rows) + "\n",
    )
    (out / "sweep.png.tmp").write_bytes(plot(rows))
    (out / "sweep.png.tmp").replace(out / "sweep.png")
