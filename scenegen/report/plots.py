"""The report's plots: matplotlib figures written as SVG text to inline in the page (no pyplot, no
display; the same facts give the same bytes)."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402  (after the backend is chosen)

matplotlib.rcParams["svg.hashsalt"] = "scenegen-report"  # element ids stable between runs
matplotlib.rcParams["svg.fonttype"] = "none"  # text stays text: smaller, selectable
BLUE, GREY, RED = "#3b6ea8", "#9a9a9a", "#b8433a"


def _svg(figure: Figure) -> str:
    buffer = io.StringIO()
    figure.savefig(buffer, format="svg", bbox_inches="tight", metadata={"Date": None, "Creator": None})
    return buffer.getvalue()[buffer.getvalue().index("<svg") :]  # no XML prolog inside HTML


def funnel_svg(funnel: dict) -> str:
    """Tries into each stage and what it removed, as horizontal bars, ending with the accepted."""
    stages = funnel["stages"]
    names = [f"into {s['stage']}" for s in stages] + ["accepted"]
    entered = [s["entered"] for s in stages] + [funnel["accepted"]]
    removed = [s["removed"] for s in stages] + [0]
    figure = Figure(figsize=(6.4, 0.45 * len(names) + 0.8))
    axes = figure.subplots()
    y = list(range(len(names)))[::-1]
    axes.barh(y, [e - r for e, r in zip(entered, removed, strict=True)], color=BLUE, label="passed")
    axes.barh(
        y, removed, left=[e - r for e, r in zip(entered, removed, strict=True)], color=RED, label="rejected"
    )
    for yy, e, r in zip(y, entered, removed, strict=True):
        axes.text(e, yy, f" {e - r}" + (f" (-{r})" if r else ""), va="center", fontsize=9)
    axes.set_yticks(y, names)
    axes.set_xlabel("tries")
    axes.set_xlim(0, max(entered) * 1.25 if entered and max(entered) else 1)
    axes.legend(loc="lower right", fontsize=8, frameon=False)
    axes.spines[["top", "right"]].set_visible(False)
    return _svg(figure)


def tag_rates_svg(rates: list[dict]) -> str:
    """Each tag's share of the batch beside the reference's, with 95 % intervals."""
    figure = Figure(figsize=(6.4, 3.2))
    axes = figure.subplots()
    x = list(range(len(rates)))
    for offset, key, colour in ((-0.18, "batch", BLUE), (0.18, "reference", GREY)):
        rate = [r[key]["rate"] or 0.0 for r in rates]
        error = [
            [max(0.0, v - r[key]["low"]) for v, r in zip(rate, rates, strict=True)],
            [max(0.0, r[key]["high"] - v) for v, r in zip(rate, rates, strict=True)],
        ]
        axes.bar([i + offset for i in x], rate, width=0.34, color=colour, label=key, yerr=error, capsize=2)
    axes.set_xticks(x, [r["tag"] + ("*" if r["asked"] != "unspecified" else "") for r in rates], rotation=30)
    axes.set_ylabel("share of scenes")
    axes.set_ylim(0, 1.05)
    axes.legend(fontsize=8, frameon=False)
    axes.spines[["top", "right"]].set_visible(False)
    return _svg(figure)


def stage_svg(timings: dict) -> str:
    """Wall and CPU seconds per stage, summed over the workers."""
    stages = timings["stages"]
    figure = Figure(figsize=(6.4, 2.6))
    axes = figure.subplots()
    x = list(range(len(stages)))
    for offset, key, colour in ((-0.18, "wall", BLUE), (0.18, "cpu", GREY)):
        seconds = [s[key] or 0.0 for s in stages]
        axes.bar([i + offset for i in x], seconds, width=0.34, color=colour, label=key)
    axes.set_xticks(x, [s["stage"] for s in stages])
    axes.set_ylabel("seconds")
    axes.legend(fontsize=8, frameon=False)
    axes.spines[["top", "right"]].set_visible(False)
    return _svg(figure)


def shares_svg(labels: list[str], shares: list[float], title: str) -> str:
    """One bar per label: a mixture's effective shares, or a coverage row."""
    figure = Figure(figsize=(6.4, 0.35 * len(labels) + 0.9))
    axes = figure.subplots()
    y = list(range(len(labels)))[::-1]
    axes.barh(y, shares, color=BLUE)
    for yy, share in zip(y, shares, strict=True):
        axes.text(share, yy, f" {share:.3g}", va="center", fontsize=9)
    axes.set_yticks(y, labels)
    axes.set_title(title, fontsize=10)
    axes.set_xlim(0, max(shares, default=1) * 1.25 or 1)
    axes.spines[["top", "right"]].set_visible(False)
    return _svg(figure)


def contrasts_svg(contrasts: list[dict]) -> str:
    """Each contrast's mean with its 95 % interval, around zero (a forest plot)."""
    figure = Figure(figsize=(5.2, 0.42 * len(contrasts) + 0.9))
    axes = figure.subplots()
    y = list(range(len(contrasts)))[::-1]
    for yy, c in zip(y, contrasts, strict=True):
        axes.plot([c["low"], c["high"]], [yy, yy], color=BLUE, linewidth=2)
        axes.plot([c["mean"]], [yy], "o", color=BLUE)
    axes.axvline(0.0, color=GREY, linestyle="--", linewidth=1)
    axes.set_yticks(y, [c["contrast"] for c in contrasts])
    axes.set_xlabel("difference in success rate")
    axes.spines[["top", "right"]].set_visible(False)
    return _svg(figure)
