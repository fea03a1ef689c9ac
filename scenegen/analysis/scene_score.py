"""Per-scene realism: how typical one settled scene is of the reference set, and the recipe's
``unrealistic`` filter built on it.

:class:`SceneScorer` standardizes the layout features (scenegen.analysis.realism.layout_features) of the
reference layouts and scores a scene by its k-th-nearest-neighbour distance to them against the
reference layouts' own leave-one-out distances (docs/realism.md, "Per-scene score"). Pure numpy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.analysis.realism import feature_categories, feature_matrix, feature_names, load_rows, record_row

_KNN_CHUNK = 512  # query rows per distance block: 512 x 8,000 float64 is 33 MB

# The layout features each rare tag changes (analysis/realism.py layout_features). A composition of
# tags the reference never holds is judged per tag (:func:`composition_scores`): each tag against the
# reference layouts that hold it, on every feature but those the composition's other tags change.
TAG_FEATURES: dict[str, tuple[str, ...]] = {
    "near_edge": ("target_x", "target_y"),
    "under_overhang": ("target_x", "target_y", "target_height", "has_shelf"),
    "toppled": ("target_tilt", "target_height"),
    "occluded": ("target_nn_distance", "pair_distance_min"),
    "clutter": ("n_objects", "target_nn_distance", "pair_distance_min", "pair_distance_mean"),
    "stacked": ("target_height", "support_stacked", "support_table"),
    "low_light": ("ambient", "light_total"),
    "on_floor": ("target_x", "target_y", "target_height", "support_floor", "support_table", "mean_abs_y"),
}


def _knn_distance(queries: np.ndarray, reference: np.ndarray, k: int, exclude_self: bool) -> np.ndarray:
    """Euclidean distance (M,) from each query row to its k-th nearest reference row; with
    ``exclude_self`` the queries are the reference rows themselves and each leaves itself out."""
    ref_sq = np.einsum("ij,ij->i", reference, reference)
    out = np.empty(len(queries))
    for start in range(0, len(queries), _KNN_CHUNK):
        q = queries[start : start + _KNN_CHUNK]
        d2 = np.einsum("ij,ij->i", q, q)[:, None] + ref_sq[None, :] - 2.0 * (q @ reference.T)
        np.maximum(d2, 0.0, out=d2)
        if exclude_self:
            d2[np.arange(len(q)), np.arange(start, start + len(q))] = np.inf
        out[start : start + len(q)] = np.sqrt(np.partition(d2, k - 1, axis=1)[:, k - 1])
    return out


@dataclass(frozen=True, eq=False)
class SceneScorer:
    """Per-scene typicality against reference layouts, by k-nearest-neighbour distance.

    Features (:func:`layout_features`) are standardized by the reference's mean and standard
    deviation (a constant feature by 1). Each reference layout keeps its leave-one-out distance to
    its k-th nearest reference neighbour; a scene's score is the share of reference layouts whose
    own distance is >= the scene's k-th-neighbour distance to the reference set. In [0, 1]: a
    held-out layout of the reference distribution scores about uniformly in [0, 1] (median ~0.5),
    a scene farther from the data than almost every reference layout scores near 0. Build once with
    :meth:`from_rows` and reuse: scoring one scene against 8,000 layouts takes ~1 ms.

    Fields: ``mean``, ``scale`` (D,) of the raw features; ``reference`` (N, D) standardized;
    ``reference_knn`` (N,) the sorted leave-one-out k-NN distances (standardized units); ``k``;
    ``categories`` the feature categories.
    """

    mean: np.ndarray
    scale: np.ndarray
    reference: np.ndarray
    reference_knn: np.ndarray
    k: int
    categories: tuple[str, ...]
    columns: tuple[int, ...] | None = None  # the features scored (indices of feature_names); None: all

    @classmethod
    def from_rows(
        cls,
        rows: Sequence[dict],
        k: int = 5,
        categories: Sequence[str] | None = None,
        columns: Sequence[int] | None = None,
    ):
        """A scorer from reference layout rows (reference Parquet rows, e.g. :func:`load_rows`), on
        the features ``columns`` (default all)."""
        categories = feature_categories() if categories is None else tuple(categories)
        columns = None if columns is None else tuple(columns)
        if k < 1:
            raise ValueError(f"k={k}: the score needs k >= 1 neighbours")
        if len(rows) < k + 1:
            raise ValueError(f"{len(rows)} reference rows: k={k} needs at least {k + 1}")
        x = feature_matrix(rows, categories)
        x = x if columns is None else x[:, columns]
        if not np.isfinite(x).all():
            raise ValueError("reference rows have NaN or infinite features")
        mean, std = x.mean(axis=0), x.std(axis=0)
        scale = np.where(std > 1e-12, std, 1.0)
        z = (x - mean) / scale
        knn = np.sort(_knn_distance(z, z, k, exclude_self=True))
        return cls(mean, scale, z, knn, k, categories, columns)

    def knn_distances(self, rows: Sequence[dict]) -> np.ndarray:
        """(M,) distance of each layout to its k-th nearest reference layout (standardized units)."""
        x = feature_matrix(rows, self.categories)
        x = x if self.columns is None else x[:, self.columns]
        return _knn_distance((x - self.mean) / self.scale, self.reference, self.k, exclude_self=False)

    def scores(self, rows: Sequence[dict]) -> np.ndarray:
        """(M,) typicality of each layout, in [0, 1]; see the class docstring."""
        d = self.knn_distances(rows)
        n = len(self.reference_knn)
        return (n - np.searchsorted(self.reference_knn, d, side="left")) / n

    def score(self, row: dict) -> float:
        """Typicality of one layout (a reference Parquet row), in [0, 1]."""
        return float(self.scores([row])[0])


def scene_score_for_record(record, scorer: SceneScorer) -> float:
    """Typicality (:class:`SceneScorer`) of a stored scene (``SceneRecord``), through :func:`record_row`."""
    return scorer.score(record_row(record))


_SCORERS: dict[tuple[str, int], SceneScorer] = {}
_ARRAYS = ("mean", "scale", "reference", "reference_knn")


def reference_scorer(reference: str, k: int) -> SceneScorer:
    """The scorer of a reference Parquet file's train split, once per process: handed over by
    :func:`install_scorer`, else read from the cache (:func:`scorer_cache_path`, ~10 ms), else built
    (~3 s: most of it reading the rows) and cached."""
    from scenegen.paths import PROJECT_ROOT

    if (reference, k) not in _SCORERS:
        path = Path(reference) if Path(reference).is_absolute() else PROJECT_ROOT / reference
        cache = scorer_cache_path(path, k)
        scorer = _load_scorer(cache, k)
        if scorer is None:
            scorer = SceneScorer.from_rows(load_rows(path, "train"), k)
            _save_scorer(scorer, cache)
        _SCORERS[(reference, k)] = scorer
    return _SCORERS[(reference, k)]


def scorer_cache_path(reference: Path, k: int) -> Path:
    """The cache file of a scorer: named by the reference file's bytes, k, the catalog's categories
    and the source of the feature and score code, so any change to one of them builds anew."""
    import hashlib

    from scenegen.analysis import realism
    from scenegen.core.files import sha256_file
    from scenegen.paths import cache_dir

    key = hashlib.sha256()
    for part in (sha256_file(reference), str(k), ",".join(feature_categories())):
        key.update(part.encode() + b"\0")
    for module in (realism.__file__, __file__):
        key.update(Path(module).read_bytes())
    return cache_dir() / "scene_scorer" / f"{key.hexdigest()[:24]}.npz"


def _load_scorer(path: Path, k: int) -> SceneScorer | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in _ARRAYS}
            categories = tuple(str(c) for c in data["categories"])
    except (OSError, KeyError, ValueError):
        return None  # absent or unreadable: rebuilt
    return SceneScorer(**arrays, k=k, categories=categories)


def _save_scorer(scorer: SceneScorer, path: Path) -> None:
    arrays = {name: getattr(scorer, name) for name in _ARRAYS}
    _save_npz(path, **arrays, categories=np.array(scorer.categories, dtype=str))


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    """Write a cache file atomically; a cache that cannot be written is only a slower next run."""
    import os
    import tempfile

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError:
        pass


def install_scorer(reference: str, k: int, scorer: SceneScorer) -> None:
    """Use ``scorer`` as this process's :func:`reference_scorer` of (``reference``, ``k``): a pool
    worker gets the coordinator's instead of reading the reference set again."""
    _SCORERS[(reference, k)] = scorer


def placement_row(target: str, objects, furniture, lighting) -> dict:
    """A layout row (the keys :func:`layout_features` reads) of placed objects, furniture and lights."""
    return {
        "target": target,
        "objects": [
            {
                "name": o.name,
                "category": o.category,
                "support": o.support,
                "position": list(o.position),
                "quat": list(o.quat),
            }
            for o in objects
        ],
        "furniture": [{"kind": f.kind} for f in furniture],
        "ambient": float(np.mean(lighting.ambient)),
        "lights": [{"colour": list(light.colour), "intensity": light.intensity} for light in lighting.lights],
    }


# ---------------------------------------------------------------- compositions the reference lacks

_TRAIN_ROWS: dict[str, list[dict]] = {}
_TAG_MATRICES: dict[str, np.ndarray] = {}
_TAG_SCORERS: dict[tuple, tuple[SceneScorer, int]] = {}


def _reference_path(reference: str) -> Path:
    from scenegen.paths import PROJECT_ROOT

    return Path(reference) if Path(reference).is_absolute() else PROJECT_ROOT / reference


def _train_rows(reference: str) -> list[dict]:
    if reference not in _TRAIN_ROWS:
        _TRAIN_ROWS[reference] = load_rows(_reference_path(reference), "train")
    return _TRAIN_ROWS[reference]


def _tag_matrix(reference: str) -> np.ndarray:
    """(N, len(RARE_TAGS)) whether each train layout holds each rare tag: read from the cache beside
    the scorer's (~1 ms) instead of the rows (~3 s), so a worker reads the rows only to build the
    scorer of a composition it meets."""
    from scenegen.schema.condition import RARE_TAGS

    if reference not in _TAG_MATRICES:
        cache = scorer_cache_path(_reference_path(reference), 0).with_suffix(".tags.npz")
        try:
            with np.load(cache, allow_pickle=False) as data:
                matrix = data["tags"]
        except (OSError, KeyError, ValueError):
            rows = _train_rows(reference)
            matrix = np.array([[bool(r.get(f"tag_{t}")) for t in RARE_TAGS] for r in rows], bool)
            _save_npz(cache, tags=matrix)
        _TAG_MATRICES[reference] = matrix
    return _TAG_MATRICES[reference]


def composition_layouts(reference: str, composition: Sequence[str]) -> int:
    """How many train layouts of ``reference`` hold every tag of ``composition``."""
    from scenegen.schema.condition import RARE_TAGS

    held = _tag_matrix(reference)[:, [RARE_TAGS.index(t) for t in composition]]
    return int(held.all(axis=1).sum())


def tag_columns(
    tag: str, composition: Sequence[str], categories: Sequence[str] | None = None
) -> tuple[int, ...]:
    """The features ``tag`` is judged on within ``composition``: all but those the composition's
    other tags change (``TAG_FEATURES``)."""
    names = feature_names(categories)
    changed = {f for other in composition if other != tag for f in TAG_FEATURES[other]}
    return tuple(i for i, name in enumerate(names) if name not in changed)


@dataclass(frozen=True)
class CompositionScores:
    """A composition's per-tag judgement: the reference layouts holding the whole composition
    (``layouts``, fewer than k), and per tag its score against the layouts holding it
    (``scores``) and their number (``tag_layouts``). ``score``: the lowest."""

    composition: tuple[str, ...]
    layouts: int
    scores: dict[str, float]
    tag_layouts: dict[str, int]

    @property
    def score(self) -> float:
        return min(self.scores.values())

    def detail(self) -> str:
        judged = ", ".join(f"{t} {self.scores[t]:.3f} of {self.tag_layouts[t]}" for t in self.composition)
        return (
            f"composition {'+'.join(self.composition)}: {self.layouts} reference layouts, too few to score; "
            f"judged per tag against its own layouts on the features the others leave: {judged}"
        )


def composition_scores(
    reference: str, k: int, composition: Sequence[str], row: dict
) -> CompositionScores | None:
    """The per-tag judgement of a layout ``row`` holding the rare tags ``composition`` (at least two),
    or None when the reference's train split holds the composition in k layouts or more (the whole
    reference's score judges it, as before). Each tag's scorer is built once per process."""
    composition = tuple(composition)
    if len(composition) < 2:
        return None
    layouts = composition_layouts(reference, composition)
    if layouts >= k:
        return None
    scores, counts = {}, {}
    for tag in composition:
        columns = tag_columns(tag, composition)
        key = (reference, k, tag, columns)
        if key not in _TAG_SCORERS:
            own = [r for r in _train_rows(reference) if r.get(f"tag_{tag}")]
            _TAG_SCORERS[key] = (SceneScorer.from_rows(own, k, columns=columns), len(own))
        scorer, counts[tag] = _TAG_SCORERS[key]
        scores[tag] = round(scorer.score(row), 6)
    return CompositionScores(composition, layouts, scores, counts)
