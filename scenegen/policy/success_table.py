"""Success of each primitive per rare tag (and per tag x target category), from expert labels.

A scene counts for every rare tag it holds, and for ``nominal`` when it holds none. Each cell gives
successes / scenes with a 95 % Wilson interval; cells of (tag, category) are shown where they hold at
least ``MIN_CELL`` scenes. The best primitive of a tag is the one with the highest success rate.
:func:`differs_from_nominal` asks the question the task was built for: within one target category,
does a rare tag's best primitive beat the primitive that is best on nominal scenes (of that category)
by at least 15 points? If no three tags do, the task does not make the rare case matter.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

MIN_CELL = 30  # scenes in a (tag, category) cell before it is reported
MARGIN = 0.15  # success points a rare tag's best primitive must gain over nominal's best


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95 % by default)."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass(frozen=True)
class Cell:
    successes: int
    n: int

    @property
    def rate(self) -> float:
        return self.successes / self.n if self.n else 0.0

    @property
    def interval(self) -> tuple[float, float]:
        return wilson(self.successes, self.n)


def _groups(row: dict) -> list[str]:
    return list(row["tags"]) or ["nominal"]


def success_cells(rows: Sequence[dict], by_category: bool = False) -> dict[tuple, Cell]:
    """{(tag, primitive) or (tag, category, primitive): Cell} over label rows."""
    counts: dict[tuple, list[int]] = defaultdict(lambda: [0, 0])
    for row in rows:
        for tag in _groups(row):
            key = (tag, row["target_category"], row["primitive"]) if by_category else (tag, row["primitive"])
            counts[key][0] += bool(row["success"])
            counts[key][1] += 1
    return {key: Cell(s, n) for key, (s, n) in counts.items()}


def best_primitives(cells: dict[tuple, Cell]) -> dict[tuple, tuple[str, Cell]]:
    """For every group (all of a key but its last element, the primitive): the best primitive."""
    best: dict[tuple, tuple[str, Cell]] = {}
    for key, cell in sorted(cells.items()):
        group, primitive = key[:-1], key[-1]
        if group not in best or cell.rate > best[group][1].rate:
            best[group] = (primitive, cell)
    return best


def differs_from_nominal(
    rows: Sequence[dict], min_cell: int = MIN_CELL, margin: float = MARGIN
) -> list[dict]:
    """(tag, category) cells with at least ``min_cell`` scenes whose best primitive beats, on that
    cell, nominal's best primitive of the same category by ``margin`` or more."""
    cells = success_cells(rows, by_category=True)
    best = best_primitives(cells)
    found = []
    for (tag, category), (primitive, cell) in sorted(best.items()):
        if tag == "nominal" or cell.n < min_cell or ("nominal", category) not in best:
            continue
        nominal_best = best[("nominal", category)][0]
        baseline = cells.get((tag, category, nominal_best), Cell(0, cell.n))
        if primitive != nominal_best and cell.rate - baseline.rate >= margin:
            found.append(
                {
                    "tag": tag,
                    "category": category,
                    "best": primitive,
                    "best_rate": round(cell.rate, 3),
                    "nominal_best": nominal_best,
                    "nominal_best_rate_here": round(baseline.rate, 3),
                    "scenes": cell.n,
                }
            )
    return found


def markdown_table(rows: Sequence[dict], min_cell: int = MIN_CELL) -> str:
    """Success per tag x primitive (rate, Wilson interval, n), the best per tag marked, then the
    (tag, category) cells with at least ``min_cell`` scenes."""
    cells = success_cells(rows)
    primitives = sorted({key[-1] for key in cells})
    best = best_primitives(cells)
    lines = ["| tag | " + " | ".join(primitives) + " |", "|---" * (len(primitives) + 1) + "|"]
    for tag in sorted({key[0] for key in cells}):
        entries = []
        for p in primitives:
            cell = cells.get((tag, p))
            if cell is None:
                entries.append("")
                continue
            lo, hi = cell.interval
            mark = "**" if best[(tag,)][0] == p else ""
            entries.append(f"{mark}{cell.rate:.2f}{mark} [{lo:.2f}, {hi:.2f}] n={cell.n}")
        lines.append(f"| {tag} | " + " | ".join(entries) + " |")
    by_category = success_cells(rows, by_category=True)
    best_in_category = best_primitives(by_category)
    lines += ["", "| tag | category | " + " | ".join(primitives) + " |", "|---" * (len(primitives) + 2) + "|"]
    for tag, category in sorted({key[:2] for key in by_category}):
        n = max(by_category.get((tag, category, p), Cell(0, 0)).n for p in primitives)
        if n < min_cell:
            continue
        top = best_in_category[(tag, category)][0]
        entries = []
        for p in primitives:
            cell = by_category.get((tag, category, p))
            mark = "**" if p == top else ""
            entries.append(
                f"{mark}{cell.rate:.2f}{mark} [{cell.interval[0]:.2f}, {cell.interval[1]:.2f}]"
                if cell
                else ""
            )
        lines.append(f"| {tag} | {category} (n={n}) | " + " | ".join(entries) + " |")
    return "\n".join(lines) + "\n"
