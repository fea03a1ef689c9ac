"""Coverage of a data source: how many scenes each (task x tag) cell holds, and which cells are sparse.

A source is a reference or real-data Parquet table (``scenegen reference``, ``scenegen import-real``:
columns ``task`` and ``tag_<name>``), a batch directory (``index.jsonl`` lists each scene's tags, the
scene's ``scene.json`` its task under ``condition.task``), or a manifest YAML (the project's
``data_manifest.yaml`` or a batch's ``manifest.yaml``), whose sources are summed. A scene holding
several tags counts once in each of their columns; ``nominal`` is the column of scenes holding none.

A cell is sparse when it holds fewer than ``sparse`` scenes (default 20) or less than ``min_share``
(default 1 %) of all scenes of the source: too few examples to train on or to evaluate with.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.core.files import SCENE_ID
from scenegen.data import CHART_NAME, SPARSE_COUNT
from scenegen.schema.condition import TAGS, TASKS

SPARSE_SHARE = 0.01  # ... and so is a cell with less than this share of all scenes
LOG_SCALE_RATIO = 20  # the chart's axis turns logarithmic when the tallest bar exceeds this x the threshold


class CoverageError(ValueError):
    """A source cannot be read for coverage; the message is one line naming the path and what to do."""


@dataclass(frozen=True)
class CoverageTable:
    """Scenes per (task x tag) of one source.

    ``counts[(task, tag)]``: scenes of that task holding that tag; ``scenes[task]``: scenes of that task;
    ``total``: all scenes. ``skipped``: manifest sources that were not counted, with the reason.
    """

    source: str
    counts: Counter
    scenes: Counter
    total: int
    sparse: int = SPARSE_COUNT
    min_share: float = SPARSE_SHARE
    skipped: tuple[str, ...] = ()
    tags: tuple[str, ...] = TAGS

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks of ``TASKS`` in their order, then any other task the source holds (sorted)."""
        return (*TASKS, *sorted(t for t in self.scenes if t not in TASKS))

    def count(self, task: str, tag: str) -> int:
        return self.counts.get((task, tag), 0)

    def share(self, task: str, tag: str) -> float:
        """The cell's share of all scenes of the source (0 for an empty source)."""
        return self.count(task, tag) / self.total if self.total else 0.0

    def is_sparse(self, task: str, tag: str) -> bool:
        return self.count(task, tag) < self.sparse or self.share(task, tag) < self.min_share

    def sparse_below(self) -> int:
        """The smallest count that is not sparse: max(``sparse``, ``min_share`` of all scenes, rounded up)."""
        return max(self.sparse, math.ceil(round(self.min_share * self.total, 9)))

    def sparse_cells(self) -> list[tuple[str, str]]:
        """Every sparse (task, tag), row by row."""
        return [(task, tag) for task in self.tasks for tag in self.tags if self.is_sparse(task, tag)]

    def __add__(self, other: CoverageTable) -> CoverageTable:
        return CoverageTable(
            self.source,
            self.counts + other.counts,
            self.scenes + other.scenes,
            self.total + other.total,
            self.sparse,
            self.min_share,
            self.skipped + other.skipped,
            self.tags,
        )

    def format_table(self) -> str:
        """A text table: one row per task (and ``all``), one column per tag; sparse cells end in ``*``."""
        head = ["task", "scenes", *self.tags]
        rows = [[task, str(self.scenes.get(task, 0))] + self._cells(task) for task in self.tasks]
        totals = Counter()
        for (_, tag), n in self.counts.items():
            totals[tag] += n
        rows.append(["all", str(self.total)] + [str(totals[tag]) for tag in self.tags])
        widths = [max(len(r[i]) for r in [head, *rows]) + (1 if i >= 2 else 0) for i in range(len(head))]
        lines = [
            f"coverage of {self.source}: {self.total} scenes; * sparse: fewer than {self.sparse} scenes "
            f"or under {self.min_share:.0%} of all"
        ]
        for row in [head, *rows]:
            cells = []
            for i, (cell, w) in enumerate(zip(row, widths, strict=True)):
                if i == 0:
                    cells.append(cell.ljust(w))
                elif i >= 2 and row is not head and not cell.endswith("*"):
                    cells.append((cell + " ").rjust(w))  # counts line up whether starred or not
                else:
                    cells.append(cell.rjust(w))
            lines.append("  ".join(cells).rstrip())
        lines += [f"not counted: {reason}" for reason in self.skipped]
        return "\n".join(lines)

    def _cells(self, task: str) -> list[str]:
        return [f"{self.count(task, tag)}{'*' if self.is_sparse(task, tag) else ''}" for tag in self.tags]

    def bar_chart(self, path: str | Path, log: bool | None = None) -> Path:
        """Write a PNG bar chart: a group of bars per tag, one colour per task, counts on the bars.

        Sparse counts are red and starred, and a dashed line marks the threshold. ``log``: count axis
        log(1 + n); None (default) picks it when the tallest bar dwarfs the threshold (``LOG_SCALE_RATIO``).
        """
        from scenegen.store.batch import atomic_write

        image = _draw_chart(self, log)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        import cv2

        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise CoverageError(f"{path}: cannot encode the chart as PNG")
        atomic_write(path, png.tobytes())
        return path


def _empty(source: str) -> CoverageTable:
    return CoverageTable(source, Counter(), Counter(), 0)


def _from_rows(source: str, rows: list[tuple[str, list[str]]]) -> CoverageTable:
    """A table from (task, tags held) per scene."""
    counts, scenes = Counter(), Counter()
    for task, held in rows:
        scenes[task] += 1
        for tag in held:
            if tag in TAGS:
                counts[(task, tag)] += 1
    return CoverageTable(source, counts, scenes, len(rows))


# ------------------------------------------------------------------------------------ sources


def _is_parquet(path: Path) -> bool:
    if path.suffix == ".parquet":
        return True
    with open(path, "rb") as f:
        return f.read(4) == b"PAR1"


def _parquet(path: Path) -> CoverageTable:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except (pa.ArrowException, OSError) as exc:
        raise CoverageError(f"{path}: not a readable Parquet file ({_first_line(exc)})") from None
    columns = ["task", *(f"tag_{t}" for t in TAGS)]
    missing = [c for c in columns if c not in schema.names]
    if missing:
        raise CoverageError(
            f"{path}: no column {missing[0]!r}; coverage reads tables of `scenegen reference` or "
            "`scenegen import-real` (columns task, tag_<name>)"
        )
    table = pq.read_table(path, columns=columns)
    tasks = table.column("task").to_pylist()
    held = {t: table.column(f"tag_{t}").to_pylist() for t in TAGS}
    rows = [(task, [t for t in TAGS if held[t][i]]) for i, task in enumerate(tasks)]
    return _from_rows(str(path), rows)


def _batch(path: Path) -> CoverageTable:
    from scenegen.store.batch import INDEX

    rows = []
    try:
        lines = (path / INDEX).read_text().splitlines()
    except OSError as exc:
        raise CoverageError(f"{path / INDEX}: cannot read ({_first_line(exc)})") from None
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
            scene_id, held = entry["scene_id"], entry["tags"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise CoverageError(
                f"{path / INDEX}: line {n} is not an index row with scene_id and tags; a killed batch is "
                "repaired by rerunning its `scenegen generate` command"
            ) from None
        scene_json = path / str(scene_id) / "scene.json"
        if not SCENE_ID.match(str(scene_id)) or not scene_json.resolve().is_relative_to(path.resolve()):
            shown = str(scene_id)[:40]
            raise CoverageError(f"{path / INDEX}: line {n}: scene_id {shown!r} is not a scene of this batch")
        try:
            task = json.loads(scene_json.read_text())["condition"]["task"]
        except FileNotFoundError:
            raise CoverageError(f"{scene_json}: missing, but {INDEX} line {n} lists {scene_id}") from None
        except (json.JSONDecodeError, KeyError, TypeError, OSError):
            raise CoverageError(f"{scene_json}: no condition.task; not a scenegen scene record") from None
        rows.append((task, list(held)))
    return _from_rows(str(path), rows)


def _manifest(path: Path) -> CoverageTable:
    import yaml
    from pydantic import ValidationError

    from scenegen.manifest import Manifest

    try:
        manifest = Manifest(**(yaml.safe_load(path.read_text()) or {}))
    except yaml.YAMLError as exc:
        raise CoverageError(f"{path}: not valid YAML ({_first_line(exc)})") from None
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        raise CoverageError(
            f"{path}: not a data manifest: {where}: {err['msg']} (scenegen/manifest/schema.py)"
        ) from None
    except TypeError:
        raise CoverageError(
            f"{path}: not a data manifest (a mapping with schema_version, kind, sources)"
        ) from None
    folder = path.parent.resolve()
    located = []
    for source in manifest.sources:
        location = (folder / source.location).resolve()
        if not location.is_relative_to(folder):
            raise CoverageError(
                f"{path}: source {source.name!r}: location {source.location!r} lies outside the manifest's "
                "folder; a manifest may only name data inside its folder"
            )
        located.append((source, location))
    table = _empty(str(path))
    for source, location in located:
        if location.is_dir() and (location / "index.jsonl").is_file():
            table = table + _batch(location)
        elif location.is_file() and _is_parquet(location):
            table = table + _parquet(location)
        else:
            reason = "missing" if not location.exists() else "not a batch directory or Parquet file"
            table = table + CoverageTable(
                str(path), Counter(), Counter(), 0, skipped=(f"{source.name} ({source.location}: {reason})",)
            )
    return table


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def coverage_table(
    source: str | Path, sparse: int = SPARSE_COUNT, min_share: float = SPARSE_SHARE
) -> CoverageTable:
    """Count scenes per (task x tag) of a Parquet table, a batch directory or a manifest YAML.

    Raises :class:`CoverageError` (one line) for a source that is none of these, or a manifest naming a
    location outside its own folder.
    """
    path = Path(source)
    if not path.exists():
        raise CoverageError(f"{path}: no such file or directory")
    if path.is_dir():
        if not (path / "index.jsonl").is_file():
            raise CoverageError(
                f"{path}: a directory without index.jsonl; give a batch directory, a Parquet table or a "
                "manifest YAML"
            )
        table = _batch(path)
    elif path.suffix in (".yaml", ".yml"):
        table = _manifest(path)
    elif _is_parquet(path):
        table = _parquet(path)
    else:
        raise CoverageError(
            f"{path}: not a Parquet table, batch directory or manifest YAML (.yaml); "
            "see `scenegen coverage -h`"
        )
    return CoverageTable(
        str(path), table.counts, table.scenes, table.total, sparse, min_share, table.skipped, table.tags
    )


# -------------------------------------------------------------------------------------- chart

# Okabe-Ito colours (distinguishable with colour blindness), BGR for OpenCV.
_PALETTE = (
    (178, 114, 0),  # blue
    (0, 159, 230),  # orange
    (115, 158, 0),  # bluish green
    (167, 121, 204),  # reddish purple
    (233, 180, 86),  # sky blue
    (0, 94, 213),  # vermillion
    (66, 228, 240),  # yellow
)
_INK, _GRID, _SPARSE_INK = (40, 40, 40), (225, 225, 225), (30, 30, 200)
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX


def _nice_ceiling(value: float) -> int:
    """The smallest 1, 2 or 5 x 10^k at or above ``value``."""
    power = 10 ** int(np.floor(np.log10(max(value, 1.0))))
    return int(next(m * power for m in (1, 2, 5, 10) if m * power >= value))


def _nice_step(top: float, ticks: int = 5) -> int:
    """A round tick step (1, 2 or 5 x 10^k) giving about ``ticks`` ticks up to ``top``."""
    raw = max(top / ticks, 1.0)
    power = 10 ** int(np.floor(np.log10(raw)))
    return int(next(m * power for m in (1, 2, 5, 10) if m * power >= raw))


def _text(image, text, org, scale=0.5, colour=_INK, thickness=1, anchor="left") -> None:
    import cv2

    (w, h), _ = cv2.getTextSize(text, _FONT, scale, thickness)
    x, y = org
    x = {"left": x, "centre": x - w // 2, "right": x - w}[anchor]
    cv2.putText(image, text, (int(x), int(y)), _FONT, scale, colour, thickness, cv2.LINE_AA)


def _draw_labels(image: np.ndarray, table, tasks, threshold: int, log: bool, frame: tuple) -> None:
    """Axis titles, the chart's title and sparse note, and the legend of tasks, drawn in place."""
    import cv2

    left, top, plot_w, plot_h, height = frame
    _text(image, "rare-case tag", (left + plot_w // 2, height - 22), 0.55, anchor="centre")
    label = "scenes (log scale)" if log else "scenes"
    (lw, lh), _ = cv2.getTextSize(label, _FONT, 0.55, 1)
    strip = np.full((lh + 12, lw + 8, 3), 255, np.uint8)
    _text(strip, label, (4, lh + 4), 0.55)
    strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
    sy = top + (plot_h - strip.shape[0]) // 2
    image[sy : sy + strip.shape[0], 18 : 18 + strip.shape[1]] = strip

    source = table.source if len(table.source) <= 70 else "..." + table.source[-67:]
    _text(image, f"Coverage of {source}: {table.total} scenes per task x tag", (left, 34), 0.65, thickness=2)
    _text(
        image,
        f"* sparse (red count, below the dashed line at {threshold}): fewer than {table.sparse} scenes "
        f"or under {table.min_share:.0%} of all",
        (left, 62),
        0.48,
        _SPARSE_INK,
    )
    lx = left
    for i, task in enumerate(tasks):
        colour = _PALETTE[i % len(_PALETTE)]
        cv2.rectangle(image, (lx, 78), (lx + 16, 94), colour, -1)
        entry = f"{task} ({table.scenes.get(task, 0)})"
        _text(image, entry, (lx + 22, 92), 0.5)
        lx += 22 + cv2.getTextSize(entry, _FONT, 0.5, 1)[0][0] + 24


def _draw_chart(table: CoverageTable, log: bool | None = None) -> np.ndarray:
    """The chart as a BGR image (H, W, 3) uint8; its width grows with the number of bars.

    ``log``: a log(1 + count) axis; None chooses it when the tallest bar exceeds ``LOG_SCALE_RATIO``
    times the sparse threshold.
    """
    import cv2

    tasks, tags = table.tasks, table.tags
    bar_w, gap = 46, 26
    group_w = len(tasks) * bar_w + gap
    left, right, top, bottom = 90, 30, 110, 90
    width = max(left + right + len(tags) * group_w, 900)
    height = 640
    plot_w, plot_h = width - left - right, height - top - bottom
    image = np.full((height, width, 3), 255, np.uint8)

    threshold = table.sparse_below()
    peak = max([table.count(t, g) for t in tasks for g in tags] + [threshold, 1])
    if log is None:  # rare tags next to nominal: a linear axis would flatten exactly the cells of interest
        log = peak > LOG_SCALE_RATIO * max(threshold, 1)
    if log:
        y_max = _nice_ceiling(peak * 1.3)
        ticks = [0] + [m * 10**k for k in range(len(str(y_max))) for m in (1, 2, 5) if m * 10**k <= y_max]
        if len(ticks) > 12:
            ticks = [t for t in ticks if t == 0 or str(t).startswith("1")]

        def fraction(value: float) -> float:
            return math.log10(1 + value) / math.log10(1 + y_max)
    else:
        step = _nice_step(peak)
        y_max = step * int(np.ceil(peak * 1.08 / step))  # headroom for the counts above the tallest bar
        ticks = list(range(0, y_max + 1, step))

        def fraction(value: float) -> float:
            return value / y_max

    def y_of(value: float) -> int:
        return int(round(top + plot_h - fraction(value) * plot_h))

    for tick in ticks:
        y = y_of(tick)
        cv2.line(image, (left, y), (left + plot_w, y), _GRID, 1)
        _text(image, str(tick), (left - 8, y + 5), 0.45, anchor="right")
    if threshold > 0:  # dashed: bars below this line are sparse
        y = y_of(threshold)
        for x in range(left, left + plot_w, 14):
            cv2.line(image, (x, y), (min(x + 7, left + plot_w), y), _SPARSE_INK, 1)
    cv2.line(image, (left, top), (left, top + plot_h), _INK, 1)
    cv2.line(image, (left, top + plot_h), (left + plot_w, top + plot_h), _INK, 1)

    x0 = left + (plot_w - len(tags) * group_w) // 2 + gap // 2
    for j, tag in enumerate(tags):
        gx = x0 + j * group_w
        for i, task in enumerate(tasks):
            n = table.count(task, tag)
            bx = gx + i * bar_w
            y = y_of(n)
            colour = _PALETTE[i % len(_PALETTE)]
            if n:
                cv2.rectangle(image, (bx + 2, y), (bx + bar_w - 3, top + plot_h), colour, -1)
            sparse = table.is_sparse(task, tag)
            label = f"{n}*" if sparse else str(n)
            scale = 0.42
            while scale > 0.3 and cv2.getTextSize(label, _FONT, scale, 1)[0][0] > bar_w - 2:
                scale -= 0.02
            _text(
                image,
                label,
                (bx + bar_w // 2, y - 6),
                scale,
                _SPARSE_INK if sparse else _INK,
                anchor="centre",
            )
        centre = gx + len(tasks) * bar_w // 2
        _text(image, tag, (centre, top + plot_h + 24), 0.5, anchor="centre")

    _draw_labels(image, table, tasks, threshold, log, (left, top, plot_w, plot_h, height))
    return image


# ------------------------------------------------------------------------------- chart path


def default_chart_path(source: str | Path) -> Path:
    """``coverage.png`` next to the source: inside a batch directory, beside a file."""
    source = Path(source)
    return (source if source.is_dir() else source.parent) / CHART_NAME
